"""colgnn bench: the contract fields, measured on a tiny trained model against the IPC solver in one run."""

import json
import math

import pytest

from colgnn_core.cli import main
from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import rmse_fraction
from colgnn_core.evaluation.speed import bench, format_bench
from tests.helpers import train_data as fx

CONTRACT = ("total_ms", "graph_ms", "gnn_ms", "correction_ms", "ipc_ms")


def test_bench_reports_the_contract_fields():
    r = bench(fx.SCENE, checkpoint=str(fx.trained_checkpoint("full")), frames=6, threads=1)
    for key in CONTRACT:
        assert set(r[key]) == {"median", "p95"} and 0 <= r[key]["median"] <= r[key]["p95"]
    assert r["total_ms"]["median"] >= r["gnn_ms"]["median"] > 0
    assert r["ipc_ms"]["median"] > 0
    assert r["speedup_vs_ipc"] == pytest.approx(r["ipc_ms"]["median"] / r["total_ms"]["median"])
    assert all(math.isfinite(v) and v >= 0 for v in r["rollout_rmse"].values())
    scene = fx.scene()
    assert (r["vertices"], r["edges"], r["faces"], r["threads"]) == (
        len(scene.object.vertices), len(scene.object.edges), len(scene.object.faces), 1)
    assert r["crossings_after_correction"] == 0
    assert "speedup vs IPC" in format_bench(r)
    json.dumps(r)  # JSON-ready


def test_rmse_fraction_by_hand():
    import numpy as np

    truth = np.zeros((2, 2, 3))
    pred = truth.copy()
    pred[1, 0] = [3.0, 4.0, 0.0]  # one of two vertices off by 5 m at frame 1
    np.testing.assert_allclose(rmse_fraction(pred, truth, 10.0), [0.0, np.sqrt(25 / 2) / 10])


def test_bench_bad_input(capsys):
    with pytest.raises(InputError, match="unknown scene"):
        bench("jelly", frames=5)
    assert main(["bench", "--scene", "cone_bunny", "--checkpoint", str(fx.trained_checkpoint("full")),
                 "--frames", "2"]) == 2
    assert "frames must be >= 3" in capsys.readouterr().err


def test_collision_bench_cli_reports_both_timings_and_no_missed_hit(capsys):
    """`colgnn bench --collision`: ours vs ipctk on the same step, in one run (timings only reported)."""
    assert main(["bench", "--collision", "--scene", "cone_bunny", "--resolution", "ci", "--repeats", "3",
                 "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["ipctk_hits_culled_by_filter"] == 0
    assert sum(r["candidates"].values()) > 0 and r["crossings"] == r["ipctk_hits"]
    assert 0 < r["broad_ms"] < r["ours_ms"] and r["ipctk_pairs_ms"] > 0
    assert r["speedup_vs_ipctk_pairs"] == pytest.approx(r["ipctk_pairs_ms"] / r["ours_ms"])
    assert main(["bench", "--collision", "--scene", "cone_bunny", "--resolution", "ci", "--repeats", "2"]) == 0
    assert "speed-up vs ipctk same pairs" in capsys.readouterr().out
