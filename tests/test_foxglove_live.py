"""The Foxglove live view (msg_tools.foxglove_live) against a real WebSocket client.

A client (``websocket-client``) speaks the Foxglove WebSocket protocol to the SDK's real server: it reads
``serverInfo`` and ``advertise``, builds the protobuf classes from the schema the server advertises, subscribes, and
decodes the binary message-data frames (opcode 1, subscription id u32, log time u64, payload). The last test does
the same through the ``predictor`` node with ``foxglove_port`` set.
"""

from __future__ import annotations

import base64
import json
import socket
import struct
import sys
import time
from dataclasses import dataclass

import numpy as np
import pytest

foxglove = pytest.importorskip("foxglove")
websocket = pytest.importorskip("websocket")
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402

from msg_tools.foxglove_live import (COUNTS_SCHEMA_NAME, COUNTS_TOPIC, SCENE_TOPIC, LiveView,  # noqa: E402
                                     TriangleListEncoder, import_sdk, scene_update)

SUBPROTOCOL = "foxglove.sdk.v1"  # what the SDK's server (0.30) accepts; it refuses "foxglove.websocket.v1"
TIMEOUT_S = 5.0
T_NS = 1_795_000_000_123_456_789


def message_class(schema_b64_or_bytes: str | bytes, name: str):
    """The protobuf message class ``name`` from a serialized FileDescriptorSet (base64 text or bytes)."""
    data = (base64.b64decode(schema_b64_or_bytes) if isinstance(schema_b64_or_bytes, str)
            else bytes(schema_b64_or_bytes))
    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(data).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


@dataclass
class Frame:
    subscription: int
    log_time_ns: int
    payload: bytes


class FoxgloveClient:
    """A minimal client of the Foxglove WebSocket protocol (JSON control messages, binary message data)."""

    def __init__(self, port: int) -> None:
        self.ws = websocket.create_connection(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                              timeout=TIMEOUT_S)
        self.server_info: dict | None = None
        self.channels: dict[str, dict] = {}   # topic -> advertised channel
        self.frames: list[Frame] = []

    def close(self) -> None:
        self.ws.close()

    def receive(self) -> None:
        """One message: JSON ops are remembered, binary message-data frames kept in ``frames``."""
        msg = self.ws.recv()
        if not msg:  # websocket-client returns "" for the server's close frame
            raise ConnectionError("the server closed the connection")
        if isinstance(msg, bytes):
            assert msg[0] == 0x01, f"unexpected binary opcode {msg[0]}"
            sub, log_time = struct.unpack_from("<IQ", msg, 1)
            self.frames.append(Frame(sub, log_time, msg[13:]))
            return
        op = json.loads(msg)
        if op["op"] == "serverInfo":
            self.server_info = op
        elif op["op"] == "advertise":
            self.channels.update({c["topic"]: c for c in op["channels"]})

    def wait_for(self, cond, what: str) -> None:
        end = time.monotonic() + TIMEOUT_S
        while not cond():
            assert time.monotonic() < end, f"timed out waiting for {what}"
            self.receive()

    def subscribe(self, topics: dict[str, int]) -> None:
        """Subscribe to {topic: subscription id} (each topic must be advertised)."""
        subs = [{"id": sid, "channelId": self.channels[t]["id"]} for t, sid in topics.items()]
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def frame(self, subscription: int) -> Frame | None:
        return next((f for f in self.frames if f.subscription == subscription), None)


def connect_and_subscribe(port: int) -> tuple[FoxgloveClient, type]:
    """A client subscribed to the scene (id 1) and the counts (id 2); returns it and the SceneUpdate class."""
    client = FoxgloveClient(port)
    client.wait_for(lambda: client.server_info is not None and {SCENE_TOPIC, COUNTS_TOPIC} <= set(client.channels),
                    "serverInfo and advertise")
    scene = client.channels[SCENE_TOPIC]
    assert (scene["encoding"], scene["schemaName"], scene["schemaEncoding"]) == \
        ("protobuf", "foxglove.SceneUpdate", "protobuf")
    counts = client.channels[COUNTS_TOPIC]
    assert (counts["encoding"], counts["schemaName"], counts["schemaEncoding"]) == \
        ("json", COUNTS_SCHEMA_NAME, "jsonschema")
    client.subscribe({SCENE_TOPIC: 1, COUNTS_TOPIC: 2})
    return client, message_class(scene["schema"], "foxglove.SceneUpdate")


def receive_both(client: FoxgloveClient, publish) -> tuple[Frame, Frame]:
    """Call ``publish()`` until the scene (subscription 1) and counts (2) frames arrive (the server registers a
    subscription asynchronously; nothing is sent to a channel before it)."""
    end = time.monotonic() + TIMEOUT_S
    client.ws.settimeout(0.1)
    try:
        while client.frame(1) is None or client.frame(2) is None:
            assert time.monotonic() < end, "timed out waiting for the scene and the counts"
            publish()
            try:
                while True:
                    client.receive()
            except websocket.WebSocketTimeoutException:
                pass
    finally:
        client.ws.settimeout(TIMEOUT_S)
    return client.frame(1), client.frame(2)


def points(primitive) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in primitive.points])


def colors(primitive) -> np.ndarray:
    return np.array([[c.r, c.g, c.b, c.a] for c in primitive.colors])


@pytest.fixture
def mesh():
    """An object (two triangles, 5 vertices) with per-vertex colours and a tool (one triangle)."""
    rng = np.random.default_rng(3)
    return dict(faces=np.array([[0, 1, 2], [2, 3, 4]]), vertices=rng.normal(size=(5, 3)), colors=rng.random((5, 4)),
                tool_faces=np.array([[0, 2, 1]]), tool_vertices=rng.normal(size=(3, 3)))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------------ encoding

def test_numpy_encoding_equals_the_sdks_own_scene_update(mesh):
    """The numpy-written SceneUpdate decodes to the same message as the one the SDK's classes encode."""
    m = foxglove.messages
    enc = TriangleListEncoder(mesh["faces"], entity_id="object", frame_id="map", color=(0.1, 0.2, 0.3, 1.0))
    ours = scene_update([enc.encode(T_NS, mesh["vertices"], mesh["colors"])])
    identity = m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0), orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    primitive = m.TriangleListPrimitive(
        pose=identity, color=m.Color(r=0.1, g=0.2, b=0.3, a=1.0),
        points=[m.Point3(x=x, y=y, z=z) for x, y, z in mesh["vertices"].tolist()],
        colors=[m.Color(r=r, g=g, b=b, a=a) for r, g, b, a in mesh["colors"].tolist()],
        indices=mesh["faces"].ravel().tolist())
    sdk = m.SceneUpdate(entities=[m.SceneEntity(timestamp=m.Timestamp(*divmod(T_NS, 10**9)), frame_id="map",
                                                id="object", triangles=[primitive])]).encode()
    cls = message_class(m.SceneUpdate.get_schema().data, "foxglove.SceneUpdate")
    decoded = cls.FromString(ours)
    assert decoded == cls.FromString(sdk)
    tri = decoded.entities[0].triangles[0]
    np.testing.assert_array_equal(points(tri), mesh["vertices"])
    np.testing.assert_array_equal(colors(tri), mesh["colors"])
    assert list(tri.indices) == mesh["faces"].ravel().tolist()


def test_missing_sdk_names_the_pip_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "foxglove", None)  # what Python does for a package that is not installed
    with pytest.raises(ImportError, match=r"pip install foxglove-sdk==0\.30\.3"):
        import_sdk()


# ------------------------------------------------------------------------------------------------ the server

def test_a_websocket_client_receives_and_decodes_the_mesh_the_tool_and_the_counts(mesh):
    counts = {"vertex_face_before": 3, "edge_edge_before": np.int64(7), "vertex_face_after": 0, "fallback": 0}
    with LiveView(0, mesh["faces"], mesh["tool_faces"], frame_id="world", count_labels=list(counts)) as live:
        assert live.port > 0 and live.url == f"ws://127.0.0.1:{live.port}"
        # nothing is encoded while no client subscribes, but the input is still checked
        assert live.publish(T_NS, mesh["vertices"], mesh["tool_vertices"], counts, mesh["colors"]) is False
        with pytest.raises(ValueError, match="NaN"):
            live.publish(T_NS, np.full((5, 3), np.nan), None, counts)
        client, scene_cls = connect_and_subscribe(live.port)
        try:
            schema = json.loads(client.channels[COUNTS_TOPIC]["schema"])
            assert set(schema["properties"]) == set(counts)
            scene, counted = receive_both(client, lambda: live.publish(T_NS, mesh["vertices"], mesh["tool_vertices"],
                                                                       counts, mesh["colors"]))
        finally:
            client.close()
    assert scene.log_time_ns == counted.log_time_ns == T_NS
    assert json.loads(counted.payload) == {k: int(v) for k, v in counts.items()}
    update = scene_cls.FromString(scene.payload)
    assert [e.id for e in update.entities] == ["object", "tool"] and not update.deletions
    obj, tool = update.entities
    assert obj.frame_id == tool.frame_id == "world"
    assert obj.timestamp.seconds * 10**9 + obj.timestamp.nanos == T_NS
    tri = obj.triangles[0]
    assert len(tri.points) == 5 and len(tri.indices) == 6  # 2 triangles: 6 corners indexing 5 vertices
    assert tri.points[3].y == mesh["vertices"][3, 1]
    np.testing.assert_array_equal(points(tri)[list(tri.indices)], mesh["vertices"][mesh["faces"]].reshape(-1, 3))
    np.testing.assert_array_equal(colors(tri), mesh["colors"])
    assert (tri.pose.orientation.w, tri.pose.position.x) == (1.0, 0.0)
    ttri = tool.triangles[0]
    np.testing.assert_array_equal(points(ttri)[list(ttri.indices)],
                                  mesh["tool_vertices"][mesh["tool_faces"]].reshape(-1, 3))
    assert not ttri.colors and ttri.color.a == pytest.approx(0.6)


def test_close_disconnects_clients_and_frees_the_port(mesh):
    live = LiveView(0, mesh["faces"])
    client = FoxgloveClient(live.port)
    try:
        client.wait_for(lambda: client.server_info is not None, "serverInfo")
        live.close()
        live.close()  # idempotent
        with pytest.raises(ConnectionError, match="closed"):
            for _ in range(20):  # any advertise/unadvertise still queued, then the close
                client.receive()
    finally:
        client.close()
    with pytest.raises(RuntimeError, match="closed"):
        live.publish(T_NS, mesh["vertices"], None, {})
    LiveView(live.port, mesh["faces"]).close()  # the port can be bound again


def test_a_taken_port_is_the_sdks_error(mesh):
    with LiveView(0, mesh["faces"]) as live, pytest.raises(RuntimeError, match="Address already in use"):
        LiveView(live.port, mesh["faces"])


@pytest.mark.parametrize("kwargs, message", [
    (dict(port=70000), r"port must be an int in \[0, 65535\]"),
    (dict(port=-1), r"port must be an int in \[0, 65535\]"),
    (dict(port=True), r"port must be an int"),
    (dict(object_faces=np.array([[0, 1]])), r"faces must have shape \(F, 3\) with F > 0"),
    (dict(object_faces=np.zeros((1, 3))), r"faces must be integers"),
    (dict(object_faces=np.array([[0, -1, 2]])), r"faces must lie in \[0, 2\*\*32\)"),
    (dict(frame_id=" "), r"frame_id must be a non-empty string"),
    (dict(object_color=(1.0, 0.0, 0.0)), r"color must be 4 floats \(RGBA\) in \[0, 1\]"),
])
def test_bad_arguments_are_value_errors(mesh, kwargs, message):
    args = dict(port=0, object_faces=mesh["faces"]) | kwargs
    with pytest.raises(ValueError, match=message):
        LiveView(**args)


@pytest.mark.parametrize("change, message", [
    (dict(object_vertices=np.zeros((4, 3))), r"object vertices must have shape \(V, 3\) with V >= 5"),
    (dict(object_vertices=np.zeros((5, 2))), r"object vertices must have shape"),
    (dict(tool_vertices=np.zeros((3, 3))), r"tool_vertices given, but the live view was made without tool_faces"),
    (dict(colors=np.ones((5, 3))), r"object colors must have shape \(5, 4\)"),
    (dict(colors=np.full((5, 4), 2.0)), r"object colors must lie in \[0, 1\]"),
    (dict(counts={"steps": 1.5}), r"count 'steps' must be an integer"),
    (dict(counts={"steps": "many"}), r"count 'steps' must be an integer"),
    (dict(counts={"": 1}), r"count labels must be non-empty strings"),
    (dict(timestamp_ns=-1), r"timestamp_ns must lie in \[0, 2\*\*32 s\)"),
    (dict(timestamp_ns=1.5), r"timestamp_ns must be an int"),
])
def test_bad_publish_input_is_a_value_error(mesh, change, message):
    good = dict(timestamp_ns=T_NS, object_vertices=mesh["vertices"], tool_vertices=None, counts={"steps": 1},
                colors=None)
    with LiveView(0, mesh["faces"]) as live:
        with pytest.raises(ValueError, match=message):
            live.publish(**(good | change))
        assert live.publish(**good) is False  # the good input passes (no client subscribed: nothing sent)


# ------------------------------------------------------------------------------------------------ the node

@pytest.fixture(scope="module")
def predictor_node_module():
    pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from colgnn_ros import predictor_node
    from msg_tools import COLLISION_COUNT_LABELS, array_to_pose_stamped

    return predictor_node, Parameter, COLLISION_COUNT_LABELS, array_to_pose_stamped


def test_predictor_node_serves_each_step_on_its_live_view(ros, predictor_node_module):
    """The node with foxglove_port set: a client decodes the stepped mesh and tool, equal to the Predictor's."""
    mod, Parameter, labels, pose_stamped = predictor_node_module
    ctx, _, _ = ros
    port = free_port()
    params = [Parameter(k, value=v) for k, v in dict(scene="sphere_mat", threads=1, compile=False,
                                                     foxglove_port=port).items()]
    n = mod.PredictorNode(context=ctx, parameter_overrides=params)
    try:
        assert n.describe_parameter("foxglove_port").integer_range[0].to_value == 65535
        assert n._live is not None and n._live.port == port
        client, scene_cls = connect_and_subscribe(port)
        pose = n.scene.tool_rest_pose.copy()
        try:
            def step() -> int:
                pose[2] -= 1e-4  # the tool creeps down; each pose is a new, later stamp
                stamp = n.get_clock().now().nanoseconds
                assert n.process_pose(pose_stamped(pose, "world", stamp))
                return stamp

            receive_both(client, step)  # the subscriptions are registered now
            stamp = step()              # so this step's frames must come
            client.wait_for(lambda: any(f.subscription == 2 and f.log_time_ns == stamp for f in client.frames) and
                            any(f.subscription == 1 and f.log_time_ns == stamp for f in client.frames),
                            "the last step's scene and counts")
        finally:
            client.close()
        scene = next(f for f in client.frames if f.subscription == 1 and f.log_time_ns == stamp)
        counted = next(f for f in client.frames if f.subscription == 2 and f.log_time_ns == stamp)
        pred = n.predictor
        obj, tool = scene_cls.FromString(scene.payload).entities
        tri, ttri = obj.triangles[0], tool.triangles[0]
        assert (obj.id, tool.id, obj.frame_id) == ("object", "tool", "world")
        assert len(tri.points) == len(n._surface_ids) and len(tri.indices) == 3 * len(pred.surface_faces)
        np.testing.assert_array_equal(points(tri)[list(tri.indices)], pred.positions[pred.surface_faces].reshape(-1, 3))
        np.testing.assert_array_equal(points(ttri)[list(ttri.indices)],
                                      pred.state.tool_vertices[pred.tool_faces].reshape(-1, 3))
        assert len(tri.colors) == len(tri.points)  # color_by_distance (default)
        c = json.loads(counted.payload)
        assert list(c) == list(labels) and c["substeps"] >= 1
        # live-view errors never stop the node: a port in use at start-up, a failing publish
        assert n._start_live_view(port, pred.surface_faces, pred.tool_faces) is None  # logged, no live view
        n._live.close()
        steps = n.stats["steps"]
        step()
        assert n.stats["steps"] == steps + 1 and "live_view" in n._last_warn
    finally:
        n.destroy_node()
    assert n._live is None
    LiveView(port, np.array([[0, 1, 2]])).close()  # destroy_node closed the server: the port is free again
