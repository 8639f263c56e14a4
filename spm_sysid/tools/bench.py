"""Benchmark: the cached, batched evaluator against a naive per-structure lstsq.

Both run the very same GA (same seeds, so the same chromosomes) at the paper's
settings on the robot-arm data; only the way structures are scored differs.
Figures are medians over repeats, measured in one process. A benchmark, not a
test: nothing here asserts a time.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import numpy as np

from ..core.criteria import get_criterion
from ..core.evaluator import NaiveEvaluator, StructureEvaluator
from ..core.ga import GAConfig, run_ga
from ..core.terms import TermSpace

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
