"""One-file checkpoints: model + normalizers + config + scene identity + training state.

The file is a ``torch.save`` dict written atomically (a crash never leaves a
half-written checkpoint under the final name) and read back with
``weights_only=True`` (no arbitrary pickles). Keys:

* ``format`` / ``version``: ``"colgnn-checkpoint"``, 1;
* ``meta``: scene name, resolution, mesh fingerprint, dt, variant, step;
* ``config``: :class:`ModelConfig` as a dict;
* ``model``: the Simulator's ``state_dict`` (the online normalizers are module
  buffers, so their statistics are in here: one file restores the model);
* ``optimizer``, ``scheduler``: their state dicts or None (None for shipped models);
* ``rng``: RNG states for a bit-exact resume (see :func:`capture_rng_state`);
* ``extra``: anything else the training loop needs (plain Python / tensors).

Loading (:func:`colgnn_core.learn.registry.load_checkpoint`, which knows the model kinds) checks the file
and that it belongs to the scene it is used with (name, mesh fingerprint, dt): otherwise :class:`InputError`.
"""

from __future__ import annotations

import math
import os
import random
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.io import atomic_write
from colgnn_core.learn.model import ModelConfig, Simulator
from colgnn_core.scenes import load_scene

FORMAT = "colgnn-checkpoint"
VERSION = 1
_REQUIRED = ("format", "version", "meta", "config", "model")


@dataclass(frozen=True)
class CheckpointMeta:
    """Which scene and training run a checkpoint belongs to."""

    scene: str
    resolution: str
    fingerprint: str
    dt: float
    variant: str
    step: int = 0

    @classmethod
    def for_scene(cls, scene, variant: str, step: int = 0) -> "CheckpointMeta":
        return cls(scene.name, scene.resolution, scene.object.fingerprint(), float(scene.dt), variant, int(step))

    def load_scene(self):
        """The Scene this checkpoint was trained on (its name, at its resolution)."""
        return load_scene(self.scene, self.resolution)


@dataclass
class LoadedCheckpoint:
    simulator: Simulator
    meta: CheckpointMeta
    config: ModelConfig
    optimizer: dict | None
    scheduler: dict | None
    rng: dict | None
    extra: dict


def capture_rng_state(generators: dict[str, torch.Generator] | None = None) -> dict:
    """Global torch / numpy / Python RNG states plus the named torch generators' states."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": (kind, keys.tolist(), int(pos), int(has_gauss), float(cached)),
        "python": random.getstate(),
        "generators": {name: g.get_state() for name, g in (generators or {}).items()},
    }


def restore_rng_state(state: dict, generators: dict[str, torch.Generator] | None = None) -> None:
    """Inverse of :func:`capture_rng_state` (generators are restored by name, in place)."""
    torch.set_rng_state(state["torch"])
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    for name, g in (generators or {}).items():
        if name not in state["generators"]:
            raise InputError(f"checkpoint has no RNG state for generator {name!r}")
        g.set_state(state["generators"][name])


def save_checkpoint(path: str | os.PathLike, simulator: Simulator, meta: CheckpointMeta, *,
                    optimizer: torch.optim.Optimizer | None = None, scheduler: Any = None,
                    rng: dict | None = None, extra: dict | None = None) -> None:
    """Write the checkpoint atomically. ``rng`` defaults to :func:`capture_rng_state` ().

    ``extra`` must hold only what ``torch.load(weights_only=True)`` accepts: tensors
    and plain Python containers / numbers / strings (no numpy arrays).
    """
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "kind": getattr(simulator, "checkpoint_kind", "gnn"),  # 'gnn' (Simulator) or 'subspace' (baseline)
        "meta": asdict(meta),
        "config": simulator.config.to_dict(),
        "model": simulator.state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "rng": rng if rng is not None else capture_rng_state(),
        "extra": dict(extra or {}),
    }
    with atomic_write(path) as fh:
        torch.save(payload, fh)


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Read and sanity-check the raw payload; missing, truncated, corrupt or foreign files raise InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such checkpoint: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError/EOFError/UnpicklingError/... for damaged files
        raise InputError(f"{path}: not a readable checkpoint (corrupt or truncated?): {exc}".splitlines()[0]) from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise InputError(f"{path}: not a colgnn checkpoint")
    missing = [k for k in _REQUIRED if k not in payload]
    if missing:
        raise InputError(f"{path}: checkpoint lacks {', '.join(missing)}")
    if payload["version"] != VERSION:
        raise InputError(f"{path}: checkpoint version {payload['version']} is not supported (expected {VERSION})")
    try:
        CheckpointMeta(**payload["meta"])
        if payload.get("kind", "gnn") == "gnn":
            ModelConfig.from_dict(payload["config"])
        elif payload["kind"] != "subspace":
            raise InputError(f"unknown model kind {payload['kind']!r}")
    except (TypeError, InputError) as exc:
        raise InputError(f"{path}: bad checkpoint header: {exc}") from exc
    return payload


def strip_training_state(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Copy a checkpoint without optimizer, scheduler and RNG state (shipped models: ~1/3 of the size)."""
    payload = read_checkpoint(src)
    payload.update(optimizer=None, scheduler=None, rng=None)
    with atomic_write(dst) as fh:
        torch.save(payload, fh)


def check_compatible(meta: CheckpointMeta, scene_name: str, fingerprint: str, dt: float,
                     source: str = "checkpoint") -> None:
    """InputError when the checkpoint was trained for another scene, mesh or time step."""
    if meta.scene != scene_name:
        raise InputError(f"{source} is for scene {meta.scene!r}, not {scene_name!r}")
    if meta.fingerprint != fingerprint:
        raise InputError(f"{source} was trained on a different {scene_name!r} mesh (resolution {meta.resolution!r}, "
                         f"fingerprint {meta.fingerprint[:12]}… vs {fingerprint[:12]}…)")
    if not math.isclose(meta.dt, dt, rel_tol=1e-9, abs_tol=0.0):
        raise InputError(f"{source} was trained with dt={meta.dt} s, the scene uses dt={dt} s")


def simulator_from_payload(payload: dict, template, source: str = "checkpoint") -> Simulator:
    """Build a Simulator on ``template`` and load the weights and normalizers."""
    config = ModelConfig.from_dict(payload["config"])
    sim = Simulator(template, config)
    try:
        sim.load_state_dict(payload["model"])
    except RuntimeError as exc:
        raise InputError(f"{source}: model weights do not match its config/scene: {str(exc).splitlines()[0]}") from exc
    sim.eval()
    return sim
