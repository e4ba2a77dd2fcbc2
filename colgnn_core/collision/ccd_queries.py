"""`colgnn ccd-check`: run the non-penetration filter over CCD benchmark query files.

Format (Wang, Ferguson et al., "A Large Scale Benchmark and an Inclusion-Based
Algorithm for Continuous Collision Detection", MIT): each CSV has 8*n rows of 7
integers. Columns 1/2, 3/4 and 5/6 are numerator/denominator of x, y, z; column 7
is the ground truth (1 = colliding). Every 8 rows are one query:

* vertex-face: v_t0, f0_t0, f1_t0, f2_t0, v_t1, f0_t1, f1_t1, f2_t1
* edge-edge:   ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1

The query type comes from a folder named ``vertex-face`` or ``edge-edge`` in the
file's path. Files may sit at any depth and may be gzip-compressed (``.csv.gz``).
The rationals are rounded to the nearest float64 (Python's int/int division is
correctly rounded), as the benchmark intends for floating-point methods.
"""

from __future__ import annotations

import gzip
import time
from pathlib import Path

import numpy as np

from colgnn_core.collision.filter import filter_edge_edge, filter_vertex_face
from colgnn_core.errors import InputError

KINDS = ("vertex-face", "edge-edge")

__all__ = ["load_query_file", "find_query_files", "run_ccd_check", "format_ccd_report"]


def _query_kind(path: Path) -> str:
    for part in reversed(path.parts[:-1]):
        if part in KINDS:
            return part
    raise InputError(f"{path}: cannot tell the query type; put the file under a 'vertex-face' or 'edge-edge' folder")


def load_query_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read one query CSV. Returns ``(points [n,8,3] float64, truth [n] bool)``."""
    path = Path(path)
    opener = gzip.open if path.name.endswith(".gz") else open
    try:
        with opener(path, "rt") as fh:
            lines = [ln.strip() for ln in fh]
    except (OSError, UnicodeDecodeError, EOFError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from exc
    lines = [ln for ln in lines if ln]
    if not lines:
        return np.zeros((0, 8, 3)), np.zeros(0, dtype=bool)
    if len(lines) % 8:
        raise InputError(f"{path}: {len(lines)} rows is not a multiple of 8")
    coords = np.empty((len(lines), 3))
    truth = np.empty(len(lines), dtype=np.int64)
    for i, line in enumerate(lines):
        cells = line.split(",")
        if len(cells) != 7:
            raise InputError(f"{path}:{i + 1}: expected 7 integers, got {len(cells)} values")
        try:
            v = [int(c) for c in cells]
            coords[i] = (v[0] / v[1], v[2] / v[3], v[4] / v[5])
        except ValueError as exc:
            raise InputError(f"{path}:{i + 1}: not an integer ({exc})") from exc
        except ZeroDivisionError as exc:
            raise InputError(f"{path}:{i + 1}: zero denominator") from exc
        except OverflowError as exc:
            raise InputError(f"{path}:{i + 1}: coordinate out of float64 range") from exc
        truth[i] = v[6]
    if not np.all(np.isin(truth, (0, 1))):
        raise InputError(f"{path}: the last column must be 0 or 1")
    t = truth.reshape(-1, 8)
    if np.any(t != t[:, :1]):
        raise InputError(f"{path}: the 8 rows of a query disagree on the ground truth")
    return coords.reshape(-1, 8, 3), t[:, 0].astype(bool)


def find_query_files(root: str | Path) -> list[Path]:
    """All ``*.csv`` / ``*.csv.gz`` files under ``root`` (any depth), sorted; or ``[root]`` for a file."""
    root = Path(root)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise InputError(f"no such folder: {root}")
    files = sorted(p for p in root.rglob("*")
                   if p.is_file() and (p.name.endswith(".csv") or p.name.endswith(".csv.gz")))
    if not files:
        raise InputError(f"{root}: no .csv query files found (searched all sub-folders)")
    return files


def _keep(kind: str, q: np.ndarray) -> np.ndarray:
    cols = [q[:, i, :] for i in range(8)]
    return filter_vertex_face(*cols) if kind == "vertex-face" else filter_edge_edge(*cols)


def _row(folder: str, kind: str, truth: np.ndarray, keep: np.ndarray) -> dict:
    non = ~truth
    n_non = int(non.sum())
    culled = int((non & ~keep).sum())
    return {
        "folder": folder,
        "kind": kind,
        "queries": int(truth.size),
        "colliding": int(truth.sum()),
        "noncolliding": n_non,
        "culled": culled,
        "false_negatives": int((truth & ~keep).sum()),
        "culled_fraction_of_noncolliding": (culled / n_non) if n_non else None,
    }


def run_ccd_check(path: str | Path) -> dict:
    """Run the filter over every query file under ``path``.

    Returns a JSON-ready dict: ``queries``, ``colliding``, ``false_negatives``
    (colliding queries the filter culled: must be 0), ``culled_fraction_of_noncolliding``,
    ``by_kind`` (vertex-face / edge-edge totals), ``folders`` (one row per folder
    holding query files, path relative to ``path``), ``filter_seconds`` and
    ``queries_per_second`` (filter only, parsing excluded).
    """
    root = Path(path)
    files = find_query_files(root)
    base = root if root.is_dir() else root.parent
    groups: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = {}
    for f in files:
        kind = _query_kind(f.resolve())
        q, truth = load_query_file(f)
        folder = f.parent.relative_to(base).as_posix() or "."
        groups.setdefault((folder, kind), []).append((q, truth))
    rows = []
    per_kind: dict[str, tuple[list, list]] = {k: ([], []) for k in KINDS}
    seconds = 0.0
    for (folder, kind), parts in sorted(groups.items()):
        q = np.concatenate([p[0] for p in parts])
        truth = np.concatenate([p[1] for p in parts])
        start = time.perf_counter()
        keep = _keep(kind, q) if len(q) else np.zeros(0, dtype=bool)
        seconds += time.perf_counter() - start
        rows.append(_row(folder, kind, truth, keep))
        per_kind[kind][0].append(truth)
        per_kind[kind][1].append(keep)
    by_kind = {}
    all_t, all_k = [], []
    for kind, (ts, ks) in per_kind.items():
        if ts:
            t, k = np.concatenate(ts), np.concatenate(ks)
            by_kind[kind] = _row("*", kind, t, k)
            all_t.append(t)
            all_k.append(k)
    total = _row("*", "all", np.concatenate(all_t), np.concatenate(all_k))
    n = total["queries"]
    return {
        "path": str(root),
        "files": len(files),
        "queries": n,
        "colliding": total["colliding"],
        "noncolliding": total["noncolliding"],
        "culled": total["culled"],
        "false_negatives": total["false_negatives"],
        "culled_fraction_of_noncolliding": total["culled_fraction_of_noncolliding"],
        "by_kind": by_kind,
        "folders": rows,
        "filter_seconds": seconds,
        "queries_per_second": (n / seconds) if seconds > 0 else None,
    }


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def format_ccd_report(d: dict) -> str:
    """Readable table of a :func:`run_ccd_check` result."""
    header = ("folder", "kind", "queries", "colliding", "culled", "culled %", "false neg")
    table = [header]
    for r in d["folders"]:
        table.append((r["folder"], r["kind"], str(r["queries"]), str(r["colliding"]), str(r["culled"]),
                      _pct(r["culled_fraction_of_noncolliding"]), str(r["false_negatives"])))
    table.append(("-",) * len(header))
    for kind, r in d["by_kind"].items():
        table.append(("all", kind, str(r["queries"]), str(r["colliding"]), str(r["culled"]),
                      _pct(r["culled_fraction_of_noncolliding"]), str(r["false_negatives"])))
    table.append(("all", "all", str(d["queries"]), str(d["colliding"]), str(d["culled"]),
                  _pct(d["culled_fraction_of_noncolliding"]), str(d["false_negatives"])))
    widths = [max(len(row[i]) for row in table if row[0] != "-") for i in range(len(header))]
    lines = []
    for row in table:
        if row[0] == "-":
            lines.append("  ".join("-" * w for w in widths))
            continue
        cells = [row[0].ljust(widths[0]), row[1].ljust(widths[1])] + [c.rjust(w) for c, w in zip(row[2:], widths[2:])]
        lines.append("  ".join(cells))
    verdict = "PASS: no colliding query was culled" if d["false_negatives"] == 0 else (
        f"FAIL: {d['false_negatives']} colliding queries were culled")
    qps = d.get("queries_per_second")
    speed = f"; filter {qps / 1e6:.2f} M queries/s" if qps else ""
    lines.append(f"{d['files']} files under {d['path']}{speed}. {verdict}.")
    return "\n".join(lines)
