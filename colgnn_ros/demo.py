"""``make demo``: the predictor node live on ``sphere_mat``, recorded, rendered and summarised.

Starts two processes, the ``predictor`` node (the scene's shipped model, or ``--checkpoint``) and
``pose_publisher`` with a scripted press at the model's rate, records their topics (rosbag2, MCAP)
from this process with :class:`msg_tools.recorder.TopicRecorder` for the length of the trajectory
(``--duration``, 10 s), stops the node, reads the recording back, rebuilds the object and tool
meshes from the markers and renders a picture strip with :func:`colgnn_core.evaluation.render.render_strip`.
It prints a summary (steps, step ms, end-to-end pose→marker latency, collisions before and after
the correction) and writes it as JSON. Outputs, under ``--out`` (``out/demo``)::

    bag/            rosbag2 folder (MCAP): open it in Foxglove, or `ros2 bag play` + RViz
    demo.png        the rendered strip (3-D views and cross-sections through the contact)
    summary.json    the printed numbers
    summary.md      the same as a table (with --docs also written to DOCS/DEMO.md, picture in DOCS/img/demo.png)

Run with the venv's interpreter (``.venv/bin/colgnn_demo`` or ``.venv/bin/python -m colgnn_ros.demo``).
ROS traffic stays on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless set) on
``ROS_DOMAIN_ID`` if set, else on a random domain (printed). Exit code 0 on success, 2 on bad
input (e.g. no model for the scene), 1 if the run failed; the child processes are always stopped.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from colgnn_core.collision.exact import has_intersections
from colgnn_core.collision.metrics import triangle_pairs_intersecting
from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import stats
from colgnn_core.evaluation.provenance import provenance_line
from colgnn_core.evaluation.render import render_strip
from colgnn_core.io import Sequence
from colgnn_core.learn.checkpoint import CheckpointMeta, read_checkpoint
from colgnn_core.runtime.models import shipped_checkpoint
from msg_tools import diagnostic_values, msg_to_counts, pose_to_array, stamp_to_ns
from msg_tools.recorder import TopicRecorder, read_bag_messages

MESSAGE_WAIT_S = 60.0     # start-up budget: both nodes up and matched (torch + model load)
QUIET_AFTER_S = 1.0       # after the last pose: stop once no mesh arrived for this long
DIAG_NAME = "predictor: {scene}"


def child_env(domain: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return env


def stop(proc: subprocess.Popen | None, sig: int = signal.SIGINT, timeout: float = 10.0) -> int | None:
    """Signal a child and wait; kill it if it does not end. Returns its exit code."""
    if proc is None:
        return None
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


# ----------------------------------------------------------------------------- reading the recording

def read_recording(bag: Path, scene) -> dict:
    """The recorded run as arrays: meshes/tools per step, their stamps and receive times, counts, poses, diagnostics."""
    faces = np.asarray(scene.object.faces, dtype=np.int64)
    surface_ids = np.unique(faces)
    local = np.full(scene.object.vertices.shape[0], -1, dtype=np.int64)
    local[surface_ids] = np.arange(len(surface_ids))
    local_faces = local[faces].reshape(-1)
    tool_faces = np.asarray(scene.tool.faces, dtype=np.int64).reshape(-1)

    meshes, tools, counts, poses, diags = {}, {}, [], {}, []
    for topic, t_ns, msg in read_bag_messages(bag, deserializer="marker"):
        if topic == "/deformed_mesh":
            v = np.empty((len(surface_ids), 3))
            v[local_faces] = msg.corners.reshape(-1, 3)  # every surface vertex is a corner of some face
            meshes[msg.stamp_ns] = (v, t_ns)
        elif topic == "/tool_marker":
            v = np.empty((scene.tool.vertices.shape[0], 3))
            v[tool_faces] = msg.corners.reshape(-1, 3)
            tools[msg.stamp_ns] = v
        elif topic == "/collision_counts":
            counts.append(msg_to_counts(msg))
        elif topic == "/tool_pose":
            poses[stamp_to_ns(msg.header.stamp)] = pose_to_array(msg)
        elif topic == "/diagnostics":
            for st in msg.status:
                if st.name == DIAG_NAME.format(scene=scene.name):
                    diags.append(diagnostic_values(msg, st.name))
    stamps = sorted(s for s in meshes if s in tools and s in poses)
    return {
        "stamps": np.array(stamps, dtype=np.int64),
        "object": np.stack([meshes[s][0] for s in stamps]) if stamps else np.zeros((0, len(surface_ids), 3)),
        "received_ns": np.array([meshes[s][1] for s in stamps], dtype=np.int64),
        "tool": np.stack([tools[s] for s in stamps]) if stamps else np.zeros((0, len(scene.tool.vertices), 3)),
        "poses": np.stack([poses[s] for s in stamps]) if stamps else np.zeros((0, 7)),
        "faces": local[faces],
        "surface_ids": surface_ids,
        "counts": counts,
        "diagnostics": diags,
        "poses_recorded": len(poses),
        "meshes_recorded": len(meshes),
    }


def strip_frames(tool_z: np.ndarray, count: int = 5) -> list[int]:
    """Frames of the first press: rest, going down, deepest, coming up, back up (or evenly spaced)."""
    T = len(tool_z)
    if T < count:
        return list(range(T))
    deepest = int(np.argmin(tool_z[: max(2, T // 2)] if T > 40 else tool_z))
    top = float(tool_z[0])
    up = next((i for i in range(deepest, T) if tool_z[i] >= top - 0.1 * (top - tool_z[deepest])), T - 1)
    frames = sorted({0, deepest // 2, deepest, (deepest + up) // 2, up})
    return frames if len(frames) == count else sorted({int(round(x)) for x in np.linspace(0, T - 1, count)})


def render(rec: dict, scene, out: Path, label: str) -> Path:
    seq = Sequence(object_positions=rec["object"], object_faces=rec["faces"], tool_positions=rec["tool"],
                   tool_faces=np.asarray(scene.tool.faces, dtype=np.int64), tool_poses=rec["poses"],
                   dt=float(scene.dt)).validate("recording")
    return render_strip([seq], [label], out, frames=strip_frames(rec["poses"][:, 2]))


def summarise(rec: dict, published: int) -> dict:
    latency_ms = (rec["received_ns"] - rec["stamps"]) * 1e-6
    latency = stats(latency_ms, empty=float("nan"))
    last = rec["diagnostics"][-1] if rec["diagnostics"] else {}
    total = {k: int(sum(c.get(k, 0) for c in rec["counts"])) for k in
             ("vertex_face_before", "edge_edge_before", "vertex_face_after", "edge_edge_after",
              "penetrating_vertices_after", "fallback", "substeps")}
    return {
        "poses_published": published,
        "meshes_received": int(len(rec["stamps"])),
        "mesh_fraction": float(len(rec["stamps"]) / published) if published else 0.0,
        "steps": int(last.get("steps", len(rec["stamps"]))),
        "step_ms_median": float(last.get("step_ms_median", "nan")),
        "step_ms_p95": float(last.get("step_ms_p95", "nan")),
        "latency_ms_median": latency["median"],
        "latency_ms_p95": latency["p95"],
        "rejected_poses": int(last.get("rejected_total", 0)),
        "collisions_before": {"vertex_face": total["vertex_face_before"], "edge_edge": total["edge_edge_before"]},
        "collisions_after": {"vertex_face": total["vertex_face_after"], "edge_edge": total["edge_edge_after"]},
        "penetrating_vertices_after": total["penetrating_vertices_after"],
        "fallbacks": total["fallback"],
    }


def exact_check(rec: dict, scene, every: int = 10) -> tuple[int, int]:
    """(frames whose object and tool triangles intersect, of all recorded steps;
    frames where ipctk.has_intersections, which also counts object self-intersections, finds any, of every
    ``every``-th step)."""
    faces, tool_faces = rec["faces"], np.asarray(scene.tool.faces, dtype=np.int64)
    tool_hits = sum(len(triangle_pairs_intersecting(rec["object"][i], faces, rec["tool"][i], tool_faces)) > 0
                    for i in range(len(rec["stamps"])))
    any_hits = sum(has_intersections(rec["object"][i], faces, rec["tool"][i], tool_faces)
                   for i in range(0, len(rec["stamps"]), every))
    return int(tool_hits), int(any_hits)


def node_parameters(scene: str, checkpoint: Path, args: argparse.Namespace) -> list[str]:
    """The predictor's ``-p name:=value`` arguments: the node's defaults unless the demo's flags set them."""
    params = {"scene": scene, "checkpoint": str(checkpoint)}
    if args.threads is not None:
        params["threads"] = str(args.threads)
    if args.foxglove:
        params["foxglove_port"] = str(args.foxglove)
    if args.self_contact is not None:
        params["self_contact"] = str(args.self_contact).lower()
    return [a for k, v in params.items() for a in ("-p", f"{k}:={v}")]


def startup_seconds(log: Path) -> float | None:
    """The node's start-up time, from its 'ready in X s' log line (None if absent)."""
    match = re.search(r"ready in ([0-9.]+) s", log.read_text(errors="replace")) if log.is_file() else None
    return float(match.group(1)) if match else None


def summary_markdown(s: dict, provenance: str) -> str:
    """The demo's summary as a markdown page (what ``--docs`` writes to DEMO.md)."""
    rows = [
        ("poses meshed", f"{s['meshes_received']} of {s['poses_published']} ({100 * s['mesh_fraction']:.1f}%)"),
        ("rejected poses", f"{s['rejected_poses']}"),
        ("node step, median (p95)", f"{s['step_ms_median']:.1f} ms ({s['step_ms_p95']:.1f} ms)"),
        ("pose → marker latency, median (p95)", f"{s['latency_ms_median']:.1f} ms ({s['latency_ms_p95']:.1f} ms)"),
        ("node start-up (launch to ready)", "unknown" if s.get("startup_s") is None else f"{s['startup_s']:.1f} s"),
        ("node settings", f"{s.get('node_threads', '?')} thread(s), {s.get('node_network', '?')} network"),
        ("collisions before correction (vertex-face, edge-edge)",
         f"{s['collisions_before']['vertex_face']}, {s['collisions_before']['edge_edge']}"),
        ("collisions after correction (vertex-face, edge-edge)",
         f"{s['collisions_after']['vertex_face']}, {s['collisions_after']['edge_edge']}"),
        ("frames whose mesh intersects the tool (exact, every frame)",
         f"{s['tool_intersecting_frames']} of {s['meshes_received']}"),
        ("frames with any intersection, self included (ipctk, every 10th)",
         f"{s['ipctk_intersecting_frames_every_10th']} of {(s['meshes_received'] + 9) // 10}"),
        ("demo wall time (start-up, run, check, picture)", f"{s['wall_s']:.0f} s"),
    ]
    table = "\n".join(["| | |", "|---|---:|", *(f"| {k} | {v} |" for k, v in rows)])
    return (f"# The latest `make demo`\n\n{provenance}\n\n"
            f"Scene `{s['scene']}` ({s['resolution']}), model `{Path(s['checkpoint']).name}`, trajectory "
            f"`{s['trajectory']}`, dt {s['dt']:g} s, the predictor node's default parameters unless stated above. "
            f"This page is written by the demo itself; do not edit it by hand.\n\n{table}\n\n"
            f"![demo](img/demo.png)\n\nThe recording (`out/demo/bag`, rosbag2 MCAP) opens in Foxglove (3D panel: "
            f"`/deformed_mesh` and `/tool_marker`; Plot or Raw Messages: `/collision_counts`, `/diagnostics`) and "
            f"plays with `ros2 bag play out/demo/bag` into RViz (Marker displays on the same two topics).\n")


def write_docs(s: dict, picture: Path, docs: Path, provenance: str) -> Path:
    """DEMO.md and img/demo.png in ``docs`` (atomically: a reader never sees half a page)."""
    (docs / "img").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(picture, docs / "img" / "demo.png.tmp")
    os.replace(docs / "img" / "demo.png.tmp", docs / "img" / "demo.png")
    page = docs / "DEMO.md"
    tmp = page.with_suffix(".md.tmp")
    tmp.write_text(summary_markdown(s, provenance))
    os.replace(tmp, page)
    return page


def node_settings(log: Path) -> tuple[str, str]:
    """(threads, 'compiled' or 'eager') from the node's start-up log line."""
    text = log.read_text(errors="replace") if log.is_file() else ""
    match = re.search(r"(\d+) thread\(s\), (compiled|eager) network", text)
    return (match.group(1), match.group(2)) if match else ("?", "?")


# ----------------------------------------------------------------------------- the run

def run(args: argparse.Namespace) -> int:
    started = time.monotonic()
    checkpoint = Path(args.checkpoint) if args.checkpoint else shipped_checkpoint(args.scene)
    meta = CheckpointMeta(**read_checkpoint(checkpoint)["meta"])
    if meta.scene != args.scene:
        raise InputError(f"--checkpoint {checkpoint} is a {meta.scene!r} model, not {args.scene!r}")
    scene = meta.load_scene()
    rate = 1.0 / meta.dt
    frames = max(2, int(round(args.duration * rate)))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag, picture, summary_file = out / "bag", out / "demo.png", out / "summary.json"
    shutil.rmtree(bag, ignore_errors=True)
    domain = int(os.environ.get("ROS_DOMAIN_ID") or random.SystemRandom().randint(20, 39))
    env = child_env(domain)
    print(f"demo: scene {scene.name} ({scene.resolution}), checkpoint {checkpoint}, dt {meta.dt:g} s; "
          f"'{args.trajectory}' for {frames} poses at {rate:g} Hz; ROS_DOMAIN_ID={domain}", flush=True)

    py = sys.executable
    logs = {name: open(out / f"{name}.log", "w") for name in ("predictor", "pose_publisher")}
    predictor = publisher = None
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    interrupted = False

    def on_signal(*_):
        nonlocal interrupted
        interrupted = True
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        node = rclpy.create_node("colgnn_demo_recorder", context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        predictor = subprocess.Popen(
            [py, "-m", "colgnn_ros.predictor_node", "--ros-args", *node_parameters(scene.name, checkpoint, args)],
            env=env, stdout=logs["predictor"], stderr=subprocess.STDOUT)
        publisher = subprocess.Popen(
            [py, "-m", "colgnn_ros.pose_publisher_node", "--ros-args", "-p", f"scene:={scene.name}",
             "-p", f"resolution:={scene.resolution}", "-p", f"trajectory:={args.trajectory}",
             "-p", f"frames:={frames}", "-p", f"rate:={rate}", "-p", "wait_for_subscribers:=2"],
            env=env, stdout=logs["pose_publisher"], stderr=subprocess.STDOUT)
        with TopicRecorder(node, bag, compression="zstd") as recorder:
            def spin_while(cond, timeout: float) -> bool:
                end = time.monotonic() + timeout
                while cond() and not interrupted:
                    if time.monotonic() > end:
                        return False
                    executor.spin_once(timeout_sec=0.02)
                return not interrupted
            # 1. until the publisher has finished its trajectory (it waits for the node and us first)
            budget = MESSAGE_WAIT_S + frames / rate + 10.0
            finished = spin_while(lambda: publisher.poll() is None and predictor.poll() is None, budget)
            if predictor.poll() is not None:
                raise RuntimeError(f"the predictor exited with code {predictor.returncode}; see "
                                   f"{out / 'predictor.log'}")
            if not finished:
                raise RuntimeError("interrupted" if interrupted else "the pose publisher did not finish in time")
            if publisher.returncode != 0:
                raise RuntimeError(f"the pose publisher exited with code {publisher.returncode}; "
                                   f"see {out / 'pose_publisher.log'}")
            # 2. the last meshes, then one more diagnostics message
            count = lambda: recorder.counts.get("/deformed_mesh", 0)  # noqa: E731
            last, last_t = count(), time.monotonic()
            while not interrupted and time.monotonic() - last_t < QUIET_AFTER_S:
                executor.spin_once(timeout_sec=0.05)
                if count() != last:
                    last, last_t = count(), time.monotonic()
            n_diag = recorder.counts.get("/diagnostics", 0)
            spin_while(lambda: recorder.counts.get("/diagnostics", 0) == n_diag, 2.0)
            code = stop(predictor, signal.SIGINT)
            if code != 0:
                raise RuntimeError(f"the predictor exited with code {code}; see {out / 'predictor.log'}")
            counts = recorder.counts
        executor.shutdown()
        node.destroy_node()
    finally:
        for proc in (publisher, predictor):
            stop(proc)
        for f in logs.values():
            f.close()
        for s, h in old.items():
            signal.signal(s, h)
        rclpy.try_shutdown(context=ctx)

    print("recorded " + ", ".join(f"{t} {n}" for t, n in sorted(counts.items())) + f" -> {bag}", flush=True)
    rec = read_recording(bag, scene)
    if len(rec["stamps"]) < 2:
        raise RuntimeError(f"only {len(rec['stamps'])} meshes recorded; see {out / 'predictor.log'}")
    s = summarise(rec, frames)
    s["tool_intersecting_frames"], s["ipctk_intersecting_frames_every_10th"] = exact_check(rec, scene)
    s.update(scene=scene.name, resolution=scene.resolution, checkpoint=str(checkpoint), dt=meta.dt,
             trajectory=args.trajectory, bag=str(bag), picture=str(picture))
    render(rec, scene, picture, "node")
    s["startup_s"] = startup_seconds(out / "predictor.log")
    s["node_threads"], s["node_network"] = node_settings(out / "predictor.log")
    s["wall_s"] = time.monotonic() - started
    summary_file.write_text(json.dumps(s, indent=2) + "\n")
    markdown = summary_markdown(s, provenance_line(args.command))
    (out / "summary.md").write_text(markdown)
    print(markdown)
    if args.docs:
        print(f"wrote {write_docs(s, picture, Path(args.docs), provenance_line(args.command))}")
    print(f"steps: {s['steps']} ({s['meshes_received']} meshes for {s['poses_published']} poses, "
          f"{100 * s['mesh_fraction']:.1f}%), rejected poses {s['rejected_poses']}")
    print(f"step ms: median {s['step_ms_median']:.1f}, p95 {s['step_ms_p95']:.1f}")
    print(f"end-to-end pose->marker latency ms: median {s['latency_ms_median']:.1f}, p95 {s['latency_ms_p95']:.1f}")
    cb, ca = s["collisions_before"], s["collisions_after"]
    print(f"collisions before correction: vertex-face {cb['vertex_face']}, edge-edge {cb['edge_edge']}; "
          f"after: vertex-face {ca['vertex_face']}, edge-edge {ca['edge_edge']} "
          f"(fallbacks {s['fallbacks']})")
    print(f"exact check of the recorded meshes: object-tool intersections in {s['tool_intersecting_frames']} of "
          f"{s['meshes_received']} frames; ipctk.has_intersections (object-tool or object self-intersection) in "
          f"{s['ipctk_intersecting_frames_every_10th']} of {(s['meshes_received'] + 9) // 10} frames checked")
    print(f"wrote {bag}, {picture}, {summary_file}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="colgnn_demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="sphere_mat")
    ap.add_argument("--checkpoint", default=None, help="model (.pt); default: the scene's shipped model")
    ap.add_argument("--trajectory", default="press", help="pose_publisher's scripted motion (default press)")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of poses to record (default 10)")
    ap.add_argument("--threads", type=int, default=None, help="the node's torch threads (default: the node's, chosen "
                    "for the machine)")
    ap.add_argument("--self-contact", action=argparse.BooleanOptionalAction, default=None,
                    help="the node's self-contact stage on or off (default: the scene's [correction] self_contact)")
    ap.add_argument("--foxglove", type=int, default=0, metavar="PORT",
                    help="also stream the scene live to Foxglove on ws://localhost:PORT (default 0: off)")
    ap.add_argument("--docs", default=None, help="also write DOCS/DEMO.md and DOCS/img/demo.png (make demo: docs)")
    ap.add_argument("--command", default="python -m colgnn_ros.demo", help=argparse.SUPPRESS)
    ap.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    args = ap.parse_args(argv)
    if not 0.1 <= args.duration <= 3600:
        ap.error(f"--duration must be in [0.1, 3600] s, got {args.duration}")
    try:
        return run(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"demo failed: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
