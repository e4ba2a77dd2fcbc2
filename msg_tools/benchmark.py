"""Benchmark of the ways to build a TRIANGLE_LIST Marker with rclpy Jazzy.

    .venv/bin/python -m msg_tools.benchmark [--vertices 6000] [--faces 12000] [--repeats 20] [--publish]

Options measured (median ms over `repeats`, per frame of a mesh whose
vertices move every frame):
- ``naive``: a new Marker with one geometry_msgs/Point (and ColorRGBA) per corner;
- ``pool``: preallocated Point/ColorRGBA objects whose fields are updated in place;
- ``cdr``: :class:`msg_tools.markers.TriangleListMarker`, CDR bytes spliced from numpy;
- ``*_serialize``: what publishing a message *object* adds on top (rclpy converts
  every Point to C and serializes; ``serialize_message`` does exactly that work);
- ``receive_*``: reading a received Marker: ``deserialize_message`` vs
  :func:`msg_tools.markers.parse_marker_cdr` on the raw bytes;
- ``numpy_points_publishable``: whether rclpy can publish an ndarray as ``Marker.points``
  (it takes arrays for sequences of primitives only).
With ``publish=True`` the time of ``Publisher.publish`` itself (one matched
subscriber in the same process) is measured for a message object (includes its
conversion to C) and for already built bytes, on ROS_DOMAIN_ID (default 97).

Measured on the development machine (2 CPU cores shared with other jobs),
6084 vertices, 12000 faces = 36000 corners, per-corner colours, median ms:
naive build 121-145 + conversion 49; point pool 86-94 + 54; CDR splice 0.20
(plus colormap 0.09); Publisher.publish of the message 53-54, of the bytes 0.07.
Without colours: naive 62 + 23, pool 15 + 26, CDR 0.14. Receiving:
deserialize_message 120-165, parse_marker_cdr 0.04-0.14. Build + publish bytes +
Fast DDS delivery in one process + parse: 3.6 ms (``dds_build_to_parse_ms``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable

import numpy as np
import rclpy
from geometry_msgs.msg import Point
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

from .conversions import triangle_marker_naive
from .markers import DistanceColormap, TriangleListMarker, parse_marker_cdr


def grid_mesh(n_vertices: int, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A wavy square sheet with ceil(sqrt(n_vertices))**2 vertices and exactly n_faces triangles (0.3 m wide)."""
    side = max(2, int(np.ceil(np.sqrt(n_vertices))))
    u, v = np.meshgrid(np.linspace(0, 0.3, side), np.linspace(0, 0.3, side), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), 0.01 * np.sin(40 * u.ravel()) * np.cos(30 * v.ravel())], axis=1)
    i, j = np.meshgrid(np.arange(side - 1), np.arange(side - 1), indexing="ij")
    a = (i * side + j).ravel()
    quads = np.stack([np.stack([a, a + side, a + 1], 1), np.stack([a + 1, a + side, a + side + 1], 1)], 1)
    faces = quads.reshape(-1, 3)
    faces = np.resize(faces, (int(n_faces), 3))  # repeat rows if more faces than the grid has
    return verts, faces


def _median_ms(fn: Callable[[int], object], repeats: int) -> float:
    fn(0)  # warm-up (allocations, first-touch)
    times = []
    for k in range(repeats):
        t0 = time.perf_counter()
        fn(k + 1)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def bench_marker(n_vertices: int = 6000, n_faces: int = 12000, repeats: int = 10,
                 colors: bool = True, publish: bool = False) -> dict:
    """Median build/serialize/publish ms of each Marker-building option (see module docstring)."""
    verts, faces = grid_mesh(n_vertices, n_faces)
    n = verts.shape[0]
    k = faces.size
    rng = np.random.default_rng(0)
    frames = [verts + rng.normal(scale=1e-3, size=verts.shape) for _ in range(3)]
    cmap = DistanceColormap(0.0, 0.02)
    vcols = [cmap(f[:, 2] + 0.01) for f in frames] if colors else [None] * 3
    out: dict = {"n_vertices": n, "n_faces": int(faces.shape[0]), "n_corners": int(k),
                 "colors": colors, "repeats": repeats}

    # naive: a fresh list of Point objects per frame
    last: dict = {}

    def naive(i: int) -> None:
        last["naive"] = triangle_marker_naive(frames[i % 3], faces, colors=vcols[i % 3], stamp=i)
    out["naive_build_ms"] = _median_ms(naive, repeats)
    out["naive_serialize_ms"] = _median_ms(lambda i: serialize_message(last["naive"]), repeats)

    # pool: preallocated message objects, fields updated in place
    pool_pts = [Point() for _ in range(k)]
    pool_cols = [ColorRGBA() for _ in range(k)] if colors else []
    pool_msg = triangle_marker_naive(frames[0], faces, colors=vcols[0])

    def pool(i: int) -> None:
        corners = frames[i % 3][faces.reshape(-1)].tolist()
        for p, (x, y, z) in zip(pool_pts, corners):
            p.x = x
            p.y = y
            p.z = z
        pool_msg.points = pool_pts
        if colors:
            for q, (r, g, b, a) in zip(pool_cols, vcols[i % 3][faces.reshape(-1)].tolist()):
                q.r = r
                q.g = g
                q.b = b
                q.a = a
            pool_msg.colors = pool_cols
        pool_msg.header.stamp.sec = i
    out["pool_build_ms"] = _median_ms(pool, repeats)
    out["pool_serialize_ms"] = _median_ms(lambda i: serialize_message(pool_msg), repeats)

    out["numpy_points_publishable"] = _numpy_points_publishable(k)

    # cdr: template + numpy splice
    t0 = time.perf_counter()
    builder = TriangleListMarker(faces, n, per_vertex_colors=colors)
    out["cdr_setup_ms"] = (time.perf_counter() - t0) * 1e3
    out["cdr_build_ms"] = _median_ms(lambda i: builder.build(frames[i % 3], i, colors=vcols[i % 3]),
                                     max(repeats, 50))
    out["colormap_ms"] = _median_ms(lambda i: cmap(frames[i % 3][:, 2]), max(repeats, 50))
    raw = builder.build(frames[0], 0, colors=vcols[0])
    out["cdr_bytes"] = len(raw)
    # the receiving side: rclpy's deserialization into Point objects vs the numpy parser
    out["receive_deserialize_ms"] = _median_ms(lambda i: deserialize_message(raw, Marker), min(repeats, 5))
    out["receive_parse_cdr_ms"] = _median_ms(lambda i: parse_marker_cdr(raw), max(repeats, 50))
    out["naive_total_ms"] = out["naive_build_ms"] + out["naive_serialize_ms"]
    out["pool_total_ms"] = out["pool_build_ms"] + out["pool_serialize_ms"]
    if publish:
        out.update(_bench_publish(builder, pool_msg, frames, vcols, repeats))
    return out


def _numpy_points_publishable(k: int) -> bool:
    """Can Marker.points be an ndarray [k,3]? (The setter only checks with ROS_PYTHON_CHECK_FIELDS=1;
    the conversion to C, done by publish and serialize_message, is what decides.)"""
    m = Marker()
    try:
        m.points = np.zeros((k, 3))
        serialize_message(m)
        return True
    except (AssertionError, TypeError, ValueError, AttributeError):
        return False


def _bench_publish(builder: TriangleListMarker, msg: Marker, frames, vcols, repeats: int) -> dict:
    """Publisher.publish ms for a message object vs serialized bytes, and the in-process DDS round trip.

    ``dds_build_to_parse_ms``: build bytes, publish, wait in the executor for
    the raw subscription's callback, parse with parse_marker_cdr (one process,
    through Fast DDS, no intra-process shortcut in rclpy).
    """
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "97")))
    try:
        node = rclpy.create_node("msg_tools_bench", context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        pub = node.create_publisher(Marker, "bench_marker", qos)
        got: list = []
        node.create_subscription(Marker, "bench_marker", lambda m: got.append(parse_marker_cdr(m)), qos, raw=True)
        deadline = time.monotonic() + 3.0
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        raw = [builder.build(frames[i % 3], i, colors=vcols[i % 3]) for i in range(3)]
        res = {
            "publish_message_ms": _median_ms(lambda i: pub.publish(msg), repeats),
            "publish_bytes_ms": _median_ms(lambda i: pub.publish(raw[i % 3]), repeats),
        }
        executor.spin_once(timeout_sec=0.2)  # drain what the timing loops sent
        while got:
            got.clear()
            executor.spin_once(timeout_sec=0.1)

        def round_trip(i: int) -> None:
            got.clear()
            pub.publish(builder.build(frames[i % 3], i, colors=vcols[i % 3]))
            end = time.monotonic() + 2.0
            while not any(a.stamp_ns == i for a in got) and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.5)
        res["dds_build_to_parse_ms"] = _median_ms(round_trip, repeats)
        executor.shutdown()
        node.destroy_node()
        return res
    finally:
        rclpy.shutdown(context=ctx)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--vertices", type=int, default=6000)
    ap.add_argument("--faces", type=int, default=12000)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--no-colors", action="store_true")
    ap.add_argument("--publish", action="store_true", help="also time Publisher.publish (isolated DDS domain)")
    args = ap.parse_args(argv)
    res = bench_marker(args.vertices, args.faces, args.repeats, colors=not args.no_colors, publish=args.publish)
    print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in res.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
