"""The identification core: numpy, scipy and the bag libraries, never rclpy.

Folders by idea, dependencies pointing down:

* ``settings``, ``job``: one schema of settings; one job that identifies and validates;
* ``narx/``: the model and its search (terms, criteria, least squares, evaluator,
  GA with single parent mating, identification, segments, validation, correlation tests);
* ``io/``: data files, the robot-arm data set, rosbag2 bags, message fields;
* ``stream/``: what the streaming node needs (the sample buffer, its diagnostics);
* ``errors``, ``files``, ``memory``: at the bottom, used by all.
"""
