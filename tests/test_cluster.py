"""`colgnn generate --dask ADDRESS`: sequences simulated on a real Dask cluster (distributed.LocalCluster, 2 worker
processes) equal the local ones, the run resumes, and bad addresses are refused."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.io import load_sequence
from colgnn_core.sim.dataset import generate_dataset

REPO = Path(__file__).resolve().parents[1]
distributed = pytest.importorskip("distributed")


def run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "colgnn_core", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.timeout(600)
def test_generate_on_a_local_cluster_matches_local_processes_and_resumes(tmp_path, monkeypatch):
    args = ["--scene", "cone_bunny", "--resolution", "ci", "--sequences", "1", "--test-sequences", "1",
            "--frames", "6", "--quiet"]
    # The workers are processes of their own: they import colgnn from PYTHONPATH, as a user's cluster would.
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        res = run("generate", "--out", str(tmp_path / "dask"), "--dask", cluster.scheduler_address, *args)
        assert res.returncode == 0, res.stderr[-3000:]
        manifest = json.loads((tmp_path / "dask" / "manifest.json").read_text())
        assert sorted(manifest["sequences"]) == ["test_0000.npz", "train_0000.npz"]
        again = run("generate", "--out", str(tmp_path / "dask"), "--dask", cluster.scheduler_address, *args)
        assert again.returncode == 0, again.stderr[-3000:]
        assert json.loads((tmp_path / "dask" / "manifest.json").read_text())["sequences"] == manifest["sequences"]
    generate_dataset("cone_bunny", "ci", tmp_path / "local", sequences=1, test_sequences=1, frames=6, progress=False)
    for name in ("train_0000.npz", "test_0000.npz"):
        a, b = load_sequence(tmp_path / "dask" / name), load_sequence(tmp_path / "local" / name)
        np.testing.assert_allclose(a.object_positions, b.object_positions, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(a.tool_poses, b.tool_poses)
        assert int(a.extra["seed"]) == int(b.extra["seed"])


@pytest.mark.parametrize("kwargs, message", [
    ({"dask": "local:0"}, "--dask: expected a scheduler address (tcp://HOST:PORT) or local:N with N >= 1"),
    ({"dask": "not an address"}, "--dask: expected a scheduler address"),
    ({"dask": "local:2", "jobs": 2}, "give either --jobs (local processes) or --dask (a cluster), not both"),
])
def test_bad_dask_arguments_are_refused(tmp_path, kwargs, message):
    with pytest.raises(InputError, match=re.escape(message)):
        generate_dataset("cone_bunny", "ci", tmp_path / "d", sequences=1, progress=False, **kwargs)
    assert not (tmp_path / "d").exists()


def test_bad_dask_address_on_the_command_line_exits_2(tmp_path):
    res = run("generate", "--scene", "cone_bunny", "--resolution", "ci", "--out", str(tmp_path / "d"),
              "--sequences", "1", "--dask", "local:0")
    assert res.returncode == 2, res.stderr
    assert "--dask: expected a scheduler address" in res.stderr and "Traceback" not in res.stderr
