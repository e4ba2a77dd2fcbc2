"""numpy <-> ROS 2 message conversion, fast Marker building, rosbag2 (MCAP) recording.

Used only by the ROS side (colgnn_ros); colgnn_core never imports it.

- :mod:`msg_tools.conversions`: poses, collision counts, diagnostics, triangle markers <-> numpy.
- :mod:`msg_tools.markers`: :class:`TriangleListMarker` (serialized TRIANGLE_LIST in
  ~0.2 ms for 36k corners), :class:`DistanceColormap`, :func:`parse_marker_cdr`.
- :mod:`msg_tools.recorder`: :class:`BagWriter`, :class:`TopicRecorder`, :func:`read_bag`,
  :func:`read_bag_messages`, :func:`bag_summary`, ``python -m msg_tools.recorder``.
- :mod:`msg_tools.foxglove_live`: :class:`LiveView`, the optional live view over the Foxglove SDK's WebSocket
  server (the ``foxglove`` package is imported only when one starts).
- :mod:`msg_tools.benchmark`: ``python -m msg_tools.benchmark`` (naive vs pool vs CDR).
"""

from .conversions import (
    COLLISION_COUNT_LABELS,
    REQUIRED_COLLISION_COUNT_LABELS,
    apply_pose,
    array_to_pose,
    array_to_pose_stamped,
    counts_to_msg,
    diagnostic_array,
    diagnostic_values,
    marker_corner_colors,
    marker_corners,
    marker_world_corners,
    msg_to_counts,
    ns_to_stamp,
    pose_to_array,
    stamp_to_ns,
    triangle_marker_naive,
    weld_corners,
)
from .markers import DistanceColormap, MarkerArrays, TriangleListMarker, parse_marker_cdr
from .recorder import (
    DEFAULT_TOPICS,
    BagClosedError,
    BagMessage,
    BagWriter,
    TopicRecorder,
    bag_summary,
    read_bag,
    read_bag_messages,
    record,
)

__all__ = [
    "COLLISION_COUNT_LABELS", "REQUIRED_COLLISION_COUNT_LABELS", "apply_pose", "array_to_pose",
    "array_to_pose_stamped", "counts_to_msg", "diagnostic_array", "diagnostic_values", "marker_corner_colors",
    "marker_corners", "marker_world_corners",
    "msg_to_counts", "ns_to_stamp", "pose_to_array", "stamp_to_ns", "triangle_marker_naive", "weld_corners",
    "DistanceColormap", "MarkerArrays", "TriangleListMarker", "parse_marker_cdr",
    "DEFAULT_TOPICS", "BagClosedError", "BagMessage", "BagWriter", "TopicRecorder", "bag_summary", "read_bag",
    "read_bag_messages", "record",
]
