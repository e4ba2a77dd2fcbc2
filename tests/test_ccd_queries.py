"""`colgnn ccd-check` core: the CCD benchmark sample queries (MIT, tests/data/ccd-sample-queries)."""

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from colgnn_core.collision.ccd_queries import format_ccd_report, load_query_file, run_ccd_check
from colgnn_core.errors import InputError

DATA = Path(__file__).parent / "data" / "ccd-sample-queries"


@pytest.fixture(scope="module")
def report():
    return run_ccd_check(DATA)


def test_all_sample_queries_no_false_negatives(report):
    assert report["files"] == 42
    assert report["queries"] == 7279
    assert report["colliding"] == 435
    assert report["false_negatives"] == 0
    for row in report["folders"]:
        assert row["false_negatives"] == 0, row


def test_culls_at_least_70_percent_of_noncolliding(report):
    assert report["culled_fraction_of_noncolliding"] >= 0.70
    assert report["by_kind"]["vertex-face"]["culled_fraction_of_noncolliding"] >= 0.70
    assert report["by_kind"]["edge-edge"]["culled_fraction_of_noncolliding"] >= 0.70
    # Exact figures of this filter (regression guard): 5879 of 6844 non-colliding queries.
    assert report["culled"] == 5879


def test_report_structure_and_json(report):
    folders = {r["folder"] for r in report["folders"]}
    assert "erleben-spike-hole/edge-edge" in folders and "unit-tests/vertex-face" in folders
    assert len(report["folders"]) == 22
    row = next(r for r in report["folders"] if r["folder"] == "erleben-spike-hole/edge-edge")
    assert row["queries"] == 1870 and row["kind"] == "edge-edge"
    json.dumps(report)  # JSON-ready
    text = format_ccd_report(report)
    assert "PASS" in text and "7279" in text and "erleben-wedges/vertex-face" in text


def test_rationals_converted_to_nearest_float64(tmp_path):
    d = tmp_path / "deep" / "er" / "vertex-face"
    d.mkdir(parents=True)
    rows = ["-8388609,8388608,1,3,-1,1,1"] * 8
    (d / "q.csv").write_text("\n".join(rows) + "\n")
    q, truth = load_query_file(d / "q.csv")
    assert q.shape == (1, 8, 3) and truth.tolist() == [True]
    assert q[0, 0, 0] == -8388609 / 8388608 and q[0, 0, 1] == 1 / 3 and q[0, 0, 2] == -1.0
    # Huge numerators (beyond int64) are read exactly before rounding.
    (d / "q.csv").write_text("\n".join(["36893488147419103233,36893488147419103232,0,1,0,1,0"] * 8))
    q, _ = load_query_file(d / "q.csv")
    assert q[0, 0, 0] == 1.0


def test_plain_and_gzip_files_at_any_depth(tmp_path):
    src = DATA / "unit-tests" / "vertex-face" / "data_0_0.csv.gz"
    plain = tmp_path / "a" / "b" / "c" / "vertex-face"
    plain.mkdir(parents=True)
    with gzip.open(src, "rt") as fh:
        (plain / "x.csv").write_text(fh.read())
    packed = tmp_path / "z" / "edge-edge"
    packed.mkdir(parents=True)
    shutil.copy(DATA / "unit-tests" / "edge-edge" / "data_0_0.csv.gz", packed / "y.csv.gz")
    r = run_ccd_check(tmp_path)
    assert {row["folder"] for row in r["folders"]} == {"a/b/c/vertex-face", "z/edge-edge"}
    assert r["false_negatives"] == 0
    single = run_ccd_check(plain / "x.csv")
    assert single["files"] == 1 and single["queries"] == r["by_kind"]["vertex-face"]["queries"]


@pytest.mark.parametrize("content, message", [
    ("1,1,1,1,1,1,0\n" * 7, "multiple of 8"),
    ("1,1,1,1,1,0\n" * 8, "expected 7"),
    ("1,1,x,1,1,1,0\n" * 8, "not an integer"),
    ("1,0,1,1,1,1,0\n" * 8, "zero denominator"),
    ("1,1,1,1,1,1,2\n" * 8, "0 or 1"),
])
def test_malformed_files_raise(tmp_path, content, message):
    d = tmp_path / "edge-edge"
    d.mkdir()
    (d / "bad.csv").write_text(content)
    with pytest.raises(InputError, match=message):
        run_ccd_check(tmp_path)


def test_missing_or_empty_folders_raise(tmp_path):
    with pytest.raises(InputError, match="no such folder"):
        run_ccd_check(tmp_path / "nope")
    with pytest.raises(InputError, match="no .csv"):
        run_ccd_check(tmp_path)
    (tmp_path / "q.csv").write_text("1,1,1,1,1,1,0\n" * 8)
    with pytest.raises(InputError, match="query type"):
        run_ccd_check(tmp_path)


def test_filter_keeps_every_colliding_query_in_float64(report):
    # The same data through the public filter functions directly (no report plumbing).
    from colgnn_core.collision.filter import filter_edge_edge, filter_vertex_face

    q, truth = load_query_file(DATA / "unit-tests" / "edge-edge" / "data_0_1.csv.gz")
    keep = filter_edge_edge(*[q[:, i] for i in range(8)])
    assert truth.sum() == 15 and np.all(keep[truth])
    q, truth = load_query_file(DATA / "erleben-spikes" / "vertex-face" / "data_0_0.csv.gz")
    keep = filter_vertex_face(*[q[:, i] for i in range(8)])
    assert np.all(keep[truth])
