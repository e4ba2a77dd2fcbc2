"""docs/SPEED.md as ``colgnn bench --scene all --markdown FILE`` writes it: one row per scene, from one run.

The page is never edited by hand: the command that measures the numbers writes them, with its provenance (command,
machine, load, code version), and the raw results go to ``bench/<scene>.json`` beside it.
"""

from __future__ import annotations

import json
from pathlib import Path

from colgnn_core.evaluation.provenance import provenance_line
from colgnn_core.io import atomic_write

PAPER_MS = "60–135 ms per step on a GTX 1080 Ti (network on the GPU)"


def speed_row(r: dict) -> str:
    """One markdown table row of a :func:`colgnn_core.evaluation.speed.bench` result."""
    t, g, n, c = r["total_ms"], r["graph_ms"], r["gnn_ms"], r["correction_ms"]
    rel = r.get("relative_displacement_error")
    rel_text = "–" if rel is None else f"{rel:.2f}"
    self_text = (f"{r['self_contact_ms']['median']:.1f} ({r['self_contact_ms']['p95']:.1f}) ms"
                 if r.get("self_contact") else "off")
    return (f"| `{r['scene']}` ({r['resolution']}) | {r['surface_vertices']:,} / {r['edges']:,} / {r['faces']:,} | "
            f"**{t['median']:.1f}** ({t['p95']:.1f}) ms{_spread(r)} | {g['median']:.1f} / {n['median']:.1f} / "
            f"{c['median']:.1f} ms | {self_text} | {r['ipc_ms']['median']:,.0f} ms | **{r['speedup_vs_ipc']:.0f}×** | "
            f"{r['crossings_before_correction']} → {r['crossings_after_correction']} | {rel_text} | "
            f"{r['load_average_1min']:.1f} |")


def _spread(r: dict) -> str:
    """", passes 17.0-25.7" for a result of several timed passes (their step medians' range), else ""."""
    medians = r.get("rollout_medians_ms") or []
    return f"; passes {min(medians):.1f}-{max(medians):.1f}" if len(medians) > 1 else ""


def busy_note(results: list[dict]) -> str:
    """A sentence naming the scenes whose collision kernels ran on 1 thread in some steps because tasks waited for a
    CPU (``kernel_threads_reduced_steps``; :class:`~colgnn_core.runtime.threads.ContentionGuard`), or
    "" when none did."""
    busy = [f"`{r['scene']}` {r['kernel_threads_reduced_steps']} of {r.get('rollouts', 1) * (r['frames'] - 1)} steps"
            for r in results
            if r.get("kernel_threads_reduced_steps")]
    if not busy:
        return ""
    return (f"Tasks waited for a CPU during the run (the kernel's stall counter; other processes, or this one's own "
            f"threads, held the cores): the collision kernels ran on 1 thread in {', '.join(busy)}, so those times "
            "are not a free machine's.")


def speed_markdown(results: list[dict], command: str, load: float | None = None) -> str:
    """The SPEED.md page for ``results`` (one :func:`bench` dict per scene, measured by ``command``)."""
    if not results:
        raise ValueError("no bench results")
    first = results[0]
    passes = first.get("rollouts", 1)
    settings = (f"{first['frames'] - 1} steps of each scene's family trajectory"
                + (f", timed over {passes} passes (the median over all {passes * (first['frames'] - 1)} steps; "
                   "\"passes\": the range of each pass's median)" if passes > 1 else "")
                + f", {first['threads']} torch thread(s), "
                f"{'compiled' if first.get('compiled') else 'eager'} network, correction "
                f"{'on' if first['correction'] else 'off'}, the self-contact stage where its column gives a time, "
                + ("the Predictor warmed up right before its timed steps, as the node does before it serves"
                   if first.get("warm_up_s", 0.0) > 0 else "the Predictor timed cold (no warm-up: `--cold`)"))
    fewer = [f"`{r['scene']}`" for r in results if r.get("network_threads", r["threads"]) < r["threads"]]
    if fewer:  # the Predictor times its compiled network on 1 thread against the request when it warms up
        settings += f"; the network itself on 1 thread, faster there at warm-up, on {', '.join(fewer)}"
    header = ("| scene | surface V / E / F | step median (p95) | graph / GNN / correction (median) | self-contact "
              "stage, median (p95) | IPC solver (median) | speedup | crossings before → after correction | relative "
              "displacement error | load |")
    table = "\n".join([header, "|---|---|---:|---|---:|---:|---:|---|---:|---:|", *(speed_row(r) for r in results)])
    note = busy_note(results)
    busy = f" {note}" if note else ""
    return (f"# Speed\n\n{provenance_line(command, load)}\n\n"
            f"`colgnn bench`: the Predictor (GNN step + collision-aware correction) and the project's IPC solver on "
            f"the same poses, one after the other in the same run, {settings}. Raw results: [bench/](bench). This page "
            f"is written by that command; do not edit it by hand.\n\n{table}\n\n"
            f"The load column is the 1-minute load average after each scene (above the core count the machine was "
            f"shared, and the times are inflated). The relative displacement error is ‖X − X_gt‖ / ‖X_gt − X_rest‖ "
            f"over the run (1.0: no better than \"nothing moves\"; [FIDELITY.md](FIDELITY.md)). "
            f"The paper: {PAPER_MS}.{busy}\n")


def write_speed_page(results: list[dict], page: Path, command: str) -> Path:
    """Write ``page`` and ``page.parent/bench/<scene>.json`` atomically; returns the page."""
    page = Path(page)
    text = speed_markdown(results, command)  # before the JSON files change: the page's code version is the run's
    json_dir = page.parent / "bench"
    json_dir.mkdir(parents=True, exist_ok=True)
    for r in results:
        with atomic_write(json_dir / f"{r['scene']}.json", "w") as fh:
            fh.write(json.dumps(r, indent=2) + "\n")
    with atomic_write(page, "w") as fh:
        fh.write(text)
    return page
