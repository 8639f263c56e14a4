"""Applications that combine the tools and ROS: make run, the node benchmark, spm-sysid."""
