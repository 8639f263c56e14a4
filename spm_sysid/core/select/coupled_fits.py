"""Least-squares fits of a coupled model's structures on several row sets, one pass each.

The coupled judgement (:mod:`.coupled`) fits every finalist by least squares on
the training part of every fold: six folds, each row in five of them. Each fit
built the structure's columns over its training rows again, then an SVD for the
rank and another for the solution: on two outputs of 10^6 samples, 20
finalists x 6 folds such fits were most of a 20-minute command, and each held
its columns several times.

Here a long record's regression rows are cut into pieces at every row set's
edges. The triangular factor of each piece's ``[X y]`` is computed once, a
slice of rows at a time (:func:`~spm_sysid.core.memory.slice_rows`), and a
row set's fit is the QR of its pieces' factors stacked: the same least-squares
problem in ``k + 1`` rows per piece. The rank is read from that factor's
singular values, which are ``X``'s, with numpy's ``matrix_rank`` tolerance for
``X``'s shape. A record whose largest regression matrix fits in one slice takes
the direct route (:func:`fit_least_squares`), so its numbers are unchanged.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..linalg import column_scales, scaled_lstsq
from ..memory import slice_rows
from ..model.mimo import MimoModel, augmented_inputs
from ..model.narx import NarxModel
from ..model.uncertainty import solve_upper, stacked_factor

__all__ = ["fit_least_squares", "least_squares_fits", "one_pass", "row_factor"]


def fit_least_squares(model: MimoModel, u: np.ndarray, Y: np.ndarray,
                      segments: list[tuple[int, int]]) -> MimoModel | None:
    """The same structures, each output's coefficients by least squares on the segments.

    None when a structure cannot be fitted there (too few rows, dependent columns).
    """
    return least_squares_fits(model, u, Y, [segments])[0]


def least_squares_fits(model: MimoModel, u: np.ndarray, Y: np.ndarray,
                       row_sets: list[list[tuple[int, int]]]) -> list[MimoModel | None]:
    """:func:`fit_least_squares` on each of ``row_sets`` (segments of samples), in one pass.

    A long record's pieces are factored once for all the sets (see the module doc).
    """
    if _direct(model, len(Y)):
        return [_direct_fit(model, u, Y, segments) for segments in row_sets]
    coefficients: list[list[np.ndarray] | None] = [[] for _ in row_sets]
    for i, m in enumerate(model.models):
        for j, theta in enumerate(_output_fits(m, augmented_inputs(u, Y, i), Y[:, i],
                                               row_sets)):
            if coefficients[j] is not None:
                coefficients[j] = None if theta is None else [*coefficients[j], theta]
    return [None if thetas is None else
            replace(model, models=[replace(m, coefficients=t, metadata=dict(m.metadata))
                                   for m, t in zip(model.models, thetas)],
                    metadata=dict(model.metadata))
            for thetas in coefficients]


def _direct(model: MimoModel, n: int) -> bool:
    """Every output's regression matrix of the whole record fits in one slice."""
    return all(one_pass(m, n) for m in model.models)


def one_pass(m: NarxModel, n: int) -> bool:
    """The output's regression matrix of ``n`` samples fits in one slice (built whole)."""
    return n <= slice_rows(len(m.term_indices))


def row_factor(m: NarxModel, u: np.ndarray, y: np.ndarray,
               segments: list[tuple[int, int]]) -> tuple[np.ndarray, int]:
    """The triangular factor of ``[X y]`` over the segments' rows, and their count.

    Its first ``k`` columns have ``X``'s column norms and ``X^T X``; the last holds
    ``Q^T y`` above the norm of ``y``'s part outside ``X``'s span.
    """
    k = len(m.term_indices)
    ranges = _rows(segments, m.term_space.max_lag)
    parts = [_factor(m, u, y, r) for r in ranges]
    stacked = np.vstack(parts) if parts else np.zeros((0, k + 1))
    return np.linalg.qr(stacked, mode="r"), sum(b - a for a, b in ranges)


def _direct_fit(model: MimoModel, u, Y, segments) -> MimoModel | None:
    """Least squares on the structures' columns built whole (a short record)."""
    models = []
    for i, m in enumerate(model.models):
        P, t = m.term_space.regression(augmented_inputs(u, Y, i), Y[:, i], segments,
                                       terms=m.term_indices)
        if len(t) <= P.shape[1] or np.linalg.matrix_rank(P / column_scales(P)) < P.shape[1]:
            return None
        theta = scaled_lstsq(P, t)
        models.append(replace(m, coefficients=theta, metadata=dict(m.metadata)))
    return replace(model, models=models, metadata=dict(model.metadata))


def _rows(segments: list[tuple[int, int]], lag: int) -> list[tuple[int, int]]:
    """The regression rows ``[first, stop)`` of sample segments (rows need ``lag`` samples)."""
    return [(a + lag, b) for a, b in segments if b - a > lag]


def _pieces(row_ranges: list[list[tuple[int, int]]]) -> list[tuple[int, int]]:
    """Row intervals between consecutive edges of any set, inside at least one set."""
    edges = sorted({e for ranges in row_ranges for r in ranges for e in r})
    return [(p, q) for p, q in zip(edges, edges[1:])
            if any(a <= p and q <= b for ranges in row_ranges for a, b in ranges)]


def _factor(m: NarxModel, u: np.ndarray, y: np.ndarray, piece: tuple[int, int]) -> np.ndarray:
    """Triangular factor of ``[X y]`` over a piece's rows, a slice of rows at a time."""
    rows = [(piece[0] - m.term_space.max_lag, piece[1])]
    return stacked_factor((np.column_stack(pair) for pair in m.regression_slices(u, y, rows)),
                          len(m.term_indices) + 1)


def _output_fits(m: NarxModel, u: np.ndarray, y: np.ndarray,
                 row_sets: list[list[tuple[int, int]]]) -> list[np.ndarray | None]:
    """One output's coefficients on each row set (None: too few rows, dependent columns)."""
    k = len(m.term_indices)
    ranges = [_rows(s, m.term_space.max_lag) for s in row_sets]
    factors = {piece: _factor(m, u, y, piece) for piece in _pieces(ranges)}
    out = []
    for own in ranges:
        parts = [f for (p, q), f in factors.items() if any(a <= p and q <= b for a, b in own)]
        rows = sum(b - a for a, b in own)
        out.append(_solve(np.vstack(parts), k, rows) if parts and rows > k else None)
    return out


def _solve(stacked: np.ndarray, k: int, rows: int) -> np.ndarray | None:
    """The least-squares coefficients from stacked factors (None when ``X`` is rank-deficient)."""
    r = np.linalg.qr(stacked, mode="r")
    if r.shape[0] < k:
        return None
    R = r[:k, :k]
    s = np.linalg.svd(R, compute_uv=False)
    if s[0] == 0 or np.sum(s > s[0] * max(rows, k) * np.finfo(float).eps) < k:
        return None  # numpy's matrix_rank of X, whose singular values these are
    return solve_upper(R, r[:k, k])
