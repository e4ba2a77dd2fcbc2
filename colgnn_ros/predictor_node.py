"""``predictor``: the real-time node. Tool poses in, the deforming object mesh out.

A thin shell over :class:`colgnn_core.runtime.predictor.Predictor` (GNN step + collision-aware correction)
and msg_tools (marker bytes, counts, diagnostics):

- in: ``tool_pose`` (geometry_msgs/PoseStamped, best-effort, depth 1). The callback only stores the
  latest pose (and wakes the step callback).
- stepping: the model's dt (from the checkpoint; no parameter changes it) paces the Predictor. A
  timer with period dt steps it with the latest unprocessed pose. With ``step_on_arrival`` (default)
  a pose whose *stamp* is at least 0.75 dt after the last stepped pose's is stepped at once instead
  of waiting up to dt for the next tick, and the timer restarts with each step (so a pose that comes
  early in pose time is stepped dt after the previous one, unless a newer pose supersedes it).
  Judging "early" by the stamps, not by the node's wall clock, matters: with a wall-clock rule the
  publisher's and the node's clocks can lock into a phase where every pose waits for the timer (a
  300 s full-resolution cone_bunny run measured 37 ms median latency that way, 17 ms without).
- out (reliable): ``deformed_mesh`` (Marker TRIANGLE_LIST of the object surface, optionally coloured
  by the distance to the tool), ``tool_marker`` (the tool mesh at the pose used), ``collision_counts``
  (Int32MultiArray, labelled fields), ``/diagnostics`` (1 Hz: step ms median/p95, rate, fallbacks,
  rejected poses per reason). Output stamps are the input pose's stamp.
- optional live view (``foxglove_port`` > 0): the same mesh, tool and counts on the Foxglove SDK's WebSocket
  server at ws://127.0.0.1:PORT (msg_tools.foxglove_live); its errors are logged, never fatal.
- service ``reset`` (std_srvs/Trigger): object back at rest, tool at its rest pose.
- bad input (NaN, non-unit quaternion, wrong frame_id, stale or out-of-order stamp, outside the
  workspace, a jump needing more than ``max_substeps`` model steps) is rejected with a throttled
  warning and a counter; the last good state is kept.

    predictor --ros-args -p scene:=sphere_mat
    predictor --ros-args -p checkpoint:=model.pt -p scene:=cone_bunny -p correction:=false
    predictor --ros-args -p foxglove_port:=8765    # live view: Foxglove -> Open connection -> ws://localhost:8765
    predictor --help
"""

from __future__ import annotations

import faulthandler
import time
from collections import deque
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from std_msgs.msg import Int32MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import stats
from colgnn_core.geometry.transforms import validate_pose
from colgnn_core.runtime.models import checkpoint_resolution, shipped_checkpoint
from colgnn_core.runtime.predictor import REALTIME_INTERIOR, Predictor, self_contact_default
from colgnn_core.runtime.threads import auto_threads
from colgnn_core.scenes import load_scene, scene_names
from colgnn_ros.common import OUTPUT_QOS, POSE_QOS, ParamSpec, declare_parameters, run_node
from msg_tools.conversions import (COLLISION_COUNT_LABELS, NS_PER_S, counts_to_msg, diagnostic_array, pose_to_array,
                                   stamp_to_ns)
from msg_tools.foxglove_live import LiveView
from msg_tools.markers import DistanceColormap, TriangleListMarker

NODE_NAME = "predictor"
EARLY_STEP_FRACTION = 0.75   # step_on_arrival: a pose is stepped at once when its stamp is this many dt after the last
DIAGNOSTICS_PERIOD_S = 1.0
WARN_PERIOD_S = 2.0          # at most one warning per rejection reason per this many seconds
STEP_WINDOW = 250            # step times kept for the diagnostics' median / p95
PACE_WINDOW = 20             # steps whose median step time is compared with dt (the "cannot keep up" warning)

#: Rejection reasons, in the order the checks run; each is a diagnostics counter ``rejected_<reason>``.
REJECT_REASONS = ("nan", "non_unit", "frame_id", "stale", "out_of_order", "outside_workspace", "jump")

SUMMARY = ("Steps the colgnn Predictor (GNN + collision-aware correction) with the tool poses on 'tool_pose' at the "
           "model's dt and publishes the deformed mesh and the tool (visualization_msgs/Marker TRIANGLE_LIST), "
           "collision counts and /diagnostics; service 'reset' (std_srvs/Trigger).")

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("scene", "sphere_mat", "scene of the model (the checkpoint must be trained for it)",
              choices=tuple(scene_names())),
    ParamSpec("checkpoint", "", "model checkpoint (.pt); empty: the shipped model of the scene. The step dt is "
              "the checkpoint's"),
    ParamSpec("frame_id", "world", "frame of the poses (others are rejected) and of the markers"),
    ParamSpec("correction", True, "run the collision-aware correction after each GNN step"),
    ParamSpec("max_substeps", 16, "most model steps one pose may take (a larger jump is rejected)", range=(1, 1000)),
    ParamSpec("publish_tool_marker", True, "publish the tool mesh on 'tool_marker'"),
    ParamSpec("color_by_distance", True, "colour the mesh by the distance to the tool (per-vertex colours)"),
    ParamSpec("max_pose_age", 0.5, "reject poses whose stamp is older than this (s) on arrival at the step; "
              "0 disables the check", range=(0.0, 3600.0)),
    ParamSpec("step_on_arrival", True, "step a pose as soon as it arrives when its stamp is at least 0.75 dt after the "
              "last stepped pose's (false: only the dt timer steps, adding up to dt of latency)"),
    ParamSpec("threads", 0, "torch intra-op threads; 0: chosen for the machine (1 up to 4 cores, where a 2-thread "
              "pool collapses once another process holds a core; else half the cores, at most 4)", range=(0, 256)),
    ParamSpec("limits", "data", "cap the network output by its training data's extremes ('data': 2x the largest "
              "per-step motion, 1.5x the largest distance from rest; bounds a long run's drift) or not ('none')",
              choices=("data", "none")),
    ParamSpec("rest_relaxation", 0.05,  # = predictor.RECOMMENDED_REST_RELAXATION (torch-free import here)
              "while the tool is out of the network's reach, move the object this fraction "
              "of the way back to its rest shape per step (the objects are elastic; a learned model drifts instead); "
              "0 disables", range=(0.0, 0.99)),
    ParamSpec("self_contact", False, "also keep the object from passing through itself and its surface valid (no "
              "flipped or torn faces; docs/COLLISION_GUARANTEE.md). Default: the scene's [correction] self_contact "
              "at the model's resolution (on for sphere_mat, cylinder_banana and cone_bunny's full model, whose steps "
              "are mostly valid surfaces, so the stage costs 1-3 ms; off for knife_torus, where it ruins the deep "
              "cuts)", default_text="the scene's [correction] self_contact"),
    ParamSpec("compile", True, "torch.compile the network at start-up (~1.8x faster GNN step; a few seconds with "
              "torch's disk cache, which make setup warms, 10-30 s without); falls back to eager with a warning"),
    ParamSpec("foxglove_port", 0, "live view: serve the mesh, the tool and the collision counts to the Foxglove app "
              "on ws://127.0.0.1:PORT (Foxglove SDK WebSocket; pip install foxglove-sdk); 0: off",
              range=(0, 65535)),
)


def _scene_self_contact(values: dict) -> bool:
    """The scene's ``[correction] self_contact`` at the resolution of the model the node will run (a
    ``[correction.full]`` table may turn the stage on for the full-resolution model only)."""
    scene = str(values["scene"])
    resolution = checkpoint_resolution(values["checkpoint"] or shipped_checkpoint(scene))
    return self_contact_default(load_scene(scene, resolution))


#: Parameters whose default is the scene's own setting (from the ``scene`` and ``checkpoint`` parameters, declared
#: before them).
SCENE_DEFAULTS = {"self_contact": _scene_self_contact}


class PredictorNode(Node):
    """The ``predictor`` node (see module docstring). Raises InputError for bad parameters.

    Node keyword arguments (context, parameter_overrides, ...) pass through to rclpy. ``stats``
    holds the counters that /diagnostics reports.
    """

    def __init__(self, **node_kwargs) -> None:
        started = time.monotonic()
        super().__init__(NODE_NAME, **node_kwargs)
        try:
            self.params = p = declare_parameters(self, PARAMETERS, defaults=SCENE_DEFAULTS)
            if not p["frame_id"].strip():
                raise InputError("parameter 'frame_id' must not be empty")
            self.predictor = self._load_predictor(p)
        except BaseException:
            self.destroy_node()
            raise
        pred = self.predictor
        self.scene = pred.scene
        self.frame_id: str = p["frame_id"]
        self.dt = float(pred.loaded.meta.dt)
        self.max_pose_age_ns = int(p["max_pose_age"] * NS_PER_S)
        self.step_on_arrival: bool = p["step_on_arrival"]
        self.publish_tool: bool = p["publish_tool_marker"]

        surface_ids = pred.surface_vertex_ids
        local = np.full(pred.scene.object.vertices.shape[0], -1, dtype=np.int64)
        local[surface_ids] = np.arange(len(surface_ids))
        self._surface_ids = surface_ids
        self._mesh_marker = TriangleListMarker(local[pred.surface_faces], len(surface_ids), frame_id=self.frame_id,
                                               ns="deformed_mesh", color=(0.35, 0.55, 0.85, 1.0),
                                               per_vertex_colors=p["color_by_distance"])
        self._colormap = (DistanceColormap(0.0, 0.1 * pred.scene.bbox_diagonal(), "viridis")
                          if p["color_by_distance"] else None)
        self._tool_marker = TriangleListMarker(pred.tool_faces, pred.scene.tool.vertices.shape[0],
                                               frame_id=self.frame_id, ns="tool", color=(0.6, 0.6, 0.65, 0.6))
        self._live = self._start_live_view(p["foxglove_port"], local[pred.surface_faces], pred.tool_faces)

        self.stats: dict[str, int] = {"poses_received": 0, "poses_superseded": 0, "steps": 0, "model_steps": 0,
                                      "fallbacks": 0, "out_of_domain": 0, "resets": 0, "publish_errors": 0,
                                      "self_contact_steps": 0, "invalid_surface_steps": 0, "self_fallbacks": 0}
        self.stats.update({f"rejected_{r}": 0 for r in REJECT_REASONS})
        self._step_ms: deque[float] = deque(maxlen=STEP_WINDOW)
        self._step_times: deque[float] = deque(maxlen=STEP_WINDOW)  # time.monotonic() of each step
        self._last_warn: dict[str, float] = {}
        self._pending: PoseStamped | None = None
        self._last_stamp_ns: int | None = None   # stamp of the last stepped pose (out-of-order check)
        self._last_step_t = -np.inf               # time.monotonic() of the last step

        self._mesh_pub = self.create_publisher(Marker, "deformed_mesh", OUTPUT_QOS)
        self._tool_pub = self.create_publisher(Marker, "tool_marker", OUTPUT_QOS) if self.publish_tool else None
        self._counts_pub = self.create_publisher(Int32MultiArray, "collision_counts", OUTPUT_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", OUTPUT_QOS)
        self._sub = self.create_subscription(PoseStamped, "tool_pose", self._on_pose, POSE_QOS)
        self._srv = self.create_service(Trigger, "reset", self._on_reset)
        self._timer = self.create_timer(self.dt, self._tick)
        self._wake = self.create_guard_condition(self._on_arrival)
        self._diag_timer = self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        self.get_logger().info(
            f"scene {self.scene.name} ({self.scene.resolution}), checkpoint {self.checkpoint_name}, dt {self.dt:g} s, "
            f"correction {'on' if pred.correction else 'off'}, {len(surface_ids)} surface vertices, "
            f"{pred.threads} thread(s), {'compiled' if pred.compiled else 'eager'} network; "
            f"listening on {self._sub.topic_name}, frame '{self.frame_id}'; ready in "
            f"{time.monotonic() - started:.1f} s")
        self._slow_warned = False

    # -- set-up -----------------------------------------------------------------------------------------------------
    def _load_predictor(self, p: dict):
        path = p["checkpoint"] or str(shipped_checkpoint(p["scene"]))
        self.checkpoint_name = path
        pred = Predictor.from_checkpoint(path, correction=p["correction"], max_substeps=p["max_substeps"],
                                         threads=p["threads"] or auto_threads(), compile=p["compile"],
                                         limits=p["limits"], self_contact=p["self_contact"],
                                         rest_relaxation=p["rest_relaxation"], warm_up=True,
                                         interior=REALTIME_INTERIOR)  # only the surface is published
        if pred.scene.name != p["scene"]:
            raise InputError(f"parameter 'checkpoint': {path} is a {pred.scene.name!r} model, not {p['scene']!r} "
                             f"(set scene:={pred.scene.name})")
        return pred

    def _start_live_view(self, port: int, object_faces: np.ndarray, tool_faces: np.ndarray) -> LiveView | None:
        """The Foxglove live view on ``port`` (0: none). A failure to start is logged; the node runs without it."""
        if not port:
            return None
        try:
            live = LiveView(port, object_faces, tool_faces, frame_id=self.frame_id, count_labels=COLLISION_COUNT_LABELS)
        except Exception as exc:  # optional: a missing SDK or a port in use must not stop the node
            self.get_logger().error(f"Foxglove live view not started on port {port}: {exc}")
            return None
        self.get_logger().info(f"Foxglove live view on {live.url} (Foxglove: Open connection -> Foxglove WebSocket)")
        return live

    def destroy_node(self) -> None:
        live = getattr(self, "_live", None)
        if live is not None:
            self._live = None
            live.close()
        super().destroy_node()

    # -- callbacks --------------------------------------------------------------------------------------------------
    def _on_pose(self, msg: PoseStamped) -> None:
        self.stats["poses_received"] += 1
        if self._pending is not None:
            self.stats["poses_superseded"] += 1
        self._pending = msg
        if self.step_on_arrival:
            self._wake.trigger()

    def _tick(self) -> None:
        """Timer (every dt): step the latest unprocessed pose, if any."""
        if self._pending is not None:
            msg, self._pending = self._pending, None
            self.process_pose(msg)

    def _on_arrival(self) -> None:
        """Wake-up (a pose arrived, step_on_arrival): step it now unless it is early in pose time."""
        if self._pending is not None and not self._too_early(self._pending):
            self._tick()

    def _too_early(self, msg: PoseStamped) -> bool:
        """Whether ``msg`` is less than EARLY_STEP_FRACTION x dt after the last stepped pose, in pose time."""
        if self._last_stamp_ns is None:
            return False
        return stamp_to_ns(msg.header.stamp) - self._last_stamp_ns < EARLY_STEP_FRACTION * self.dt * NS_PER_S

    def process_pose(self, msg: PoseStamped) -> bool:
        """Check ``msg``, step the Predictor and publish; False (state kept) if the pose was rejected."""
        pose, stamp_ns = self._check(msg)
        if pose is None:
            return False
        started = time.monotonic()
        try:
            res = self.predictor.step(pose)
        except InputError as exc:  # checked above; kept so that no pose can end the node
            self._reject("jump", str(exc))
            return False
        self._last_step_t = started
        if self.step_on_arrival:
            self._timer.reset()  # paced from the step's start: the next timer step is a full dt after this one
        self._last_stamp_ns = stamp_ns
        try:
            self._publish(res, msg.header.stamp)
        except ValueError as exc:  # e.g. a non-finite mesh: never sent, never fatal
            self.stats["publish_errors"] += 1
            self._warn("publish", f"step result not published: {exc}")
        st = self.stats
        st["steps"] += 1
        st["model_steps"] += res.substeps
        st["fallbacks"] += int(res.fallback)
        # Self-contact stage: steps whose tool-corrected shape touched itself / had invalid triangles (repaired).
        st["self_contact_steps"] += int(res.self_pairs_before > 0)
        st["invalid_surface_steps"] += int(res.invalid_faces_before > 0)
        st["self_fallbacks"] += int(res.self_fallback)
        if res.out_of_domain and not st["out_of_domain"]:
            self._warn("out_of_domain", "the tool or the shape is outside the model's training data: the published "
                       "shape is an extrapolation (counted in /diagnostics 'out_of_domain')")
        st["out_of_domain"] += res.out_of_domain
        self._step_ms.append(res.timings_ms["total"])
        self._step_times.append(self._last_step_t)
        self._check_pace()
        return True

    def _check_pace(self) -> None:
        """Say once when the step cannot keep up with the model's dt (poses are then superseded, not queued)."""
        if self._slow_warned or len(self._step_ms) < PACE_WINDOW:
            return
        median = float(np.median(list(self._step_ms)[-PACE_WINDOW:]))
        if median > 1e3 * self.dt:
            self._slow_warned = True
            self.get_logger().warning(
                f"cannot keep up: the step takes {median:.1f} ms (median of the last {PACE_WINDOW}), more than the "
                f"model's dt {1e3 * self.dt:g} ms; newer poses supersede the waiting one "
                f"({self.stats['poses_superseded']} so far, 'poses_superseded' in /diagnostics). Try compile:=true, "
                f"another threads value, or a smaller model")

    def _check(self, msg: PoseStamped) -> tuple[np.ndarray | None, int]:
        """(validated pose, stamp ns), or (None, stamp) after counting and warning about a rejection."""
        raw = pose_to_array(msg)
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if not np.all(np.isfinite(raw)):
            return self._reject("nan", "pose contains NaN or inf"), stamp_ns
        try:
            validate_pose(raw)
        except InputError as exc:
            return self._reject("non_unit", str(exc)), stamp_ns
        if msg.header.frame_id != self.frame_id:
            return self._reject("frame_id", f"pose frame_id {msg.header.frame_id!r}, expected {self.frame_id!r}"), \
                stamp_ns
        if self.max_pose_age_ns:
            age = self.get_clock().now().nanoseconds - stamp_ns
            if age > self.max_pose_age_ns:
                return self._reject("stale", f"pose stamp is {age / NS_PER_S:.3f} s old "
                                             f"(max_pose_age {self.max_pose_age_ns / NS_PER_S:g} s)"), stamp_ns
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            return self._reject("out_of_order", f"pose stamp {stamp_ns / NS_PER_S:.6f} s is not after the last "
                                                f"stepped pose's {self._last_stamp_ns / NS_PER_S:.6f} s"), stamp_ns
        try:
            pose = self.scene.check_pose(raw)
        except InputError as exc:
            return self._reject("outside_workspace", str(exc)), stamp_ns
        try:
            pose, _ = self.predictor.check(pose)
        except InputError as exc:
            return self._reject("jump", str(exc)), stamp_ns
        return pose, stamp_ns

    def _reject(self, reason: str, text: str) -> None:
        key = f"rejected_{reason}"
        self.stats[key] += 1
        self._warn(reason, f"rejected pose ({reason}, {self.stats[key]} so far): {text}; keeping the last good state")
        return None

    def _warn(self, kind: str, text: str) -> None:
        """A warning, at most one per ``kind`` every WARN_PERIOD_S."""
        now = time.monotonic()
        if now - self._last_warn.get(kind, -np.inf) >= WARN_PERIOD_S:
            self._last_warn[kind] = now
            self.get_logger().warning(text)

    def _publish(self, res, stamp) -> None:
        surface = res.positions[self._surface_ids]
        colors = None
        if self._colormap is not None:
            colors = self._colormap(self.scene.tool.sdf(surface, res.tool_pose))
        self._mesh_pub.publish(self._mesh_marker.build(surface, stamp, colors=colors))
        if self._tool_pub is not None:
            self._tool_pub.publish(self._tool_marker.build(res.tool_vertices, stamp))
        self._counts_pub.publish(counts_to_msg(res.collision_counts()))
        if self._live is not None:
            self._publish_live(stamp_to_ns(stamp), surface, res, colors)

    def _publish_live(self, stamp_ns: int, surface: np.ndarray, res, colors: np.ndarray | None) -> None:
        """The step on the Foxglove live view; its errors are warned about (throttled), never raised."""
        try:
            self._live.publish(stamp_ns, surface, res.tool_vertices, res.collision_counts(), colors)
        except Exception as exc:  # the live view is optional: never let it stop the node
            self._warn("live_view", f"Foxglove live view not updated: {exc}")

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        steps = self.stats["steps"]
        self.predictor.reset()
        self._pending = None
        self._last_stamp_ns = None
        self.stats["resets"] += 1
        response.success = True
        response.message = f"reset to rest after {steps} steps"
        self.get_logger().info(response.message)
        return response

    # -- diagnostics ------------------------------------------------------------------------------------------------
    def diagnostics_values(self) -> dict[str, object]:
        """The /diagnostics key-values (also handy in tests)."""
        step = stats(self._step_ms, empty=0.0)
        now = time.monotonic()
        recent = [t for t in self._step_times if now - t <= 5.0]
        rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0
        values: dict[str, object] = {
            "scene": self.scene.name,
            "dt_s": self.dt,
            "step_ms_median": step["median"],
            "step_ms_p95": step["p95"],
            "rate_hz": float(rate),
        }
        values.update(self.stats)
        # Steps whose collision kernels ran on one thread because other processes held the cores (ContentionGuard).
        values["kernel_threads_reduced"] = self.predictor.kernel_guard.reduced_steps
        values["rejected_total"] = sum(self.stats[f"rejected_{r}"] for r in REJECT_REASONS)
        return values

    def _publish_diagnostics(self) -> None:
        values = self.diagnostics_values()
        rejected = values["rejected_total"]
        level = (DiagnosticStatus.WARN if rejected or self.stats["fallbacks"] or self.stats["out_of_domain"]
                 else DiagnosticStatus.OK)
        message = (f"{values['steps']} steps, {rejected} poses rejected, {self.stats['fallbacks']} fallbacks"
                   if values["steps"] or rejected else "waiting for tool poses")
        self._diag_pub.publish(diagnostic_array(self.get_clock().now().nanoseconds, f"{NODE_NAME}: {self.scene.name}",
                                                values, level=level, message=message,
                                                hardware_id=self.get_fully_qualified_name()))


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``predictor``; returns the process exit code."""
    # A fatal signal in native code (torch, numba, DDS) then leaves the Python stack of every thread in the log.
    # That is how the intermittent SIGSEGV on Ctrl-C was traced to tearing the node down after rclpy's own signal
    # handler had shut the context down (fixed in colgnn_ros.common.run_node).
    faulthandler.enable()
    return run_node(PredictorNode, prog=NODE_NAME, summary=SUMMARY, specs=PARAMETERS, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
