"""Benchmarks: figures, never assertions (tests stay robust on a noisy machine).

* :mod:`.engine` -- ``make bench``: the cached, batched
  evaluator against a naive per-structure lstsq, and the simulation kernel;
* :mod:`.sizes` -- ``make bench-sizes``: GA time and
  memory against term-space size and samples (FastCan as a baseline);
* :mod:`.certify` -- ``make bench-certify``: the branch and bound on the
  robot-arm data and on records made hard on purpose;
* :mod:`.cluster` -- ``make bench-dask``: the paper's study on the local pool
  and on a Dask cluster;
* :mod:`.node` -- ``make bench-node``: the ROS node's ingest, identify latency
  and memory.

This package sits beside ``spm_sysid``, not in it (it is not installed, and the
user's command line never imports it): it uses the package as any user would,
above the tools and the ROS layer (the node benchmark drives ROS processes).
Each module runs as ``python -m benchmarks.NAME`` from the project's folder
(the Makefile's ``bench-*`` targets); :mod:`.commands` holds ``bench`` and
``bench-sizes``.
"""
