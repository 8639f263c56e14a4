"""Command line, benchmark, experiments, figures (no rclpy)."""
