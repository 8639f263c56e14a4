"""Refining a model's coefficients on its free-run simulation error.

Least squares minimises the one-step prediction error; a model used as a
simulator should minimise the error of its own fed-back outputs,

    min_theta  sum_t ( y(t) - ysim(t; theta) )^2 ,

over every estimation segment (each simulated from its own initial
conditions). This is a nonlinear least-squares problem; it is solved by
Levenberg-Marquardt (:func:`~spm_sysid.core.fit.levenberg.refine_free_run`, compiled)
started from the least-squares coefficients, with the exact Jacobian from the
sensitivity equations (:func:`~spm_sysid.core.model.simulation.free_run_sensitivities`).

Stability: a step that would make the model's linear part unstable (a pole
of its output-lag polynomial on or outside the unit circle, see
:func:`linear_radius`) is rejected when the least-squares model's is stable --
a model can fit the estimation record well while growing slowly, and then fail
on any other record. A refinement that ends unstable or diverging from an
unstable least-squares start gets a second start when every pole outside the
circle is real and positive (an integrator's, which least squares puts a
little beyond 1 on a drive sampled fast): the poles scaled inside
(:func:`stabilised_start`), every step guarded. One that still ends unstable
fails, so simulation-focused selection never returns a model whose linear
part is unstable. On the estimation data, a
simulation that leaves the measured range
(see :mod:`~spm_sysid.core.model.simulation`) costs as if every later output sat
on the range's edge, with no gradient, so a step into divergence is always
rejected; a result that still diverges is never returned (the start is kept,
and when that diverges too, the refinement fails and says so).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import REAL_ANGLE, STABLE_START_RADIUS
from ..model.narx import NarxModel
from ..model.uncertainty import Uncertainty, from_jacobian
from .free_run import FreeRun, _output_lags, _stable
from .levenberg import evaluate_free_run, refine_free_run

__all__ = ["Refinement", "free_run_uncertainty", "linear_poles", "linear_radius",
           "linear_stability_check", "refine_simulation", "stabilised_start"]


def linear_poles(term_space, term_indices, theta) -> np.ndarray:
    """The poles of the model's linear output part (empty without output lags).

    The terms ``y(t-l)`` alone (products left out) give the characteristic
    polynomial ``z^n - sum_l a_l z^(n-l)``; its roots.
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
        return np.zeros(0, dtype=complex)
    return np.roots(np.trim_zeros(a, "b")).astype(complex)


def linear_radius(term_space, term_indices, theta) -> float:
    """Spectral radius of the model's linear output part (its poles about zero).

    Below 1, the linearised model forgets its initial conditions. 0 without
    output lags (:func:`linear_poles`).
    """
    poles = linear_poles(term_space, term_indices, theta)
    return float(np.max(np.abs(poles))) if poles.size else 0.0


def linear_stability_check(term_space, term_indices):
    """A fast test of :func:`linear_radius` < 1 for coefficient vectors of one structure.

    Returns ``stable(theta) -> bool``: the characteristic polynomial's roots all
    lie inside the unit circle, decided by the Schur-Cohn step-down recursion
    (reflection coefficients of modulus below 1) instead of computing the roots:
    the compiled test every step of a refinement runs (:mod:`.free_run`).
    """
    pos, lags = _output_lags(term_space, term_indices)
    ny = int(term_space.ny)
    return lambda theta: bool(_stable(np.ascontiguousarray(theta, dtype=float), pos, lags, ny))


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


#: Growth of the free run's sensitivities along a segment (largest over the
#: segment / largest over its first half) beyond which its linearisation is
#: unstable: a bounded model grows them by far less (an integrator by about the
#: record's length), one whose linearisation diverges by e^(rate * samples).
SENSITIVITY_GROWTH = 1e6


def free_run_uncertainty(model: NarxModel, u: np.ndarray, y: np.ndarray,
                         segments: list[tuple[int, int]] | None = None,
                         rows: int | None = None) -> tuple[Uncertainty | None, str]:
    """The coefficients' covariance for the free-run problem (Gauss-Newton), or None and why.

    None when the simulation diverges on u, y, or when its sensitivities grow
    without bound along the record (the free run stays in range but its
    linearisation does not: a Gauss-Newton covariance would then claim standard
    errors of about zero), or when the Jacobian is singular. See
    :mod:`spm_sysid.core.model.uncertainty`.

    ``rows``: the estimation rows the covariance stands for when ``segments`` are
    windows of a long record (a Jacobian of every row would be hundreds of MB):
    ``J'J`` of the windows' rows, times ``rows`` over their count, estimates the
    whole record's (each row adds its own term), so the covariance is the
    windows' times their share; ``dof`` is ``rows`` less the coefficients.
    """
    run = FreeRun(model, u, y, segments, guard=False)
    r, J, at = evaluate_free_run(run, model.coefficients)
    if at is not None:
        return None, f"the free run leaves the measured range at sample {at}"
    ends = np.cumsum([b - a - model.term_space.max_lag for a, b in run.segs])
    if any(_grows(part) for part in np.split(J, ends[:-1])):
        return None, ("the free run's sensitivities to the coefficients grow without "
                      "bound along the record (its linearisation is unstable), so a "
                      "local covariance would claim a certainty the model does not have")
    if J.shape[0] <= J.shape[1]:
        return None, "too few rows for the coefficients"
    found = from_jacobian(J, float(r @ r)).standing_for(J.shape[0], rows)
    se = found.standard_errors
    if not np.all(np.isfinite(se) & (se > 0)):
        return None, "the free-run Jacobian is singular (terms the free run cannot tell apart)"
    return found, ""


def _grows(jac: np.ndarray) -> bool:
    """Whether the sensitivities grow by more than :data:`SENSITIVITY_GROWTH` along the rows."""
    if len(jac) < 4:
        return False
    whole, head = _largest_size(jac), _largest_size(jac[:len(jac) // 2])
    return not np.isfinite(whole) or (head > 0 and whole > SENSITIVITY_GROWTH * head)


def _largest_size(values: np.ndarray) -> float:
    """``max |values|`` (NaN if any is NaN) without the copy ``np.abs`` would make.

    A long record's free-run Jacobian is hundreds of MB (10^6 rows x 60 terms: 480
    MB); its absolute values were a second one at the job's peak.
    """
    top, bottom = float(values.max()), float(values.min())
    if np.isnan(top) or np.isnan(bottom):
        return float("nan")
    return max(top, -bottom)


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
    stable = linear_stability_check(ts, model.term_indices)
    run = FreeRun(model, u, y, segments, guard=stable(theta0))
    if len(run.measured) <= len(theta0):
        return _kept(run, theta0, "too few rows to refine; least squares kept")
    try:
        sol = refine_free_run(run, theta0, max_evaluations)
    except (ValueError, FloatingPointError) as exc:  # pragma: no cover - numerical failure
        return _kept(run, theta0, f"refinement failed ({exc}); least squares kept")
    theta, nfev, msg = sol.x, sol.nfev, sol.message
    sse0, div0, sse, div = sol.sse_start, sol.diverged_start, sol.sse, sol.diverged
    if div is None and not stable(theta):
        radius = linear_radius(ts, model.term_indices, theta)
        return _stabilised(model, u, y, segments, max_evaluations, sse0, div0, stable) or (
            Refinement(theta, float("inf"), sse0, div0, nfev, False,
                       f"the refined model's linear part is unstable (pole radius "
                       f"{radius:.4f}): it may fit this record and fail on any other"))
    if div is not None or not sse < sse0:
        if div0 is None:
            return Refinement(theta0, sse0, sse0, div0, nfev, True,
                              "the least-squares coefficients simulate best; kept")
        return _stabilised(model, u, y, segments, max_evaluations, sse0, div0, stable) or (
            Refinement(theta0, float("inf"), sse0, div0, nfev, False,
                       f"the simulation diverges at sample {div0} and refinement did not "
                       "find stable coefficients"))
    return Refinement(theta, sse, sse0, div0, nfev, True, msg)


def stabilised_start(term_space, term_indices, theta: np.ndarray,
                     radius: float = STABLE_START_RADIUS) -> np.ndarray | None:
    """``theta`` with an integrator's pole scaled inside ``radius`` (None: no such pole).

    Least squares puts the integrator of a drive sampled fast a little beyond 1
    (1.0004-1.005 at 1 kHz), and a refinement from there may end beyond 1 too.
    When every pole outside the unit circle is real and positive (angle below
    :data:`~spm_sysid.core.defaults.REAL_ANGLE`: an integrator's, not a
    resonance's), each ``y(t-l)`` coefficient times ``r**l`` multiplies every
    pole by r, so that the largest lies at ``radius``: the structure keeps its
    lags and only the poles move. Started there, under the stability guard, a
    refinement keeps the integrator inside (or on) the circle. None when the
    poles are inside, or when one outside is complex or negative.
    """
    poles = linear_poles(term_space, term_indices, theta)
    outside = poles[np.abs(poles) >= 1.0]
    if not outside.size or np.any(np.abs(np.angle(outside)) >= REAL_ANGLE):
        return None
    pos, lags = _output_lags(term_space, term_indices)
    out = np.array(theta, dtype=float)
    out[pos] *= (radius / float(np.max(np.abs(outside)))) ** lags.astype(float)
    return out


def _stabilised(model: NarxModel, u, y, segments, max_evaluations: int, sse0: float,
                div0: int | None, stable) -> Refinement | None:
    """The refinement from :func:`stabilised_start`, guarded; None when it finds nothing.

    The second chance of a structure whose least-squares fit is unstable and whose
    refinement from there ended unstable or diverging (an integrating output's);
    ``stable``: the structure's :func:`linear_stability_check`.
    """
    ts = model.term_space
    start = stabilised_start(ts, model.term_indices, model.coefficients)
    if start is None:
        return None
    run = FreeRun(model, u, y, segments, guard=True)
    try:
        sol = refine_free_run(run, start, max_evaluations)
    except (ValueError, FloatingPointError):  # pragma: no cover - numerical failure
        return None
    if sol.diverged is not None or not np.isfinite(sol.sse) or not stable(sol.x):
        return None
    return Refinement(sol.x, sol.sse, sse0, div0, sol.nfev, True,
                      f"{sol.message} (from the least-squares fit with its poles scaled inside "
                      f"the unit circle: its linear part was unstable)")


def _kept(run: FreeRun, theta0: np.ndarray, why: str) -> Refinement:
    """The start kept without a refinement (a success when its free run stays in range)."""
    r0, _, div0 = evaluate_free_run(run, theta0)
    sse0 = float(r0 @ r0) if div0 is None else float("inf")
    return Refinement(theta0, sse0, sse0, div0, 1, div0 is None, why)
