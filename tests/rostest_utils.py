"""Shared helpers of the ROS tests (real rclpy + Fast DDS), imported by the test modules:

    from rostest_utils import node, ros, spin_until  # noqa: F401  (pytest fixtures)

ROS traffic is isolated on a random ROS_DOMAIN_ID (40-99) with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, in a private rclpy Context per test module. Processes that
a test starts inherit both variables from ``os.environ`` while the ``ros`` fixture is active (or
get them explicitly from :func:`ros_env`).
"""

from __future__ import annotations

import os
import random
import re
import subprocess
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402

ROS_ENV_KEYS = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")


@pytest.fixture(scope="module")
def ros():
    """A private rclpy context on a random domain, localhost discovery only: (ctx, executor, domain)."""
    saved = {k: os.environ.get(k) for k in ROS_ENV_KEYS}
    domain = random.SystemRandom().randint(40, 99)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    executor = SingleThreadedExecutor(context=ctx)
    try:
        yield ctx, executor, domain
    finally:
        executor.shutdown()
        rclpy.shutdown(context=ctx)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def ros_env(domain: int, **extra: str) -> dict[str, str]:
    """Environment for a child process on the test's isolated domain."""
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", **extra)


def spin_until(executor, cond, timeout: float = 5.0) -> bool:
    """Spin ``executor`` until ``cond()`` is true; False after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True


@pytest.fixture
def node(ros, request):
    """A node in the module's context, added to its executor; named after the module and test."""
    ctx, executor, _ = ros
    name = re.sub(r"\W", "_", f"{request.module.__name__.rsplit('.', 1)[-1]}_{request.node.name.split('[')[0]}")
    n = rclpy.create_node(name, context=ctx)
    executor.add_node(n)
    yield n
    executor.remove_node(n)
    n.destroy_node()


def finish(proc: "subprocess.Popen", timeout: float = 15.0) -> str:
    """Wait for ``proc``; kill it if it does not end. Returns its output."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return out
