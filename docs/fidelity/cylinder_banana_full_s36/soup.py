"""Weight interpolation between the shipped banana model and a fine-tune (WiSE-FT style), session 36's experiment.

Usage, from the repository root: .venv/bin/python docs/fidelity/cylinder_banana_full_s36/soup.py ALPHA FINETUNED OUT.pt
OUT holds alpha x FINETUNED + (1 - alpha) x shipped for every learned weight, and FINETUNED's normalizer statistics
(the fine-tune kept accumulating them on its data). Not a shipped tool: the result was not shipped (README.md).
"""

import os
import sys

import torch


def main(alpha: float, finetuned: str, out: str) -> None:
    shipped = torch.load("colgnn_core/assets/models/cylinder_banana.pt", weights_only=False)
    tuned = torch.load(finetuned, weights_only=False)
    model = {}
    for key, value in tuned["model"].items():
        keep = "normalizer" in key or not torch.is_floating_point(value)
        model[key] = value if keep else (1 - alpha) * shipped["model"][key] + alpha * value
    payload = dict(shipped, model=model, meta=tuned["meta"], config=tuned["config"])
    torch.save(payload, out + ".tmp")
    os.replace(out + ".tmp", out)


if __name__ == "__main__":
    main(float(sys.argv[1]), sys.argv[2], sys.argv[3])
