"""A user's scene made and fitted once per test session: ``colgnn scene new`` on the shipped test pebble
(tests/data/own_object/pebble.obj) and ``colgnn fit`` at ci with a tiny budget, through the real command line
(pytetwild, the IPC solver, training, evaluation), in a temporary folder removed at exit."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
import time
from functools import lru_cache
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PEBBLE = REPO / "tests" / "data" / "own_object" / "pebble.obj"
NAME = "pebble"
FIT_MINUTES = 2.0

_root = Path(tempfile.mkdtemp(prefix="colgnn-own-scene-"))
atexit.register(shutil.rmtree, _root, True)


def scene_dir() -> Path:
    return _root / "scenes"


def env(**extra: str) -> dict[str, str]:
    """The environment of a child process that finds the test's scenes."""
    return dict(os.environ, COLGNN_SCENE_PATH=str(scene_dir()), PYTHONPATH=str(REPO), **extra)


def colgnn(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "colgnn_core", *args], cwd=REPO, env=env(), capture_output=True,
                          text=True, timeout=timeout)


@lru_cache(maxsize=None)
def created() -> tuple[subprocess.CompletedProcess, float]:
    """``colgnn scene new pebble ...`` (and its wall time, s)."""
    t0 = time.perf_counter()
    res = colgnn("scene", "new", NAME, "--object", str(PEBBLE), "--size", "0.1", "--tool", "sphere",
                 "--out", str(scene_dir()))
    return res, time.perf_counter() - t0


@lru_cache(maxsize=None)
def fitted() -> tuple[subprocess.CompletedProcess, float]:
    """``colgnn fit pebble --resolution ci --minutes 2`` after :func:`created` (and its wall time, s)."""
    res, _ = created()
    assert res.returncode == 0, res.stderr
    t0 = time.perf_counter()
    out = colgnn("fit", NAME, "--resolution", "ci", "--minutes", str(FIT_MINUTES), "--quiet")
    return out, time.perf_counter() - t0
