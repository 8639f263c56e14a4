"""Compiled kernels: numba's JIT loaded on first use, or an ahead-of-time build.

A kernel is plain Python decorated with :func:`jit` (sums may be reordered) or
:func:`jit_exact` (Python's order of operations). Called from Python, a
:class:`Kernel` runs

1. the ahead-of-time build (:mod:`spm_sysid.core.narx.aot`, a C extension that
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

import threading
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import MissingDependencyError

__all__ = ["Kernel", "jit", "jit_available", "jit_exact", "jit_loaded", "kernels",
           "load_numba", "require_kernels"]

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
    from .aot import build_status

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
        from .aot import exports_for

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
    taken as missing: the kernel is compiled again and the entry rewritten.
    """
    options = {"fastmath": {"reassoc", "contract"}} if fastmath else {}
    try:
        dispatcher = numba.njit(cache=True, nogil=True, **options)(fn)
    except RuntimeError as exc:  # "cannot cache function ...: no locator available"
        _warn_once("locator", f"numba cannot cache the compiled kernels ({exc}); they are "
                   "compiled again in each process (set NUMBA_CACHE_DIR to a writable folder)")
        return numba.njit(cache=False, nogil=True, **options)(fn)
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if cache_file is not None:
        cache_file.__class__ = _tolerant(type(cache_file))
    return dispatcher


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
