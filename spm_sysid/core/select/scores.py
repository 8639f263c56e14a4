"""Held-out scores of structures: mean error over the blocks and its standard error.

:class:`Scores` keeps each structure's mean held-out error and standard error;
its rule (:meth:`Scores.best`) takes, among the structures within one standard
error of the lowest mean (:data:`~spm_sysid.core.defaults.ONE_SE`), the one with
the fewest terms. :func:`mean_and_stderr` is the one place that statistic is
computed (single-output folds, sub-blocks, the coupled judgement).
:func:`cv_scores` scores structures fitted by least squares on each fold;
:func:`candidate_structures` names the structures worth judging.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..defaults import MAX_CANDIDATES, ONE_SE
from ..fit.lstsq import columns_product, sse_floor, structure_fit
from ..model.simulation import divergence_bounds, run_model
from .folds import Fold

__all__ = ["Scores", "candidate_structures", "cv_scores", "held_out_floor", "mean_and_stderr"]


def mean_and_stderr(values: Sequence[float]) -> tuple[float, float]:
    """Mean of held-out errors and its standard error; (inf, inf) when one is not finite.

    A single value has no spread: its standard error is 0. Computed on the values
    over a power of two near their largest (exact: the same bits), so errors of a
    record in huge units (1e100) do not overflow when squared.
    """
    values = np.asarray(values, dtype=float)
    if not len(values) or not np.all(np.isfinite(values)):
        return np.inf, np.inf
    top = float(np.exp2(np.floor(np.log2(np.max(np.abs(values)))))) if np.any(values) else 1.0
    spread = float(np.std(values / top, ddof=1)) * top if len(values) > 1 else 0.0
    return float(np.mean(values)), float(spread / np.sqrt(len(values)))


@dataclass
class Scores:
    """Validated scores of structures: mean held-out MSE and its standard error.

    ``floor``: the error of an exact fit (rounding); means below it count as equal.
    ``degrees``: each term's degree, which breaks ties among equal sizes and errors.
    """

    masks: list[np.ndarray] = field(default_factory=list)
    mean: list[float] = field(default_factory=list)
    stderr: list[float] = field(default_factory=list)
    rejected: int = 0  # structures whose held-out simulation left the range
    floor: float = 0.0
    degrees: np.ndarray | None = None

    def best(self) -> int | None:
        """Index of the chosen structure: fewest terms within one SE of the lowest mean.

        Among as many terms, the lower mean; among exact fits (means at the floor,
        where rounding alone orders them: a noise-free step record's three-term
        models, each exact, at 1e-30), the lower total degree.
        """
        finite = [i for i, v in enumerate(self.mean) if np.isfinite(v)]
        if not finite:
            return None
        level = [max(v, self.floor) for v in self.mean]
        low = min(finite, key=lambda i: level[i])
        limit = level[low] + ONE_SE * self.stderr[low]
        near = [i for i in finite if level[i] <= limit]
        return min(near, key=lambda i: (int(self.masks[i].sum()), level[i], self._degree(i)))

    def _degree(self, i: int) -> int:
        return 0 if self.degrees is None else int(self.degrees[self.masks[i]].sum())

    def order(self) -> list[int]:
        """Indices by the selection rule: the chosen first, then by mean."""
        first = self.best()
        rest = sorted((i for i, v in enumerate(self.mean) if np.isfinite(v) and i != first),
                      key=lambda i: self.mean[i])
        return ([first] if first is not None else []) + rest


def held_out_floor(problem) -> float:
    """The mean square error of an exact fit, in the record's units: rounding, no more."""
    return sse_floor(float(np.linalg.norm(problem.target)) * problem.y_scale) / problem.rows


def cv_scores(problem, folds: list[Fold], masks, simulate: bool,
              horizon: int | None = None) -> Scores:
    """Validated scores of structures (masks over the whole term space).

    ``simulate``: the held-out free run, or with ``horizon`` the k-step prediction.
    """
    out = Scores(floor=held_out_floor(problem), degrees=problem.term_space.term_degrees)
    for mask in masks:
        values = [_fold_mse(problem, f, mask, simulate, horizon) for f in folds]
        out.masks.append(np.asarray(mask, dtype=bool))
        mean, stderr = mean_and_stderr(values)
        out.mean.append(mean)
        out.stderr.append(stderr)
        out.rejected += bool(simulate and any(v == np.inf for v in values))
    return out


def _fold_mse(problem, fold: Fold, mask: np.ndarray, simulate: bool,
              horizon: int | None = None) -> float:
    """Held-out MSE of the structure fitted on the fold's training rows (inf: unusable)."""
    mask = np.asarray(mask, dtype=bool)
    train = fold.train
    if not mask.any() or (mask & ~problem.usable).any() or train.sum() <= mask.sum():
        return np.nan
    cols = problem.column_index(np.flatnonzero(mask))  # its columns only, in slices of rows
    fit, _ = structure_fit(problem.columns, problem.target, cols, train)
    if fit.rank_deficient:
        return np.nan
    theta = fit.coefficients  # on the scaled problem
    ts = problem.term_space
    lag = ts.max_lag
    if not simulate:
        held = np.zeros(len(train), dtype=bool)
        t = problem.row_times
        for a, b in fold.held_out:
            held |= (t >= a + lag) & (t < b)
        e = problem.target[held] - columns_product(problem.columns, cols, theta, held)
        return float(np.mean(e * e)) * problem.sse_scale
    model = _scaled_model(problem, mask, theta)
    u = problem.u / problem.u_scale
    y = problem.y / problem.y_scale
    bounds = divergence_bounds(y)
    sse, rows = 0.0, 0
    for a, b in fold.held_out:
        yhat, at = run_model(model.compiled, theta, u[a:b], y[a:b], horizon, bounds)
        if at is not None:
            return np.inf
        e = y[a + lag:b] - yhat
        sse += float(e @ e)
        rows += len(e)
    return sse / rows * problem.sse_scale


def _scaled_model(problem, mask, theta):
    from ..model.narx import NarxModel

    return NarxModel(problem.term_space, [int(i) for i in np.flatnonzero(mask)], theta)


def candidate_structures(problem, evaluator, shortlist: int, forward: Callable | None = None,
                         max_candidates: int = MAX_CANDIDATES) -> np.ndarray:
    """Masks (whole term space) to judge: the short-list, a ladder of sizes, forward path.

    ``forward`` returns forward selection's path (masks over the usable columns).
    """
    sets = [evaluator.ranked(shortlist)]
    each = max(2, (max_candidates - shortlist) // 2)
    for ladder in (evaluator.best_per_size(), forward() if forward is not None else None):
        if ladder is None or not len(ladder):
            continue
        if len(ladder) > each:  # sizes spread over the whole range
            pick = np.unique(np.linspace(0, len(ladder) - 1, each).round()).astype(int)
            ladder = ladder[pick]
        sets.append(ladder)
    masks = np.concatenate([s for s in sets if len(s)]) if any(len(s) for s in sets) \
        else np.zeros((0, evaluator.n_terms), dtype=bool)
    if not len(masks):
        return np.zeros((0, problem.term_space.n_terms), dtype=bool)
    masks = np.unique(masks, axis=0)
    return problem.expand(masks)
