"""One identification job on a snapshot of recorded samples: identify + validate.

This is what the ROS node runs for ``~/identify``, in a worker process so the
node keeps recording meanwhile. Settings come in as a plain dictionary (the
node's parameters) and the result goes out as plain data (the model document,
the residuals, a summary), so the job crosses a process boundary cheaply and
the node only turns it into messages.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .errors import DataError
from .narx.ga import GAConfig
from .narx.identify import identify
from .narx.segments import describe_data, find_segments, segment_report
from .narx.terms import TermSpace
from .narx.validation import split_segments, validate_model

__all__ = ["JobSettings", "run_job"]


@dataclass
class JobSettings:
    """Everything an identification job needs besides the data."""

    ny: int = 4
    nu: int = 4
    degree: int = 2
    delay: int = 1
    constant: bool = False
    criterion: str = "aic"
    population_size: int = 200
    generations: int = 300
    crossover_prob: float = 0.6
    mutation_prob: float = 0.01
    spm_fraction: float = 0.15
    fitness: str = "akaike"
    seed: int | None = None
    validation: str = "estimation"  # or "holdout"
    validation_split: float = 0.5
    correlation_lags: int = 20
    sample_period: float = 0.0  # seconds; 0: estimated from the stamps
    gap_factor: float = 1.5
    progress_every: int = 25
    extra: dict = field(default_factory=dict)

    def term_space(self) -> TermSpace:
        """The candidate terms."""
        return TermSpace(ny=self.ny, nu=self.nu, degree=self.degree, delay=self.delay,
                         constant=self.constant)

    def ga(self) -> GAConfig:
        """The GA settings."""
        return GAConfig(population_size=self.population_size, generations=self.generations,
                        crossover_prob=self.crossover_prob, mutation_prob=self.mutation_prob,
                        spm_fraction=self.spm_fraction, fitness=self.fitness)

    def check(self) -> None:
        """Raise ValueError with a clear reason when a setting is invalid."""
        from .narx.criteria import get_criterion

        self.term_space()
        self.ga()
        get_criterion(self.criterion)
        if self.validation not in ("estimation", "holdout"):
            raise ValueError(f"validation must be 'estimation' or 'holdout', got "
                             f"{self.validation!r}")
        if not 0.1 <= self.validation_split <= 0.9:
            raise ValueError(f"validation_split must be in [0.1, 0.9], got "
                             f"{self.validation_split}")
        if self.correlation_lags < 1:
            raise ValueError("correlation_lags must be >= 1")
        if not (self.sample_period >= 0 and np.isfinite(self.sample_period)):
            raise ValueError(f"sample_period must be >= 0 seconds (0: estimate from the "
                             f"stamps), got {self.sample_period}")
        if not self.gap_factor > 1:
            raise ValueError(f"gap_factor must be > 1, got {self.gap_factor}")


def run_job(stamps_ns: np.ndarray, u: np.ndarray, y: np.ndarray, settings: JobSettings,
            progress=None) -> dict:
    """Identify and validate; return plain data.

    Parameters
    ----------
    stamps_ns, u, y : ndarray, shape (n,)
        The snapshot, oldest first.
    settings : JobSettings
        Term space, criterion, GA and validation settings.
    progress : callable, optional
        Called as ``progress(generation, best, evaluations)`` every
        ``settings.progress_every`` generations.

    Returns
    -------
    dict
        ``model`` (the JSON model document, with validation and stamps in its
        metadata), ``residuals`` (one-step, list of float), ``summary`` (one
        paragraph), ``seconds``.
    """
    t0 = time.perf_counter()
    settings.check()
    space = settings.term_space()
    period_ns = int(round(settings.sample_period * 1e9)) or None
    info = find_segments(stamps_ns, period_ns, settings.gap_factor)
    bounds, data = segment_report(info, space.max_lag)
    if not bounds:
        raise DataError(
            f"no contiguous segment is longer than the largest lag ({space.max_lag}): "
            f"{len(y)} samples in {len(info.bounds)} segment(s) with {info.gaps} gap(s)")
    est, val = bounds, bounds
    if settings.validation == "holdout":
        est, val = split_segments(bounds, len(y), settings.validation_split, space.max_lag)

    def callback(stats):
        if progress is not None and (stats.generation % settings.progress_every == 0
                                     or stats.generation == settings.generations):
            progress(stats.generation, stats.best, stats.evaluations)

    result = identify(u=u, y=y, term_space=space, criterion=settings.criterion,
                      ga=settings.ga(), seed=settings.seed, callback=callback, segments=est)
    model = result.model
    report = validate_model(model, u, y, max_lag=settings.correlation_lags,
                            segment=settings.validation, segments=val)
    seconds = time.perf_counter() - t0
    model.metadata.update({
        "validation": report.to_dict(),
        "samples_used": data["used_samples"],
        "data": data,
        "first_stamp_ns": int(stamps_ns[0]),
        "last_stamp_ns": int(stamps_ns[-1]),
        "identify_seconds": round(seconds, 4),
        **settings.extra,
    })
    o = report.one_step_metrics
    f = report.free_run_metrics
    failed = [t.name for t in report.tests if not t.passed]
    summary = (
        f"{model.equation()} | {settings.criterion.upper()} {result.ga.best_score:.2f}, "
        f"{len(model.term_indices)} terms, one-step MSE {model.mse:.4e}, "
        f"{describe_data(data)} ({settings.validation} validation: one-step fit "
        f"{o['fit_percent']:.1f} %, free-run fit {f['fit_percent']:.1f} %, correlation tests "
        f"{'all inside the band' if not failed else 'outside the band: ' + ', '.join(failed)}"
        f"), {seconds:.2f} s"
    )
    return {
        "model": model.to_dict(),
        "residuals": report.residuals.tolist(),
        "summary": summary,
        "seconds": seconds,
        "data": data,
    }
