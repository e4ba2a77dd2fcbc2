"""docs/stability/README.md's table as ``colgnn bench --stability --scene S --markdown PAGE`` writes it.

Each run writes ``<scene>.json`` beside ``PAGE`` (with its command, code version, load and time), then rebuilds
the page's generated block from every ``*.json`` there, one row per scene: the scenes can be run one at a time, in
different sessions, and each row still says where it came from. Prose around the block stays as written.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

from colgnn_core.evaluation.provenance import code_version, load_average, machine
from colgnn_core.io import atomic_write, write_generated_section

SECTION = "stability"


def stability_row(r: dict) -> str:
    """One markdown row of a :func:`colgnn_core.evaluation.stability.stability` result (with provenance)."""
    def pct(x: float) -> str:
        return f"{100 * x:.2f}"

    load = r.get("load_average_1min")
    stage = "yes" if r.get("self_contact") else "no"
    return (f"| `{r['scene']}` ({r['resolution']}) | {stage} | {r['random_steps']:,} + {r['leave_and_settle_steps']} "
            f"| {r['tool_intersecting_frames']} ({r['checked_frames']:,}) | {r['self_intersecting_frames']} | "
            f"{r.get('invalid_surface_frames', '–')} | {r['fallbacks']} | "
            f"{r['rss_mb_start']:.0f} → {r['rss_mb_end']:.0f} | {r['rss_mb_per_1000_steps']:+.2f} | "
            f"{pct(r['rest_rmse_fraction'])} / {pct(r['rest_max_fraction'])} | {r['step_ms_median']:.1f} "
            f"({r['threads']}) | {r['wall_s'] / 60:.0f} min | "
            f"{'–' if load is None else f'{load:.1f}'} | {r.get('machine', 'not recorded')} | "
            f"{r.get('code', 'not recorded')} {r.get('measured_utc', '')} |")


def stability_markdown(results: list[dict]) -> str:
    """The generated block: the exact command of each row, then the table."""
    header = ("| scene | self-contact stage | steps | tool-intersecting frames (checked) | self-intersecting frames | "
              "frames with flipped or degenerate faces | fallbacks | RSS start → end (MB) | MB per 1,000 steps | "
              "shape after the tool left: RMSE / max (% bbox diag.) | step ms median (threads) | wall | load | "
              "machine | code, measured |")
    table = "\n".join([header, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
                       *(stability_row(r) for r in results)])
    commands = "\n".join(f"{r.get('command', '(command not recorded)')}" for r in results)
    return ("Written by `colgnn bench --stability ... --markdown` from the files `<scene>.json` in this folder; do "
            "not edit by hand. Each row gives the machine it ran on (rows from before session 52 did not record it) "
            "and the 1-minute load average when it finished (above the machine's cores they were shared, and the "
            "step times are inflated). The commands:\n\n"
            f"```bash\n{commands}\n```\n\n{table}\n")


def write_stability_page(result: dict, page: str | Path, command: str) -> Path:
    """Store ``result`` as ``<scene>.json`` beside ``page`` (with its provenance) and rebuild the page's table."""
    page = Path(page)
    folder = page.parent
    folder.mkdir(parents=True, exist_ok=True)
    m = machine()
    stamped = {**result, "command": command, "code": code_version(), "load_average_1min": load_average(),
               "machine": f"{m.cpu} ({m.cores} cores)",
               "measured_utc": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    with atomic_write(folder / f"{result['scene']}.json", "w") as fh:
        fh.write(json.dumps(stamped, indent=2) + "\n")
    results = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
    return write_generated_section(page, SECTION, stability_markdown(results))
