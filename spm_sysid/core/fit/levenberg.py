"""Levenberg-Marquardt for the free-run refinements: small problems, many of them.

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

On the structures a simulation focus screens (robot arm, dryer, heat
exchanger) it takes the evaluations MINPACK takes and ends at the same sum of
squares on most of them; the selections they make are the same.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["Solution", "levenberg_marquardt"]

#: MINPACK's (and scipy's) default tolerances.
TOLERANCE = 1e-8

#: Largest Jacobian entry whose square, summed over 10^5 rows, stays a float:
#: a point whose sensitivities are larger (a free run whose linearisation grows
#: without bound) gives no quadratic model, so it is never a step.
JACOBIAN_LIMIT = 1e150


@dataclass(frozen=True)
class Solution:
    """The solver's end: coefficients, evaluations run, and why it stopped."""

    x: np.ndarray
    nfev: int
    message: str


def levenberg_marquardt(evaluate: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                        x0: np.ndarray, max_evaluations: int, tol: float = TOLERANCE
                        ) -> Solution:
    """Minimise ``|r(x)|^2`` from ``x0`` in at most ``max_evaluations`` evaluations.

    Parameters
    ----------
    evaluate : callable
        ``x -> (r, J)``: residuals (m,) and their Jacobian (m, k); a non-finite
        sum of squares rejects the step.
    x0 : ndarray, shape (k,)
        The start (least squares' coefficients, for a refinement).
    max_evaluations : int
        Evaluations at most, the first (at ``x0``) included.
    tol : float
        ``ftol``, ``xtol`` and ``gtol`` (as scipy's ``least_squares``).
    """
    x = np.array(x0, dtype=float)
    r, jac = evaluate(x)
    f = _cost(r, jac)
    if not np.isfinite(f):
        return Solution(x, 1, "the start's residuals are not finite, or its sensitivities are "
                              "out of floating-point range")
    scale = np.zeros(len(x))
    region, nfev = None, 1
    while True:
        a, g = jac.T @ jac, jac.T @ r
        norms = np.sqrt(a.diagonal())
        scale = np.maximum(scale, norms)
        scale[scale == 0] = 1.0
        if f == 0.0 or np.max(np.abs(g) / np.where(norms > 0, norms, 1.0)) <= tol * np.sqrt(f):
            return Solution(x, nfev, "`gtol` termination condition is satisfied.")
        model = _ScaledModel(a, g, scale)
        while True:
            if nfev >= max_evaluations:
                return Solution(x, nfev, "The maximum number of function evaluations is "
                                         "exceeded.")
            if region is None:
                step, damped, region = model.first_step(_norm(scale * x))
            else:
                step, damped = model.step(region)
            size = _norm(scale * step)
            r_new, jac_new = evaluate(x + step)
            nfev += 1
            f_new = _cost(r_new, jac_new)
            predicted = -float(2.0 * step @ g + step @ (a @ step))
            actual = f - f_new if np.isfinite(f_new) else -np.inf
            rho = actual / predicted if predicted > 0 else -np.inf
            region = _new_region(region, size, rho, actual, float(step @ g), f, f_new, damped)
            accepted = rho >= 1e-4
            if accepted:
                x, r, jac, f_old, f = x + step, r_new, jac_new, f, f_new
            else:
                f_old = f
            if abs(actual) <= tol * f_old and predicted <= tol * f_old and rho <= 2.0:
                return Solution(x, nfev, "`ftol` termination condition is satisfied.")
            if region <= tol * _norm(scale * x):
                return Solution(x, nfev, "`xtol` termination condition is satisfied.")
            if accepted:
                break


def _cost(r: np.ndarray, jac: np.ndarray) -> float:
    """The sum of squares, infinite where ``J'J`` would overflow (see :data:`JACOBIAN_LIMIT`)."""
    bounded = jac.size == 0 or np.max(np.abs(jac)) < JACOBIAN_LIMIT
    return float(r @ r) if bounded else np.inf


def _new_region(region: float, size: float, rho: float, actual: float, slope: float,
                f: float, f_new: float, damped: bool) -> float:
    """MINPACK's update of the trust region's radius after a step of scaled ``size``.

    ``slope``: the sum of squares' derivative along the step, halved (``p'J'r``).
    """
    if rho <= 0.25:
        if actual >= 0:
            shrink = 0.5
        else:  # the sum of squares rose: where a quadratic along the step is least
            shrink = 0.5 * slope / (slope + 0.5 * actual) if np.isfinite(actual) else 0.0
        if not f_new <= 100.0 * f or shrink < 0.1:
            shrink = 0.1
        return shrink * min(region, 10.0 * size)
    if rho >= 0.75 or not damped:
        return 2.0 * size
    return region


class _ScaledModel:
    """The quadratic model ``|r + J p|^2`` in scaled steps, solved on a trust region.

    With ``A = J'J`` and the column scales ``D``: ``p(lam) = -(A + lam D^2)^-1 g``,
    and ``lam`` the one (Newton on the secular equation, as MINPACK's ``lmpar``)
    that puts ``|D p|`` within 10 % of the region's radius, or 0 when the
    Gauss-Newton step lies inside it. One eigendecomposition of the scaled
    ``D^-1 A D^-1`` serves every radius.
    """

    def __init__(self, a: np.ndarray, g: np.ndarray, scale: np.ndarray) -> None:
        values, vectors = np.linalg.eigh(a / np.outer(scale, scale))
        self.values = np.maximum(values, 0.0)
        self.vectors, self.scale = vectors, scale
        self.coef = vectors.T @ (g / scale)  # the scaled gradient in the eigenbasis
        self.floor = 1e-12 * max(float(self.values[-1]), 1e-300)

    def _size(self, lam: float) -> float:
        return float(np.sqrt(np.sum((self.coef / (self.values + lam)) ** 2)))

    def first_step(self, size: float) -> tuple[np.ndarray, bool, float]:
        """MINPACK's first region (100x the scaled start ``size``, or the step), its step."""
        first = 100.0 * (size or 1.0)
        step, damped = self.step(first)
        region = min(first, _norm(self.scale * step))
        if damped and region < first:  # solved again on the smaller region
            step, damped = self.step(region)
        return step, damped, region

    def step(self, region: float) -> tuple[np.ndarray, bool]:
        """The step in the coefficients' units, and whether it was damped (lam > 0)."""
        lam = self.floor
        if self._size(lam) > region:
            for _ in range(30):
                size = self._size(lam)
                if abs(size - region) <= 0.1 * region:
                    break
                slope = -float(np.sum(self.coef**2 / (self.values + lam) ** 3)) / size
                lam = max(lam - (size - region) / region * size / slope, 0.5 * lam)
        p = -(self.vectors @ (self.coef / (self.values + lam)))
        return p / self.scale, lam > self.floor


def _norm(v: np.ndarray) -> float:
    return float(np.sqrt(v @ v))
