"""``colgnn models``: the table of shipped checkpoints, read from the checkpoints themselves.

Each checkpoint stores its scene, resolution, variant, network size, training steps, the dataset it was trained on
and the training wall time (``extra`` of :func:`colgnn_core.learn.checkpoint.save_checkpoint`). The models README's
table is generated from those values, so it cannot drift from the files it describes; the ``train`` command in
each row is rebuilt from the stored settings.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from colgnn_core.evaluation.provenance import provenance_line
from colgnn_core.io import write_generated_section
from colgnn_core.learn.checkpoint import read_checkpoint
from colgnn_core.learn.model import ModelConfig
from colgnn_core.learn.train import TrainConfig

SECTION = "models"  # the marker name of the generated block in the README
SIZE_KEYS = ("latent", "message_passing_steps", "mlp_layers")
NOT_OPTIONS = (*SIZE_KEYS, "world_radius", "surface_only", "noise_std", "noise_gamma")


@dataclass(frozen=True)
class ModelCard:
    """What one checkpoint file says about itself."""

    file: str                  # path relative to the models folder
    kind: str                  # "gnn" or "subspace"
    scene: str
    resolution: str
    variant: str
    size: str                  # "latent/MP/MLP" (gnn) or "PCA k + MLP h×l" (subspace)
    options: dict              # model settings that differ from ModelConfig's defaults (gnn only)
    world_radius: float        # r_W (m)
    steps: int
    data: str                  # the dataset folder's name
    sequences: int | None      # training sequences (None where the checkpoint does not list them)
    wall_s: float | None       # training wall time (s), None where not recorded
    megabytes: float           # file size (MB)
    command: str               # the `colgnn train` command that makes it


def read_card(path: Path, root: Path) -> ModelCard:
    """The :class:`ModelCard` of the checkpoint ``path`` (``root``: the folder its name is relative to)."""
    payload = read_checkpoint(path)
    meta, config, extra = payload["meta"], payload["config"], payload.get("extra") or {}
    kind = payload.get("kind", "gnn")
    data = Path(str(extra.get("data_dir", "?"))).name
    steps = int(meta.get("step", 0))
    base = (f"colgnn train --scene {meta['scene']} --data data/{data} --out RUN.pt --variant {meta['variant']} "
            f"--steps {steps} --seed {extra.get('seed', 0)}")
    if kind == "subspace":
        size, options = f"PCA {config['components']} + MLP {config['hidden']}×{config['layers']}", {}
        command = base
    else:
        defaults = ModelConfig().to_dict()
        size = "/".join(str(config[k]) for k in SIZE_KEYS)
        options = {k: v for k, v in config.items() if k not in NOT_OPTIONS and v != defaults.get(k)}
        # a fine-tune takes its network's size and settings from the checkpoint it started from
        command = (f"{base} --init {extra['init_from']}" if extra.get("init_from")
                   else f"{base} --model {size}" + (f" --model-options '{json.dumps(options)}'" if options else ""))
        if extra.get("symmetry_order"):  # trained with the scene's symmetry turns (learn.symmetry)
            command += " --symmetry"
    rates = _learning_rates(extra.get("train_config") or {})
    if rates:
        command += f" --lr {rates}"
    w_valid = (extra.get("train_config") or {}).get("w_valid", 0.0)
    if w_valid:
        command += f" --validity-weight {w_valid:g}"
    files = extra.get("data_files")
    return ModelCard(file=str(path.relative_to(root)), kind=kind, scene=meta["scene"],
                     resolution=meta.get("resolution", "?"), variant=meta["variant"], size=size, options=options,
                     world_radius=float(config.get("world_radius", 0.0)), steps=steps, data=data,
                     sequences=len(files) if files else None, wall_s=extra.get("wall_s"),
                     megabytes=path.stat().st_size / 1e6, command=command)


def _learning_rates(train_config: dict) -> str:
    """``INIT:FINAL`` for ``colgnn train --lr`` when the run's rates differ from the defaults, else ''."""
    default = TrainConfig()
    init = train_config.get("lr_init", default.lr_init)
    final = train_config.get("lr_final", default.lr_final)
    return "" if (init, final) == (default.lr_init, default.lr_final) else f"{init:g}:{final:g}"


def model_cards(models_dir: str | Path) -> list[ModelCard]:
    """Every ``*.pt`` under ``models_dir`` (recursively), sorted by path: scene defaults first, then sub-folders."""
    root = Path(models_dir)
    paths = sorted(root.rglob("*.pt"), key=lambda p: (len(p.relative_to(root).parts), str(p)))
    return [read_card(p, root) for p in paths]


def card_row(c: ModelCard) -> str:
    """One markdown row of :func:`models_markdown`."""
    opts = ", ".join(f"{k} {v}" for k, v in c.options.items()) or "–"
    seqs = "–" if c.sequences is None else str(c.sequences)
    wall = "not recorded" if c.wall_s is None else f"{c.wall_s:,.0f} s"
    return (f"| `{c.file}` | {c.scene} ({c.resolution}) | {c.variant} | {c.size} | {opts} | "
            f"{c.world_radius * 1000:g} mm | `{c.data}` ({seqs}) | {c.steps:,} | {wall} | {c.megabytes:.2f} |")


def models_markdown(cards: list[ModelCard], command: str) -> str:
    """The generated block: provenance, the table, and one `colgnn train` command per file."""
    header = ("| file | scene (resolution) | variant | size (latent/MP/MLP) | other model settings | r_W | training "
              "data (sequences) | steps | training time | MB |")
    table = "\n".join([header, "|---|---|---|---|---|---:|---|---:|---:|---:|", *(card_row(c) for c in cards)])
    commands = "\n".join(f"{c.command}   # {c.file}" for c in cards)
    return (f"{provenance_line(command)} The values are read from the checkpoint files; the training times are "
            f"the wall times that training recorded (on a shared machine they are upper bounds).\n\n{table}\n\n"
            f"The `colgnn train` command of each file, rebuilt from its stored settings (`data/NAME` is the dataset "
            f"folder it was trained on, made by `colgnn generate`):\n\n"
            f"```bash\n{commands}\n```\n")


def write_models_section(models_dir: str | Path, page: str | Path, command: str) -> Path:
    """Write the generated models table into ``page`` between its ``models`` markers (atomically)."""
    return write_generated_section(page, SECTION, models_markdown(model_cards(models_dir), command))
