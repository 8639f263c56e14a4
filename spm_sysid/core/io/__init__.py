"""Input and output: data files, the robot-arm data set, bags, message fields."""
