"""Tiny real ground truth and a tiny trained model for the training / rollout / subspace tests.

Built once per test session (module-level caches shared by the test modules): two
short cone_bunny ``ci`` sequences from the project's own IPC solver
(``generate_dataset``), in a temporary folder removed at exit.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from functools import lru_cache
from pathlib import Path

import torch

from colgnn_core.errors import SimulationError

SCENE = "cone_bunny"
FRAMES = 16          # the cone touches the bunny from about frame 5
TINY_MODEL = dict(latent=16, message_passing_steps=2, mlp_layers=1)

_root = Path(tempfile.mkdtemp(prefix="colgnn-train-tests-"))
atexit.register(shutil.rmtree, _root, True)


@lru_cache(maxsize=None)
def scene():
    from colgnn_core.scenes import load_scene

    return load_scene(SCENE, "ci")


@lru_cache(maxsize=None)
def dataset_dir() -> Path:
    """2 train + 1 test sequences of FRAMES frames (a sequence the solver rejects is left out)."""
    from colgnn_core.sim.dataset import generate_dataset

    out = _root / "data"
    try:
        generate_dataset(SCENE, "ci", out, sequences=2, frames=FRAMES, jobs=1, progress=False, test_sequences=1)
    except SimulationError:
        pass  # the other sequences were written; the fixture needs at least one train file
    assert list(out.glob("train_*.npz")), "the solver produced no training sequence"
    return out


def tiny_config(**overrides):
    from colgnn_core.learn.train import TrainConfig

    cfg = dict(steps=60, warmup_steps=10, lr_init=1e-3, lr_final=1e-4, log_every=5, checkpoint_every=1000,
               ramp_begin=0.0, ramp_end=0.2, model=dict(TINY_MODEL))
    cfg.update(overrides)
    return TrainConfig(**cfg)


@lru_cache(maxsize=None)
def trained_checkpoint(variant: str = "full") -> Path:
    """A tiny model trained for a few steps (same seed every time)."""
    from colgnn_core.learn.train import train

    torch.set_num_threads(1)
    path = _root / f"tiny_{variant}.pt"
    train(scene(), dataset_dir(), path, variant=variant, seed=0, config=tiny_config(), progress=False, log_dir=False)
    return path


def tmp_dir(name: str) -> Path:
    p = _root / name
    p.mkdir(parents=True, exist_ok=True)
    return p
