"""The ROS 2 nodes: one thin adapter per executable (``ros2 run damon_ros <node>``)."""
