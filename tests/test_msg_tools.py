"""msg_tools on real rclpy + Fast DDS: conversions, fast markers, publishing, rosbag2 recording.

ROS traffic is isolated on a random ROS_DOMAIN_ID (40-99) with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, in a private rclpy Context.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import Pose, PoseStamped  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from std_msgs.msg import Int32MultiArray  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from colgnn_core.geometry.transforms import transform_points  # noqa: E402
from msg_tools import (  # noqa: E402
    COLLISION_COUNT_LABELS,
    BagWriter,
    DistanceColormap,
    TopicRecorder,
    TriangleListMarker,
    apply_pose,
    array_to_pose,
    array_to_pose_stamped,
    bag_summary,
    counts_to_msg,
    diagnostic_array,
    diagnostic_values,
    marker_corner_colors,
    marker_corners,
    marker_world_corners,
    msg_to_counts,
    ns_to_stamp,
    parse_marker_cdr,
    pose_to_array,
    read_bag,
    read_bag_messages,
    stamp_to_ns,
    triangle_marker_naive,
    weld_corners,
)
from msg_tools.benchmark import grid_mesh  # noqa: E402
from msg_tools.markers import canonical_cdr  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
MARKER = "visualization_msgs/msg/Marker"


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-0.5, 0.5, size=(n, 3)), q], axis=1)


def random_mesh(rng: np.random.Generator, n: int, f: int) -> tuple[np.ndarray, np.ndarray]:
    return rng.normal(scale=0.1, size=(n, 3)), rng.integers(0, n, size=(f, 3))


# ----------------------------------------------------------------------------- ROS fixtures

from tests.helpers.ros import spin_until  # noqa: E402


RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


# ----------------------------------------------------------------------------- conversions

def test_pose_round_trip_through_cdr():
    rng = np.random.default_rng(1)
    for p in random_poses(rng, 20):
        msg = array_to_pose(p)
        assert isinstance(msg, Pose)
        back = pose_to_array(deserialize_message(serialize_message(msg), Pose))
        np.testing.assert_array_equal(back, p)
    p = random_poses(rng, 1)[0]
    ps = array_to_pose_stamped(p, "world", 1_700_000_123_456_789_012)
    ps2 = deserialize_message(serialize_message(ps), PoseStamped)
    np.testing.assert_array_equal(pose_to_array(ps2), p)
    assert ps2.header.frame_id == "world"
    assert stamp_to_ns(ps2.header.stamp) == 1_700_000_123_456_789_012
    assert (ps2.header.stamp.sec, ps2.header.stamp.nanosec) == (1_700_000_123, 456_789_012)
    with pytest.raises(ValueError):
        array_to_pose([0, 0, 0, 1])
    with pytest.raises(ValueError):
        ns_to_stamp(-1)


def test_collision_counts_round_trip():
    counts = {"vertex_face_before": 17, "edge_edge_before": 5, "vertex_face_after": 0, "edge_edge_after": 0,
              "fallback": 1, "substeps": 3}
    msg = deserialize_message(serialize_message(counts_to_msg(counts)), Int32MultiArray)
    # the layout names every field, in the canonical order, one per data entry
    assert [d.label for d in msg.layout.dim] == [k for k in COLLISION_COUNT_LABELS if k in counts]
    assert [(d.size, d.stride) for d in msg.layout.dim] == [(1, 1)] * len(counts)
    assert list(msg.data) == [17, 5, 0, 0, 1, 3]
    assert msg_to_counts(msg) == counts
    minimal = {k: i for i, k in enumerate(COLLISION_COUNT_LABELS[:4])}
    assert msg_to_counts(counts_to_msg(minimal)) == minimal
    with pytest.raises(ValueError, match="missing"):
        counts_to_msg({"vertex_face_before": 1})
    with pytest.raises(ValueError, match="unknown"):
        counts_to_msg({**minimal, "vertex_vertex": 2})
    with pytest.raises(ValueError, match="int32"):
        counts_to_msg({**minimal, "edge_edge_after": 1.5})
    with pytest.raises(ValueError, match="int32"):
        counts_to_msg({**minimal, "edge_edge_after": 2**31})


def test_diagnostics_round_trip():
    arr = diagnostic_array(Time(sec=3, nanosec=4), "colgnn_predictor",
                           {"step_ms_median": 4.25, "step_ms_p95": 7.123456789, "rejected_poses": 2,
                            "scene": "sphere_mat"},
                           level=DiagnosticStatus.WARN, message="2 poses rejected", hardware_id="cpu")
    back = deserialize_message(serialize_message(arr), DiagnosticArray)
    assert back == arr
    st = back.status[0]
    assert (st.level, st.name, st.message, st.hardware_id) == (DiagnosticStatus.WARN, "colgnn_predictor",
                                                               "2 poses rejected", "cpu")
    assert diagnostic_values(back, "colgnn_predictor") == {"step_ms_median": "4.25", "step_ms_p95": "7.12346",
                                                           "rejected_poses": "2", "scene": "sphere_mat"}
    assert stamp_to_ns(back.header.stamp) == 3_000_000_004
    with pytest.raises(KeyError):
        diagnostic_values(back, "other")
    with pytest.raises(ValueError):
        diagnostic_array(0, "x", {}, level=7)


def test_apply_pose_matches_core_transform():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(50, 3))
    for pose in random_poses(rng, 5):
        np.testing.assert_allclose(apply_pose(pts, pose), transform_points(pts, pose), atol=1e-12)


# ----------------------------------------------------------------------------- markers

@pytest.mark.parametrize("frame_id", ["w", "world", "odom_frame"])   # shifts the alignment of every later field
@pytest.mark.parametrize("n_faces", [1, 2, 7])                       # odd and even corner counts
@pytest.mark.parametrize("with_colors", [False, True])
def test_fast_marker_equals_naive(frame_id, n_faces, with_colors):
    rng = np.random.default_rng(n_faces)
    v, f = random_mesh(rng, 9, n_faces)
    cols = rng.random((9, 4)).astype(np.float32) if with_colors else None
    pose = random_poses(rng, 1)[0]
    kw = dict(frame_id=frame_id, ns="colgnn", marker_id=4, color=(0.2, 0.4, 0.6, 0.8))
    builder = TriangleListMarker(f, 9, per_vertex_colors=with_colors, **kw)
    for stamp in (0, 1_700_000_000_123_456_789):
        fast = builder.build(v, stamp, colors=cols, pose=pose)
        naive = triangle_marker_naive(v, f, colors=cols, stamp=stamp, pose=pose, **kw)
        assert isinstance(fast, bytes)
        # byte-exact against rclpy's serializer (with its uninitialised padding zeroed)
        assert fast == canonical_cdr(serialize_message(naive), MARKER)
        # and as messages (the naive one round-tripped so its float32 colours are rounded alike)
        assert deserialize_message(fast, Marker) == deserialize_message(serialize_message(naive), Marker)
        v = v + 0.01  # the next frame moves


def test_marker_builder_rejects_bad_input():
    v, f = random_mesh(np.random.default_rng(3), 5, 4)
    b = TriangleListMarker(f, 5)
    with pytest.raises(ValueError, match="shape"):
        b.build(v[:4], 0)
    with pytest.raises(ValueError, match="NaN"):
        b.build(np.where(np.arange(5)[:, None] == 2, np.nan, v), 0)
    with pytest.raises(ValueError, match="per_vertex_colors"):
        b.build(v, 0, colors=np.ones((5, 4)))
    with pytest.raises(ValueError, match="pose"):
        b.build(v, 0, pose=[0, 0, 0])
    with pytest.raises(ValueError, match="face indices"):
        TriangleListMarker(f, 3)
    with pytest.raises(ValueError, match="colors"):
        TriangleListMarker(f, 5, per_vertex_colors=True).build(v, 0)


def test_marker_read_back_helpers():
    rng = np.random.default_rng(4)
    v, f = random_mesh(rng, 30, 40)
    cols = rng.random((30, 4)).astype(np.float32)
    pose = random_poses(rng, 1)[0]
    raw = TriangleListMarker(f, 30, per_vertex_colors=True, frame_id="map", ns="mesh", marker_id=2).build(
        v, Time(sec=12, nanosec=34), colors=cols, pose=pose)
    msg = deserialize_message(raw, Marker)
    np.testing.assert_array_equal(marker_corners(msg), v[f])
    np.testing.assert_array_equal(marker_corner_colors(msg), cols[f])
    np.testing.assert_allclose(marker_world_corners(msg), transform_points(v[f].reshape(-1, 3), pose).reshape(-1, 3, 3),
                               atol=1e-12)
    arr = parse_marker_cdr(raw)
    assert (arr.stamp_ns, arr.frame_id, arr.ns, arr.id, arr.type, arr.action) == (12 * 10**9 + 34, "map", "mesh", 2,
                                                                                  Marker.TRIANGLE_LIST, Marker.ADD)
    np.testing.assert_array_equal(arr.corners, v[f])
    np.testing.assert_array_equal(arr.corner_colors, cols[f])
    np.testing.assert_array_equal(arr.pose, pose)
    np.testing.assert_array_equal(arr.scale, [1, 1, 1])
    # welding the soup gives back the mesh up to vertex order (unused vertices drop out)
    wv, wf = weld_corners(arr.corners)
    np.testing.assert_array_equal(wv[wf], v[f])
    used = np.unique(f)
    assert len(wv) == len(used)
    with pytest.raises(ValueError):
        parse_marker_cdr(raw[:200])


def test_full_resolution_marker_is_exact_across_frames():
    """The preallocated buffer is reused frame after frame; each build must carry only its own frame.

    Speed (target <= 1 ms) is measured by `python -m msg_tools.benchmark`, not here.
    """
    v, f = grid_mesh(6000, 12000)  # ~6k surface vertices, 12k faces: 36k corners
    cmap = DistanceColormap(0.0, 0.02)
    b = TriangleListMarker(f, len(v), per_vertex_colors=True)
    for i in (0, 1, 7):
        vi = v + 1e-4 * i
        arr = parse_marker_cdr(b.build(vi, i, colors=cmap(vi[:, 2])))
        np.testing.assert_array_equal(arr.corners, vi[f])
        assert arr.stamp_ns == i
    assert arr.corners.shape == (12000, 3, 3)


def test_distance_colormap():
    cmap = DistanceColormap(near=0.0, far=0.04, colormap="viridis", alpha=0.5)
    c = cmap(np.array([-0.01, 0.0, 0.02, 0.04, 1.0, np.nan]))
    assert c.dtype == np.float32 and c.shape == (6, 4)
    np.testing.assert_array_equal(c[0], cmap.lut[0])
    np.testing.assert_array_equal(c[1], cmap.lut[0])
    np.testing.assert_array_equal(c[3], cmap.lut[255])
    np.testing.assert_array_equal(c[4], cmap.lut[255])
    np.testing.assert_array_equal(c[5], cmap.lut[255])
    np.testing.assert_array_equal(c[2], cmap.lut[127])
    assert np.all(c[:, 3] == 0.5)
    assert not np.allclose(cmap.lut[0], cmap.lut[255])
    with pytest.raises(ValueError):
        DistanceColormap(0.1, 0.1)
    with pytest.raises(ValueError):
        DistanceColormap(0.0, 0.1, colormap="no_such_map")


# ----------------------------------------------------------------------------- DDS

def test_publish_serialized_marker_through_dds(node, ros):
    _, executor, _ = ros
    rng = np.random.default_rng(5)
    v, f = random_mesh(rng, 50, 60)
    cols = rng.random((50, 4)).astype(np.float32)
    big_v, big_f = grid_mesh(6000, 12000)
    small = TriangleListMarker(f, 50, per_vertex_colors=True, frame_id="world", ns="t", marker_id=1)
    big = TriangleListMarker(big_f, len(big_v), frame_id="world")
    got, got_raw = [], []
    pub = node.create_publisher(Marker, "mt_mesh", RELIABLE)
    pub_big = node.create_publisher(Marker, "mt_mesh_big", RELIABLE)
    node.create_subscription(Marker, "mt_mesh", got.append, RELIABLE)             # deserialized by rclpy
    node.create_subscription(Marker, "mt_mesh_big", got_raw.append, RELIABLE, raw=True)
    assert spin_until(executor, lambda: pub.get_subscription_count() and pub_big.get_subscription_count())
    pub.publish(small.build(v, 42, colors=cols))   # rclpy publishes bytes with publish_raw
    pub_big.publish(big.build(big_v, 43))
    assert spin_until(executor, lambda: got and got_raw)
    naive = triangle_marker_naive(v, f, colors=cols, stamp=42, frame_id="world", ns="t", marker_id=1)
    assert got[0] == deserialize_message(serialize_message(naive), Marker)
    arr = parse_marker_cdr(got_raw[0])
    assert arr.stamp_ns == 43
    np.testing.assert_array_equal(arr.corners, big_v[big_f])


def _publish_node_topics(node, executor, rec_counts, n: int):
    """Publish n messages on each predictor topic (as the node would); return what was sent per topic."""
    rng = np.random.default_rng(6)
    v, f = random_mesh(rng, 40, 50)
    tv, tf = random_mesh(rng, 12, 20)
    mesh_b = TriangleListMarker(f, 40, per_vertex_colors=True, frame_id="world")
    tool_b = TriangleListMarker(tf, 12, frame_id="world", ns="tool", color=(1, 0, 0, 1))
    pubs = {
        "/deformed_mesh": node.create_publisher(Marker, "deformed_mesh", RELIABLE),
        "/tool_marker": node.create_publisher(Marker, "tool_marker", RELIABLE),
        "/collision_counts": node.create_publisher(Int32MultiArray, "collision_counts", RELIABLE),
        "/tool_pose": node.create_publisher(PoseStamped, "tool_pose", BEST_EFFORT),
        "/diagnostics": node.create_publisher(DiagnosticArray, "/diagnostics", RELIABLE),
    }
    assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs.values()))
    sent: dict[str, list] = {k: [] for k in pubs}
    for i in range(n):
        stamp = 1_000_000_000 + 40_000_000 * i
        pose = random_poses(rng, 1)[0]
        vi = v + 0.001 * i
        cols = rng.random((40, 4)).astype(np.float32)
        items = {
            "/deformed_mesh": mesh_b.build(vi, stamp, colors=cols),
            "/tool_marker": tool_b.build(tv, stamp, pose=pose),
            "/collision_counts": counts_to_msg({"vertex_face_before": i, "edge_edge_before": 2 * i,
                                                "vertex_face_after": 0, "edge_edge_after": 0}),
            "/tool_pose": array_to_pose_stamped(pose, "world", stamp),
            "/diagnostics": diagnostic_array(stamp, "colgnn_predictor", {"step_ms_median": i + 0.5, "fallbacks": i}),
        }
        for topic, item in items.items():
            pubs[topic].publish(item)
            sent[topic].append(item)
        spin_until(executor, lambda i=i: all(c >= i + 1 for c in rec_counts().values()), timeout=2.0)
    assert spin_until(executor, lambda: all(c >= n for c in rec_counts().values()))
    for p in pubs.values():
        node.destroy_publisher(p)
    return sent


def test_record_live_topics_and_read_back(node, ros, tmp_path):
    _, executor, _ = ros
    out = tmp_path / "bag"
    n = 5
    with TopicRecorder(node, out) as rec:
        sent = _publish_node_topics(node, executor, lambda: rec.counts, n)
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # renamed into place, no partial folder left
    assert sorted(p.name for p in out.iterdir()) == ["bag.mcap", "metadata.yaml"]
    summary = bag_summary(out)
    assert summary["storage"] == "mcap"
    assert summary["topics"] == {
        "/deformed_mesh": {"type": MARKER, "count": n},
        "/tool_marker": {"type": MARKER, "count": n},
        "/collision_counts": {"type": "std_msgs/msg/Int32MultiArray", "count": n},
        "/tool_pose": {"type": "geometry_msgs/msg/PoseStamped", "count": n},
        "/diagnostics": {"type": "diagnostic_msgs/msg/DiagnosticArray", "count": n},
    }
    # contents, deserialized by rclpy, in publication order per topic
    got: dict[str, list] = {k: [] for k in sent}
    for topic, _, msg in read_bag_messages(out):
        got[topic].append(msg)
    for topic in ("/collision_counts", "/tool_pose", "/diagnostics"):
        assert got[topic] == sent[topic], topic
    for topic in ("/deformed_mesh", "/tool_marker"):
        assert got[topic] == [deserialize_message(b, Marker) for b in sent[topic]], topic
    assert [msg_to_counts(m)["edge_edge_before"] for m in got["/collision_counts"]] == [2 * i for i in range(n)]
    assert [diagnostic_values(m, "colgnn_predictor")["fallbacks"] for m in got["/diagnostics"]] == \
        [str(i) for i in range(n)]
    # raw bytes are stored untouched; receive timestamps are increasing per topic
    raw = [m for m in read_bag(out, ["/deformed_mesh"])]
    assert [m.data for m in raw] == sent["/deformed_mesh"]
    assert all(a.timestamp_ns <= b.timestamp_ns for a, b in zip(raw, raw[1:]))
    # rosbags (no ROS) reads it too, with the Jazzy definitions
    rb = [m for t, _, m in read_bag_messages(out, ["/tool_pose"], deserializer="rosbags")]
    assert [[m.pose.position.x, m.pose.orientation.w] for m in rb] == \
        [[m.pose.position.x, m.pose.orientation.w] for m in sent["/tool_pose"]]
    fast = [m for t, _, m in read_bag_messages(out, ["/tool_marker"], deserializer="marker")]
    assert all(m.ns == "tool" and m.corners.shape == (20, 3, 3) for m in fast)


def test_bag_metadata_type_hashes_match_installed_interfaces(tmp_path):
    """ros2 bag play / Foxglove need the right type name, definition and RIHS01 hash per topic."""
    import yaml  # ruamel is what rosbags uses; PyYAML comes with the ROS wheels

    with BagWriter(tmp_path / "b") as w:
        w.add_topic("/deformed_mesh", MARKER)
        w.add_topic("/collision_counts", Int32MultiArray)
        w.write_message("/collision_counts", counts_to_msg(dict.fromkeys(COLLISION_COUNT_LABELS[:4], 1)), 5)
    meta = yaml.safe_load((tmp_path / "b" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["b.mcap"]
    share = Path(sys.prefix) / "share"
    for t in meta["topics_with_message_count"]:
        md = t["topic_metadata"]
        desc = json.loads((share / (md["type"] + ".json")).read_text())
        want = next(h["hash_string"] for h in desc["type_hashes"] if h["type_name"] == md["type"])
        assert md["type_description_hash"] == want
        assert md["serialization_format"] == "cdr"
    assert (tmp_path / "b" / "b.mcap").read_bytes()[:8] == b"\x89MCAP0\r\n"


def test_bag_writer_is_atomic(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with BagWriter(tmp_path / "x") as w:
            w.add_topic("/tool_pose", "geometry_msgs/msg/PoseStamped")
            w.write_message("/tool_pose", array_to_pose_stamped([0, 0, 0, 0, 0, 0, 1], "world", 1), 1)
            assert not (tmp_path / "x").exists()  # still under the hidden partial folder
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "y").mkdir()
    with pytest.raises(FileExistsError):
        BagWriter(tmp_path / "y")
    with BagWriter(tmp_path / "z") as w:
        with pytest.raises(ValueError):
            w.add_topic("/a", "no_pkg/msg/Nothing")
        with pytest.raises(KeyError):
            w.write("/b", b"\x00\x01\x00\x00", 1)
    assert bag_summary(tmp_path / "z")["message_count"] == 0
    with pytest.raises(ValueError, match="not in"):
        list(read_bag(tmp_path / "z", ["/nothing"]))
    w = BagWriter(tmp_path / "w")
    w.add_topic("/a", "std_msgs/msg/Int32MultiArray")
    w.close()
    with pytest.raises(RuntimeError, match="closed"):
        w.write("/a", b"\x00\x01\x00\x00", 1)


def test_recorder_cli_refuses_existing_output(ros, tmp_path, capsys):  # ros: isolated domain env
    from msg_tools import recorder

    (tmp_path / "exists").mkdir()
    assert recorder.main(["--out", str(tmp_path / "exists"), "--duration", "1"]) == 2
    assert "exists already" in capsys.readouterr().out
    assert recorder.main(["--out", str(tmp_path / "new"), "--duration", "0.2",
                          "--topic", "x:no_pkg/msg/Nothing"]) == 2
    assert list(tmp_path.iterdir()) == [tmp_path / "exists"]


def test_recorder_process_stops_cleanly_on_sigterm(node, ros, tmp_path):
    """`python -m msg_tools.recorder` in its own process, reached only through DDS."""
    _, executor, domain = ros
    out = tmp_path / "rec"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(REPO))
    proc = subprocess.Popen([PY, "-m", "msg_tools.recorder", "--out", str(out), "--duration", "60",
                             "--topic", "collision_counts:std_msgs/msg/Int32MultiArray"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        pub = node.create_publisher(Int32MultiArray, "collision_counts", RELIABLE)
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, timeout=15.0)
        sent = [counts_to_msg({k: 10 * i + j for j, k in enumerate(COLLISION_COUNT_LABELS[:4])}) for i in range(4)]
        for m in sent:
            pub.publish(m)
        time.sleep(0.5)  # reliable delivery to the other process
        proc.send_signal(signal.SIGTERM)
        stdout, _ = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stdout
    assert "/collision_counts: 4 messages" in stdout
    assert [m for _, _, m in read_bag_messages(out)] == sent


def test_benchmark_runs_on_a_small_mesh():
    from msg_tools.benchmark import bench_marker

    res = bench_marker(200, 300, repeats=2)
    assert (res["n_faces"], res["n_corners"]) == (300, 900)
    assert res["numpy_points_publishable"] is False
    assert res["cdr_bytes"] > 900 * (24 + 16)
    assert res["cdr_build_ms"] < res["naive_build_ms"]
