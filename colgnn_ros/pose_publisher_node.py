"""``pose_publisher``: tool poses (geometry_msgs/PoseStamped) on ``tool_pose``, for demos and tests.

The poses are a scene's scripted trajectory (:func:`colgnn_core.scenes.scripted_poses`: press, stab,
slice, drag, circle, random) or the rows of a poses CSV (:func:`colgnn_core.io.read_poses_csv`,
checked against the scene's workspace). A timer publishes one pose per tick at ``rate`` Hz, stamped
with the node clock, best-effort with depth 1 (the predictor's subscription QoS). At the end of the
trajectory the node starts over (``loop``) or exits with code 0. SIGINT and SIGTERM stop it
cleanly (exit 0); bad parameters log one error line and exit 2.

    pose_publisher --ros-args -p trajectory:=press -p rate:=25.0
    pose_publisher --ros-args -p poses_file:=poses.csv -p loop:=true
    pose_publisher --help
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.task import Future

from colgnn_core.errors import InputError
from colgnn_core.io import read_poses_csv
from colgnn_core.scenes import RESOLUTIONS, load_scene, scene_names, scripted_poses
from colgnn_core.scenes.trajectories import SCRIPTED_KINDS
from colgnn_ros.common import POSE_QOS, ParamSpec, declare_parameters, run_node
from msg_tools.conversions import array_to_pose_stamped

NODE_NAME = "pose_publisher"
TOPIC = "tool_pose"
# After the wanted subscriptions have matched, give their side of DDS discovery this long to match
# the writer too, or the first best-effort poses are dropped by readers that do not know it yet.
SETTLE_S = 0.25
# Keep spinning this long after the last pose so it leaves the process before DDS is torn down.
LINGER_S = 0.25

SUMMARY = ("Publishes tool poses (geometry_msgs/PoseStamped, best-effort, depth 1) on 'tool_pose': a scene's "
           "scripted trajectory or a poses CSV, at a fixed rate.")

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("scene", "sphere_mat", "scene whose trajectory and workspace are used", choices=tuple(scene_names())),
    ParamSpec("resolution", "full", "scene resolution (the object mesh decides the contact heights)",
              choices=tuple(RESOLUTIONS)),
    ParamSpec("trajectory", "press", "scripted motion of the scene (ignored when poses_file is set)",
              choices=tuple(SCRIPTED_KINDS)),
    ParamSpec("frames", 250, "number of poses of the scripted trajectory (ignored when poses_file is set)",
              range=(1, 100_000)),
    ParamSpec("seed", 0, "random seed of the 'random' trajectory", range=(0, 2**31 - 1)),
    ParamSpec("poses_file", "", "poses CSV (t,px,py,pz,qx,qy,qz,qw) to publish instead of a scripted trajectory; "
              "its t column is ignored, poses go out at 'rate'"),
    ParamSpec("rate", 25.0, "poses per second (Hz)", range=(0.1, 1000.0)),
    ParamSpec("frame_id", "world", "header.frame_id of the poses"),
    ParamSpec("loop", False, "start over at the end of the trajectory instead of exiting"),
    ParamSpec("wait_for_subscribers", 0, "hold the first pose until this many subscriptions match 'tool_pose'",
              range=(0, 1000)),
)


def load_poses(scene_name: str, resolution: str, trajectory: str, frames: int, seed: int,
               poses_file: str) -> np.ndarray:
    """Poses [T,7] to publish: the CSV's rows (checked against the scene's workspace) or the scripted motion."""
    scene = load_scene(scene_name, resolution)
    if poses_file:
        _, poses = read_poses_csv(poses_file)
        try:
            return scene.check_poses(poses)
        except InputError as exc:
            raise InputError(f"{poses_file}: {exc}") from None
    return scripted_poses(scene, trajectory, frames, seed)


class PosePublisher(Node):
    """Publishes ``poses`` [T,7] one per timer tick on ``tool_pose``.

    ``done`` completes when a non-looping trajectory has been published (``run_node`` then ends
    the process). Node keyword arguments (context, parameter_overrides, ...) pass through to rclpy.
    Raises InputError for bad parameters.
    """

    def __init__(self, **node_kwargs) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        try:
            self.params = declare_parameters(self, PARAMETERS)
            p = self.params
            if not p["frame_id"].strip():
                raise InputError("parameter 'frame_id' must not be empty")
            self.poses = load_poses(p["scene"], p["resolution"], p["trajectory"], p["frames"], p["seed"],
                                    p["poses_file"])
        except BaseException:
            self.destroy_node()
            raise
        self.frame_id: str = p["frame_id"]
        self.loop: bool = p["loop"]
        self.index = 0  # next pose to publish
        self.published = 0
        self.done = Future()
        self._wait_for: int = p["wait_for_subscribers"]
        self._settle_until: float | None = None  # time.monotonic() when publishing may start after the match
        self._publisher = self.create_publisher(PoseStamped, TOPIC, POSE_QOS)
        self._timer = self.create_timer(1.0 / p["rate"], self._tick)
        self._linger = None  # one-shot timer that completes `done` after the last pose
        source = Path(p["poses_file"]).name if p["poses_file"] else f"'{p['trajectory']}' of {p['scene']}"
        self.get_logger().info(
            f"publishing {len(self.poses)} poses ({source}) on {self._publisher.topic_name} at {p['rate']:g} Hz, "
            f"frame '{self.frame_id}'{', looping' if self.loop else ''}"
            + (f"; waiting for {self._wait_for} subscriber(s)" if self._wait_for else ""))

    def _ready(self) -> bool:
        """False while waiting for subscribers (and the settle time after they match)."""
        if self._wait_for == 0:
            return True
        now = time.monotonic()  # wall time: the node clock may be simulated and not running yet
        if self._settle_until is None:
            if self._publisher.get_subscription_count() < self._wait_for:
                return False
            self._settle_until = now + SETTLE_S
        if now < self._settle_until:
            return False
        self.get_logger().info(f"{self._publisher.get_subscription_count()} subscriber(s) matched, starting")
        self._wait_for = 0
        return True

    def _tick(self) -> None:
        if self.done.done() or not self._ready():
            return
        if self.index == len(self.poses):
            self.index = 0  # only reached when looping
        stamp = self.get_clock().now().to_msg()
        self._publisher.publish(array_to_pose_stamped(self.poses[self.index], self.frame_id, stamp))
        self.index += 1
        self.published += 1
        if self.index == len(self.poses) and not self.loop:
            self._timer.cancel()
            self.get_logger().info(f"trajectory finished: {self.published} poses published")
            self._linger = self.create_timer(LINGER_S, self._finish)

    def _finish(self) -> None:
        if self._linger is not None:
            self._linger.cancel()
        self.done.set_result(self.published)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``pose_publisher``; returns the process exit code."""
    return run_node(PosePublisher, prog=NODE_NAME, summary=SUMMARY, specs=PARAMETERS, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
