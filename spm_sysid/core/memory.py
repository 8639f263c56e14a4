"""A documented memory bound, checked before anything large is built.

Large inputs fail early with a message that says how much they would need,
instead of exhausting the machine. The bound is ``SPM_SYSID_MAX_MEMORY``
(bytes, or with a suffix: ``8G``, ``512M``) when set, otherwise half of the
memory the system reports as available (``MemAvailable`` in /proc/meminfo;
8 GiB where that cannot be read).
"""

from __future__ import annotations

import os

from .errors import MemoryLimitError

__all__ = ["MemoryLimitError", "check_memory", "format_bytes", "memory_limit"]

_SUFFIX = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def format_bytes(n: float) -> str:
    """``1.5 GB``-style text (binary units)."""
    for unit, size in (("TB", 2**40), ("GB", 2**30), ("MB", 2**20), ("kB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _available() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def memory_limit() -> tuple[int, str]:
    """The bound in bytes and where it comes from."""
    text = os.environ.get("SPM_SYSID_MAX_MEMORY", "").strip()
    if text:
        try:
            mult = _SUFFIX.get(text[-1].upper(), 1)
            value = int(float(text[:-1] if text[-1].upper() in _SUFFIX else text) * mult)
        except ValueError:
            raise MemoryLimitError(f"SPM_SYSID_MAX_MEMORY={text!r} is not a size such as "
                                   "8G or 512M") from None
        return value, "SPM_SYSID_MAX_MEMORY"
    avail = _available()
    if avail is None:
        return 8 * 2**30, "the default of 8 GB"
    return avail // 2, "half of the available memory"


def check_memory(needed: float, what: str) -> None:
    """Raise MemoryLimitError when ``needed`` bytes exceed the bound."""
    limit, source = memory_limit()
    if needed > limit:
        raise MemoryLimitError(
            f"{what} would need about {format_bytes(needed)}, more than the limit of "
            f"{format_bytes(limit)} ({source}); use less data or fewer candidate terms, or "
            "set SPM_SYSID_MAX_MEMORY")
