"""ROS 2 layer: thin rclpy nodes over the core."""
