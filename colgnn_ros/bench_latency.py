"""End-to-end latency of the ``predictor`` node: poses in, meshes out, in separate processes over DDS.

Starts the node (``python -m colgnn_ros.predictor_node``) and ``pose_publisher`` (a looping scripted
motion at ``--rate`` Hz, 25 by default) as separate processes and listens from this process:

- latency: receive time of each ``deformed_mesh`` minus its stamp, which is the stamp the pose
  publisher gave the pose (its clock at publishing): pose→marker, through two DDS hops;
- mesh fraction: poses that produced a mesh (stamps matched) among the poses published, as seen by
  this process (a best-effort pose subscription; the last second is left out);
- the node's resident memory (VmRSS of its process tree) every second, with the slope after warm-up.

    .venv/bin/python -m colgnn_ros.bench_latency --scene sphere_mat --duration 60
    .venv/bin/python -m colgnn_ros.bench_latency --scene cone_bunny --checkpoint model.pt --duration 600 --json out.json

All on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless set), on ROS_DOMAIN_ID if set, else a
random domain. Exit 0 and a JSON summary on stdout's last line (and in ``--json``).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from visualization_msgs.msg import Marker

from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import stats
from colgnn_core.evaluation.provenance import provenance_line
from colgnn_core.io import atomic_write
from colgnn_core.learn.checkpoint import CheckpointMeta, read_checkpoint
from colgnn_core.runtime.models import shipped_checkpoint
from colgnn_ros.common import OUTPUT_QOS
from colgnn_ros.demo import child_env, stop
from msg_tools import stamp_to_ns
from msg_tools.markers import parse_marker_cdr

WARMUP_S = 3.0   # left out of the latency and memory slope: model load, first steps, DDS discovery


def tree_rss_mb(pid: int) -> float:
    """VmRSS (MB) of ``pid`` and its descendants (the venv's python may re-launch itself as a child)."""
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024.0
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
    return total


def run(args: argparse.Namespace) -> dict:
    checkpoint = Path(args.checkpoint) if args.checkpoint else shipped_checkpoint(args.scene)
    meta = CheckpointMeta(**read_checkpoint(checkpoint)["meta"])
    domain = int(os.environ.get("ROS_DOMAIN_ID") or random.SystemRandom().randint(20, 39))
    env = child_env(domain)
    py = sys.executable
    node_cmd = [py, "-m", "colgnn_ros.predictor_node", "--ros-args", "-p", f"scene:={meta.scene}",
                "-p", f"checkpoint:={checkpoint}", "-p", f"threads:={args.threads}",  # 0: the node chooses
                "-p", f"correction:={'true' if args.correction else 'false'}",
                "-p", f"color_by_distance:={'true' if args.color else 'false'}",
                "-p", f"step_on_arrival:={'false' if args.timer_only else 'true'}",
                "-p", f"compile:={'true' if args.compile else 'false'}"]
    pub_cmd = [py, "-m", "colgnn_ros.pose_publisher_node", "--ros-args", "-p", f"scene:={meta.scene}",
               "-p", f"resolution:={meta.resolution}", "-p", f"trajectory:={args.trajectory}",
               "-p", "frames:=250", "-p", f"rate:={float(args.rate)}", "-p", "loop:=true",
               "-p", "wait_for_subscribers:=2"]
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node_proc = pub_proc = None
    received: list[tuple[int, int]] = []   # (stamp ns, receive ns)
    sent: list[tuple[int, int]] = []       # (stamp ns, receive ns) of the poses
    rss: list[tuple[float, float]] = []    # (s since the first pose, MB)
    stopping = False

    def on_signal(*_):
        nonlocal stopping
        stopping = True
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        node = rclpy.create_node("colgnn_bench_latency", context=ctx)
        clock = node.get_clock()

        def on_mesh(raw: bytes) -> None:
            received.append((parse_marker_cdr(raw).stamp_ns, clock.now().nanoseconds))

        def on_pose(msg: PoseStamped) -> None:
            sent.append((stamp_to_ns(msg.header.stamp), clock.now().nanoseconds))
        node.create_subscription(Marker, "deformed_mesh", on_mesh, OUTPUT_QOS, raw=True)
        diag: dict = {}

        def on_diag(msg: DiagnosticArray) -> None:
            for st in msg.status:
                if st.name.startswith("predictor"):
                    diag.clear()
                    diag.update({kv.key: kv.value for kv in st.values})
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, OUTPUT_QOS)
        node.create_subscription(PoseStamped, "tool_pose", on_pose,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        node_proc = subprocess.Popen(node_cmd, env=env, stdout=subprocess.DEVNULL if args.quiet else None,
                                     stderr=subprocess.STDOUT if args.quiet else None)
        pub_proc = subprocess.Popen(pub_cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 90.0
        while not sent and not stopping:
            if time.monotonic() > deadline or node_proc.poll() is not None or pub_proc.poll() is not None:
                raise RuntimeError("the node or the pose publisher did not start (or exited)")
            executor.spin_once(timeout_sec=0.05)
        t0 = time.monotonic()
        next_rss = t0
        while not stopping and time.monotonic() - t0 < args.duration:
            executor.spin_once(timeout_sec=0.02)
            if time.monotonic() >= next_rss:
                rss.append((time.monotonic() - t0, tree_rss_mb(node_proc.pid)))
                next_rss += 1.0
            if node_proc.poll() is not None:
                raise RuntimeError(f"the node exited with code {node_proc.returncode}")
        stop(pub_proc)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
        code = stop(node_proc)
        executor.shutdown()
        node.destroy_node()
    finally:
        stop(pub_proc)
        stop(node_proc)
        for s, h in old.items():
            signal.signal(s, h)
        rclpy.try_shutdown(context=ctx)

    first = sent[0][1]
    warm = first + int(WARMUP_S * 1e9)
    last_ok = sent[-1][1] - int(1e9)  # the newest poses may still be in flight when the publisher stops
    meshes = dict(received)
    counted = [s for s, r in sent if warm <= r <= last_ok]
    latency_ms = np.array([(meshes[s] - s) * 1e-6 for s in counted if s in meshes])
    latency = stats(latency_ms, empty=float("nan"))
    t = np.array([x for x, _ in rss])
    mb = np.array([y for _, y in rss])
    after = t >= min(WARMUP_S + 7.0, t[-1] / 2) if len(t) else t
    slope = float(np.polyfit(t[after], mb[after], 1)[0] * 60.0) if after.sum() >= 3 else float("nan")
    return {
        "scene": meta.scene, "resolution": meta.resolution, "checkpoint": str(checkpoint), "rate_hz": args.rate,
        "threads": args.threads, "compile": args.compile, "correction": args.correction,
            "step_on_arrival": not args.timer_only, "duration_s": round(float(t[-1]) if len(t) else 0, 1),
        "poses": len(counted), "meshes": int(len(latency_ms)),
        "mesh_fraction": float(len(latency_ms) / len(counted)) if counted else 0.0,
        "latency_ms_median": latency["median"], "latency_ms_p95": latency["p95"],
        "latency_ms_max": float(latency_ms.max()) if latency_ms.size else float("nan"),
        "rss_mb_start": float(mb[after][0]) if after.sum() else float("nan"),
        "rss_mb_end": float(mb[-1]) if len(mb) else float("nan"),
        "rss_mb_per_min": slope, "node_exit_code": code,
        "rss_mb_every_10s": [round(float(y), 1) for x, y in rss[::10]],
        "node_diagnostics": dict(diag),  # the node's last /diagnostics: step ms, superseded and rejected poses
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="colgnn_bench_latency", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="sphere_mat")
    ap.add_argument("--checkpoint", default=None, help="model (.pt); default: the scene's shipped model")
    ap.add_argument("--rate", type=float, default=25.0, help="poses per second (default 25)")
    ap.add_argument("--duration", type=float, default=30.0,
                    help="seconds of poses (default 30; 600 for the memory check)")
    ap.add_argument("--trajectory", default="press", help="pose_publisher's scripted motion, looped (default press)")
    ap.add_argument("--threads", type=int, default=0, help="the node's torch threads (default 0: the node's "
                    "choice for the machine)")
    ap.add_argument("--compile", action=argparse.BooleanOptionalAction, default=True,
                    help="the node torch.compiles its network at start-up (default: yes, as the node)")
    ap.add_argument("--no-correction", dest="correction", action="store_false")
    ap.add_argument("--no-color", dest="color", action="store_false", help="no per-vertex colours in the marker")
    ap.add_argument("--timer-only", action="store_true",
                    help="step_on_arrival:=false: only the dt timer steps (up to dt more latency)")
    ap.add_argument("--json", default=None, help="also write the summary here")
    ap.add_argument("--markdown", default=None, metavar="FILE",
                    help="also write the result as a page (docs/LATENCY.md), with command, machine and load")
    ap.add_argument("--quiet", action="store_true", help="hide the node's log")
    args = ap.parse_args(argv)
    try:
        result = run(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"benchmark failed: {exc}", file=sys.stderr)
        return 1
    print(f"{result['scene']} ({result['resolution']}), {result['rate_hz']:g} Hz poses, {result['duration_s']} s: "
          f"latency median {result['latency_ms_median']:.1f} ms, p95 {result['latency_ms_p95']:.1f} ms, "
          f"max {result['latency_ms_max']:.1f} ms; {100 * result['mesh_fraction']:.1f}% of {result['poses']} poses "
          f"gave a mesh; node RSS {result['rss_mb_start']:.0f} -> {result['rss_mb_end']:.0f} MB "
          f"({result['rss_mb_per_min']:+.2f} MB/min)")
    print(json.dumps(result))
    if args.json:
        with atomic_write(args.json, "w") as fh:
            fh.write(json.dumps(result, indent=2) + "\n")
    if args.markdown:
        command = "colgnn_bench_latency " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
        with atomic_write(args.markdown, "w") as fh:
            fh.write(latency_markdown(result, provenance_line(command)))
        print(f"wrote {args.markdown}")
    return 0


def latency_markdown(r: dict, provenance: str) -> str:
    """The page ``--markdown`` writes: one run's latency, mesh fraction and memory."""
    diag = r.get("node_diagnostics") or {}
    rows = [
        ("run", f"`{r['scene']}` ({r['resolution']}), `{Path(r['checkpoint']).name}`, {r['rate_hz']:g} Hz looping "
                f"poses, {r['duration_s']} s, threads {r['threads'] or 'node default'}, "
                f"{'compiled' if r['compile'] else 'eager'}, correction {'on' if r['correction'] else 'off'}"),
        ("pose → mesh latency median / p95 / max",
         f"**{r['latency_ms_median']:.1f} / {r['latency_ms_p95']:.1f} / {r['latency_ms_max']:.1f} ms**"),
        ("poses that gave a mesh", f"**{100 * r['mesh_fraction']:.1f}%** of {r['poses']}"),
        ("node step median / p95 (its /diagnostics)",
         f"{float(diag.get('step_ms_median', 'nan')):.1f} / {float(diag.get('step_ms_p95', 'nan')):.1f} ms"),
        ("node memory (RSS)", f"{r['rss_mb_start']:.0f} → {r['rss_mb_end']:.0f} MB ({r['rss_mb_per_min']:+.2f} "
                              f"MB/min fitted after warm-up)"),
    ]
    table = "\n".join(["| | |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)])
    return (f"# Latency\n\n{provenance}\n\n`colgnn_bench_latency` runs the `predictor` node and a looping "
            f"`pose_publisher` as separate processes over DDS and measures, from a third, the latency from each "
            f"pose's stamp to the receipt of its mesh. This page is written by that command; do not edit it by "
            f"hand.\n\n{table}\n")


if __name__ == "__main__":
    raise SystemExit(main())
