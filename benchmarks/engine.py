"""Benchmark: the cached, batched evaluator against a naive per-structure lstsq.

Both run the very same GA (same seeds, so the same chromosomes) at the paper's
settings on the robot-arm data; only the way structures are scored differs.
Figures are medians over repeats, measured in one process. A benchmark, not a
test: nothing here asserts a time.
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np

from spm_sysid.core.fit.criteria import Criterion, get_criterion
from spm_sysid.core.fit.evaluator import StructureEvaluator
from spm_sysid.core.fit.lstsq import DEFAULT_RANK_TOL, score_one, sse_floor
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.search.ga import GAConfig, run_ga

__all__ = ["BenchFigures", "run_benchmark"]


@dataclass
class BenchFigures:
    """Medians of one evaluator's runs."""

    name: str
    seconds: float
    evaluations: float
    lookups: float
    hit_rate: float
    best_scores: list[float]

    @property
    def evals_per_second(self) -> float:
        """Structures scored (look-ups) per second of GA run."""
        return self.lookups / self.seconds



class NaiveEvaluator:
    """Benchmark baseline: numpy ``lstsq`` on the raw columns for every chromosome.

    No cache and no shared work; rank handling as in :func:`reference_fit`.
    """

    def __init__(self, P: np.ndarray, target: np.ndarray, criterion: str | Criterion = "aic",
                 rank_tol: float = DEFAULT_RANK_TOL) -> None:
        self.P = np.asarray(P, dtype=float)
        self.target = np.asarray(target, dtype=float)
        self.criterion = get_criterion(criterion)
        self.n, self.n_terms = self.P.shape
        self.rank_tol = rank_tol
        self._y_norm = float(np.linalg.norm(self.target)) or 1.0
        self.evaluations = 0
        self.lookups = 0

    def score(self, masks: np.ndarray, keys: np.ndarray | None = None) -> np.ndarray:
        """Criterion values, one lstsq per row (``keys`` is ignored: no cache)."""
        masks = np.asarray(masks, dtype=bool)
        out = np.empty(len(masks))
        for i, mask in enumerate(masks):
            out[i] = self._one(mask)
        self.evaluations += len(masks)
        self.lookups += len(masks)
        return out

    def _one(self, mask: np.ndarray) -> float:
        cols = np.flatnonzero(mask)
        if cols.size == 0:
            return np.inf
        A = self.P[:, cols]
        theta, _, rank, sv = np.linalg.lstsq(A, self.target, rcond=None)
        norms = np.linalg.norm(A, axis=0)
        if rank < cols.size or np.any(norms == 0):
            return np.inf
        resid = self.target - A @ theta
        sse = max(float(resid @ resid), sse_floor(float(np.linalg.norm(self.target))))
        return score_one(self.criterion, sse, self.n, self.n_terms, cols,
                          theta * norms / self._y_norm)


def _measure(name, make_evaluator, config, seeds) -> BenchFigures:
    times, evals, lookups, hits, best = [], [], [], [], []
    for seed in seeds:
        ev = make_evaluator()
        t0 = time.perf_counter()
        res = run_ga(ev, config, seed=seed)
        times.append(time.perf_counter() - t0)
        evals.append(res.evaluations)
        lookups.append(res.lookups)
        hits.append(res.cache_hit_rate)
        best.append(res.best_score)
    return BenchFigures(name, statistics.median(times), statistics.median(evals),
                        statistics.median(lookups), statistics.median(hits), best)


def run_benchmark(
    u: np.ndarray, y: np.ndarray, *, criterion: str = "aic", repeats: int = 5,
    naive_repeats: int = 3, config: GAConfig | None = None, term_space: TermSpace | None = None,
    out=print,
) -> tuple[BenchFigures, BenchFigures]:
    """Time engine and naive GA runs and print a table; returns both figures."""
    config = config or GAConfig()
    space = term_space or TermSpace()
    P = space.regression_matrix(u, y)
    target = space.target(y)
    crit = get_criterion(criterion)
    seeds = list(range(repeats))
    # Warm-up (imports, BLAS threads) so the first timed run is not penalised.
    run_ga(StructureEvaluator(P, target, crit), GAConfig(population_size=20, generations=5), seed=0)
    # say up front how long the slow baseline will take (its first generations, scaled)
    t0 = time.perf_counter()
    probe = 10
    run_ga(NaiveEvaluator(P, target, crit), GAConfig(**{**config.to_dict(),
                                                        "generations": probe}), seed=0)
    per_run = (time.perf_counter() - t0) * max(config.generations, 1) / probe
    out(f"benchmark: {repeats} engine run(s), then {naive_repeats} naive run(s) of about "
        f"{per_run:.0f} s each (about {naive_repeats * per_run / 60:.1f} min in all)")
    sys.stdout.flush()
    engine = _measure("engine", lambda: StructureEvaluator(P, target, crit), config, seeds)
    naive = _measure("naive", lambda: NaiveEvaluator(P, target, crit), config,
                     seeds[:naive_repeats])
    same = all(abs(a - b) < 1e-6 for a, b in zip(engine.best_scores, naive.best_scores))
    out(f"benchmark: {crit.name.upper()}, population {config.population_size}, "
        f"{config.generations} generations, SPM {config.spm_fraction}, N = {len(target)}, "
        f"{space.n_terms} candidate terms")
    out(f"{'evaluator':<10}{'runs':>6}{'median s/run':>14}{'fits/run':>10}"
        f"{'scored/s':>12}{'cache hits':>12}")
    for fig, runs in ((engine, repeats), (naive, naive_repeats)):
        out(f"{fig.name:<10}{runs:>6}{fig.seconds:>14.3f}{fig.evaluations:>10.0f}"
            f"{fig.evals_per_second:>12.0f}{fig.hit_rate:>12.1%}")
    out(f"naive/engine time ratio: {naive.seconds / engine.seconds:.1f}x "
        f"(same best scores on shared seeds: {same})")
    return engine, naive


def run_simulation_benchmark(u: np.ndarray, y: np.ndarray, *, repeats: int = 3,
                             config: GAConfig | None = None, out=print) -> dict[str, float]:
    """Time the simulation kernel and a simulation-focused identification; print them.

    The kernel: one free-run of the whole record with a 30-term structure of the
    paper's space, compiled against the same code uncompiled (what runs without
    numba; the numbers are identical). The identification: ``focus="simulation"``,
    BIC, GA settings ``config`` (default the paper's), seeds 1..repeats.
    """
    from spm_sysid.core.fit.problem import fit_structure
    from spm_sysid.core.identify import identify
    from spm_sysid.core.model import simulation
    from spm_sysid.core.validate.validation import metrics

    space = TermSpace()
    mask = np.zeros(space.n_terms, dtype=bool)
    mask[:30] = True
    model = fit_structure(u, y, mask, space)
    cm, theta = model.compiled, model.coefficients
    u2 = space.inputs_2d(u)
    lo, hi = simulation.divergence_bounds(y)
    buf = np.empty(len(y) - space.max_lag)
    args = (cm.gather, cm.y_lags, cm.u_lags, cm.u_cols, theta, u2, np.asarray(y, float),
            len(y), cm.max_lag, lo, hi, buf)
    simulation._run(*args)  # compile / load once

    def median_time(fn, n):
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn(*args)
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    compiled = median_time(simulation._run, 200)
    plain = median_time(getattr(simulation._run, "py_func", simulation._run), 3)
    out(f"simulation kernel: free-run of {len(y)} samples, 30 terms: compiled "
        f"{compiled * 1e3:.3f} ms, uncompiled {plain * 1e3:.1f} ms (median of 200 / 3 runs; "
        f"ratio {plain / compiled:.0f}x)")
    pred = identify(u=u, y=y, criterion="bic", seed=1, ga=config)
    pred_fit = metrics(space.target(y), pred.model.simulate(u, y))["fit_percent"]
    times, fits = [], []
    for seed in range(1, repeats + 1):
        t0 = time.perf_counter()
        res = identify(u=u, y=y, criterion="bic", seed=seed, focus="simulation", ga=config)
        times.append(time.perf_counter() - t0)
        fits.append(metrics(space.target(y), res.model.simulate(u, y))["fit_percent"])
    cfg = config or GAConfig()
    out(f"focus simulation (BIC, population {cfg.population_size}, {cfg.generations} "
        f"generations): median "
        f"{statistics.median(times):.2f} s per identification over {repeats} seeds, free-run "
        f"fit {', '.join(f'{f:.1f} %' for f in fits)} (focus prediction, the same settings: "
        f"{len(pred.model.terms)} terms, free-run fit {pred_fit:.1f} %)")
    return {"kernel_ms": compiled * 1e3, "uncompiled_ms": plain * 1e3,
            "focus_simulation_s": statistics.median(times)}
