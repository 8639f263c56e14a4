"""Compiled kernels: numba's JIT loaded on first use, or an ahead-of-time build.

A kernel is plain Python decorated with :func:`jit` (sums may be reordered) or
:func:`jit_exact` (Python's order of operations). Called from Python, a
:class:`Kernel` runs

1. the ahead-of-time build (:mod:`spm_sysid.core.compiled.aot`, a C extension that
   ``spm-sysid compile`` makes from the same functions with numba's pycc) when
   it exists for these sources, holds the argument types of the call, and the
   process has not imported numba: no numba import, no JIT set-up -- about
   0.7 s less for every command;
2. else numba's JIT (cached on disk after the first compilation). Once a
   process has loaded it (a long certification, outputs on threads, the
   node), every kernel runs on it: it releases the GIL, the build does not.

Both run the same compiled code (the build's entry points call the JIT
functions with their own options), so they give the same numbers. numba
imports only when a kernel first needs the JIT; inside compiled code a
:class:`Kernel` is its numba dispatcher. The build holds the GIL while it
runs; callers that run kernels on threads use :attr:`Kernel.jit`.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
import sysconfig
import threading
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import MissingDependencyError

__all__ = ["BuildStatus", "KERNEL_MODULES", "Kernel", "build_forced", "build_status",
           "exports_for", "jit", "jit_available", "jit_exact", "jit_loaded", "jit_only",
           "kernels", "load_numba", "prefer_jit", "require_kernels", "source_hash"]

_KERNELS: list[Kernel] = []
_LOCK = threading.RLock()
_numba = None


def load_numba():
    """Import numba once, and teach it that a :class:`Kernel` is its dispatcher."""
    global _numba
    with _LOCK:
        if _numba is None:
            try:
                import numba
                from numba.core import types
                from numba.core.typing.typeof import typeof_impl
            except Exception as exc:  # ImportError, or a broken install raising anything
                raise MissingDependencyError(
                    f"spm_sysid needs numba for its compiled kernels, and it cannot be "
                    f"imported ({type(exc).__name__}: {exc}); install it with "
                    "`pip install numba`") from None

            @typeof_impl.register(Kernel)
            def _typeof_kernel(val, c):
                return types.Dispatcher(val.jit)

            _numba = numba
    return _numba


def jit_loaded() -> bool:
    """True when this process has imported numba already (the JIT costs nothing more)."""
    return _numba is not None


def jit_available() -> bool:
    """True when numba imports (False: only the ahead-of-time build can run kernels)."""
    try:
        load_numba()
    except MissingDependencyError:
        return False
    return True


def require_kernels() -> None:
    """Raise :class:`MissingDependencyError` now when no kernel could run (no build, no numba).

    For long-running processes (the node), which should fail at start, not at
    their first identification.
    """
    if not build_status():
        load_numba()


class Kernel:
    """One compiled function, callable from Python and from other kernels.

    Parameters
    ----------
    fn : callable
        The plain Python function (kept as ``py_func``; runs without numba).
    fastmath : bool
        Let the compiler reorder sums (:func:`jit`), or keep Python's order.
    """

    def __init__(self, fn: Callable, fastmath: bool) -> None:
        self.py_func = fn
        self.fastmath = fastmath
        self.__name__ = fn.__name__
        self.__qualname__ = fn.__qualname__
        self.__module__ = fn.__module__
        self.__doc__ = fn.__doc__
        self.__wrapped__ = fn
        self.called = False  # called from Python (an entry point the build exports)
        self._jit = None

    @property
    def key(self) -> str:
        """``module.function`` (the module's last name): the build's name for it."""
        return f"{self.__module__.rsplit('.', 1)[-1]}.{self.__name__}"

    @property
    def jit(self):
        """The numba dispatcher of this kernel (imports numba the first time)."""
        if self._jit is None:
            numba = load_numba()
            with _LOCK:
                if self._jit is None:
                    self._jit = _dispatcher(numba, self.py_func, self.fastmath)
        return self._jit

    def __call__(self, *args):
        self.called = True
        for accepts, fn in exports_for(self.key):
            if accepts(args):
                return fn(*args)
        return self.jit(*args)

    def __repr__(self) -> str:
        return f"<Kernel {self.key}>"


_warned: set[str] = set()


def _warn_once(key: str, text: str) -> None:
    """One warning line on stderr per kind of trouble and process."""
    import sys

    if key not in _warned:
        _warned.add(key)
        print(f"spm_sysid: warning: {text}", file=sys.stderr)


def _dispatcher(numba, fn: Callable, fastmath: bool):
    """The numba dispatcher of ``fn``, cached on disk where it can be.

    Where numba finds no writable cache location it compiles in memory only
    (one warning line); a cache entry that cannot be read (a truncated file) is
    taken as missing: the kernel is compiled again and the entry rewritten. A
    cache entry is keyed by :func:`source_hash` too: numba renews an entry
    when its own function's file changes, not when a kernel it calls in
    another module does (the refinement's solver calls the simulation's), and
    would run the old callee compiled into the caller.
    """
    options = {"fastmath": {"reassoc", "contract"}} if fastmath else {}
    try:
        dispatcher = numba.njit(cache=True, nogil=True, **options)(fn)
    except RuntimeError as exc:  # "cannot cache function ...: no locator available"
        _warn_once("locator", f"numba cannot cache the compiled kernels ({exc}); they are "
                   "compiled again in each process (set NUMBA_CACHE_DIR to a writable folder)")
        return numba.njit(cache=False, nogil=True, **options)(fn)
    cache = getattr(dispatcher, "_cache", None)
    if cache is not None and hasattr(cache, "_index_key"):
        cache.__class__ = _keyed(type(cache))
    cache_file = getattr(cache, "_cache_file", None)
    if cache_file is not None:
        cache_file.__class__ = _tolerant(type(cache_file))
    return dispatcher


_KEYED: dict[type, type] = {}


def _keyed(base: type) -> type:
    """The cache class of numba with its entries keyed by the kernel sources as well."""
    if base not in _KEYED:
        class KeyedCache(base):
            def _index_key(self, sig, codegen):
                return (*super()._index_key(sig, codegen), source_hash())

        _KEYED[base] = KeyedCache
    return _KEYED[base]


_TOLERANT: dict[type, type] = {}


def _tolerant(base: type) -> type:
    """The cache file class of numba, reading an unreadable entry as a missing one."""
    if base not in _TOLERANT:
        import pickle

        unreadable = (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError,
                      ImportError, IndexError, KeyError, MemoryError)

        class TolerantCacheFile(base):
            def _load_index(self):
                try:
                    return super()._load_index()
                except unreadable as exc:
                    _warn_once("cache", f"numba's cache entry {self._index_path} cannot be read "
                               f"({type(exc).__name__}); compiling the kernel again")
                    return {}

            def _load_data(self, name):
                try:
                    return super()._load_data(name)
                except unreadable as exc:
                    _warn_once("cache", f"numba's cache entry {name} cannot be read "
                               f"({type(exc).__name__}); compiling the kernel again")
                    raise OSError(str(exc)) from None  # numba's load: a missing entry

        _TOLERANT[base] = TolerantCacheFile
    return _TOLERANT[base]


def _register(fn: Callable, fastmath: bool) -> Kernel:
    kernel = Kernel(fn, fastmath)
    _KERNELS.append(kernel)
    return kernel


def jit(fn: Callable) -> Kernel:
    """A kernel whose sums may be reordered (faster; last bits may differ from Python)."""
    return _register(fn, fastmath=True)


def jit_exact(fn: Callable) -> Kernel:
    """A kernel that keeps Python's order of operations (the same results as Python)."""
    return _register(fn, fastmath=False)


def kernels() -> Sequence[Kernel]:
    """Every kernel defined so far (the modules that define them imported)."""
    return tuple(_KERNELS)


def as_array_check(dtype: str, ndim: int, contiguous: bool, mutable: bool
                   ) -> Callable[[object], bool]:
    """A test that a value is an array numba would type as this one (used by the build)."""
    num = np.dtype(dtype).num

    def accepts(value) -> bool:
        if type(value) is not np.ndarray or value.ndim != ndim:
            return False
        dt, flags = value.dtype, value.flags
        return (dt.num == num and dt.isnative and flags.aligned
                and (not contiguous or flags.c_contiguous) and flags.writeable == mutable)
    return accepts


# -- the ahead-of-time build: where it is, whether it is intact, its functions ----------

#: The modules that define kernels, under ``spm_sysid.core`` (a test checks that none is
#: missing); a kernel's key is its module's last name and its own.
KERNEL_MODULES = ("compiled.kernels", "model.chain", "model.simulation", "search.branch_bound",
                  "model.coupled", "model.regressor_sim", "fit.levenberg", "fit.free_run")
_FORMAT = 1
_HERE = Path(__file__).resolve().parent
_BUILD_LOCK = threading.Lock()
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
    # the kernels, this loader, the builder, and the warm-up (what is exported)
    for name in (*KERNEL_MODULES, "compiled.registry", "compiled.aot", "jobs.warmup"):
        path = _HERE.parent / (name.replace(".", "/") + ".py")
        h.update(path.read_bytes())
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
        with _BUILD_LOCK:
            if _loaded is None:
                _loaded = _load()
    return _loaded.get(key, [])


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
