"""`colgnn_ros.common.run_node`, the shell of every node process: signals end it cleanly, in order.

A node process is stopped by SIGINT (Ctrl-C, the demo) or SIGTERM (a supervisor). It must destroy its node while
the ROS context is still valid and only then shut the context down: destroying a Fast DDS subscription of a node
whose context was already shut down (rclpy's own signal handlers do that first) crashed the installed predictor with
SIGSEGV now and then. The node here has what the predictor has (a subscription, a publisher, timers, a guard
condition) and prints, from ``destroy_node``, whether its context was still valid there.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from tests.helpers.ros import finish, ros_env  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

NODE_PROCESS = textwrap.dedent("""
    import sys, time
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import String
    from colgnn_ros.common import run_node

    class Probe(Node):
        def __init__(self):
            if sys.argv[1] == "slow-start":
                print("building", flush=True)
                time.sleep(30.0)  # a signal arrives while the node is being built
            super().__init__("probe")
            self.create_subscription(String, "probe_in", lambda m: None, 1)
            self.pub = self.create_publisher(String, "probe_out", 1)
            self.create_timer(0.04, self.tick)
            self.create_guard_condition(lambda: None)
            self.ticks = 0
            print("ready", flush=True)

        def tick(self):
            self.ticks += 1
            if self.ticks == 1:
                print("spinning", flush=True)

        def destroy_node(self):
            print(f"destroy_node: context ok {self.context.ok()}", flush=True)
            super().destroy_node()

    code = run_node(Probe, prog="probe", summary="", specs=[], args=["probe"])
    print(f"exit {code}, context ok {rclpy.ok()}", flush=True)
    sys.exit(code)
""")


def start(domain: int, mode: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", NODE_PROCESS, mode], cwd=REPO,
                            env=ros_env(domain, PYTHONPATH=str(REPO)),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def wait_for_line(proc: subprocess.Popen, line: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = proc.stdout.readline()
        if got.strip() == line:
            return
        if not got and proc.poll() is not None:
            break
    raise AssertionError(f"no {line!r} from the node process: {finish(proc)}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_destroys_the_node_before_the_context_shuts_down(sig):
    proc = start(91, "run")
    try:
        wait_for_line(proc, "spinning")
        t0 = time.monotonic()
        proc.send_signal(sig)
        proc.wait(timeout=10.0)
        stopped_s = time.monotonic() - t0
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert "destroy_node: context ok True" in out, out
    assert "exit 0, context ok False" in out and "Traceback" not in out, out
    assert stopped_s < 5.0, f"took {stopped_s:.1f} s to stop"  # the executor waits at most SPIN_WAIT_S at a time


def test_a_signal_while_the_node_is_built_ends_the_process_with_0():
    proc = start(92, "slow-start")
    try:
        wait_for_line(proc, "building")
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10.0)
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert "exit 0, context ok False" in out and "ready" not in out and "Traceback" not in out, out


# -- the transport profile run_node sets -------------------------------------------------------------------------
def test_nodes_publish_with_the_large_data_profile_unless_the_user_chose_one():
    from colgnn_ros.common import FASTDDS_PROFILE, use_large_data_transport

    env: dict[str, str] = {}
    assert use_large_data_transport(env) == str(FASTDDS_PROFILE)
    assert env == {"FASTRTPS_DEFAULT_PROFILES_FILE": str(FASTDDS_PROFILE)} and FASTDDS_PROFILE.is_file()
    for mine in ({"FASTRTPS_DEFAULT_PROFILES_FILE": "/my/profile.xml"}, {"FASTDDS_DEFAULT_PROFILES_FILE": "/p.xml"},
                 {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}):
        env = dict(mine)
        assert use_large_data_transport(env) is None and env == mine


def test_the_profile_holds_the_largest_mesh_marker_in_one_piece_and_keeps_udp():
    import xml.etree.ElementTree as ET

    from colgnn_core.scenes import load_scene
    from colgnn_ros.common import FASTDDS_PROFILE

    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(FASTDDS_PROFILE).getroot()
    kinds = {d.findtext("f:transport_id", namespaces=ns): d for d in root.iterfind(".//f:transport_descriptor", ns)}
    shm = next(d for d in kinds.values() if d.findtext("f:type", namespaces=ns) == "SHM")
    assert any(d.findtext("f:type", namespaces=ns) == "UDPv4" for d in kinds.values())
    participant = root.find(".//f:participant", ns)
    assert participant.get("is_default_profile") == "true"
    assert participant.findtext(".//f:useBuiltinTransports", namespaces=ns) == "false"
    assert {t.text for t in participant.iterfind(".//f:userTransports/f:transport_id", ns)} == set(kinds)
    # A coloured TRIANGLE_LIST: 24 bytes a corner for the point, 16 for the colour, 3 corners a face.
    scenes = ("cone_bunny", "knife_torus", "sphere_mat", "cylinder_banana")
    largest = max(len(load_scene(name, "full").object.faces) * 3 * 40 for name in scenes)
    assert int(shm.findtext("f:maxMessageSize", namespaces=ns)) >= 2 * largest
    assert int(shm.findtext("f:segment_size", namespaces=ns)) >= 8 * largest  # several messages in flight


def test_a_shutdown_that_lands_in_a_destructor_is_not_printed_as_a_crash():
    # A signal whose exception lands in a __del__ reaches sys.unraisablehook ("Exception ignored ... Traceback"),
    # while the shutdown flag stops the spin loop; other unraisable exceptions still reach the previous hook.
    from types import SimpleNamespace

    from colgnn_ros.common import ShutdownRequested, quiet_shutdown

    seen = []
    hook = quiet_shutdown(seen.append)
    hook(SimpleNamespace(exc_value=ShutdownRequested("SIGTERM")))
    assert seen == []
    other = SimpleNamespace(exc_value=ValueError("a real bug"))
    hook(other)
    assert seen == [other]
