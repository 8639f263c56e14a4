"""Least-squares fits of one structure, shared by the model and the evaluator.

:func:`reference_fit` is the numerically preferred path (Householder QR of the
selected, unit-norm columns): it gives a model's coefficients and is the
yardstick the evaluator's fast path is tested against. Both use one rank rule
(see :mod:`spm_sysid.core.fit.evaluator`): a squared relative pivot below
``rank_tol`` makes a structure rank-deficient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import SSE_FLOOR_RELATIVE
from ..memory import slice_rows
from ..model.uncertainty import solve_upper, stacked_factor
from .criteria import Criterion, get_criterion

__all__ = ["DEFAULT_RANK_TOL", "FitResult", "column_norms", "columns_product", "reference_fit",
           "reference_score", "score_one", "sse_floor", "structure_fit"]

DEFAULT_RANK_TOL = 1e-9

#: Bytes of a matrix's rows whose squares :func:`column_norms` forms at a time.
NORM_SLICE_BYTES = 64 << 20


def column_norms(P: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(P, axis=0)`` without a squared copy of a long matrix.

    A matrix of more than :data:`NORM_SLICE_BYTES` is summed a slice of rows at a
    time; a smaller one takes numpy's one pass, so its norms are unchanged.
    """
    rows = max(1, NORM_SLICE_BYTES // (8 * max(P.shape[1], 1)))
    if P.shape[0] <= rows:
        return np.linalg.norm(P, axis=0)
    squares = np.zeros(P.shape[1])
    for a in range(0, P.shape[0], rows):
        block = P[a:a + rows]
        squares += np.add.reduce(block * block, axis=0)
    return np.sqrt(squares)


def sse_floor(target_norm: float) -> float:
    """The SSE below which a fit is exact to rounding (criteria see this floor instead).

    Noise-free data fit exactly by the true structure and by every larger one;
    their SSEs then differ only by rounding (1e-30 and below), which would reward
    extra terms at random. With the floor, all exact fits score alike on fit and
    the fewest terms win.
    """
    return float((SSE_FLOOR_RELATIVE * target_norm) ** 2)


@dataclass(frozen=True)
class FitResult:
    """Least-squares fit of one structure.

    Attributes
    ----------
    coefficients : ndarray, shape (k,)
        Parameters of the selected terms, in term order (NaN when rank-deficient).
    sse : float
        Sum of squared one-step residuals.
    rank_deficient : bool
        True when the selected regressors are (numerically) linearly dependent.
    r_factor : ndarray, shape (k, k)
        R of the QR factorisation of the selected columns scaled to unit norm.
    column_norms : ndarray, shape (k,)
        Norms of the selected columns.
    """

    coefficients: np.ndarray
    sse: float
    rank_deficient: bool
    r_factor: np.ndarray | None = None
    column_norms: np.ndarray | None = None


def reference_fit(
    P: np.ndarray, target: np.ndarray, mask: np.ndarray, rank_tol: float = DEFAULT_RANK_TOL
) -> FitResult:
    """Fit one structure by Householder QR of its unit-norm columns.

    Parameters
    ----------
    P : ndarray, shape (N, n_terms)
        Regression matrix of all candidate terms.
    target : ndarray, shape (N,)
        y(t) for the regression rows.
    mask : ndarray of bool, shape (n_terms,)
        Selected terms.
    rank_tol : float
        Squared relative pivot below which the structure is rank-deficient.
    """
    cols = np.flatnonzero(mask)
    k = cols.size
    if k == 0:
        return FitResult(np.empty(0), float(target @ target), False)
    A = P[:, cols]
    norms = np.linalg.norm(A, axis=0)
    if np.any(norms == 0) or k > A.shape[0]:  # a zero column, or more terms than rows
        return FitResult(np.full(k, np.nan), np.nan, True)
    An = A / norms
    Q, R = np.linalg.qr(An, mode="reduced")
    if np.min(np.abs(np.diag(R))) ** 2 < rank_tol:
        return FitResult(np.full(k, np.nan), np.nan, True)
    z = Q.T @ target
    theta_n = solve_upper(R, z)
    resid = target - An @ theta_n
    return FitResult(theta_n / norms, float(resid @ resid), False, R, norms)


def _slices(P: np.ndarray, cols: np.ndarray, rows: np.ndarray | None,
            extra: np.ndarray | None = None):
    """(the columns ``cols`` of a slice of P's rows, ``extra`` there), ``rows`` kept only."""
    step = slice_rows(len(cols))
    for a in range(0, P.shape[0], step):
        X, e = P[a:a + step][:, cols], None if extra is None else extra[a:a + step]
        if rows is not None:
            keep = rows[a:a + step]
            X, e = X[keep], None if e is None else e[keep]
        yield X, e


def columns_product(P: np.ndarray, cols: np.ndarray, theta: np.ndarray,
                    rows: np.ndarray | None = None) -> np.ndarray:
    """``P[rows][:, cols] @ theta``, a slice of rows at a time (no copy of the columns).

    ``rows``: a boolean mask over P's rows (None: all).
    """
    return np.concatenate([X @ theta for X, _ in _slices(P, np.asarray(cols), rows)]
                          or [np.empty(0)])


def structure_fit(P: np.ndarray, target: np.ndarray, cols: np.ndarray,
                  rows: np.ndarray | None = None, rank_tol: float = DEFAULT_RANK_TOL
                  ) -> tuple[FitResult, np.ndarray | None]:
    """:func:`reference_fit` of P's columns ``cols`` on ``rows``, and its residuals.

    A long matrix is read a slice of rows at a time
    (:func:`~spm_sysid.core.memory.slice_rows`): the column norms summed,
    then the triangular factor of the unit-norm ``[X y]`` updated by the QR of the
    factor so far stacked on the next rows; its last column gives ``Q^T y``. So a fit
    of 10^6 rows holds no copy of its columns (one-pass QR held five). A matrix of
    one slice takes the one-pass route, so its numbers are unchanged.

    Parameters
    ----------
    P, target, rank_tol
        As for :func:`reference_fit`.
    cols : ndarray of int
        The structure's columns.
    rows : ndarray of bool, shape (N,), optional
        The rows to fit on (None: all).

    Returns
    -------
    fit : FitResult
    residuals : ndarray or None
        ``target - X @ coefficients`` on the rows (None when rank-deficient).
    """
    cols = np.asarray(cols)
    k = len(cols)
    if k == 0 or P.shape[0] <= slice_rows(k):
        X, t = P[:, cols], target
        if rows is not None:
            X, t = X[rows], t[rows]
        res = reference_fit(X, t, np.ones(k, dtype=bool), rank_tol)
        return res, None if res.rank_deficient else t - X @ res.coefficients
    squares, count = np.zeros(k), 0
    for X, _ in _slices(P, cols, rows, target):
        squares += np.add.reduce(X * X, axis=0)
        count += len(X)
    norms = np.sqrt(squares)
    if np.any(norms == 0) or k > count:  # a zero column, or more terms than rows
        return FitResult(np.full(k, np.nan), np.nan, True), None
    r = stacked_factor((np.column_stack([X / norms, t])
                        for X, t in _slices(P, cols, rows, target)), k + 1)
    R = r[:k, :k]
    if np.min(np.abs(np.diag(R))) ** 2 < rank_tol:
        return FitResult(np.full(k, np.nan), np.nan, True), None
    coefficients = solve_upper(R, r[:k, k]) / norms
    residuals = np.concatenate([t - X @ coefficients
                                for X, t in _slices(P, cols, rows, target)])
    return FitResult(coefficients, float(residuals @ residuals), False, R, norms), residuals


def score_one(crit: Criterion, sse: float, n: int, n_terms: int, cols: np.ndarray,
               beta_selected: np.ndarray) -> float:
    """Criterion value of one fitted structure; non-finite values become +inf."""
    beta = np.zeros((1, n_terms))
    beta[0, cols] = beta_selected
    value = float(crit(sse, n, np.array([cols.size]), beta)[0])
    return value if np.isfinite(value) else np.inf


def reference_score(
    P: np.ndarray, target: np.ndarray, mask: np.ndarray, criterion: str | Criterion = "aic",
    rank_tol: float = DEFAULT_RANK_TOL,
) -> float:
    """Criterion value of one structure from :func:`reference_fit` (inf if not fittable)."""
    crit = get_criterion(criterion)
    mask = np.asarray(mask, dtype=bool)
    fit = reference_fit(P, target, mask, rank_tol)
    if fit.rank_deficient or not mask.any():
        return np.inf
    cols = np.flatnonzero(mask)
    beta = fit.coefficients * np.linalg.norm(P[:, cols], axis=0) / (np.linalg.norm(target) or 1.0)
    sse = max(fit.sse, sse_floor(np.linalg.norm(target)))
    return score_one(crit, sse, P.shape[0], P.shape[1], cols, beta)
