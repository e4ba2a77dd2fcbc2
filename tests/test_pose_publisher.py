"""`pose_publisher` on real rclpy + Fast DDS: parameters, poses through DDS, rate, loop, signals.

The node runs in its own process (``python -m colgnn_ros.pose_publisher_node``), reached only
through DDS on an isolated domain (the ``ros`` fixture, tests/conftest.py); the parameter checks also run in-process.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from colgnn_core.errors import InputError  # noqa: E402
from colgnn_core.io import write_poses_csv  # noqa: E402
from colgnn_core.scenes import load_scene, scripted_poses  # noqa: E402
from colgnn_ros.pose_publisher_node import PARAMETERS, PosePublisher  # noqa: E402
from msg_tools import pose_to_array, stamp_to_ns  # noqa: E402
from tests.helpers.ros import finish, ros_env, spin_until  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
# Best-effort like the publisher, but deep enough that the test never overwrites an unread pose.
RECEIVE_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)


def unique_topic() -> str:
    """A topic of this test alone: a stray publisher on the same random domain cannot feed it."""
    return f"/test_{uuid.uuid4().hex[:12]}/tool_pose"


def start_publisher(domain: int, *params: str, topic: str = "tool_pose") -> subprocess.Popen:
    args = [PY, "-m", "colgnn_ros.pose_publisher_node", "--ros-args", "-r", f"tool_pose:={topic}"]
    for p in params:
        args += ["-p", p]
    return subprocess.Popen(args, cwd=REPO, env=ros_env(domain, PYTHONPATH=str(REPO)),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def subscribe(node, topic: str) -> list[PoseStamped]:
    got: list[PoseStamped] = []
    node.create_subscription(PoseStamped, topic, got.append, RECEIVE_QOS)
    return got


def assert_ordered_subsequence(received: np.ndarray, expected: np.ndarray) -> None:
    """Each received pose equals the next not-yet-passed expected pose (exactly: float64 through CDR)."""
    j = 0
    for i, r in enumerate(received):
        while j < len(expected) and not np.array_equal(expected[j], r):
            j += 1
        assert j < len(expected), f"received pose {i} {r} is not the next expected pose"
        j += 1


# ----------------------------------------------------------------------------- in-process

def test_parameters_have_descriptors_and_defaults(ros):
    ctx, _, _ = ros
    n = PosePublisher(context=ctx)
    try:
        rate = n.describe_parameter("rate")
        assert rate.type == ParameterType.PARAMETER_DOUBLE and rate.read_only
        assert (rate.floating_point_range[0].from_value, rate.floating_point_range[0].to_value) == (0.1, 1000.0)
        frames = n.describe_parameter("frames")
        assert frames.integer_range[0].from_value == 1 and frames.description
        assert "press|stab|slice|drag|circle|random" in n.describe_parameter("trajectory").additional_constraints
        assert {s.name for s in PARAMETERS} <= set(n._parameters)
        assert n.get_parameter("rate").value == 25.0 and n.get_parameter("loop").value is False
        np.testing.assert_array_equal(n.poses, scripted_poses(load_scene("sphere_mat"), "press", 250))
        assert n.frame_id == "world"
    finally:
        n.destroy_node()


def test_poses_file_is_read_and_checked_against_the_workspace(ros, tmp_path):
    ctx, _, _ = ros
    scene = load_scene("sphere_mat")
    poses = scripted_poses(scene, "random", 6, seed=4)
    write_poses_csv(tmp_path / "p.csv", np.arange(6) * scene.dt, poses)
    n = PosePublisher(context=ctx, parameter_overrides=[Parameter("poses_file", value=str(tmp_path / "p.csv"))])
    try:
        np.testing.assert_allclose(n.poses, poses, rtol=0, atol=1e-15)
    finally:
        n.destroy_node()
    poses[3, 2] = 10.0
    write_poses_csv(tmp_path / "far.csv", np.arange(6) * scene.dt, poses)
    with pytest.raises(InputError, match=r"far.csv: pose 3: .*outside the sphere_mat workspace"):
        PosePublisher(context=ctx, parameter_overrides=[Parameter("poses_file", value=str(tmp_path / "far.csv"))])


@pytest.mark.parametrize("name, value, message", [
    ("trajectory", "wiggle", r"'trajectory' must be one of press\|stab\|slice\|drag\|circle\|random, got 'wiggle'"),
    ("scene", "moon", r"'scene' must be one of .*sphere_mat"),
    ("resolution", "huge", r"'resolution' must be one of full\|ci"),
    ("rate", 0.01, r"'rate' must be in \[0.1, 1000\], got 0.01"),
    ("rate", 25, r"'rate' must be a double \(e.g. rate:=25.0\), got 25 \(int\)"),
    ("frames", 0, r"'frames' must be in \[1, 100000\], got 0"),
    ("loop", "yes", r"'loop' must be a bool"),
    ("frame_id", " ", r"'frame_id' must not be empty"),
    ("poses_file", "/no/such/poses.csv", r"no such poses file"),
])
def test_bad_parameters_raise_input_error(ros, name, value, message):
    ctx, _, _ = ros
    with pytest.raises(InputError, match=message):
        PosePublisher(context=ctx, parameter_overrides=[Parameter(name, value=value)])


# ----------------------------------------------------------------------------- separate processes

def test_bad_parameters_exit_2_with_one_error_line(ros):
    _, _, domain = ros
    cases = {"trajectory:=wiggle": "'trajectory' must be one of", "rate:=5000.0": "'rate' must be in [0.1, 1000]"}
    procs = {p: start_publisher(domain, p) for p in cases}  # in parallel: start-up dominates
    for p, message in cases.items():
        out = finish(procs[p])
        assert procs[p].returncode == 2, out
        assert message in out and "[ERROR]" in out and "Traceback" not in out, out


def test_scripted_trajectory_through_dds(node, ros):
    """All poses of a scripted drag arrive in order, equal to scripted_poses, at the set rate; then exit 0."""
    _, executor, domain = ros
    frames, rate = 40, 50.0
    expected = scripted_poses(load_scene("sphere_mat"), "drag", frames)
    topic = unique_topic()
    got = subscribe(node, topic)
    proc = start_publisher(domain, "trajectory:=drag", f"frames:={frames}", f"rate:={rate}", "frame_id:=test_frame",
                           "wait_for_subscribers:=1", topic=topic)
    try:
        assert spin_until(executor, lambda: proc.poll() is not None, timeout=25.0), "publisher did not finish"
        spin_until(executor, lambda: False, timeout=0.1)  # anything still queued
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert f"on {topic} at 50 Hz" in out and f"trajectory finished: {frames} poses published" in out
    received = np.array([pose_to_array(m) for m in got])
    assert len(received) >= 0.9 * frames, f"only {len(received)} of {frames} poses arrived\n{out}"
    assert_ordered_subsequence(received, expected)
    np.testing.assert_array_equal(received[-1], expected[-1])
    assert {m.header.frame_id for m in got} == {"test_frame"}
    stamps = np.array([stamp_to_ns(m.header.stamp) for m in got]) * 1e-9
    assert np.all(np.diff(stamps) > 0)
    assert np.median(np.diff(stamps)) == pytest.approx(1 / rate, rel=0.15)


def test_poses_file_loops_until_sigterm_or_sigint(node, ros, tmp_path):
    """Two looping publishers at once (start-up dominates): one stopped by SIGTERM, one by SIGINT; both exit 0."""
    _, executor, domain = ros
    scene = load_scene("sphere_mat")
    poses = scripted_poses(scene, "circle", 5)
    write_poses_csv(tmp_path / "p.csv", np.arange(5) * scene.dt, poses)
    runs = {}
    for sig in (signal.SIGTERM, signal.SIGINT):
        topic = unique_topic()
        runs[sig] = (subscribe(node, topic), start_publisher(domain, f"poses_file:={tmp_path / 'p.csv'}", "loop:=true",
                                                             "rate:=100.0", topic=topic))
    try:
        assert spin_until(executor, lambda: all(len(got) >= 12 for got, _ in runs.values()), timeout=20.0), \
            "no looping poses"
        t0 = time.monotonic()
        for sig, (_, proc) in runs.items():
            proc.send_signal(sig)
        for _, proc in runs.values():
            proc.wait(timeout=10.0)
        stop_s = time.monotonic() - t0
    finally:
        outs = {sig: finish(proc) for sig, (_, proc) in runs.items()}
    assert stop_s < 5.0
    for sig, (got, proc) in runs.items():
        out = outs[sig]
        assert proc.returncode == 0, f"{sig.name}: {out}"
        assert "Traceback" not in out and "[ERROR]" not in out, out
        received = np.array([pose_to_array(m) for m in got])
        # Every received pose is one of the file's rows, and the sequence wraps around (row 4 -> row 0).
        dist = np.linalg.norm(received[:, None, :] - poses[None, :, :], axis=2)
        assert dist.min(axis=1).max() < 1e-12
        rows = dist.argmin(axis=1).tolist()
        assert any(a == 4 and b == 0 for a, b in zip(rows, rows[1:])), rows
