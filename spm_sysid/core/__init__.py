"""The identification core: numpy, scipy, numba and the bag libraries, never rclpy.

Folders by idea, dependencies pointing down (from the top):

* ``jobs/``: one job from a record to a validated model (``settings``: the typed
  settings of a job; ``single``, ``several``: one output, several; ``run``: picks);
* ``identify.py``: the search, the plan, the certification, the choice, written once;
* ``select/``: how a structure is chosen -- ``plan`` (decided once), ``choose`` (one
  selector per plan), ``folds``, ``scores``, ``call`` (the linear/nonlinear call),
  ``guard``, ``simulation`` (the simulation scorer), ``finalists`` (validated
  simulation), ``coupled`` (several outputs);
* ``validate/``: validation, correlation tests, the data check, the open-loop
  check, orders from the data, the linear ARX yardstick;
* ``search/``: the GA with single parent mating, the local search and polish,
  forward selection, the certification (``certify``, ``heaps``, ``branch_bound``,
  ``bb_state``);
* ``fit/``: the problem (built once), least squares, the cached evaluator, criteria,
  the free-run refinement;
* ``online/``: a model on a live stream (predictor, monitor, tracker, session);
* ``model/``: terms, the model and its document (``narx``, ``mimo``, ``metadata``),
  simulation, the coupled model, uncertainty, segments;
* ``io/``: data files, the robot-arm data set, rosbag2 bags, message fields;
* ``stream/``: what the streaming node needs (the sample buffer, its diagnostics);
* ``compiled/``: the numeric kernels (numba's JIT or the ahead-of-time build);
* at the bottom, used by all: ``options`` (what a search reads), ``settings`` (the
  schema), ``defaults`` (the tuning constants), ``record``, ``errors``, ``files``,
  ``memory``, ``progress``, ``blas``, ``cores``.
"""
