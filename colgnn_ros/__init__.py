"""colgnn_ros: thin rclpy nodes over colgnn_core.

- :mod:`colgnn_ros.pose_publisher_node` (console script ``pose_publisher``): publishes a scene's
  scripted tool trajectory or a poses CSV as geometry_msgs/PoseStamped on ``tool_pose``.
- :mod:`colgnn_ros.common`: what the nodes share: QoS profiles, parameters declared with
  descriptors and ranges, and the process shell (init, spin, clean SIGINT/SIGTERM shutdown, exit codes).

Importing this package does not import rclpy; the node modules do.
"""
