"""Running a polynomial NARX model: free-run, k-step-ahead, and parameter sensitivities.

A model's selected terms are products of lagged signals. Here each term is a row
of indices into the *linear* values at time t (``y(t-l)`` for the output lags,
then each input's lags; see :attr:`TermSpace.linear`), padded with an index
that points at a constant 1, so one compiled loop runs any structure:

* :func:`run_model` -- k-step-ahead prediction ``yhat(t | t-k)`` for every t:
  measured outputs up to ``t-k``, the model's own outputs after that
  (``k = 1`` is one-step prediction, ``k >= n`` free-run simulation from the
  first ``max_lag`` measured samples);
* :func:`free_run_sensitivities` -- the free-run output and its derivatives with
  respect to every coefficient (the sensitivity equations), for Gauss-Newton /
  Levenberg-Marquardt refinement on the simulation error.

Divergence: a run stops at the first output that is not finite or lies outside
``[lo, hi]`` (see :func:`divergence_bounds`: the measured output's range
widened by ``DIVERGENCE_FACTOR`` times its span on each side); that sample and
all later ones are NaN and the sample index is reported, never an infinite error.

The kernels are plain Python compiled by numba in Python's order of operations
(:func:`~spm_sysid.core.compiled.kernels.jit_exact`); without numba the same Python
runs and gives the same numbers (tests compare both bit for bit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..compiled.registry import jit_exact as jit
from .chain import chain_start, mark_diverged

__all__ = ["DIVERGENCE_FACTOR", "CompiledModel", "divergence_bounds",
           "free_run_sensitivities", "run_model"]

#: A simulated output further than this many spans of the measured output beyond its
#: range has diverged.
DIVERGENCE_FACTOR = 10.0


def divergence_bounds(y: np.ndarray) -> tuple[float, float]:
    """The range a simulation of ``y`` may not leave: its range widened by 10 spans."""
    y = np.asarray(y, dtype=float)
    finite = y[np.isfinite(y)]
    if finite.size == 0:
        return -np.inf, np.inf
    lo, hi = float(finite.min()), float(finite.max())
    span = max(hi - lo, abs(hi), abs(lo), 1e-300)
    return lo - DIVERGENCE_FACTOR * span, hi + DIVERGENCE_FACTOR * span


@dataclass(frozen=True)
class CompiledModel:
    """A structure in the kernels' form (built once per model and term space)."""

    gather: np.ndarray   # (k, width) int64: linear-value indices per term; n_lin = 1
    y_lags: np.ndarray   # (n_y,) int64
    u_lags: np.ndarray   # (n_u,) int64
    u_cols: np.ndarray   # (n_u,) int64: which input each input lag belongs to
    max_lag: int
    program: object = None  # the regressors' code (regressors.Program), None without
    y_reach: int = 0        # the largest output lag any base reads (with regressors)

    @classmethod
    def from_space(cls, term_space, term_indices) -> CompiledModel:
        """The kernel form of the terms ``term_indices`` of ``term_space``."""
        lin = term_space.linear
        all_terms = term_space.terms
        # the regressors the terms use, computed after the lagged signals (the others never)
        used = sorted({f for i in term_indices for f in all_terms[i] if f >= len(lin)})
        at = {f: len(lin) + k for k, f in enumerate(used)}
        program, reach = None, 0
        if used:
            from .regressors import program as compile_regressors

            exprs = [term_space.regressor_exprs[f - len(lin)] for f in used]
            program = compile_regressors(exprs, term_space.output, term_space.inputs)
            reach = max([term_space.ny] + [lag for e in exprs for name, lag in e.signals()
                                           if name == term_space.output])
        width = max([len(all_terms[i]) for i in term_indices] + [1])
        # the constant 1 after the values
        gather = np.full((len(term_indices), width), len(lin) + len(used), dtype=np.int64)
        for row, i in enumerate(term_indices):
            gather[row, : len(all_terms[i])] = [at.get(f, f) for f in all_terms[i]]
        return cls(
            gather=gather,
            y_lags=np.array([lag for src, lag in lin if src < 0], dtype=np.int64),
            u_lags=np.array([lag for src, lag in lin if src >= 0], dtype=np.int64),
            u_cols=np.array([src for src, lag in lin if src >= 0], dtype=np.int64),
            max_lag=term_space.max_lag, program=program, y_reach=reach,
        )


@jit
def _buffers(gather, y_lags, u_lags):  # pragma: no cover - compiled
    """Work arrays: the lagged values (and a trailing 1) and the term values."""
    return np.ones(y_lags.shape[0] + u_lags.shape[0] + 1), np.empty(gather.shape[0])


@jit
def _run(gather, y_lags, u_lags, u_cols, theta, u, y, horizon, lag0, lo, hi,
         out):  # pragma: no cover - compiled
    """Write k-step-ahead predictions into ``out`` (rows t = lag0..n-1).

    Returns the first diverged t, or -1. A step's arithmetic is written out
    here rather than called: a compiled call with arrays cost about a third of
    a step.
    """
    n = y.shape[0]
    n_y = y_lags.shape[0]
    vals, phi = _buffers(gather, y_lags, u_lags)
    work = np.empty(n)  # outputs seen by the chain: measured up to its origin
    free = horizon >= n - lag0
    for t in range(lag0, n):
        first = chain_start(work, y, t, horizon, lag0, free)
        for s in range(first, t + 1):  # the model's output at s from work and u before it
            for j in range(n_y):
                vals[j] = work[s - y_lags[j]]
            for j in range(u_lags.shape[0]):
                vals[n_y + j] = u[s - u_lags[j], u_cols[j]]
            acc = 0.0
            for i in range(gather.shape[0]):
                p = 1.0
                for q in range(gather.shape[1]):
                    p *= vals[gather[i, q]]
                acc += theta[i] * p
            work[s] = acc
        v = work[t]
        if not (v >= lo and v <= hi):  # also NaN
            return mark_diverged(out, t, lag0)
        out[t - lag0] = v
    return -1


def run_model(model: CompiledModel, theta: np.ndarray, u: np.ndarray, y: np.ndarray,
              horizon: int | None = None, bounds: tuple[float, float] | None = None
              ) -> tuple[np.ndarray, int | None]:
    """k-step-ahead prediction (``horizon`` k; None = free-run) of one record.

    Parameters
    ----------
    model : CompiledModel
        The structure.
    theta : ndarray, shape (k,)
        Its coefficients.
    u : ndarray, shape (n, n_inputs)
        The inputs.
    y : ndarray, shape (n,)
        Measured outputs: initial conditions, and the chain origins for k-step.
    horizon : int or None
        Steps ahead, >= 1; None (or >= n - max_lag) is free-run.
    bounds : (lo, hi), optional
        Divergence range (default :func:`divergence_bounds` of ``y``).

    Returns
    -------
    yhat : ndarray, shape (n - max_lag,)
        Rows t = max_lag..n-1; NaN from the divergence on.
    diverged_at : int or None
        Sample index t where the output left the range, or None.
    """
    n = len(y)
    lag0 = model.max_lag
    if horizon is not None and horizon < 1:
        raise ValueError(f"horizon must be >= 1 (or None for free-run), got {horizon}")
    h = n if horizon is None else int(horizon)
    lo, hi = divergence_bounds(y) if bounds is None else bounds
    out = np.empty(max(n - lag0, 0))
    if n <= lag0:
        return out, None
    if model.program is not None:
        from .regressor_sim import run_model_r

        at = run_model_r(model, theta, u, y, h, lag0, lo, hi, out)
        return out, (None if at < 0 else int(at))
    at = _run(model.gather, model.y_lags, model.u_lags, model.u_cols,
              np.ascontiguousarray(theta, dtype=float), np.ascontiguousarray(u, dtype=float),
              np.ascontiguousarray(y, dtype=float), h, lag0, float(lo), float(hi), out)
    return out, (None if at < 0 else int(at))


@jit
def _factors(gather, n_y, pad):  # pragma: no cover - compiled
    """Per term: its factors' count (the padding 1s left out), where its output lags are.

    Multiplying by the padding's 1.0 is exact, so a product over the factors
    alone is the same number; the sensitivity step then loops over what each
    term has, not over the widest term's width twice. ``pad``: the padding's
    index (a term's factors come first).
    """
    k, width = gather.shape
    count = np.zeros(k, dtype=np.int64)
    lags = np.zeros(k, dtype=np.int64)
    where = np.zeros((k, max(width, 1)), dtype=np.int64)
    for i in range(k):
        for q in range(width):
            g = gather[i, q]
            if g != pad:
                count[i] = q + 1
            if g < n_y:
                where[i, lags[i]] = q
                lags[i] += 1
    return count, lags, where


@jit
def sens_kernel(gather, y_lags, u_lags, u_cols, theta, u, y, lag0, lo, hi, out,
          jac):  # pragma: no cover - compiled
    """Write the free-run output into ``out`` and d out / d theta into ``jac``.

    Returns the first diverged t, or -1. The sensitivities of the outputs
    before ``lag0`` (measured, not simulated) are zero; later ones are read
    back from ``jac``.
    """
    n = y.shape[0]
    n_y = y_lags.shape[0]
    k = gather.shape[0]
    vals, phi = _buffers(gather, y_lags, u_lags)
    count, lags, where = _factors(gather, n_y, n_y + u_lags.shape[0])
    ys = np.empty(n)
    dy = np.zeros(n_y)    # d yhat(t) / d yhat(t - y_lags[j]) at the current t
    for s in range(lag0):
        ys[s] = y[s]
    for t in range(lag0, n):  # the output at t (as _run's step), its term values in phi
        for j in range(n_y):
            vals[j] = ys[t - y_lags[j]]
        for j in range(u_lags.shape[0]):
            vals[n_y + j] = u[t - u_lags[j], u_cols[j]]
        acc = 0.0
        for i in range(k):
            p = 1.0
            for q in range(count[i]):
                p *= vals[gather[i, q]]
            phi[i] = p
        for i in range(k):
            acc += theta[i] * phi[i]
        ys[t] = acc
        if not (acc >= lo and acc <= hi):
            return mark_diverged(out, t, lag0)
        out[t - lag0] = acc
        # d yhat(t) / d y(t - lag_j): each factor that is an output lag, times the others
        for j in range(n_y):
            dy[j] = 0.0
        for i in range(k):
            for f in range(lags[i]):
                q = where[i, f]
                p = theta[i]
                for r in range(count[i]):
                    if r != q:
                        p *= vals[gather[i, r]]
                dy[gather[i, q]] += p
        row = t - lag0
        for i in range(k):
            acc = phi[i]
            for j in range(n_y):
                src = row - y_lags[j]
                acc += dy[j] * (jac[src, i] if src >= 0 else 0.0)
            jac[row, i] = acc
    return -1


def free_run_sensitivities(model: CompiledModel, theta: np.ndarray, u: np.ndarray,
                           y: np.ndarray, bounds: tuple[float, float] | None = None
                           ) -> tuple[np.ndarray, np.ndarray, int | None]:
    """Free-run output of one record and its Jacobian with respect to ``theta``.

    Returns
    -------
    yhat : ndarray, shape (n - max_lag,)
    jacobian : ndarray, shape (n - max_lag, k)
        ``d yhat(t) / d theta_i``, from the sensitivity equations (exact up to rounding).
    diverged_at : int or None
    """
    n = len(y)
    lag0 = model.max_lag
    lo, hi = divergence_bounds(y) if bounds is None else bounds
    rows = max(n - lag0, 0)
    out = np.empty(rows)
    jac = np.zeros((rows, model.gather.shape[0]))
    if rows == 0:
        return out, jac, None
    if model.program is not None:
        from .regressor_sim import free_run_sensitivities_r

        at = free_run_sensitivities_r(model, theta, u, y, lag0, lo, hi, out, jac)
        return out, jac, (None if at < 0 else int(at))
    at = sens_kernel(model.gather, model.y_lags, model.u_lags, model.u_cols,
                     np.ascontiguousarray(theta, dtype=float),
                     np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(y, dtype=float),
                     lag0, float(lo), float(hi), out, jac)
    return out, jac, (None if at < 0 else int(at))
