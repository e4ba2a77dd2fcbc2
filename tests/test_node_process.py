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
