"""The identification core: numpy/scipy only, never rclpy."""
