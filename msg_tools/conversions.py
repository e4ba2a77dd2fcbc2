"""Conversions between ROS 2 messages and numpy arrays.

Conventions (docs/ARCHITECTURE.md, "Contracts"): poses are ``[px, py, pz, qx, qy, qz, qw]``
(metres, unit quaternion in ROS xyzw order); time stamps are integer
nanoseconds where a single number is needed.

These helpers build ordinary rclpy message objects and are meant for the
non-hot paths (poses, counts, tests, reading recordings). The per-frame
TRIANGLE_LIST marker is built without Python objects by
:class:`msg_tools.markers.TriangleListMarker`; this module's
:func:`triangle_marker_naive` is the field-by-field reference it is tested
against.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseStamped
from std_msgs.msg import ColorRGBA, Int32MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker

NS_PER_S = 1_000_000_000

# Fields of the `collision_counts` topic, in data order. Each is one entry of
# Int32MultiArray.data and is named by the dimension with the same index in
# layout.dim (label = field name, size = 1, stride = 1). The first four are
# always present; the others are optional extras a publisher may add.
COLLISION_COUNT_LABELS: tuple[str, ...] = (
    "vertex_face_before",      # crossings found by the fast check after the GNN step
    "edge_edge_before",
    "vertex_face_after",       # crossings left after the collision-aware correction
    "edge_edge_after",
    "penetrating_vertices_after",  # object vertices with tool SDF < 0 in the published mesh
    "correction_iterations",   # iterations the correction used this step
    "fallback",                # 1 when the correction budget ran out and the safe fallback was used
    "substeps",                # model steps taken to reach this pose (large jumps are subdivided)
    "self_pairs_before",       # object self pairs closer than the self clearance in the step, after the tool pass
    "self_pairs_after",        # ... left after the self-contact stage (0: the object never passes through itself)
    "invalid_faces_before",    # surface triangles flipped, collapsed or torn against rest, after the tool pass
    "invalid_faces_after",     # ... left after the self-contact stage
    "self_fallback",           # 1 when the self-contact stage used its certified fallback
)
REQUIRED_COLLISION_COUNT_LABELS: tuple[str, ...] = COLLISION_COUNT_LABELS[:4]

_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


# --------------------------------------------------------------------------- time

def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (>= 0) -> builtin_interfaces/Time."""
    ns = int(ns)
    if ns < 0:
        raise ValueError(f"time stamp must be >= 0 ns, got {ns}")
    sec, nanosec = divmod(ns, NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


# --------------------------------------------------------------------------- poses

def pose_to_array(msg: Pose | PoseStamped) -> np.ndarray:
    """geometry_msgs/Pose or PoseStamped -> float64 [7] (px,py,pz,qx,qy,qz,qw).

    No validation: the caller (the node) decides what a bad pose is.
    """
    pose = msg.pose if isinstance(msg, PoseStamped) else msg
    p, q = pose.position, pose.orientation
    return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=np.float64)


def array_to_pose(pose: np.ndarray | Sequence[float]) -> Pose:
    """float [7] (px,py,pz,qx,qy,qz,qw) -> geometry_msgs/Pose."""
    a = np.asarray(pose, dtype=np.float64)
    if a.shape != (7,):
        raise ValueError(f"pose must have shape (7,), got {a.shape}")
    msg = Pose()
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in a[:3])
    (msg.orientation.x, msg.orientation.y,
     msg.orientation.z, msg.orientation.w) = (float(v) for v in a[3:])
    return msg


def array_to_pose_stamped(pose: np.ndarray | Sequence[float], frame_id: str,
                          stamp: Time | int) -> PoseStamped:
    """float [7] -> geometry_msgs/PoseStamped; `stamp` is a Time or integer ns."""
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp if isinstance(stamp, Time) else ns_to_stamp(stamp)
    msg.pose = array_to_pose(pose)
    return msg


# --------------------------------------------------------------------------- collision counts

def counts_to_msg(counts: Mapping[str, int]) -> Int32MultiArray:
    """{label: count} -> std_msgs/Int32MultiArray with one labelled dimension per field.

    The four REQUIRED_COLLISION_COUNT_LABELS must be present; other keys must be
    among COLLISION_COUNT_LABELS. Fields keep the order of COLLISION_COUNT_LABELS.
    """
    unknown = sorted(set(counts) - set(COLLISION_COUNT_LABELS))
    if unknown:
        raise ValueError(f"unknown collision count labels {unknown}; valid: {list(COLLISION_COUNT_LABELS)}")
    missing = [k for k in REQUIRED_COLLISION_COUNT_LABELS if k not in counts]
    if missing:
        raise ValueError(f"missing collision count labels {missing}")
    labels = [k for k in COLLISION_COUNT_LABELS if k in counts]
    values = []
    for k in labels:
        v = counts[k]
        if isinstance(v, (bool, np.bool_)) or not float(v).is_integer() or not _INT32_MIN <= int(v) <= _INT32_MAX:
            raise ValueError(f"collision count {k!r} must be an int32 integer, got {v!r}")
        values.append(int(v))
    msg = Int32MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=k, size=1, stride=1) for k in labels]
    msg.layout.data_offset = 0
    msg.data = values
    return msg


def msg_to_counts(msg: Int32MultiArray) -> dict[str, int]:
    """std_msgs/Int32MultiArray written by counts_to_msg -> {label: count}."""
    labels = [d.label for d in msg.layout.dim]
    data = list(msg.data)
    off = int(msg.layout.data_offset)
    if len(data) - off != len(labels):
        raise ValueError(f"collision counts: {len(labels)} labels but {len(data) - off} values")
    return {k: int(v) for k, v in zip(labels, data[off:])}


# --------------------------------------------------------------------------- diagnostics

def diagnostic_array(stamp: Time | int, name: str, values: Mapping[str, object], *,
                     level: int | bytes = 0, message: str = "", hardware_id: str = "") -> DiagnosticArray:
    """One-status diagnostic_msgs/DiagnosticArray; values become KeyValue strings (floats with 6 significant digits).

    level: 0..3 or DiagnosticStatus.OK / WARN / ERROR / STALE (bytes in rclpy).
    """
    if isinstance(level, (bytes, bytearray)) and len(level) == 1:
        level = level[0]
    if level not in (0, 1, 2, 3):
        raise ValueError(f"diagnostic level must be 0..3 (OK, WARN, ERROR, STALE), got {level}")
    kv = [KeyValue(key=str(k), value=f"{v:.6g}" if isinstance(v, float) else str(v)) for k, v in values.items()]
    arr = DiagnosticArray()
    arr.header.stamp = stamp if isinstance(stamp, Time) else ns_to_stamp(stamp)
    arr.status = [DiagnosticStatus(level=bytes([level]), name=name, message=message,
                                   hardware_id=hardware_id, values=kv)]
    return arr


def diagnostic_values(arr: DiagnosticArray, name: str) -> dict[str, str]:
    """KeyValues of the status called `name` in a DiagnosticArray (KeyError if absent)."""
    for st in arr.status:
        if st.name == name:
            return {kv.key: kv.value for kv in st.values}
    raise KeyError(f"no diagnostic status named {name!r}; have {[st.name for st in arr.status]}")


# --------------------------------------------------------------------------- meshes

def check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate and normalise a triangle mesh: float64 [N,3] finite, int64 [F,3] in range, F > 0."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F > 0, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integers, got {f.dtype}")
    f = f.astype(np.int64, copy=False)
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(f"face indices must lie in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")
    if not np.isfinite(v).all():
        raise ValueError("vertices contain NaN or inf")
    return v, f


def triangle_marker_naive(vertices: np.ndarray, faces: np.ndarray, *,
                          colors: np.ndarray | None = None,
                          color: Sequence[float] = (0.8, 0.8, 0.8, 1.0),
                          frame_id: str = "world", ns: str = "", marker_id: int = 0,
                          stamp: Time | int = 0,
                          pose: np.ndarray | Sequence[float] | None = None) -> Marker:
    """The reference TRIANGLE_LIST Marker, built field by field with one Point per corner.

    vertices [N,3] (m), faces [F,3]; colors optional per-vertex RGBA [N,4] in [0,1].
    `pose` is the marker frame in `frame_id` ([7], identity when None). Slow
    (tens of ms for 36k corners): the benchmark's baseline and the tests' oracle.
    """
    v, f = check_mesh(vertices, faces)
    m = Marker()
    m.header.frame_id = frame_id
    m.header.stamp = stamp if isinstance(stamp, Time) else ns_to_stamp(stamp)
    m.ns = ns
    m.id = int(marker_id)
    m.type = Marker.TRIANGLE_LIST
    m.action = Marker.ADD
    m.pose = array_to_pose(np.array([0, 0, 0, 0, 0, 0, 1.0]) if pose is None else pose)
    m.scale.x = m.scale.y = m.scale.z = 1.0  # TRIANGLE_LIST scales the points; 1 = metres as given
    m.color = ColorRGBA(r=float(color[0]), g=float(color[1]), b=float(color[2]), a=float(color[3]))
    corners = v[f.reshape(-1)]
    m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in corners.tolist()]
    if colors is not None:
        c = np.asarray(colors, dtype=np.float32)
        if c.shape != (v.shape[0], 4):
            raise ValueError(f"colors must have shape ({v.shape[0]}, 4), got {c.shape}")
        m.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in c[f.reshape(-1)].tolist()]
    return m


def marker_corners(msg: Marker) -> np.ndarray:
    """TRIANGLE_LIST Marker -> per-triangle corners float64 [F,3,3] in the marker frame.

    (The marker's `pose` is not applied; use `marker_world_corners` for that.)
    """
    if msg.type != Marker.TRIANGLE_LIST:
        raise ValueError(f"expected a TRIANGLE_LIST marker (type {Marker.TRIANGLE_LIST}), got type {msg.type}")
    n = len(msg.points)
    if n % 3:
        raise ValueError(f"TRIANGLE_LIST marker has {n} points, not a multiple of 3")
    flat = np.fromiter((c for p in msg.points for c in (p.x, p.y, p.z)), dtype=np.float64, count=3 * n)
    return flat.reshape(n // 3, 3, 3)


def marker_corner_colors(msg: Marker) -> np.ndarray | None:
    """Per-corner RGBA float32 [F,3,4] of a TRIANGLE_LIST Marker, or None without per-point colours."""
    if len(msg.colors) == 0:
        return None
    n = len(msg.colors)
    flat = np.fromiter((c for q in msg.colors for c in (q.r, q.g, q.b, q.a)), dtype=np.float32, count=4 * n)
    return flat.reshape(n // 3, 3, 4)


def marker_world_corners(msg: Marker) -> np.ndarray:
    """Corners [F,3,3] of a TRIANGLE_LIST Marker transformed by its pose into header.frame_id."""
    return apply_pose(marker_corners(msg), pose_to_array(msg.pose))


def apply_pose(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Transform points [...,3] given in a frame with `pose` [7] (xyzw) into the parent frame."""
    x, y, z, w = (float(c) for c in pose[3:])
    n = x * x + y * y + z * z + w * w
    s = 2.0 / n if n > 0 else 0.0
    rot = np.array([
        [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
    ])
    return np.asarray(points, dtype=np.float64) @ rot.T + np.asarray(pose[:3], dtype=np.float64)


def weld_corners(corners: np.ndarray, decimals: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Triangle soup [F,3,3] -> indexed mesh (vertices [V,3], faces [F,3]) by merging equal corners.

    Exact equality by default (the marker carries the float64 positions
    unchanged); pass `decimals` to merge corners equal after rounding.
    Vertex order is sorted, not the publisher's.
    """
    c = np.asarray(corners, dtype=np.float64)
    if c.ndim != 3 or c.shape[1:] != (3, 3):
        raise ValueError(f"corners must have shape (F, 3, 3), got {c.shape}")
    flat = c.reshape(-1, 3)
    key = flat if decimals is None else np.round(flat, decimals)
    verts, inverse = np.unique(key, axis=0, return_inverse=True)
    return verts, inverse.reshape(-1, 3).astype(np.int64)
