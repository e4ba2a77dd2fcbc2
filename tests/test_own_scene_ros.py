"""`predictor --ros-args -p scene:=pebble` with COLGNN_SCENE_PATH: a user's scene (made and fitted by
tests/helpers/own_scene.py) served over DDS by the node in its own process, on its default model."""

from __future__ import annotations

import signal
import subprocess
import sys
import uuid

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from colgnn_core.collision.exact import has_intersections  # noqa: E402
from colgnn_core.io import load_sequence  # noqa: E402
from colgnn_ros.common import OUTPUT_QOS, POSE_QOS  # noqa: E402
from msg_tools import array_to_pose_stamped, parse_marker_cdr, weld_corners  # noqa: E402
from tests.helpers import own_scene as own  # noqa: E402
from tests.helpers.ros import finish, ros_env, spin_until  # noqa: E402


@pytest.mark.timeout(900)
def test_node_serves_a_users_scene_over_dds(node, ros):
    res, _ = own.fitted()
    assert res.returncode == 0, res.stderr[-3000:]
    data = own.scene_dir() / "pebble-fit" / "ci" / "data"
    seq = load_sequence(sorted(data.glob("test_*.npz"))[0])
    _, executor, domain = ros
    ns = f"/own{uuid.uuid4().hex[:8]}"
    env = ros_env(domain, PYTHONPATH=str(own.REPO), COLGNN_SCENE_PATH=str(own.scene_dir()))
    proc = subprocess.Popen([sys.executable, "-m", "colgnn_ros.predictor_node", "--ros-args", "-r", f"__ns:={ns}",
                             "-p", "scene:=pebble", "-p", "threads:=1", "-p", "compile:=false"],
                            cwd=own.REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    meshes, tools = [], []
    node.create_subscription(Marker, f"{ns}/deformed_mesh", meshes.append, OUTPUT_QOS, raw=True)
    node.create_subscription(Marker, f"{ns}/tool_marker", tools.append, OUTPUT_QOS, raw=True)
    pub = node.create_publisher(PoseStamped, f"{ns}/tool_pose", POSE_QOS)
    try:
        assert spin_until(executor, lambda: pub.get_subscription_count() == 1 or proc.poll() is not None,
                          timeout=60.0), "the node did not come up"
        assert proc.poll() is None, finish(proc)
        sent = 0
        for pose in seq.tool_poses[1:9]:
            for _ in range(20):  # best effort: repeat the first pose until the node's reader has matched ours
                pub.publish(array_to_pose_stamped(pose, "world", node.get_clock().now().nanoseconds))
                if spin_until(executor, lambda n=sent: len(meshes) > n, timeout=1.0):
                    break
            sent = len(meshes)
            assert sent > 0, "no mesh came back"
        assert spin_until(executor, lambda: len(tools) >= len(meshes) >= 8, timeout=10.0), (len(meshes), len(tools))
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=15.0)
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert "scene pebble (ci)" in out and "Traceback" not in out, out
    faces = seq.object_faces
    assert len(meshes) >= 8 and len(tools) >= 8
    for raw_mesh, raw_tool in zip(meshes, tools):
        m, t = parse_marker_cdr(raw_mesh), parse_marker_cdr(raw_tool)
        ov, of = weld_corners(m.corners)
        tv, tf = weld_corners(t.corners)
        assert len(of) == len(faces)  # the pebble's surface, not a built-in scene's
        assert np.isfinite(ov).all()
        assert not has_intersections(ov, of, tv, tf)
