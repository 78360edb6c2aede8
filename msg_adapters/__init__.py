"""Pure conversions between gscan_ros domain objects and ROS 2 messages (std_msgs, sensor_msgs)."""
