"""The console scripts: each command imported and run under one Ctrl-C guard.

A command's heavy imports (numpy, scipy, rclpy, the compiled kernels) take a
fraction of a second to a second before its own handling of Ctrl-C is in
place; a Ctrl-C then ended ``spm-sysid`` with a ``KeyboardInterrupt`` traceback
and status -2 (measured: at 0.05 s and 0.15 s after the start; at 0.3 s it said
``interrupted``, status 130). The console scripts point here, so that the
imports run inside the guard: a Ctrl-C at any time ends with ``interrupted``
and status 130, as it does later.
"""

from __future__ import annotations

import sys
from importlib import import_module

__all__ = ["bag_player", "spm_sysid", "sysid_node"]

#: The status of a command ended by Ctrl-C (128 + SIGINT), as every command uses.
INTERRUPTED = 130


def run_guarded(module: str, function: str) -> int:
    """Import ``module`` and return ``function()``; Ctrl-C anywhere gives status 130."""
    try:
        return getattr(import_module(module), function)()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return INTERRUPTED


def spm_sysid() -> int:
    """``spm-sysid``: :func:`spm_sysid.apps.main.main`."""
    return run_guarded("spm_sysid.apps.main", "main")


def sysid_node() -> int:
    """``sysid_node``: :func:`spm_sysid.ros.entry.sysid_node`."""
    return run_guarded("spm_sysid.ros.entry", "sysid_node")


def bag_player() -> int:
    """``bag_player``: :func:`spm_sysid.ros.bag_player.main`."""
    return run_guarded("spm_sysid.ros.bag_player", "main")
