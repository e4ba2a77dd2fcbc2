"""Optional live view over the Foxglove SDK: the deforming mesh, the tool and the collision counts on a WebSocket.

The ROS wheels have no RViz; with this, a user opens the Foxglove app, connects to ``ws://HOST:PORT`` (Open
connection -> Foxglove WebSocket) and sees the scene, with no ROS install. :class:`LiveView` starts the SDK's
WebSocket server in its own SDK context and logs, per step:

- :data:`SCENE_TOPIC`: a ``foxglove.SceneUpdate`` (protobuf, the SDK's schema) with two entities, ``object`` and
  ``tool``, each one ``TriangleListPrimitive``: the vertices as ``points``, the faces as ``indices`` (an indexed
  triangle list, a documented field of the schema: 5-6x fewer bytes than one point per triangle corner) and, for
  the object, optional per-vertex ``colors``. Shown by the 3D panel.
- :data:`COUNTS_TOPIC`: the collision counts as a JSON object of integers (JSON schema
  ``colgnn.CollisionCounts``). Shown by the Raw Messages and Plot panels.

Why not the SDK's message classes for the meshes: they need one Python ``Point3`` and ``Color`` per vertex
(about 50 ms for 36k corners, more than a model step). :class:`TriangleListEncoder` writes the large repeated
fields with numpy into preallocated protobuf records and lets the SDK's classes encode the small fixed parts
(entity header, pose, solid colour); protobuf concatenation merges the two. The tests decode the result with the
``protobuf`` package against the schema the server advertises, and compare it with the SDK's own encoding.

Nothing is encoded for a channel no client subscribes to, so an idle live view costs the input checks only.
The ``foxglove`` package (PyPI ``foxglove-sdk``) is imported when a LiveView starts, so the rest of msg_tools works
without it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import Any

import numpy as np

SCENE_TOPIC = "/colgnn/scene"
COUNTS_TOPIC = "/colgnn/collision_counts"
COUNTS_SCHEMA_NAME = "colgnn.CollisionCounts"
SDK_PIP_PACKAGE = "foxglove-sdk==0.30.3"
NS_PER_S = 1_000_000_000
MAX_TIMESTAMP_NS = 2**32 * NS_PER_S  # the SDK's Timestamp holds unsigned 32-bit seconds

#: Messages buffered per client (the SDK's default is 1024: ~450 MB of full-resolution scenes for a stalled client);
#: when full, the oldest is dropped: a live view only needs the newest frames.
MESSAGE_BACKLOG = 32

OBJECT_COLOR = (0.35, 0.55, 0.85, 1.0)
TOOL_COLOR = (0.6, 0.6, 0.65, 0.6)

# protobuf wire format: a field's key is (field number << 3) | wire type; 1 = 64-bit, 2 = length-delimited
_WIRE_I64, _WIRE_LEN = 1, 2


def _key(field: int, wire: int) -> int:
    return (field << 3) | wire


# Field numbers of the SDK's protobuf schemas (foxglove.SceneUpdate and its parts; checked by the tests).
_UPDATE_ENTITIES = _key(2, _WIRE_LEN)          # SceneUpdate.entities
_ENTITY_TRIANGLES = _key(12, _WIRE_LEN)        # SceneEntity.triangles
_TRIANGLES_POINTS = _key(2, _WIRE_LEN)         # TriangleListPrimitive.points (Point3)
_TRIANGLES_COLORS = _key(4, _WIRE_LEN)         # TriangleListPrimitive.colors (Color)
_TRIANGLES_INDICES = _key(5, _WIRE_LEN)        # TriangleListPrimitive.indices (packed fixed32)

# One repeated Point3 / Color sub-message: its key, its length, then each double with its own key.
_POINT_RECORD = np.dtype([("key", "u1"), ("len", "u1"),
                          ("kx", "u1"), ("x", "<f8"), ("ky", "u1"), ("y", "<f8"), ("kz", "u1"), ("z", "<f8")])
_COLOR_RECORD = np.dtype([("key", "u1"), ("len", "u1"), ("kr", "u1"), ("r", "<f8"), ("kg", "u1"), ("g", "<f8"),
                          ("kb", "u1"), ("b", "<f8"), ("ka", "u1"), ("a", "<f8")])


def varint(n: int) -> bytes:
    """The protobuf base-128 varint of a non-negative int."""
    if n < 0:
        raise ValueError(f"varint needs a non-negative int, got {n}")
    out = bytearray()
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def length_delimited(key: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field: key, varint length, payload."""
    return bytes((key,)) + varint(len(payload)) + payload


def import_sdk() -> ModuleType:
    """The ``foxglove`` package, or ImportError naming the pip package to install."""
    try:
        import foxglove  # lazy: an optional dependency, needed only when a live view starts
        import foxglove.messages  # noqa: F401  (the schema classes)
    except ImportError as exc:
        raise ImportError(f"the Foxglove live view needs the Foxglove SDK: pip install {SDK_PIP_PACKAGE} "
                          f"({exc})") from exc
    return foxglove


def check_faces(faces: np.ndarray, name: str) -> np.ndarray:
    """faces: integer [F,3], F > 0, indices >= 0 -> uint32 [F,3] (C order)."""
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"{name} must have shape (F, 3) with F > 0, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name} must be integers, got {f.dtype}")
    if f.min() < 0 or f.max() >= 2**32:
        raise ValueError(f"{name} must lie in [0, 2**32), got [{f.min()}, {f.max()}]")
    return np.ascontiguousarray(f, dtype="<u4")


def check_color(color: Sequence[float], name: str) -> tuple[float, float, float, float]:
    """RGBA, 4 floats in [0, 1]."""
    c = tuple(float(x) for x in color)
    if len(c) != 4 or not all(0.0 <= x <= 1.0 for x in c):
        raise ValueError(f"{name} must be 4 floats (RGBA) in [0, 1], got {color!r}")
    return c  # type: ignore[return-value]


def check_timestamp(timestamp_ns: int) -> int:
    """A timestamp in ns since the epoch: an int in [0, 2**32 s)."""
    if isinstance(timestamp_ns, bool) or not isinstance(timestamp_ns, (int, np.integer)):
        raise ValueError(f"timestamp_ns must be an int (ns), got {type(timestamp_ns).__name__}")
    t = int(timestamp_ns)
    if not 0 <= t < MAX_TIMESTAMP_NS:
        raise ValueError(f"timestamp_ns must lie in [0, 2**32 s), got {t}")
    return t


def check_counts(counts: Mapping[str, Any]) -> dict[str, int]:
    """{label: integer count} -> {label: int}; labels are non-empty strings."""
    out: dict[str, int] = {}
    for k, v in counts.items():
        if not isinstance(k, str) or not k:
            raise ValueError(f"count labels must be non-empty strings, got {k!r}")
        if isinstance(v, (float, np.floating)) and not (math.isfinite(v) and float(v).is_integer()):
            raise ValueError(f"count {k!r} must be an integer, got {v!r}")
        try:
            out[k] = int(v)
        except (TypeError, ValueError):
            raise ValueError(f"count {k!r} must be an integer, got {v!r}") from None
    return out


def counts_schema(labels: Sequence[str]) -> dict[str, Any]:
    """JSON schema of the counts message: the given labels as integer properties (others allowed, integers)."""
    return {"title": COUNTS_SCHEMA_NAME, "type": "object",
            "properties": {k: {"type": "integer"} for k in labels},
            "additionalProperties": {"type": "integer"}}


class TriangleListEncoder:
    """Serialized ``foxglove.SceneEntity`` with one indexed ``TriangleListPrimitive``, for a fixed face list.

    faces: integer [F,3] indices into the vertices given to :meth:`encode`; entity_id, frame_id: the entity's;
    color: the solid RGBA in [0, 1], used when no per-vertex colours are given. The constant parts (the
    packed indices, the primitive's identity pose and colour) are encoded once.
    """

    def __init__(self, faces: np.ndarray, *, entity_id: str, frame_id: str = "world",
                 color: Sequence[float] = OBJECT_COLOR) -> None:
        fg = import_sdk()
        self._messages = fg.messages
        self.faces = check_faces(faces, "faces")
        self.min_vertices = int(self.faces.max()) + 1
        self.entity_id, self.frame_id = str(entity_id), str(frame_id)
        m = self._messages
        identity = m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0),
                          orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
        r, g, b, a = check_color(color, "color")
        self._prefix = m.TriangleListPrimitive(pose=identity, color=m.Color(r=r, g=g, b=b, a=a)).encode()
        self._indices = length_delimited(_TRIANGLES_INDICES, self.faces.tobytes())
        self._points = np.empty(0, _POINT_RECORD)
        self._colors = np.empty(0, _COLOR_RECORD)

    def encode(self, timestamp_ns: int, vertices: np.ndarray, colors: np.ndarray | None = None) -> bytes:
        """SceneEntity bytes. vertices: float [V,3] (m, in frame_id), V > the largest face index; colors: float
        RGBA [V,4] in [0, 1] or None (the solid colour); timestamp_ns: the entity's stamp (ns since the epoch)."""
        v = self.check_vertices(vertices)
        c = None if colors is None else self.check_colors(colors, len(v))
        return self._encode(check_timestamp(timestamp_ns), v, c)

    def _encode(self, t: int, v: np.ndarray, c: np.ndarray | None) -> bytes:
        """encode() on checked inputs."""
        primitive = self._prefix + self._point_bytes(v) + (b"" if c is None else self._color_bytes(c)) + self._indices
        sec, nsec = divmod(t, NS_PER_S)
        header = self._messages.SceneEntity(timestamp=self._messages.Timestamp(sec, nsec), frame_id=self.frame_id,
                                            id=self.entity_id).encode()
        return header + length_delimited(_ENTITY_TRIANGLES, primitive)

    def check_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """float [V,3], finite, V > the largest face index -> float64 [V,3]."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < self.min_vertices:
            raise ValueError(f"{self.entity_id} vertices must have shape (V, 3) with V >= {self.min_vertices} "
                             f"(the faces' largest index + 1), got {v.shape}")
        if not np.isfinite(v).all():
            raise ValueError(f"{self.entity_id} vertices contain NaN or inf")
        return v

    def check_colors(self, colors: np.ndarray, n: int) -> np.ndarray:
        """float RGBA [n,4] in [0, 1] -> float64 [n,4]."""
        c = np.asarray(colors, dtype=np.float64)
        if c.shape != (n, 4):
            raise ValueError(f"{self.entity_id} colors must have shape ({n}, 4), got {c.shape}")
        if not ((c >= 0.0) & (c <= 1.0)).all():  # also false for NaN
            raise ValueError(f"{self.entity_id} colors must lie in [0, 1]")
        return c

    def _point_bytes(self, v: np.ndarray) -> bytes:
        if len(self._points) != len(v):
            self._points = np.zeros(len(v), _POINT_RECORD)
            p = self._points
            p["key"], p["len"] = _TRIANGLES_POINTS, _POINT_RECORD.itemsize - 2
            p["kx"], p["ky"], p["kz"] = _key(1, _WIRE_I64), _key(2, _WIRE_I64), _key(3, _WIRE_I64)
        p = self._points
        p["x"], p["y"], p["z"] = v[:, 0], v[:, 1], v[:, 2]
        return p.tobytes()

    def _color_bytes(self, c: np.ndarray) -> bytes:
        if len(self._colors) != len(c):
            self._colors = np.zeros(len(c), _COLOR_RECORD)
            q = self._colors
            q["key"], q["len"] = _TRIANGLES_COLORS, _COLOR_RECORD.itemsize - 2
            q["kr"], q["kg"], q["kb"], q["ka"] = (_key(i, _WIRE_I64) for i in range(1, 5))
        q = self._colors
        q["r"], q["g"], q["b"], q["a"] = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
        return q.tobytes()


def scene_update(entities: Sequence[bytes]) -> bytes:
    """Serialized ``foxglove.SceneUpdate`` holding the given serialized SceneEntity messages."""
    return b"".join(length_delimited(_UPDATE_ENTITIES, e) for e in entities)


class LiveView:
    """The Foxglove SDK's WebSocket server with the scene (object, tool) and the collision counts.

    port: TCP port, 0 lets the OS choose (the bound one is :attr:`port`); host: the address to bind
    (127.0.0.1: this machine only; 0.0.0.0: every interface); object_faces: integer [F,3], indices into the
    object vertices of each :meth:`publish`; tool_faces: integer [G,3] or None (no tool entity); frame_id: the
    entities' frame; count_labels: the counts named in the counts' JSON schema (the Plot panel offers them).
    Raises ImportError (naming the pip package) without the SDK, ValueError for bad arguments, and the SDK's
    error when the port cannot be bound. Use as a context manager or call :meth:`close`.
    """

    def __init__(self, port: int, object_faces: np.ndarray, tool_faces: np.ndarray | None = None, *,
                 host: str = "127.0.0.1", frame_id: str = "world", count_labels: Sequence[str] = (),
                 object_color: Sequence[float] = OBJECT_COLOR, tool_color: Sequence[float] = TOOL_COLOR,
                 name: str = "colgnn") -> None:
        if isinstance(port, bool) or not isinstance(port, (int, np.integer)) or not 0 <= int(port) <= 65535:
            raise ValueError(f"port must be an int in [0, 65535] (0: chosen by the OS), got {port!r}")
        if not isinstance(frame_id, str) or not frame_id.strip():
            raise ValueError(f"frame_id must be a non-empty string, got {frame_id!r}")
        fg = import_sdk()
        self._object = TriangleListEncoder(object_faces, entity_id="object", frame_id=frame_id, color=object_color)
        self._tool = (None if tool_faces is None else
                      TriangleListEncoder(tool_faces, entity_id="tool", frame_id=frame_id, color=tool_color))
        self._context = fg.Context()
        self._scene = fg.Channel(SCENE_TOPIC, schema=fg.messages.SceneUpdate.get_schema(),
                                 message_encoding="protobuf", context=self._context)
        schema = fg.Schema(name=COUNTS_SCHEMA_NAME, encoding="jsonschema",
                           data=json.dumps(counts_schema(list(count_labels))).encode())
        self._counts = fg.Channel(COUNTS_TOPIC, schema=schema, message_encoding="json", context=self._context)
        try:
            self._server = fg.start_server(name=name, host=host, port=int(port), context=self._context,
                                           message_backlog_size=MESSAGE_BACKLOG)
        except BaseException:  # e.g. RuntimeError "Failed to bind port: Address already in use"
            self._scene.close()
            self._counts.close()
            raise
        self.host = host
        self.port: int = int(self._server.port)
        self.closed = False

    @property
    def url(self) -> str:
        """The address to open in Foxglove (Open connection -> Foxglove WebSocket)."""
        return f"ws://{self.host}:{self.port}"

    def publish(self, timestamp_ns: int, object_vertices: np.ndarray, tool_vertices: np.ndarray | None,
                counts: Mapping[str, int], colors: np.ndarray | None = None) -> bool:
        """Log one step. timestamp_ns: the step's stamp (ns since the epoch; also the log time);
        object_vertices: float [V,3] (m); tool_vertices: float [M,3] (m) or None (the tool entity is not updated);
        counts: {label: int}; colors: float RGBA [V,4] in [0, 1] or None (the solid object colour).

        The inputs are checked every time (ValueError); the messages are encoded and sent only to channels a
        client subscribes to. Returns whether the scene was sent (a client subscribes to it).
        """
        if self.closed:
            raise RuntimeError("the live view is closed")
        t = check_timestamp(timestamp_ns)
        obj = self._object.check_vertices(object_vertices)
        obj_colors = None if colors is None else self._object.check_colors(colors, len(obj))
        tool = None
        if tool_vertices is not None:
            if self._tool is None:
                raise ValueError("tool_vertices given, but the live view was made without tool_faces")
            tool = self._tool.check_vertices(tool_vertices)
        c = check_counts(counts)
        if self._counts.has_sinks():
            self._counts.log(c, log_time=t)
        if not self._scene.has_sinks():
            return False
        entities = [self._object._encode(t, obj, obj_colors)]
        if tool is not None:
            entities.append(self._tool._encode(t, tool, None))
        self._scene.log(scene_update(entities), log_time=t)
        return True

    def close(self) -> None:
        """Stop the server (clients are disconnected) and close the channels; idempotent."""
        if self.closed:
            return
        self.closed = True
        self._server.stop()
        self._scene.close()
        self._counts.close()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
