"""Bridges to the robotics tools people already use (docs/interop.md): MCAP files with Foxglove's schemas
(``mcap_export``), ROS 2 bags into sessions (``rosbag_import``), and ROS camera_info (``camera_info``). Each
module imports its third-party libraries (mcap, foxglove-schemas-protobuf, rosbags) when used, so importing
lapreco_hil stays light."""
