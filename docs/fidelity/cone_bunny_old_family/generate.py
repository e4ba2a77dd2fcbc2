"""Simulate cone_bunny's training family as it was drawn before session 30 (the first stroke aimed at the scene's
`target_xy`), the family the shipped `cone_bunny.pt` and `experiments/cone_bunny_tip_side.pt` were trained on
(`cb36`: train_0000-0037).

Since session 30 `cone_bunny.toml` sets `[family.full] first_target = "surface"`, so the plain `colgnn generate`
draws another family. This script drops that one key for this process only and then runs the `colgnn` CLI with the
given arguments; the draws are those of the old family (checked in session 53: the held-out family seeds 2 and 5
of ../cone_bunny_full_heldout come out identical). Run from the repository root, one process per core:

    .venv/bin/python docs/fidelity/cone_bunny_old_family/generate.py generate --scene cone_bunny --resolution full \
        --out data/cb_old --split train --sequences 38 --frames 60 --jobs 1 --shard 0/2    # and --shard 1/2

(`--jobs 2` spawns workers that read the TOML again, without this change: use shards.) Resumable like any
`generate`.
"""
import sys

import colgnn_core.scenes as scenes
from colgnn_core.cli import main

_read = scenes.read_config_file


def _old_family(path):
    cfg = _read(path)
    if path.stem == "cone_bunny":
        cfg.get("family", {}).get("full", {}).pop("first_target", None)
    return cfg


scenes.read_config_file = _old_family

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
