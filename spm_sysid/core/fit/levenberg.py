"""Levenberg-Marquardt for the free-run refinements: small problems, many of them, compiled.

A simulation-focused selection refines hundreds of structures by a few dozen
steps each (screening, held-out folds). On problems of a few thousand rows and
a few dozen coefficients, MINPACK's QR factorisation at every step, scipy's
wrapper around it and the import of ``scipy.optimize`` (0.7 s) cost as much as
the simulations that give the residuals and their Jacobian. This solver is
MINPACK's ``lmder`` (Moré, "The Levenberg-Marquardt algorithm: implementation
and theory", 1978) on the normal equations (``J'J``, ``J'r``: a few dozen
columns): the columns' norms as scales, kept at their largest (scipy's
``x_scale="jac"``); a trust region, its first radius 100 times the scaled
start, shrunk and grown by MINPACK's rules; the damping that fits a step to the
region found by Newton's method on the secular equation, through one
eigendecomposition of the scaled ``J'J`` per accepted step; and MINPACK's
stopping rules (``ftol``, ``xtol``, ``gtol``) and messages. Each evaluation
gives residuals and Jacobian together (the sensitivity equations run with the
simulation), so a rejected step costs one evaluation, as in MINPACK.

The solver is a kernel (:func:`lm_solve`) that calls the free run's
evaluation (:func:`~spm_sysid.core.fit.free_run.residuals`), so a refinement
(:func:`refine_free_run`) is one compiled call, its steps and simulations
without returning to Python: the loop in Python cost twice the simulations
themselves on the robot arm. A compiled function passed as an argument would
keep numba from caching the kernel and the ahead-of-time build from exporting
it; so :func:`levenberg_marquardt`, the same solver for any problem (a Python
``evaluate``; the tests compare it with MINPACK), runs the kernel's own code in
Python with that call bound to ``evaluate``.

On the structures a simulation focus screens (robot arm, dryer, heat
exchanger) it takes the evaluations MINPACK takes and ends at the same sum of
squares on most of them; the selections they make are the same.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import FunctionType

import numpy as np

from ..compiled.registry import jit_exact as jit
from .free_run import FreeRun, residuals

__all__ = ["MESSAGES", "FreeRunSolution", "Solution", "evaluate_free_run", "levenberg_marquardt",
           "lm_solve", "refine_free_run"]

#: MINPACK's (and scipy's) default tolerances.
TOLERANCE = 1e-8

#: Largest Jacobian entry whose square, summed over 10^5 rows, stays a float:
#: a point whose sensitivities are larger (a free run whose linearisation grows
#: without bound) gives no quadratic model, so it is never a step.
JACOBIAN_LIMIT = 1e150

#: Why :func:`lm_solve` stopped, by the code it returns.
MESSAGES = (
    "`gtol` termination condition is satisfied.",
    "`ftol` termination condition is satisfied.",
    "`xtol` termination condition is satisfied.",
    "The maximum number of function evaluations is exceeded.",
    "the start's residuals are not finite, or its sensitivities are out of floating-point "
    "range",
)


@dataclass(frozen=True)
class Solution:
    """The solver's end: coefficients, evaluations run, and why it stopped."""

    x: np.ndarray
    nfev: int
    message: str


@dataclass(frozen=True)
class FreeRunSolution(Solution):
    """A refinement's end, and the free run's sum of squares at its start and at its end.

    A sum is infinite where the run left the measured range; ``diverged_*``:
    the first sample that did, or None.
    """

    sse_start: float = np.inf
    diverged_start: int | None = None
    sse: float = np.inf
    diverged: int | None = None


def refine_free_run(run: FreeRun, theta0: np.ndarray, max_evaluations: int,
                    tol: float = TOLERANCE) -> FreeRunSolution:
    """Levenberg-Marquardt on ``run``'s free-run residuals from ``theta0``, compiled.

    At most ``max_evaluations`` simulations with their Jacobian, the first (at
    ``theta0``) included.
    """
    m = len(run.measured)
    x, nfev, stop, sse0, at0, sse, at = _refine_entry(
        *run.args, np.ascontiguousarray(theta0, dtype=float), max(int(max_evaluations), 1),
        float(tol), np.empty(m), np.empty((m, run.k)))
    return FreeRunSolution(x, int(nfev), MESSAGES[stop],
                           float(sse0) if at0 < 0 else np.inf, None if at0 < 0 else int(at0),
                           float(sse) if at < 0 else np.inf, None if at < 0 else int(at))


def evaluate_free_run(run: FreeRun, theta: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, int | None]:
    """``run``'s residuals and Jacobian at ``theta``, and the first sample out of range.

    None: no sample left the measured range. The refinement's kernel, with no step.
    """
    m = len(run.measured)
    r, jac = np.empty(m), np.empty((m, run.k))
    *_, at = _refine_entry(*run.args, np.ascontiguousarray(theta, dtype=float), 0,
                           TOLERANCE, r, jac)
    return r, jac, (None if at < 0 else int(at))


def levenberg_marquardt(evaluate: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                        x0: np.ndarray, max_evaluations: int, tol: float = TOLERANCE
                        ) -> Solution:
    """Minimise ``|r(x)|^2`` from ``x0`` in at most ``max_evaluations`` evaluations.

    :func:`lm_solve`'s code, run in Python with ``evaluate`` as its evaluation.

    Parameters
    ----------
    evaluate : callable
        ``x -> (r, J)``: residuals (m,) and their Jacobian (m, k); a non-finite
        sum of squares rejects the step.
    x0 : ndarray, shape (k,)
        The start.
    max_evaluations : int
        Evaluations at most, the first (at ``x0``) included.
    tol : float
        ``ftol``, ``xtol`` and ``gtol`` (as scipy's ``least_squares``).
    """
    x0 = np.array(x0, dtype=float)
    first = [evaluate(x0)]  # its shapes size the buffers; it is the solver's first call

    def fill(args, x, r, jac) -> int:
        r_x, jac_x = first.pop() if first else evaluate(x)
        r[:], jac[:] = r_x, jac_x
        return -1

    code = lm_solve.py_func
    solve = FunctionType(code.__code__, {**code.__globals__, "residuals": fill})
    m, k = len(first[0][0]), len(x0)
    x, nfev, stop, _, _ = solve((), x0, np.empty(m), np.empty((m, k)), np.empty(m),
                                np.empty((m, k)), max_evaluations, tol, -2)
    return Solution(x, int(nfev), MESSAGES[stop])


@jit
def _refine_entry(gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly, u, y,
                  seg_a, seg_b, lag0, lo, hi, guard, part_pos, part_lag, ny, measured,
                  theta0, max_evaluations, tol, r, jac):  # pragma: no cover - compiled
    """:func:`lm_solve` on the free-run residuals of these arrays (:class:`FreeRun`'s).

    Returns the solution, evaluations and stop, and the sum of squares and first
    diverged sample (-1: none) at the start and at the solution. ``max_evaluations``
    0: no refinement, the residuals and Jacobian at ``theta0`` left in ``r`` and
    ``jac`` (one export serves both).
    """
    args = (gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly, u, y, seg_a,
            seg_b, lag0, lo, hi, guard, part_pos, part_lag, ny, measured)
    m, k = measured.shape[0], theta0.shape[0]
    at0 = residuals(args, theta0, r, jac)
    sse0 = r @ r
    if max_evaluations < 1:
        return theta0.copy(), 1, 3, sse0, at0, sse0, at0
    x, nfev, stop, sse, at = lm_solve(args, theta0, r, jac, np.empty(m), np.empty((m, k)),
                                      max_evaluations, tol, at0)
    return x, nfev, stop, sse0, at0, sse, at


@jit
def lm_solve(args, x0, r, jac, r_new, jac_new, max_evaluations, tol,
             at):  # pragma: no cover - compiled
    """Minimise ``|r(x)|^2`` from ``x0``; returns ``(x, evaluations, stop, |r(x)|^2, at)``.

    ``residuals(args, x, r, jac)`` writes the residuals and their Jacobian at x
    into ``r`` (m,) and ``jac`` (m, k) and returns the first diverged sample
    (``at`` of the result: x's); ``r_new``, ``jac_new`` are a second set of
    buffers (the trial step's). ``at`` given as -2: ``x0`` is evaluated here;
    else ``r`` and ``jac`` hold its evaluation already, and ``at`` is its. ``stop``
    indexes :data:`MESSAGES`.
    """
    x = x0.copy()
    if at == -2:
        at = residuals(args, x, r, jac)
    f = _cost(r, jac)
    if not np.isfinite(f):
        return x, 1, 4, r @ r, at
    scale = np.zeros(x.shape[0])
    region, nfev = -1.0, 1
    while True:
        a, g = jac.T @ jac, jac.T @ r
        norms = np.sqrt(np.diag(a).copy())
        if f == 0.0 or _gradient_small(g, norms, tol * np.sqrt(f)):
            return x, nfev, 0, r @ r, at
        scale = _scales(scale, norms)
        values, vectors, coef, floor = _scaled_model(a, g, scale)
        while True:
            if nfev >= max_evaluations:
                return x, nfev, 3, r @ r, at
            if region < 0.0:
                step, damped, region = _first_step(values, vectors, coef, floor, scale,
                                                   _norm(scale * x))
            else:
                step, damped = _step(values, vectors, coef, floor, scale, region)
            size = _norm(scale * step)
            trial = x + step
            at_new = residuals(args, trial, r_new, jac_new)
            nfev += 1
            f_new = _cost(r_new, jac_new)
            predicted = -(2.0 * (step @ g) + step @ (a @ step))
            actual = f - f_new if np.isfinite(f_new) else -np.inf
            rho = actual / predicted if predicted > 0 else -np.inf
            region = _new_region(region, size, rho, actual, step @ g, f, f_new, damped)
            accepted = rho >= 1e-4
            f_old = f
            if accepted:
                x, f, at = trial, f_new, at_new
                r, r_new = r_new, r
                jac, jac_new = jac_new, jac
            if abs(actual) <= tol * f_old and predicted <= tol * f_old and rho <= 2.0:
                return x, nfev, 1, r @ r, at
            if region <= tol * _norm(scale * x):
                return x, nfev, 2, r @ r, at
            if accepted:
                break


@jit
def _cost(r, jac):  # pragma: no cover - compiled
    """The sum of squares, infinite where ``J'J`` would overflow (see :data:`JACOBIAN_LIMIT`)."""
    for v in jac.ravel():
        if not abs(v) < JACOBIAN_LIMIT:
            return np.inf
    return r @ r


@jit
def _gradient_small(g, norms, bound):  # pragma: no cover - compiled
    """MINPACK's ``gtol`` test: every scaled gradient entry at most ``bound``."""
    for i in range(g.shape[0]):
        if not abs(g[i]) / (norms[i] if norms[i] > 0 else 1.0) <= bound:
            return False
    return True


@jit
def _scales(scale, norms):  # pragma: no cover - compiled
    """The columns' scales: the largest norm seen, 1 for a column that is zero throughout."""
    out = np.maximum(scale, norms)
    for i in range(out.shape[0]):
        if out[i] == 0.0:
            out[i] = 1.0
    return out


@jit
def _new_region(region, size, rho, actual, slope, f, f_new, damped):  # pragma: no cover
    """MINPACK's update of the trust region's radius after a step of scaled ``size``.

    ``slope``: the sum of squares' derivative along the step, halved (``p'J'r``).
    """
    if rho <= 0.25:
        if actual >= 0:
            shrink = 0.5
        elif np.isfinite(actual):  # the sum of squares rose: where a quadratic is least
            shrink = 0.5 * slope / (slope + 0.5 * actual)
        else:
            shrink = 0.0
        if not f_new <= 100.0 * f or shrink < 0.1:
            shrink = 0.1
        return shrink * min(region, 10.0 * size)
    if rho >= 0.75 or not damped:
        return 2.0 * size
    return region


@jit
def _scaled_model(a, g, scale):  # pragma: no cover - compiled
    """The quadratic model ``|r + J p|^2`` in scaled steps, in the eigenbasis of ``J'J``.

    With ``A = J'J`` and the column scales ``D``: ``p(lam) = -(A + lam D^2)^-1 g``;
    one eigendecomposition of the scaled ``D^-1 A D^-1`` serves every radius.
    Returns the eigenvalues, the eigenvectors, the scaled gradient in their
    basis and the smallest damping.
    """
    values, vectors = np.linalg.eigh(a / np.outer(scale, scale))
    values = np.maximum(values, 0.0)
    coef = vectors.T @ (g / scale)
    floor = 1e-12 * max(values[-1], 1e-300)
    return values, vectors, coef, floor


@jit
def _size(values, coef, lam):  # pragma: no cover - compiled
    return np.sqrt(np.sum((coef / (values + lam)) ** 2))


@jit
def _first_step(values, vectors, coef, floor, scale, size):  # pragma: no cover - compiled
    """MINPACK's first region (100x the scaled start ``size``, or the step), its step."""
    first = 100.0 * (size if size != 0.0 else 1.0)
    step, damped = _step(values, vectors, coef, floor, scale, first)
    region = min(first, _norm(scale * step))
    if damped and region < first:  # solved again on the smaller region
        step, damped = _step(values, vectors, coef, floor, scale, region)
    return step, damped, region


@jit
def _step(values, vectors, coef, floor, scale, region):  # pragma: no cover - compiled
    """The step in the coefficients' units, and whether it was damped (lam > floor).

    ``lam``: 0 (the floor) when the Gauss-Newton step lies inside the region,
    else Newton on the secular equation (as MINPACK's ``lmpar``) until the
    scaled step is within 10 % of the radius.
    """
    lam = floor
    if _size(values, coef, lam) > region:
        for _ in range(30):
            size = _size(values, coef, lam)
            if abs(size - region) <= 0.1 * region:
                break
            slope = -np.sum(coef**2 / (values + lam) ** 3) / size
            lam = max(lam - (size - region) / region * size / slope, 0.5 * lam)
    p = -(vectors @ (coef / (values + lam)))
    return p / scale, lam > floor


@jit
def _norm(v):  # pragma: no cover - compiled
    return np.sqrt(v @ v)
