"""Compile every numba kernel ahead of time, so that no user command waits for it.

numba compiles a kernel the first time it is called and caches the machine
code on disk (``__pycache__`` next to the sources, or ``NUMBA_CACHE_DIR``);
later processes load it in a fraction of a second. Without this step the
first ``identify`` on a machine spends its first seconds compiling, and the
first ``certify`` about 20 s. :func:`compile_all` runs one small job of each
kind -- the GA and its polish, the certification, the simulation focus with
validated selection, validation with bands, two coupled outputs -- which calls
every kernel once, then builds the ahead-of-time extension
(:mod:`spm_sysid.core.compiled.aot`) from the kernels Python called, which later
commands load without numba. ``spm-sysid compile`` runs it, and ``make setup``
(so ``make run`` and ``make test``) runs that after installing.
"""

from __future__ import annotations

import glob
import os
import time
from collections.abc import Callable

import numpy as np

from ..compiled.aot import BuildStatus, build, build_status, jit_only

__all__ = ["compile_all", "kernels_are_cached"]

#: One cached kernel of each module that has them (checked by kernels_are_cached).
_MARKERS = (("compiled", "kernels.fit_structures"), ("search", "branch_bound.expand"),
            ("model", "simulation._run"))


def kernels_are_cached() -> bool:
    """True when the ahead-of-time build or numba's disk cache holds the kernels (a fast start)."""
    if build_status():
        return True
    core = os.path.dirname(os.path.dirname(__file__))
    extra = [os.environ["NUMBA_CACHE_DIR"]] if os.environ.get("NUMBA_CACHE_DIR") else []
    return all(any(glob.glob(os.path.join(p, "**", f"{marker}-*.nbi"), recursive=True)
                   for p in [os.path.join(core, folder, "__pycache__"), *extra])
               for folder, marker in _MARKERS)


def compile_all(report: Callable[[str], None] | None = None) -> tuple[float, BuildStatus]:
    """Call every kernel once on numba's JIT, then build the ahead-of-time extension.

    The warm-up compiles what numba has not cached; the extension is built from
    the kernels Python called when there is none for these sources. Returns the
    seconds taken and the build's status.
    """
    say = report or (lambda text: None)
    t0 = time.perf_counter()
    with jit_only():
        _warm_up(say)
    status = build_status()
    if not status:
        say("building the ahead-of-time extension (numba pycc, about 15 s) ...")
        status = build()
        say(f"ahead-of-time extension: {status.path or status.reason}")
    return time.perf_counter() - t0, status


def _warm_up(say: Callable[[str], None]) -> None:
    from ..record import Record
    from ..search.certify import ensure_compiled
    from .run import run_job
    from .settings import JobSettings

    rng = np.random.default_rng(0)
    n = 300
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.6 * y[t - 1] - 0.2 * y[t - 2] + 0.5 * u[t - 1] + 0.1 * u[t - 1] * y[t - 1]
    y += 0.01 * rng.standard_normal(n)
    record = Record.from_samples(u, y, source="compile_all")
    ga = {"population_size": 20, "generations": 5}
    say("compiling the search and its polish ...")
    run_job(record, JobSettings.from_values({**ga, "ny": 2, "nu": 2, "seed": 0,
                                             "auto_certify_time_limit": 0.0}))
    say("compiling the QR arbitration of near-rank structures ...")
    from ..fit.evaluator import StructureEvaluator

    g = np.random.default_rng(0)
    P = g.standard_normal((60, 6))
    P[:, 5] = P[:, 4] + 5e-5 * g.standard_normal(60)  # smallest squared pivot 2.5e-9
    StructureEvaluator(P, P[:, 0] + g.standard_normal(60), "aic").fit_batch(
        np.ones((1, 6), dtype=bool))
    say("compiling the certification ...")
    ensure_compiled()
    say("compiling the simulation focus, validation and bands ...")
    run_job(record, JobSettings.from_values({**ga, "ny": 2, "nu": 2, "seed": 0,
                                             "focus": "simulation", "horizon": 3,
                                             "shortlist": 3}))
    say("compiling the runs of models with regressors ...")
    _warm_up_regressors(u, y)
    say("compiling the coupled simulation of several outputs ...")
    y2 = np.zeros(n)
    for t in range(1, n):
        y2[t] = 0.5 * y2[t - 1] + 0.3 * y[t - 1]
    both = Record.from_samples(u, np.column_stack([y, y2]), source="compile_all",
                               output_names=("a", "b"))
    run_job(both, JobSettings.from_values({**ga, "ny": 1, "nu": 1, "seed": 0,
                                           "focus": "simulation", "horizon": 3,
                                           "shortlist": 2}))


def _warm_up_regressors(u: np.ndarray, y: np.ndarray) -> None:
    """Free run, k-step run and refinement of a model with a regressor.

    Called directly: a small job need not choose a regressor, and a kernel that
    no warm-up called is left out of the build.
    """
    from ..fit.refine import refine_simulation
    from ..model.narx import NarxModel
    from ..model.terms import TermSpace

    space = TermSpace(ny=2, nu=1, degree=2, regressors=("sign(y(t-1)-y(t-2))",))
    names = space.term_names()
    terms = sorted(names.index(n) for n in ("y(t-1)", "u(t-1)", "sign(y(t-1)-y(t-2))",
                                            "y(t-1)*sign(y(t-1)-y(t-2))"))
    model = NarxModel(space, terms, np.array([0.5, 0.4, 0.01, 0.01]))
    model.run(u, y)
    model.run(u, y, horizon=3)
    refine_simulation(model, u, y, max_evaluations=3)
