"""Fast visualization_msgs/Marker TRIANGLE_LIST messages for deforming meshes.

Why not the obvious way: a Marker's ``points`` is a sequence of
geometry_msgs/Point *messages*, so rclpy needs one Python object per corner
(36k for a 12k-face mesh) and converts each one to C again when publishing.
That costs tens of milliseconds per frame (see ``msg_tools.benchmark``);
rclpy Jazzy only accepts numpy arrays for sequences of primitives, not here.

How: :class:`TriangleListMarker` serializes the CDR bytes directly. At
construction it asks rclpy to serialize a probe Marker with the constant
fields (frame_id, ns, id, colour, ...) and one sentinel point/colour, finds
the sentinels to learn the byte layout, and preallocates the whole message
for the mesh's fixed number of corners. ``build()`` then only writes the
stamp, the pose and ``np.take(vertices, faces)`` (and colours) into that
buffer and returns ``bytes``, which ``rclpy.publisher.Publisher.publish``
sends as-is (it accepts serialized ``bytes`` and calls ``publish_raw``).
The layout is learnt from rclpy's own serializer, so it follows the
installed message definition (padding is zeroed through rosbags' serializer,
see :func:`canonical_cdr`); the tests compare the bytes against the
field-by-field Marker serialized by rclpy.
"""

from __future__ import annotations

import functools
import struct
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from rclpy.serialization import serialize_message
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

from .conversions import NS_PER_S, array_to_pose, check_mesh

IDENTITY_POSE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])

_CDR_LE = b"\x00\x01"          # encapsulation id of little-endian plain CDR (what Fast DDS writes)
_SENTINEL_POINT = (1.2345678912345678e-7, -2.3456789123456789e-7, 3.4567891234567891e-7)
_SENTINEL_COLOR = (0.123456789, 0.234567891, 0.345678912, 0.456789123)
_SENTINEL_POSE = (4.567891234567891e-7, -5.678912345678912e-7, 6.789123456789123e-7,
                  0.1234567891234567, 0.2345678912345678, 0.3456789123456789, 0.8976543219876543)
_SENTINEL_STAMP = (1_234_567_891, 987_654_321)


@functools.cache
def jazzy_typestore():
    """rosbags' typestore of the ROS 2 Jazzy message definitions (loaded once)."""
    from rosbags.typesys import Stores, get_typestore  # lazy: rosbags loads only when a bag is written or read

    return get_typestore(Stores.ROS2_JAZZY)


def canonical_cdr(raw: bytes, msgtype: str) -> bytes:
    """The same CDR message with zeroed padding bytes.

    rclpy's serializer leaves alignment padding uninitialised (heap garbage),
    so equal messages can differ in those bytes; rosbags' pure-Python
    serializer writes zeros. Used for the marker template and for byte-exact
    comparisons in tests. Slow for large messages.
    """
    ts = jazzy_typestore()
    return bytes(ts.serialize_cdr(ts.deserialize_cdr(raw, msgtype), msgtype))


def _find_once(data: bytes, pattern: bytes, what: str) -> int:
    """Offset of the single occurrence of `pattern` in `data` (the probe must be unambiguous)."""
    i = data.find(pattern)
    if i < 0 or data.find(pattern, i + 1) >= 0:
        raise RuntimeError(f"cannot locate the {what} in the serialized probe Marker")
    return i


class TriangleListMarker:
    """Preallocated serialized TRIANGLE_LIST Marker for a mesh with fixed connectivity.

    faces [F,3] index a vertex array of n_vertices rows. The Marker has 3F
    points (the unrolled triangle soup, as RViz and Foxglove require), scale
    1, frame `frame_id`, and either one colour for all triangles or (with
    ``per_vertex_colors=True``) a colour per corner taken from per-vertex
    RGBA passed to ``build``.

    ``build`` returns a new ``bytes`` each call (safe to keep or publish
    while building the next frame); it is not thread-safe on one instance.
    """

    def __init__(self, faces: np.ndarray, n_vertices: int, *, frame_id: str = "world",
                 ns: str = "", marker_id: int = 0,
                 color: Sequence[float] = (0.8, 0.8, 0.8, 1.0),
                 per_vertex_colors: bool = False, frame_locked: bool = False) -> None:
        if sys.byteorder != "little":  # the buffer views below write native (little-endian) floats
            raise RuntimeError("TriangleListMarker needs a little-endian host")
        _, f = check_mesh(np.zeros((int(n_vertices), 3)), faces)
        self.n_vertices = int(n_vertices)
        self.faces = f.copy()
        self._flat_faces = np.ascontiguousarray(self.faces.reshape(-1))
        self.n_corners = self._flat_faces.size
        self.per_vertex_colors = bool(per_vertex_colors)
        self.frame_id = frame_id

        probe = self._probe_message(frame_id, ns, marker_id, color, frame_locked, self.per_vertex_colors)
        raw = canonical_cdr(serialize_message(probe), "visualization_msgs/msg/Marker")
        if raw[:2] != _CDR_LE:
            raise RuntimeError(f"unexpected CDR encapsulation {raw[:4]!r}")

        stamp_off = _find_once(raw, struct.pack("<iI", *_SENTINEL_STAMP), "stamp")
        pose_off = _find_once(raw, struct.pack("<7d", *_SENTINEL_POSE), "pose")
        pts_off = _find_once(raw, struct.pack("<3d", *_SENTINEL_POINT), "point")
        # The uint32 sequence length precedes the first point, maybe followed by
        # 4 bytes of padding that align the first float64 to 8.
        if struct.unpack_from("<I", raw, pts_off - 4)[0] == 1:
            len_off = pts_off - 4
        elif struct.unpack_from("<II", raw, pts_off - 8) == (1, 0):
            len_off = pts_off - 8
        else:
            raise RuntimeError("cannot locate the points length in the serialized probe Marker")
        col_len_off = pts_off + 24
        n_probe_colors = 1 if self.per_vertex_colors else 0
        if struct.unpack_from("<I", raw, col_len_off)[0] != n_probe_colors:
            raise RuntimeError("unexpected colors length in the serialized probe Marker")
        if self.per_vertex_colors:
            col_off = _find_once(raw, struct.pack("<4f", *_SENTINEL_COLOR), "colour")
            if col_off != col_len_off + 4:
                raise RuntimeError("unexpected colour offset in the serialized probe Marker")
        tail = raw[col_len_off + 4 + 16 * n_probe_colors:]

        k = self.n_corners
        kc = k if self.per_vertex_colors else 0
        pad = pts_off - len_off - 4
        size = len_off + 4 + pad + 24 * k + 4 + 16 * kc + len(tail)
        # 4 bytes of slack so that the CDR body (which starts after the 4-byte
        # encapsulation header) sits at an 8-aligned address: aligned float64 views.
        store = np.zeros(size + 4, dtype=np.uint8)
        buf = store[4:]
        buf[:len_off] = np.frombuffer(raw, np.uint8, count=len_off)
        struct.pack_into("<I", buf, len_off, k)
        p0 = len_off + 4 + pad
        c_len = p0 + 24 * k
        struct.pack_into("<I", buf, c_len, kc)
        c0 = c_len + 4
        buf[c0 + 16 * kc:] = np.frombuffer(tail, np.uint8)

        self._buf = buf
        self._points = buf[p0:p0 + 24 * k].view(np.float64).reshape(k, 3)
        self._colors = buf[c0:c0 + 16 * kc].view(np.float32).reshape(kc, 4)
        self._stamp_view = buf[stamp_off:stamp_off + 8].view(np.uint32)  # sec (int32 bits), nanosec
        self._pose = buf[pose_off:pose_off + 56].view(np.float64)
        self._pose[:] = IDENTITY_POSE
        self._vertex_colors = np.empty((self.n_vertices, 4), dtype=np.float32)

    @staticmethod
    def _probe_message(frame_id: str, ns: str, marker_id: int, color: Sequence[float],
                       frame_locked: bool, with_color: bool) -> Marker:
        m = Marker()
        m.header.frame_id = frame_id
        m.header.stamp = Time(sec=_SENTINEL_STAMP[0], nanosec=_SENTINEL_STAMP[1])
        m.ns = ns
        m.id = int(marker_id)
        m.type = Marker.TRIANGLE_LIST
        m.action = Marker.ADD
        m.pose = array_to_pose(_SENTINEL_POSE)
        m.scale.x = m.scale.y = m.scale.z = 1.0
        r, g, b, a = (float(c) for c in color)
        m.color = ColorRGBA(r=r, g=g, b=b, a=a)
        m.frame_locked = bool(frame_locked)
        m.points = [Point(x=_SENTINEL_POINT[0], y=_SENTINEL_POINT[1], z=_SENTINEL_POINT[2])]
        if with_color:
            m.colors = [ColorRGBA(r=_SENTINEL_COLOR[0], g=_SENTINEL_COLOR[1],
                                  b=_SENTINEL_COLOR[2], a=_SENTINEL_COLOR[3])]
        return m

    def build(self, vertices: np.ndarray, stamp: Time | int, *, colors: np.ndarray | None = None,
              pose: np.ndarray | Sequence[float] | None = None) -> bytes:
        """Serialized Marker (CDR bytes, ready for Publisher.publish) for this frame.

        vertices: float [n_vertices,3] in the marker frame (m); stamp: Time or ns;
        colors: float RGBA [n_vertices,4] in [0,1], required iff per_vertex_colors;
        pose: [7] marker frame in frame_id (identity when None), e.g. the tool pose
        with tool-frame vertices.
        """
        v = vertices
        if not (isinstance(v, np.ndarray) and v.dtype == np.float64 and v.flags.c_contiguous):
            v = np.ascontiguousarray(v, dtype=np.float64)
        if v.shape != (self.n_vertices, 3):
            raise ValueError(f"vertices must have shape ({self.n_vertices}, 3), got {v.shape}")
        if not np.isfinite(v).all():  # ~10 us; a NaN mesh must never reach RViz
            raise ValueError("vertices contain NaN or inf")
        if isinstance(stamp, Time):
            sec, nanosec = int(stamp.sec), int(stamp.nanosec)
        else:
            sec, nanosec = divmod(int(stamp), NS_PER_S)
        if not (-(2**31) <= sec < 2**31 and 0 <= nanosec < NS_PER_S):
            raise ValueError(f"stamp out of range: sec={sec} nanosec={nanosec}")
        self._stamp_view[0] = sec & 0xFFFFFFFF
        self._stamp_view[1] = nanosec
        if pose is None:
            self._pose[:] = IDENTITY_POSE
        else:
            p = np.asarray(pose, dtype=np.float64)
            if p.shape != (7,):
                raise ValueError(f"pose must have shape (7,), got {p.shape}")
            self._pose[:] = p
        if self.per_vertex_colors:
            if colors is None:
                raise ValueError("this marker has per-vertex colours: pass colors [N,4]")
            c = np.asarray(colors)
            if c.shape != (self.n_vertices, 4):
                raise ValueError(f"colors must have shape ({self.n_vertices}, 4), got {c.shape}")
            if c.dtype != np.float32:
                np.copyto(self._vertex_colors, c, casting="same_kind")
                c = self._vertex_colors
            np.take(c, self._flat_faces, axis=0, out=self._colors)
        elif colors is not None:
            raise ValueError("this marker has one colour; build it with per_vertex_colors=True for colors")
        np.take(v, self._flat_faces, axis=0, out=self._points)
        return self._buf.tobytes()


class DistanceColormap:
    """Per-vertex RGBA from a distance (e.g. the tool SDF): `near` and below -> first colour, `far` -> last.

    A 256-entry lookup table of a matplotlib colormap, so colouring 6k
    vertices costs a clip, a multiply and one gather.
    """

    def __init__(self, near: float = 0.0, far: float = 0.05, colormap: str = "inferno",
                 alpha: float = 1.0) -> None:
        if not (np.isfinite(near) and np.isfinite(far) and far > near):
            raise ValueError(f"need finite near < far, got near={near} far={far}")
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        import matplotlib  # local: only nodes that colour by distance pay for the import

        try:
            cmap = matplotlib.colormaps[colormap]
        except KeyError:
            raise ValueError(f"unknown colormap {colormap!r}") from None
        self.near, self.far = float(near), float(far)
        self.lut = np.asarray(cmap(np.linspace(0.0, 1.0, 256)), dtype=np.float32)
        self.lut[:, 3] = alpha
        self._scale = 255.0 / (self.far - self.near)

    def __call__(self, distances: np.ndarray) -> np.ndarray:
        """distances [N] (m) -> RGBA float32 [N,4]; NaN maps to the `far` colour."""
        d = np.asarray(distances, dtype=np.float64)
        t = np.nan_to_num((d - self.near) * self._scale, nan=255.0)
        idx = np.clip(t, 0.0, 255.0).astype(np.intp)
        return self.lut[idx]


@dataclass(frozen=True)
class MarkerArrays:
    """The fields of a serialized Marker that a mesh consumer needs, as numpy arrays.

    corners [F,3,3] float64 (triangle soup, marker frame), corner_colors
    [F,3,4] float32 or None, pose [7], scale [3], color [4].
    """

    stamp_ns: int
    frame_id: str
    ns: str
    id: int
    type: int
    action: int
    pose: np.ndarray
    scale: np.ndarray
    color: np.ndarray
    frame_locked: bool
    corners: np.ndarray
    corner_colors: np.ndarray | None


def parse_marker_cdr(raw: bytes | bytearray | memoryview) -> MarkerArrays:
    """Read a serialized visualization_msgs/Marker (raw subscription, bag) without Python objects per point.

    Reads the fields up to `colors` (the rest, texture and mesh file, is not
    used by TRIANGLE_LIST meshes). ~0.1 ms for 36k corners, against tens of ms
    for ``deserialize_message``. ValueError on a truncated or big-endian message.
    """
    mv = memoryview(raw).cast("B")
    if len(mv) < 4 or bytes(mv[:2]) != _CDR_LE:
        raise ValueError("not a little-endian CDR message")
    body = mv[4:]
    o = 0

    def align(o: int, n: int) -> int:
        return (o + n - 1) // n * n

    def string(o: int) -> tuple[str, int]:
        o = align(o, 4)
        (n,) = struct.unpack_from("<I", body, o)
        s = bytes(body[o + 4:o + 4 + max(n - 1, 0)]).decode("utf-8")  # n counts the NUL
        return s, o + 4 + n

    try:
        sec, nanosec = struct.unpack_from("<iI", body, 0)
        frame_id, o = string(8)
        ns, o = string(o)
        o = align(o, 4)
        mid, mtype, action = struct.unpack_from("<iii", body, o)
        o = align(o + 12, 8)
        head = np.frombuffer(body, np.float64, count=10, offset=o)  # pose (7) + scale (3)
        o += 80
        color = np.frombuffer(body, np.float32, count=4, offset=o).copy()
        o += 16 + 8  # color, lifetime
        frame_locked = bool(body[o])
        o = align(o + 1, 4)
        (k,) = struct.unpack_from("<I", body, o)
        o += 4
        if k:
            o = align(o, 8)
        if k % 3:
            raise ValueError(f"TRIANGLE_LIST marker has {k} points, not a multiple of 3")
        corners = np.frombuffer(body, np.float64, count=3 * k, offset=o).reshape(k // 3, 3, 3).copy()
        o += 24 * k
        (kc,) = struct.unpack_from("<I", body, o)
        o += 4
        corner_colors = None
        if kc:
            if kc != k:
                raise ValueError(f"marker has {k} points but {kc} colours")
            corner_colors = np.frombuffer(body, np.float32, count=4 * kc, offset=o).reshape(kc // 3, 3, 4).copy()
    except struct.error as e:
        raise ValueError(f"truncated Marker message: {e}") from None
    return MarkerArrays(
        stamp_ns=sec * NS_PER_S + nanosec, frame_id=frame_id, ns=ns, id=mid, type=mtype, action=action,
        pose=head[:7].copy(), scale=head[7:].copy(), color=color, frame_locked=frame_locked,
        corners=corners, corner_colors=corner_colors)
