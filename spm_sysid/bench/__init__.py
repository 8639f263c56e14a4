"""Benchmarks: figures, never assertions (tests stay robust on a noisy machine).

* :mod:`.engine` -- ``spm-sysid bench`` (``make bench``): the cached, batched
  evaluator against a naive per-structure lstsq, and the simulation kernel;
* :mod:`.sizes` -- ``spm-sysid bench-sizes`` (``make bench-sizes``): GA time and
  memory against term-space size and samples (FastCan as a baseline);
* :mod:`.certify` -- ``make bench-certify``: the branch and bound on the
  robot-arm data and on records made hard on purpose;
* :mod:`.cluster` -- ``make bench-dask``: the paper's study on the local pool
  and on a Dask cluster;
* :mod:`.node` -- ``make bench-node``: the ROS node's ingest, identify latency
  and memory.

This package sits above the tools and the ROS layer (the node benchmark drives
ROS processes); :mod:`.commands` adds ``bench`` and ``bench-sizes`` to
``spm-sysid``.
"""
