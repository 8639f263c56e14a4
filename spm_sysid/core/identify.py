"""One call from measured signals to a fitted model: the public entry point.

``identify(u=..., y=...)`` validates the data once (here, at the boundary),
builds the regression matrix, runs the GA with single parent mating on the
chosen criterion and fits the winning structure by QR least squares.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .criteria import Criterion, get_criterion
from .data import DataError, check_samples
from .evaluator import StructureEvaluator
from .ga import GAConfig, GAResult, GenerationStats, run_ga
from .model import NarxModel
from .terms import TermSpace

__all__ = ["IdentificationResult", "identify", "validate_signals"]


@dataclass
class IdentificationResult:
    """A fitted model and the search that produced it."""

    model: NarxModel
    ga: GAResult
    criterion: str
    seed: int | None

    def summary(self) -> str:
        """A few lines for people: equation, criterion, size, error, time."""
        m = self.model
        return (
            f"{m.equation()}\n"
            f"criterion {self.criterion.upper()} = {self.ga.best_score:.2f}, "
            f"{len(m.term_indices)} terms, one-step MSE {m.mse:.4e}, "
            f"{m.n_samples} samples, {self.ga.elapsed:.2f} s "
            f"({self.ga.evaluations} structures fitted, "
            f"cache hit rate {self.ga.cache_hit_rate:.0%})"
        )


def validate_signals(u, y, term_space: TermSpace) -> tuple[np.ndarray, np.ndarray]:
    """Check and convert u, y at the public boundary.

    Raises
    ------
    DataError
        Not 1-D, different lengths, non-finite values, or too few samples.
    """
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.ndim != 1 or y.ndim != 1:
        raise DataError(f"u and y must be 1-D arrays, got shapes {u.shape} and {y.shape}")
    if len(u) != len(y):
        raise DataError(f"u and y must have the same length, got {len(u)} and {len(y)}")
    for name, arr in (("u", u), ("y", y)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise DataError(
                f"{name} has {bad.size} non-finite value(s) (NaN or inf), first at index "
                f"{bad[0]}"
            )
    check_samples(len(y), term_space.max_lag, term_space.n_terms)
    return u, y


def identify(
    *,
    u: np.ndarray,
    y: np.ndarray,
    term_space: TermSpace | None = None,
    criterion: str | Criterion | Callable[..., float] = "aic",
    ga: GAConfig | None = None,
    seed: int | None = None,
    callback: Callable[[GenerationStats], bool | None] | None = None,
) -> IdentificationResult:
    """Select a NARX structure with the SPM-GA and fit it.

    Parameters
    ----------
    u, y : ndarray, shape (n,)
        Input and output samples, equally spaced.
    term_space : TermSpace, optional
        Candidate terms; default: the paper's (ny=4, nu=4, degree 2, delay 1).
    criterion : str, Criterion or callable
        ``"aic"``, ``"bic"``, ``"pmic2"`` or a user's ``f(sse, n, k, coefficients)``.
    ga : GAConfig, optional
        GA settings; default: the paper's (population 200, 300 generations, SPM 0.15).
    seed : int, optional
        Makes the run reproducible.
    callback : callable, optional
        Progress hook, see :func:`spm_sysid.core.ga.run_ga`.
    """
    term_space = term_space or TermSpace()
    crit = get_criterion(criterion)
    u, y = validate_signals(u, y, term_space)
    ga = ga or GAConfig()
    P = term_space.regression_matrix(u, y)
    target = term_space.target(y)
    evaluator = StructureEvaluator(P, target, crit)
    result = run_ga(evaluator, ga, seed=seed, callback=callback)
    if not np.isfinite(result.best_score):
        raise DataError(
            "no structure could be fitted: every candidate was rank-deficient "
            "(is the input or output constant?)"
        )
    model = NarxModel.fit(
        u, y, result.best_mask, term_space,
        criterion=crit.name, criterion_value=result.best_score,
        metadata={
            "ga": ga.to_dict(),
            "seed": seed,
            "generations_run": len(result.history) - 1,
            "first_best_generation": result.first_best_generation,
            "evaluations": result.evaluations,
            "search_seconds": round(result.elapsed, 4),
        },
    )
    return IdentificationResult(model=model, ga=result, criterion=crit.name, seed=seed)
