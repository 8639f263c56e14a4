"""How many cores this process may use.

Its CPU affinity where the OS has one (Linux: a container's or ``taskset``'s
limit), else the machine's count (macOS has no affinity call).
"""

from __future__ import annotations

import os

__all__ = ["usable_cores"]


def usable_cores() -> int:
    """Cores this process may run on (at least 1)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1
