"""Helpers of the ROS tests (real rclpy + Fast DDS); the ``ros`` and ``node`` fixtures are in tests/conftest.py."""

from __future__ import annotations

import os
import subprocess
import time


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


def finish(proc: "subprocess.Popen", timeout: float = 15.0) -> str:
    """Wait for ``proc``; kill it if it does not end. Returns its output."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return out
