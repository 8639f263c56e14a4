"""A documented memory bound, checked before anything large is built.

Large inputs fail early with a message that says how much they would need,
instead of exhausting the machine. The bound is ``SPM_SYSID_MAX_MEMORY``
(bytes, or with a suffix: ``8G``, ``512M``; ``unlimited`` or ``inf`` for no
bound) when set, otherwise half of the
memory this process can still use: the least of

* what the system reports as available (``MemAvailable`` in /proc/meminfo),
* what the process's control group may still take (cgroup v2 ``memory.max``
  minus ``memory.current``, or cgroup v1 ``memory.limit_in_bytes`` minus
  ``memory.usage_in_bytes``: a container's or a systemd unit's limit),
* the address space left under ``ulimit -v`` (``RLIMIT_AS`` minus the
  process's current size),

or 8 GiB where none of these can be read. A bound the user sets is the most the
process may hold: the regression matrix's check counts what it holds already.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from .defaults import STRUCTURE_SLICE_BYTES
from .errors import MemoryLimitError

__all__ = ["MemoryLimitError", "check_memory", "format_bytes", "memory_limit",
           "resident_bytes", "slice_rows"]

_SUFFIX = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}
_UNLIMITED = 2**60  # cgroup files say "max" or a huge number for "no limit"


def slice_rows(columns: int) -> int:
    """Rows of ``columns`` columns (and a target) in one slice of a long fit or product.

    :data:`~spm_sysid.core.defaults.STRUCTURE_SLICE_BYTES` of them, and never fewer
    rows than columns and one (a factor of the slice stays square).
    """
    return max(columns + 1, STRUCTURE_SLICE_BYTES // (8 * (columns + 1)))


def format_bytes(n: float) -> str:
    """``1.5 GB``-style text (binary units)."""
    for unit, size in (("TB", 2**40), ("GB", 2**30), ("MB", 2**20), ("kB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().split()[0]
    except (OSError, IndexError):
        return None
    if text == "max":
        return _UNLIMITED
    try:
        return int(text)
    except ValueError:
        return None


def _proc_field(path: str, name: str) -> int | None:
    """Bytes of a ``name: N kB`` line of a /proc file (None where it cannot be read)."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(name + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _meminfo() -> int | None:
    return _proc_field("/proc/meminfo", "MemAvailable")


def _cgroup_room() -> int | None:
    """Memory the process's control group may still take (None: no limit found)."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        rel = rel.lstrip("/")
        if controllers == "":  # cgroup v2
            base = Path("/sys/fs/cgroup") / rel
            limit, used = base / "memory.max", base / "memory.current"
        elif "memory" in controllers.split(","):  # cgroup v1
            base = Path("/sys/fs/cgroup/memory") / rel
            if not base.is_dir():
                base = Path("/sys/fs/cgroup/memory")
            limit, used = base / "memory.limit_in_bytes", base / "memory.usage_in_bytes"
        else:
            continue
        lim, cur = _read_int(limit), _read_int(used)
        if lim is not None and lim < _UNLIMITED:
            rooms.append(max(lim - (cur or 0), 0))
    return min(rooms) if rooms else None


def _address_space_room() -> int | None:
    """Address space left under ``ulimit -v`` (None: unlimited or unknown)."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY or soft <= 0:
        return None
    return max(soft - (_proc_field("/proc/self/status", "VmSize") or 0), 0)


def _parse_limit(text: str) -> int:
    """Bytes of ``SPM_SYSID_MAX_MEMORY`` (``8G``, ``512M``, ``1e9``; ``inf``/``none``: no bound)."""
    if text.lower() in ("inf", "infinity", "none", "unlimited"):
        return _UNLIMITED
    mult = _SUFFIX.get(text[-1].upper(), 1)
    try:
        number = float(text[:-1] if text[-1].upper() in _SUFFIX else text) * mult
    except ValueError:
        raise MemoryLimitError(f"SPM_SYSID_MAX_MEMORY={text!r} is not a size such as "
                               "8G or 512M") from None
    if math.isnan(number):
        raise MemoryLimitError(f"SPM_SYSID_MAX_MEMORY={text!r} is not a size such as 8G or 512M")
    if number == math.inf:
        return _UNLIMITED
    if number <= 0:
        raise MemoryLimitError(f"SPM_SYSID_MAX_MEMORY={text!r} must be positive (a size such "
                               "as 8G or 512M; 'unlimited' for no bound)")
    if number < 1:
        raise MemoryLimitError(f"SPM_SYSID_MAX_MEMORY={text!r} is less than one byte (the "
                               "number is bytes unless it ends in K, M, G or T: 0.5G is "
                               "half a gigabyte)")
    return int(min(number, _UNLIMITED))


def memory_limit() -> tuple[int, str]:
    """The bound in bytes and where it comes from."""
    text = os.environ.get("SPM_SYSID_MAX_MEMORY", "").strip()
    if text:
        return _parse_limit(text), "SPM_SYSID_MAX_MEMORY"
    sources = [(room, label) for room, label in (
        (_meminfo(), "the available memory"),
        (_cgroup_room(), "the memory its control group may still take"),
        (_address_space_room(), "the address space left under ulimit -v"))
        if room is not None]
    if not sources:
        return 8 * 2**30, "the default of 8 GB"
    room, label = min(sources)
    return room // 2, f"half of {label}"


def resident_bytes() -> int:
    """The memory this process holds now (``VmRSS``; 0 where it cannot be read)."""
    return _proc_field("/proc/self/status", "VmRSS") or 0


def check_memory(needed: float, what: str, held: bool = False) -> None:
    """Raise MemoryLimitError when ``needed`` bytes exceed the bound.

    With ``held`` and a bound the user set (``SPM_SYSID_MAX_MEMORY``: the most the
    process may hold), the memory the process holds already counts too: the job's
    large arrays come on top of the interpreter, the record and what else is loaded.
    The default bound is half of the room *left*, which already excludes it.
    """
    limit, source = memory_limit()
    already = resident_bytes() if held and source == "SPM_SYSID_MAX_MEMORY" else 0
    if needed + already > limit:
        besides = f" besides the {format_bytes(already)} this process holds" if already else ""
        raise MemoryLimitError(
            f"{what} would need about {format_bytes(needed)}{besides}, more than the limit "
            f"of {format_bytes(limit)} ({source}); use less data or fewer candidate terms, or "
            "set SPM_SYSID_MAX_MEMORY")
