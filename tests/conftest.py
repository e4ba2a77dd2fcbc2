"""Fixtures shared by the test modules.

ROS traffic is isolated on a random ROS_DOMAIN_ID (40-99) with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, in a
private rclpy Context per test module (``ros``); ``node`` is a node in it. Processes that a test starts inherit
both variables from ``os.environ`` while the ``ros`` fixture is active (or get them explicitly from
:func:`tests.helpers.ros.ros_env`). Without rclpy the tests that use them are skipped.
"""

from __future__ import annotations

import os
import random
import re

import pytest

ROS_ENV_KEYS = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")


@pytest.fixture(scope="module")
def ros():
    """A private rclpy context on a random domain, localhost discovery only: (ctx, executor, domain)."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

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


@pytest.fixture
def node(ros, request):
    """A node in the module's context, added to its executor; named after the module and test."""
    rclpy = pytest.importorskip("rclpy")
    ctx, executor, _ = ros
    name = re.sub(r"\W", "_", f"{request.module.__name__.rsplit('.', 1)[-1]}_{request.node.name.split('[')[0]}")
    n = rclpy.create_node(name, context=ctx)
    executor.add_node(n)
    yield n
    executor.remove_node(n)
    n.destroy_node()
