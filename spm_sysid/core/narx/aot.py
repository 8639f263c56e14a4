"""The ahead-of-time build of the kernels: a C extension made with numba's pycc.

Loading numba and its JIT set-up costs a process about 0.7 s before the first
kernel runs -- more than the identification itself on the robot-arm data. The
build removes that: ``spm-sysid compile`` (run by ``make setup``) exports every
kernel that Python calls, with the argument types the warm-up used, into one
extension module; a command then imports it in a millisecond.

The build is named by a hash of the kernels' sources, of the Python, numpy
and numba versions and of the CPU's instruction set (it is compiled for the
machine it is built on), so an edited kernel, or a copy of the environment on
another CPU, never runs from an old build: it is
simply not found (and numba's JIT runs, as without a build). It goes to
``SPM_SYSID_AOT_DIR`` when set, else next to the sources (``__pycache__``,
where numba caches too) when writable, else ``~/.cache/spm_sysid/aot``.
``SPM_SYSID_AOT=0`` turns it off. Without a C compiler the build fails with a
message and everything still runs on the JIT.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import platform
import shutil
import sys
import sysconfig
import tempfile
import threading
from collections.abc import Callable
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

import numpy as np

from .compiled import as_array_check, jit_loaded, kernels

__all__ = ["BuildStatus", "build", "build_forced", "build_status", "exports_for", "jit_only",
           "prefer_jit", "source_hash"]

#: The modules that define kernels (a test checks that none is missing).
KERNEL_MODULES = ("kernels", "simulation", "branch_bound", "coupled")
_FORMAT = 1
_HERE = Path(__file__).resolve().parent
_LOCK = threading.Lock()
_loaded: dict[str, list] | None = None
_jit_only = threading.local()
_forced = threading.local()
_prefer_jit = False


def _cpu_signature() -> str:
    """The CPU's instruction-set flags (part of the build's name).

    The build is compiled for this CPU ("host") and may use instructions another
    lacks: an environment copied to another machine must not load it.
    """
    try:
        with open("/proc/cpuinfo") as f:
            return next((line for line in f if line.startswith("flags")), "")
    except OSError:
        return f"{platform.machine()} {platform.processor()}"


@lru_cache(maxsize=1)
def source_hash() -> str:
    """Hash of what the build depends on: kernel sources, Python, numpy, numba, the CPU."""
    from importlib.metadata import version

    h = hashlib.sha256(f"{_FORMAT} {sys.version} {np.__version__} {version('numba')} "
                       f"{_cpu_signature()}".encode())
    for name in (*KERNEL_MODULES, "compiled", "aot", "warmup"):  # warmup: what is exported
        h.update((_HERE / f"{name}.py").read_bytes())
    return h.hexdigest()[:16]


def _places() -> list[Path]:
    if os.environ.get("SPM_SYSID_AOT_DIR"):
        return [Path(os.environ["SPM_SYSID_AOT_DIR"])]
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return [_HERE / "__pycache__", cache / "spm_sysid" / "aot"]


def _files(place: Path, name: str) -> tuple[Path, Path]:
    return place / f"{name}{sysconfig.get_config_var('EXT_SUFFIX')}", place / f"{name}.json"


def _current_files():
    """(extension, table) of each place that holds a build for these sources."""
    name = f"_aot_{source_hash()}"
    for place in _places():
        lib, meta = _files(place, name)
        if lib.is_file() and meta.is_file():
            yield lib, meta


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _damage(lib: Path, meta: Path) -> tuple[dict | None, str]:
    """The build's table when the extension is the one ``compile`` wrote, else why not.

    The table records the extension's size and SHA-256; a truncated or altered
    file would crash the process that loads it (SIGBUS), so it is checked first.
    """
    try:
        table = json.loads(meta.read_text())
        expected = (int(table["size"]), str(table["sha256"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None, f"its table {meta.name} is unreadable or from an older build"
    try:
        size = lib.stat().st_size
        if size != expected[0]:
            return None, f"{lib.name} has {size} bytes, the build wrote {expected[0]}"
        if _digest(lib) != expected[1]:
            return None, f"{lib.name}'s SHA-256 differs from the one the build recorded"
    except OSError as exc:
        return None, f"{lib.name} cannot be read ({exc.strerror or exc})"
    return table, ""


def _warn_damaged(lib: Path, why: str) -> None:
    import sys

    print(f"spm_sysid: warning: the compiled kernels' build {lib} is damaged ({why}); "
          "running on numba's JIT instead (`spm-sysid compile` rebuilds it)", file=sys.stderr)


def _enabled() -> bool:
    return (os.environ.get("SPM_SYSID_AOT", "1") != "0" and not _prefer_jit
            and not getattr(_jit_only, "on", False))


def prefer_jit() -> bool:
    """Run this process's kernels on numba's JIT, which releases the GIL while a kernel runs.

    For long-running processes with other threads (the node: its subscriptions
    must keep recording while an identification runs; a certification round
    holds a kernel for up to 0.4 s). Costs 0.7 s once. Keeps the build when
    numba cannot be imported. Returns whether the JIT is used.
    """
    global _prefer_jit
    from .compiled import jit_available

    _prefer_jit = jit_available()
    return _prefer_jit


@contextmanager
def _switched_on(flag: threading.local):
    """Set a per-thread flag inside the block (restored after, so blocks nest)."""
    before = getattr(flag, "on", False)
    flag.on = True
    try:
        yield
    finally:
        flag.on = before


def jit_only():
    """Run kernels on numba's JIT in this thread (the warm-up fills numba's cache so)."""
    return _switched_on(_jit_only)


def build_forced():
    """Run kernels on the build in this thread even when numba is loaded (tests compare)."""
    return _switched_on(_forced)


# -- loading ----------------------------------------------------------------------------


def _accepts(spec) -> Callable[[object], bool]:
    kind = spec[0]
    if kind == "array":
        return as_array_check(*spec[1:])
    if kind == "float":
        return lambda v: type(v) is float or type(v) is np.float64
    if kind == "int":
        return lambda v: type(v) is int or type(v) is np.int64
    if kind == "bool":
        return lambda v: type(v) is bool or type(v) is np.bool_
    name, fields = spec[1], [_accepts(f) for f in spec[2]]
    return lambda v: (type(v).__name__ == name and isinstance(v, tuple)
                      and len(v) == len(fields) and all(c(x) for c, x in zip(fields, v)))


def _signature_check(specs) -> Callable[[tuple], bool]:
    checks = [_accepts(s) for s in specs]
    n = len(checks)
    return lambda args: len(args) == n and all(c(a) for c, a in zip(checks, args))


def _load() -> dict[str, list]:
    """{kernel key: [(accepts(args), function)]} of the current build ({} without one)."""
    import importlib.util

    name = f"_aot_{source_hash()}"
    for lib, meta in _current_files():
        table, why = _damage(lib, meta)
        if table is None:
            _warn_damaged(lib, why)
            continue
        try:
            spec = importlib.util.spec_from_file_location(name, lib)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return {key: [(_signature_check(e["args"]), getattr(module, e["name"]))
                          for e in entries] for key, entries in table["exports"].items()}
        except Exception:  # a broken build: the JIT runs (build_status tells why)
            continue
    return {}


def exports_for(key: str) -> list:
    """The build's versions of one kernel for this call (none: run the JIT).

    None without a current build, and none once this process has imported
    numba (its JIT then costs nothing more and releases the GIL, which threads
    need) unless :func:`build_forced` is on.
    """
    global _loaded
    if not _enabled() or (jit_loaded() and not getattr(_forced, "on", False)):
        return []
    if _loaded is None:
        with _LOCK:
            if _loaded is None:
                _loaded = _load()
    return _loaded.get(key, [])


# -- building ---------------------------------------------------------------------------


def _spec(t):
    """The JSON description of a numba argument type the build can check (None: cannot)."""
    from numba.core import types

    if isinstance(t, types.Array):
        if t.layout not in "CA":
            return None
        return ["array", str(t.dtype), t.ndim, t.layout == "C", bool(t.mutable)]
    if isinstance(t, types.Boolean):
        return ["bool"]
    if t == types.int64:
        return ["int"]
    if t == types.float64:
        return ["float"]
    if isinstance(t, types.BaseNamedTuple):
        fields = [_spec(x) for x in t.types]
        if any(f is None for f in fields):
            return None
        return ["namedtuple", t.instance_class.__name__, fields]
    return None


def _entry(kernel, export: str):
    """A function of the kernel's arguments that calls its dispatcher (its own options)."""
    params = ", ".join(inspect.signature(kernel.py_func).parameters)
    namespace = {"_kernel": kernel.jit}
    exec(f"def {export}({params}):\n    return _kernel({params})\n", namespace)
    return namespace[export]


class BuildStatus:
    """Where the current build is, or why there is none."""

    def __init__(self, path: Path | None, reason: str) -> None:
        self.path = path
        self.reason = reason

    def __bool__(self) -> bool:
        return self.path is not None


def build_status() -> BuildStatus:
    """The current build (for these sources), if there is one and it loads."""
    damaged = ""
    for lib, meta in _current_files():
        if os.environ.get("SPM_SYSID_AOT", "1") == "0":
            return BuildStatus(None, "turned off by SPM_SYSID_AOT=0")
        table, why = _damage(lib, meta)
        if table is not None:
            return BuildStatus(lib, "built")
        damaged = damaged or f"the build {lib} is damaged ({why}); `spm-sysid compile` rebuilds it"
    return BuildStatus(None, damaged or "not built for these sources (`spm-sysid compile` "
                       "builds it)")


def build() -> BuildStatus:
    """Build the extension from the kernels Python has called in this process.

    Run after a warm-up that called every kernel (:func:`~spm_sysid.core.narx.
    warmup.compile_all`). Old builds in the same place are removed. Returns
    the status; a failure (no C compiler, a numba without pycc) is its reason.
    """
    import warnings

    name = f"_aot_{source_hash()}"
    exports: dict[str, list] = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pycc's pending deprecation
            from numba.pycc import CC
        cc = CC(name)
        cc.target_cpu = "host"
        cc.verbose = False
        for kernel in kernels():
            if not kernel.called:
                continue
            dispatcher = kernel.jit
            for i, sig in enumerate(dispatcher.signatures):
                specs = [_spec(t) for t in sig]
                if any(s is None for s in specs):
                    continue
                export = f"{kernel.key.replace('.', '__')}__{i}"
                ret = dispatcher.overloads[sig].signature.return_type
                cc.export(export, ret(*sig))(_entry(kernel, export))
                exports.setdefault(kernel.key, []).append({"name": export, "args": specs})
        if not exports:
            return BuildStatus(None, "no kernel was called: nothing to build")
    except Exception as exc:
        return BuildStatus(None, f"cannot prepare the build: {type(exc).__name__}: {exc}")
    errors = []
    for place in _places():
        try:
            place.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=place) as tmp:
                cc.output_dir = tmp
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    cc.compile()
                lib, meta = _files(place, name)
                for old in list(place.glob("_aot_*")):
                    old.unlink()
                built = Path(tmp) / lib.name
                record = {"format": _FORMAT, "size": built.stat().st_size,
                          "sha256": _digest(built), "exports": exports}
                shutil.move(built, lib)
                meta.write_text(json.dumps(record))
            return BuildStatus(lib, "built")
        except Exception as exc:  # not writable, no compiler: say so, try the next place
            errors.append(f"{place}: {type(exc).__name__}: {exc}")
    return BuildStatus(None, "cannot build: " + "; ".join(errors))
