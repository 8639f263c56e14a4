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

import inspect
import json
import shutil
import tempfile
from pathlib import Path

from .registry import (  # noqa: F401 - the build's status and switches, named here too
    _FORMAT,
    KERNEL_MODULES,
    BuildStatus,
    _digest,
    _files,
    _places,
    build_forced,
    build_status,
    exports_for,
    jit_only,
    kernels,
    prefer_jit,
    source_hash,
)

__all__ = ["BuildStatus", "build", "build_forced", "build_status", "exports_for", "jit_only",
           "prefer_jit", "source_hash"]



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


def build() -> BuildStatus:
    """Build the extension from the kernels Python has called in this process.

    Run after a warm-up that called every kernel (:func:`~spm_sysid.core.jobs.
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
