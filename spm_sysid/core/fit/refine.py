"""Refining a model's coefficients on its free-run simulation error.

Least squares minimises the one-step prediction error; a model used as a
simulator should minimise the error of its own fed-back outputs,

    min_theta  sum_t ( y(t) - ysim(t; theta) )^2 ,

over every estimation segment (each simulated from its own initial
conditions). This is a nonlinear least-squares problem; it is solved by
Levenberg-Marquardt (:func:`~spm_sysid.core.fit.levenberg.levenberg_marquardt`)
started from the least-squares coefficients, with the exact Jacobian from the
sensitivity equations (:func:`~spm_sysid.core.model.simulation.free_run_sensitivities`).

Stability: a step that would make the model's linear part unstable (a pole
of its output-lag polynomial on or outside the unit circle, see
:func:`linear_radius`) is rejected when the least-squares model's is stable --
a model can fit the estimation record well while growing slowly, and then fail
on any other record. A refinement that ends unstable (possible only from an
unstable least-squares start) fails, so simulation-focused selection never
returns a model whose linear part is unstable. On the estimation data, a
simulation that leaves the measured range
(see :mod:`~spm_sysid.core.model.simulation`) costs as if every later output sat
on the range's edge, with no gradient, so a step into divergence is always
rejected; a result that still diverges is never returned (the start is kept,
and when that diverges too, the refinement fails and says so).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.narx import NarxModel
from ..model.segments import rows_segments
from ..model.simulation import divergence_bounds, free_run_sensitivities
from ..model.uncertainty import Uncertainty, from_jacobian
from .levenberg import levenberg_marquardt

__all__ = ["Refinement", "free_run_uncertainty", "linear_radius", "linear_stability_check",
           "refine_simulation"]


def linear_radius(term_space, term_indices, theta) -> float:
    """Spectral radius of the model's linear output part (its poles about zero).

    The terms ``y(t-l)`` alone (products left out) give the characteristic
    polynomial ``z^n - sum_l a_l z^(n-l)``; the largest root modulus below 1
    means the linearised model forgets its initial conditions. 0 without
    output lags.
    """
    lin = term_space.linear
    all_terms = term_space.terms
    a = np.zeros(term_space.ny + 1)
    a[0] = 1.0
    for i, c in zip(term_indices, theta):
        t = all_terms[i]
        if len(t) == 1 and term_space.is_output_lag(t[0]):
            a[lin[t[0]][1]] -= c
    if not np.any(a[1:]):
        return 0.0
    return float(np.max(np.abs(np.roots(np.trim_zeros(a, "b")))))


def linear_stability_check(term_space, term_indices):
    """A fast test of :func:`linear_radius` < 1 for coefficient vectors of one structure.

    Returns ``stable(theta) -> bool``: the characteristic polynomial's roots all
    lie inside the unit circle, decided by the Schur-Cohn step-down recursion
    (reflection coefficients of modulus below 1) instead of computing the roots:
    a few microseconds, called at every step of a refinement.
    """
    lin = term_space.linear
    all_terms = term_space.terms
    part = [(pos, lin[all_terms[i][0]][1]) for pos, i in enumerate(term_indices)
            if len(all_terms[i]) == 1 and term_space.is_output_lag(all_terms[i][0])]
    ny = term_space.ny

    def stable(theta) -> bool:
        if not part:
            return True
        a = [0.0] * (ny + 1)
        a[0] = 1.0
        for pos, lag in part:
            a[lag] -= float(theta[pos])
        while len(a) > 1 and a[-1] == 0.0:
            a.pop()
        while len(a) > 1:
            k = a[-1] / a[0]
            if not abs(k) < 1.0:
                return False
            scale = 1.0 - k * k
            n = len(a) - 1
            a = [(a[j] - k * a[n - j]) / scale for j in range(n)]
        return True

    return stable


@dataclass(frozen=True)
class Refinement:
    """Outcome of :func:`refine_simulation` (SSE in the user's units, estimation rows)."""

    coefficients: np.ndarray
    sse: float
    sse_start: float
    diverged_start: int | None
    evaluations: int
    success: bool
    message: str


def _segments(y: np.ndarray, segments, lag0: int) -> list[tuple[int, int]]:
    return rows_segments(segments, len(y), lag0)


#: Growth of the free run's sensitivities along a segment (largest over the
#: segment / largest over its first half) beyond which its linearisation is
#: unstable: a bounded model grows them by far less (an integrator by about the
#: record's length), one whose linearisation diverges by e^(rate * samples).
SENSITIVITY_GROWTH = 1e6


def free_run_uncertainty(model: NarxModel, u: np.ndarray, y: np.ndarray,
                         segments: list[tuple[int, int]] | None = None
                         ) -> tuple[Uncertainty | None, str]:
    """The coefficients' covariance for the free-run problem (Gauss-Newton), or None and why.

    None when the simulation diverges on u, y, or when its sensitivities grow
    without bound along the record (the free run stays in range but its
    linearisation does not: a Gauss-Newton covariance would then claim standard
    errors of about zero), or when the Jacobian is singular. See
    :mod:`spm_sysid.core.model.uncertainty`.
    """
    ts = model.term_space
    u = ts.inputs_2d(u)
    y = np.asarray(y, dtype=float)
    bounds = divergence_bounds(y)
    jacs, sse = [], 0.0
    for a, b in _segments(y, segments, ts.max_lag):
        yhat, jac, at = free_run_sensitivities(model.compiled, model.coefficients, u[a:b],
                                               y[a:b], bounds)
        if at is not None:
            return None, f"the free run leaves the measured range at sample {a + at}"
        if _grows(jac):
            return None, ("the free run's sensitivities to the coefficients grow without "
                          "bound along the record (its linearisation is unstable), so a "
                          "local covariance would claim a certainty the model does not have")
        e = y[a + ts.max_lag:b] - yhat
        sse += float(e @ e)
        jacs.append(jac)
    J = np.vstack(jacs)
    if J.shape[0] <= J.shape[1]:
        return None, "too few rows for the coefficients"
    found = from_jacobian(J, sse)
    se = found.standard_errors
    if not np.all(np.isfinite(se) & (se > 0)):
        return None, "the free-run Jacobian is singular (terms the free run cannot tell apart)"
    return found, ""


def _grows(jac: np.ndarray) -> bool:
    """Whether the sensitivities grow by more than :data:`SENSITIVITY_GROWTH` along the rows."""
    if len(jac) < 4:
        return False
    with np.errstate(invalid="ignore"):
        whole = float(np.max(np.abs(jac)))
        head = float(np.max(np.abs(jac[:len(jac) // 2])))
    return not np.isfinite(whole) or (head > 0 and whole > SENSITIVITY_GROWTH * head)


def refine_simulation(model: NarxModel, u: np.ndarray, y: np.ndarray,
                      segments: list[tuple[int, int]] | None = None,
                      max_evaluations: int = 200) -> Refinement:
    """Coefficients of ``model``'s structure that minimise the free-run error on u, y.

    Parameters
    ----------
    model : NarxModel
        The structure and the starting coefficients (least squares).
    u, y : ndarray
        The estimation record(s).
    segments : list of (start, stop), optional
        Contiguous parts, each simulated from its own initial conditions (as for
        :func:`~spm_sysid.core.fit.problem.fit_structure`); None is the whole record.
    max_evaluations : int
        Most simulations (with Jacobian) Levenberg-Marquardt may run.
    """
    ts = model.term_space
    theta0 = np.asarray(model.coefficients, dtype=float)
    simulate = _FreeRunResiduals(model, u, y, segments,
                                 guard=linear_radius(ts, model.term_indices, theta0) < 1.0)
    r0, _, div0 = simulate(theta0)
    sse0 = float(r0 @ r0) if div0 is None else float("inf")
    if len(simulate.measured) <= len(theta0):
        return Refinement(theta0, sse0, sse0, div0, 1, div0 is None,
                          "too few rows to refine; least squares kept")
    try:
        sol = levenberg_marquardt(lambda t: simulate(t)[:2], theta0, max_evaluations)
        theta, nfev, msg = sol.x, sol.nfev, sol.message
    except (ValueError, FloatingPointError) as exc:  # pragma: no cover - numerical failure
        theta, nfev, msg = theta0, 1, f"refinement failed ({exc}); least squares kept"
    r, _, div = simulate(theta)
    sse = float(r @ r) if div is None else float("inf")
    radius = linear_radius(ts, model.term_indices, theta)
    if radius >= 1.0 and div is None:
        return Refinement(theta, float("inf"), sse0, div0, nfev, False,
                          f"the refined model's linear part is unstable (pole radius "
                          f"{radius:.4f}): it may fit this record and fail on any other")
    if div is not None or not sse < sse0:
        if div0 is None:
            return Refinement(theta0, sse0, sse0, div0, nfev, True,
                              "the least-squares coefficients simulate best; kept")
        return Refinement(theta0, float("inf"), sse0, div0, nfev, False,
                          f"the simulation diverges at sample {div0} and refinement did not "
                          "find stable coefficients")
    return Refinement(theta, sse, sse0, div0, nfev, True, msg)


class _FreeRunResiduals:
    """Free-run residuals and their Jacobian at theta, over every segment (the last cached).

    ``guard``: a stable start stays stable; coefficients whose linear part is
    unstable cost as much as a divergence at the first sample. Beyond a
    divergence the simulation holds the range's nearest edge, with no gradient.
    Returns ``(residuals, jacobian, first sample diverged or None)``.
    """

    def __init__(self, model: NarxModel, u: np.ndarray, y: np.ndarray,
                 segments: list[tuple[int, int]] | None, guard: bool) -> None:
        ts = model.term_space
        self.compiled = model.compiled
        self.u = ts.inputs_2d(u)
        self.y = np.asarray(y, dtype=float)
        self.lag0 = ts.max_lag
        self.segs = _segments(self.y, segments, self.lag0)
        self.bounds = divergence_bounds(self.y)
        self.measured = np.concatenate([self.y[a + self.lag0:b] for a, b in self.segs])
        self.guard = guard
        self.stable = linear_stability_check(ts, model.term_indices)
        self.cache: dict[bytes, tuple[np.ndarray, np.ndarray, int | None]] = {}

    def __call__(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, int | None]:
        key = theta.tobytes()
        if key not in self.cache:
            self.cache.clear()  # least_squares asks for fun, then jac, of the same theta
            self.cache[key] = self._evaluate(theta)
        return self.cache[key]

    def _evaluate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, int | None]:
        measured, bounds, lag0 = self.measured, self.bounds, self.lag0
        if self.guard and not self.stable(theta):
            r = measured - np.where(measured >= 0.5 * (bounds[0] + bounds[1]),
                                    bounds[0], bounds[1])
            return r, np.zeros((len(measured), len(theta))), self.segs[0][0] + lag0
        outs, jacs, first = [], [], None
        for a, b in self.segs:
            yhat, jac, at = free_run_sensitivities(self.compiled, theta, self.u[a:b],
                                                   self.y[a:b], bounds)
            if at is not None:
                if first is None:
                    first = a + at
                bad = ~np.isfinite(yhat)
                last = yhat[~bad][-1] if (~bad).any() else self.y[a + lag0 - 1]
                yhat[bad] = bounds[1] if last >= 0.5 * (bounds[0] + bounds[1]) else bounds[0]
                jac[bad] = 0.0
            outs.append(yhat)
            jacs.append(jac)
        return measured - np.concatenate(outs), -np.vstack(jacs), first
