"""Record the predictor node's topics into a rosbag2 folder with MCAP storage, and read it back.

Format: a rosbag2 folder (``metadata.yaml`` version 9 + ``<name>.mcap``)
written by the maintained ``rosbags`` library. Each topic's channel carries
the CDR ``serialization_format``, the ``ros2msg`` message definition (with
its dependencies) and the RIHS01 type hash of ROS 2 Jazzy, so Foxglove,
``ros2 bag info/play`` and rosbags read it. Message timestamps are receive
times (ns, node clock), like ``ros2 bag record``; the messages keep their
own header stamps.

The folder is written under a hidden ``.<name>.partial-*`` directory next to
the destination and renamed into place only when closed cleanly, so a
crashed recording never looks like a finished one.

    .venv/bin/python -m msg_tools.recorder --out runs/demo_bag --duration 10 [--compression none]

Exit code 0 with a per-topic count on stdout; 2 when the output exists or a
topic type is unknown. SIGINT/SIGTERM end the recording early and cleanly.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.signals import SignalHandlerOptions

from .markers import jazzy_typestore, parse_marker_cdr

DEFAULT_TOPICS: dict[str, str] = {
    "deformed_mesh": "visualization_msgs/msg/Marker",
    "tool_marker": "visualization_msgs/msg/Marker",
    "collision_counts": "std_msgs/msg/Int32MultiArray",
    "tool_pose": "geometry_msgs/msg/PoseStamped",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
# Topics whose publishers may be best-effort (the pose stream): a best-effort
# subscription matches both kinds of publisher; the node's outputs are reliable.
BEST_EFFORT_TOPICS = frozenset({"tool_pose"})


def message_class(msgtype: str) -> type:
    """'pkg/msg/Name' (or 'pkg/Name') -> the rclpy message class."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type must look like 'pkg/msg/Name', got {msgtype!r}")
    try:
        return getattr(importlib.import_module(f"{parts[0]}.{parts[1]}"), parts[2])
    except (ImportError, AttributeError):
        raise ValueError(f"unknown message type {msgtype!r}") from None


def msgtype_of(cls_or_msg: Any) -> str:
    """rclpy message class or instance -> 'pkg/msg/Name'."""
    cls = cls_or_msg if isinstance(cls_or_msg, type) else type(cls_or_msg)
    pkg, sub = cls.__module__.split(".")[:2]
    return f"{pkg}/{sub}/{cls.__name__}"


def _normalise_type(msgtype: str | type) -> str:
    if isinstance(msgtype, type):
        return msgtype_of(msgtype)
    t = msgtype.split("/")
    return f"{t[0]}/msg/{t[1]}" if len(t) == 2 else msgtype


def _rosbags_qos(qos: Any | None) -> Any:
    """rclpy QoSProfile (or None: reliable, volatile, keep last 10) -> rosbags Qos for metadata."""
    from rosbags.interfaces import (  # lazy: rosbags loads only when a bag is written or read
        Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime)

    reliable, transient, depth = True, False, 10
    if qos is not None:

        reliable = qos.reliability != ReliabilityPolicy.BEST_EFFORT
        transient = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        depth = int(qos.depth)
    zero = QosTime(0, 0)  # 0 = unspecified = the rmw default (infinite)
    return Qos(QosHistory.KEEP_LAST, depth,
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


class BagClosedError(RuntimeError):
    """A write after close() or abort()."""


class BagWriter:
    """A rosbag2 folder with MCAP storage, written atomically.

    path: the folder to create (must not exist). compression: None or 'zstd'
    (MCAP chunk compression; readable by every MCAP reader, costs CPU).
    Use as a context manager: a clean exit closes and renames the folder into
    place, an exception removes the partial recording. Thread-safe `write`.
    """

    def __init__(self, path: str | os.PathLike, *, compression: str | None = None) -> None:
        # lazy: rosbags loads only when a bag is written or read
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        self.path = Path(path).absolute()
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists already; not overwriting a recording")
        if compression not in (None, "zstd"):
            raise ValueError(f"compression must be None or 'zstd', got {compression!r}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.partial-", dir=self.path.parent))
        self._writer = Writer(self._tmpdir / self.path.name, version=9, storage_plugin=StoragePlugin.MCAP)
        if compression == "zstd":
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._connections: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._closed = False

    def add_topic(self, topic: str, msgtype: str | type, qos: Any | None = None) -> None:
        """Register a fully qualified topic (e.g. '/deformed_mesh') with its type and offered QoS."""
        msgtype = _normalise_type(msgtype)
        ts = jazzy_typestore()
        if msgtype not in ts.types:
            raise ValueError(f"message type {msgtype!r} is not in the ROS 2 Jazzy typestore")
        with self._lock:
            if topic in self._connections:
                raise ValueError(f"topic {topic!r} added twice")
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=ts, offered_qos_profiles=[_rosbags_qos(qos)])
            self._types[topic] = msgtype
            self.counts[topic] = 0

    def write(self, topic: str, data: bytes | memoryview, timestamp_ns: int) -> None:
        """Append one serialized (CDR) message of a registered topic."""
        with self._lock:
            if self._closed:
                raise BagClosedError(f"bag {self.path} is closed")
            conn = self._connections.get(topic)
            if conn is None:
                raise KeyError(f"topic {topic!r} was not added; known: {sorted(self._connections)}")
            self._writer.write(conn, int(timestamp_ns), data)
            self.counts[topic] += 1

    def write_message(self, topic: str, msg: Any, timestamp_ns: int) -> None:
        """Serialize an rclpy message with rclpy and append it."""
        self.write(topic, serialize_message(msg), timestamp_ns)

    def close(self) -> Path:
        """Finish the MCAP file and metadata.yaml, then move the folder to `path`. Returns `path`."""
        with self._lock:
            if self._closed:
                return self.path
            self._closed = True
            try:
                self._writer.close()
            except BaseException:
                shutil.rmtree(self._tmpdir, ignore_errors=True)
                raise
            done = self._tmpdir / self.path.name
            try:
                os.rename(done, self.path)  # atomic within one filesystem
            except OSError as e:  # e.g. the destination appeared meanwhile: keep the finished bag where it is
                raise FileExistsError(f"cannot move the finished bag {done} to {self.path}: {e}") from None
            self._tmpdir.rmdir()
            return self.path

    def abort(self) -> None:
        """Drop the recording (nothing is left at `path`)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._writer.abort()
            finally:
                shutil.rmtree(self._tmpdir, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class TopicRecorder:
    """Record live topics from inside a process: raw (serialized) subscriptions on `node` feed a BagWriter.

    topics: {name: 'pkg/msg/Type'}; relative names resolve in the node's
    namespace and are stored fully qualified. qos: optional {name: QoSProfile};
    by default reliable depth 10 (the node's outputs), best-effort depth 10 for
    BEST_EFFORT_TOPICS. Messages are never deserialized. Call `close()` (or use
    `with`) after the executor has stopped spinning the node.
    """

    def __init__(self, node: Any, path: str | os.PathLike,
                 topics: Mapping[str, str | type] | None = None, *,
                 qos: Mapping[str, Any] | None = None, compression: str | None = None) -> None:
        self.node = node
        self.writer = BagWriter(path, compression=compression)
        self._subs = []
        try:
            for name, msgtype in (DEFAULT_TOPICS if topics is None else topics).items():
                msgtype = _normalise_type(msgtype)
                cls = message_class(msgtype)
                profile = (qos or {}).get(name) or QoSProfile(
                    depth=10, reliability=ReliabilityPolicy.BEST_EFFORT if name in BEST_EFFORT_TOPICS
                    else ReliabilityPolicy.RELIABLE)
                full = node.resolve_topic_name(name)
                self.writer.add_topic(full, msgtype, profile)
                self._subs.append(node.create_subscription(cls, name, self._make_callback(full), profile,
                                                           raw=True))
        except BaseException:
            self._destroy_subscriptions()
            self.writer.abort()
            raise

    def _make_callback(self, topic: str):
        clock = self.node.get_clock()

        def callback(raw: bytes) -> None:
            try:
                self.writer.write(topic, raw, clock.now().nanoseconds)
            except BagClosedError:
                pass  # a message taken by the executor while the recording was being closed
        return callback

    @property
    def counts(self) -> dict[str, int]:
        """Messages recorded per fully qualified topic."""
        return dict(self.writer.counts)

    def _destroy_subscriptions(self) -> None:
        for sub in self._subs:
            self.node.destroy_subscription(sub)
        self._subs = []

    def close(self) -> Path:
        """Stop recording and finish the bag; returns its folder."""
        self._destroy_subscriptions()
        return self.writer.close()

    def abort(self) -> None:
        self._destroy_subscriptions()
        self.writer.abort()

    def __enter__(self) -> TopicRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# --------------------------------------------------------------------------- reading

@dataclass(frozen=True)
class BagMessage:
    """One recorded message: fully qualified topic, 'pkg/msg/Type', receive time (ns), CDR bytes."""

    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


def read_bag(path: str | os.PathLike, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Iterate the raw messages of a rosbag2 folder (MCAP or sqlite3) in time order.

    topics: fully qualified names to keep (all when None); an unknown name is a ValueError.
    """
    from rosbags.rosbag2 import Reader  # lazy: rosbags loads only when a bag is written or read

    with Reader(Path(path)) as reader:
        conns = reader.connections
        if topics is not None:
            wanted = set(topics)
            missing = wanted - {c.topic for c in conns}
            if missing:
                raise ValueError(f"topics {sorted(missing)} not in {path}; it has {sorted({c.topic for c in conns})}")
            conns = [c for c in conns if c.topic in wanted]
        for conn, t, data in reader.messages(connections=conns):
            yield BagMessage(conn.topic, conn.msgtype, int(t), bytes(data))


def read_bag_messages(path: str | os.PathLike, topics: Iterable[str] | None = None, *,
                      deserializer: str = "rclpy") -> Iterator[tuple[str, int, Any]]:
    """Iterate (topic, receive time ns, message) with messages deserialized.

    deserializer: 'rclpy' (rclpy message objects), 'rosbags' (rosbags
    dataclasses, no ROS needed) or 'marker' (visualization_msgs/Marker as
    :class:`msg_tools.markers.MarkerArrays` via the fast parser, other types
    with rclpy).
    """
    if deserializer not in ("rclpy", "rosbags", "marker"):
        raise ValueError(f"deserializer must be 'rclpy', 'rosbags' or 'marker', got {deserializer!r}")
    if deserializer == "rosbags":
        ts = jazzy_typestore()
        for m in read_bag(path, topics):
            yield m.topic, m.timestamp_ns, ts.deserialize_cdr(m.data, m.msgtype)
        return
    classes: dict[str, type] = {}
    for m in read_bag(path, topics):
        if deserializer == "marker" and m.msgtype == "visualization_msgs/msg/Marker":
            yield m.topic, m.timestamp_ns, parse_marker_cdr(m.data)
            continue
        cls = classes.get(m.msgtype) or classes.setdefault(m.msgtype, message_class(m.msgtype))
        yield m.topic, m.timestamp_ns, deserialize_message(m.data, cls)


def bag_summary(path: str | os.PathLike) -> dict:
    """Summary of a rosbag2 folder.

    {'storage', 'duration_s', 'start_ns', 'message_count', 'topics': {topic: {'type', 'count'}}}
    """
    from rosbags.rosbag2 import Reader  # lazy: rosbags loads only when a bag is written or read
    from ruamel.yaml import YAML  # lazy: a rosbags dependency, for a bag's metadata

    path = Path(path)
    meta = YAML(typ="safe").load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    with Reader(path) as reader:
        topics: dict[str, dict] = {}
        for c in reader.connections:
            t = topics.setdefault(c.topic, {"type": c.msgtype, "count": 0})
            t["count"] += c.msgcount
        return {"storage": meta["storage_identifier"], "duration_s": reader.duration / 1e9,
                "start_ns": reader.start_time, "message_count": reader.message_count, "topics": topics}


# --------------------------------------------------------------------------- standalone process

def record(path: str | os.PathLike, duration_s: float, topics: Mapping[str, str] | None = None, *,
           compression: str | None = None, node_name: str = "msg_tools_recorder") -> dict[str, int]:
    """Record `topics` for `duration_s` seconds (or until SIGINT/SIGTERM) in this process.

    Initialises its own rclpy context (ROS_DOMAIN_ID etc. from the environment)
    and returns the message count per topic. The bag is complete on return.
    """
    if not duration_s > 0:
        raise ValueError(f"duration must be > 0 s, got {duration_s}")
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        node = rclpy.create_node(node_name, context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        with TopicRecorder(node, path, topics, compression=compression) as rec:
            end = time.monotonic() + duration_s
            while not stop.is_set() and time.monotonic() < end:
                executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))
            counts = rec.counts
        executor.shutdown()
        node.destroy_node()
        return counts
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        rclpy.shutdown(context=ctx)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Record the colgnn predictor topics into a rosbag2 (MCAP) folder.")
    ap.add_argument("--out", required=True, help="bag folder to create (must not exist)")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds to record (SIGINT/SIGTERM stop early)")
    ap.add_argument("--topic", action="append", metavar="NAME:pkg/msg/Type",
                    help="topic to record (repeatable); default: the predictor's topics")
    ap.add_argument("--compression", choices=["zstd", "none"], default="zstd",
                    help="MCAP chunk compression (default zstd: the triangle soup repeats each vertex ~6 times, "
                         "so mesh markers shrink ~5-7x for ~2 ms of CPU per 1.4 MB message)")
    args = ap.parse_args(argv)
    topics = None
    if args.topic:
        topics = {}
        for spec in args.topic:
            name, sep, msgtype = spec.rpartition(":")
            if not sep or not name:
                ap.error(f"--topic must be NAME:pkg/msg/Type, got {spec!r}")
            topics[name] = msgtype
    try:
        counts = record(args.out, args.duration, topics,
                        compression=None if args.compression == "none" else args.compression)
    except (ValueError, FileExistsError) as e:
        print(f"error: {e}")
        return 2
    for topic, n in counts.items():
        print(f"{topic}: {n} messages")
    print(f"wrote {Path(args.out).absolute()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
