"""Running a model whose terms include regressors (:mod:`.regressors`).

The same runs as :mod:`.simulation` (k-step prediction, free-run, and the
free run's sensitivities) for a structure whose bases include regressors: at
each step the regressors are computed from the outputs and inputs before it
(the model's own outputs in a free run) by their postfix code, with their
derivatives with respect to the lagged outputs, so the sensitivity equations
stay exact. Models without regressors never come here (their kernels are
unchanged, and built ahead of time); these kernels run on numba's JIT.
"""

from __future__ import annotations

import numpy as np

from ..compiled.registry import jit_exact as jit
from .chain import chain_start, mark_diverged

__all__ = ["free_run_sensitivities_r", "run_model_r"]


@jit
def _eval(code, consts, a, b, ys, u, t, sv, sg, ly):  # pragma: no cover - compiled
    """Regressor ``code[a:b]`` at t: its value, its gradient over y(t-1..t-ly) in sg[0]."""
    top = -1
    for k in range(a, b):
        op = code[k, 0]
        if op <= 2:
            top += 1
            _push(code, consts, k, ys, u, t, sv, sg, top, ly)
        elif op <= 10 and op >= 7:
            _unary(op, sv, sg, top, ly)
        else:
            top -= 1
            _binary(op, sv, sg, top, ly)
    return sv[0]


@jit
def _push(code, consts, k, ys, u, t, sv, sg, top, ly):  # pragma: no cover - compiled
    """A lagged output (gradient 1 at its lag), a lagged input or a number."""
    op = code[k, 0]
    for j in range(ly):
        sg[top, j] = 0.0
    if op == 0:
        sv[top] = ys[t - code[k, 1]]
        sg[top, code[k, 1] - 1] = 1.0
    elif op == 1:
        sv[top] = u[t - code[k, 2], code[k, 1]]
    else:
        sv[top] = consts[code[k, 1]]


@jit
def _unary(op, sv, sg, top, ly):  # pragma: no cover - compiled
    """neg, sign, abs, tanh on the top of the stack (chain rule on its gradient)."""
    x = sv[top]
    if op == 7:
        sv[top], d = -x, -1.0
    elif op == 8:
        sv[top], d = (1.0 if x > 0 else (-1.0 if x < 0 else 0.0)), 0.0
    elif op == 9:
        sv[top], d = abs(x), (1.0 if x > 0 else (-1.0 if x < 0 else 0.0))
    else:
        sv[top] = np.tanh(x)
        d = 1.0 - sv[top] * sv[top]
    for j in range(ly):
        sg[top, j] = d * sg[top, j] if sg[top, j] != 0.0 else 0.0


@jit
def _binary(op, sv, sg, top, ly):  # pragma: no cover - compiled
    """+ - * / min max sat deadzone of ``sv[top]`` and ``sv[top + 1]`` into ``sv[top]``."""
    x, y2 = sv[top], sv[top + 1]
    if op == 3 or op == 4:
        s = 1.0 if op == 3 else -1.0
        sv[top] = x + s * y2 if op == 4 else x + y2
        for j in range(ly):
            sg[top, j] = sg[top, j] + s * sg[top + 1, j]
    elif op == 5:
        sv[top] = x * y2
        for j in range(ly):
            sg[top, j] = sg[top, j] * y2 + x * sg[top + 1, j]
    elif op == 6:
        sv[top] = x / y2
        for j in range(ly):
            sg[top, j] = sg[top, j] / y2
    elif op == 11 or op == 12:
        if (y2 < x) if op == 11 else (y2 > x):
            sv[top] = y2
            for j in range(ly):
                sg[top, j] = sg[top + 1, j]
    elif op == 13:  # sat(x, lim)
        lim = abs(y2)
        if x > lim or x < -lim:
            sv[top] = lim if x > lim else -lim
            for j in range(ly):
                sg[top, j] = 0.0
    elif abs(x) <= y2:  # deadzone(x, w), inside
        sv[top] = 0.0
        for j in range(ly):
            sg[top, j] = 0.0
    else:  # deadzone, outside
        s = 1.0 if x > 0 else -1.0
        sv[top] = x - s * y2
        for j in range(ly):
            sg[top, j] = sg[top, j] - s * sg[top + 1, j]


@jit
def _fill(y_lags, u_lags, u_cols, code, consts, start, ys, u, t, vals, grad, sv, sg,
          ly):  # pragma: no cover - compiled
    """The bases at t: lagged outputs, lagged inputs, regressors (and their gradients)."""
    n_y = y_lags.shape[0]
    n_u = u_lags.shape[0]
    for j in range(n_y):
        vals[j] = ys[t - y_lags[j]]
    for j in range(n_u):
        vals[n_y + j] = u[t - u_lags[j], u_cols[j]]
    for r in range(start.shape[0] - 1):
        g = n_y + n_u + r
        vals[g] = _eval(code, consts, start[r], start[r + 1], ys, u, t, sv, sg, ly)
        for j in range(ly):
            grad[r, j] = sg[0, j]


@jit
def _value(gather, theta, vals, phi):  # pragma: no cover - compiled
    acc = 0.0
    for i in range(gather.shape[0]):
        p = 1.0
        for q in range(gather.shape[1]):
            p *= vals[gather[i, q]]
        phi[i] = p
        acc += theta[i] * p
    return acc


@jit
def _run_r(gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly, theta, u, y,
           horizon, lag0, lo, hi, out):  # pragma: no cover - compiled
    """k-step-ahead predictions into ``out`` (rows t = lag0..n-1); the first diverged t or -1."""
    n = y.shape[0]
    n_reg = start.shape[0] - 1
    vals = np.ones(y_lags.shape[0] + u_lags.shape[0] + n_reg + 1)
    phi = np.empty(gather.shape[0])
    grad = np.zeros((max(n_reg, 1), ly))
    sv = np.empty(depth)
    sg = np.zeros((depth, ly))
    work = np.empty(n)
    free = horizon >= n - lag0
    for t in range(lag0, n):
        first = chain_start(work, y, t, horizon, lag0, free)
        for s in range(first, t + 1):
            _fill(y_lags, u_lags, u_cols, code, consts, start, work, u, s, vals, grad, sv, sg,
                  ly)
            work[s] = _value(gather, theta, vals, phi)
        v = work[t]
        if not (v >= lo and v <= hi):  # also NaN
            return mark_diverged(out, t, lag0)
        out[t - lag0] = v
    return -1


@jit
def _sens_r(gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly, theta, u, y, lag0,
            lo, hi, out, jac):  # pragma: no cover - compiled
    """Free-run output into ``out``, d out / d theta into ``jac``; the first diverged t or -1."""
    n = y.shape[0]
    n_y = y_lags.shape[0]
    n_u = u_lags.shape[0]
    n_reg = start.shape[0] - 1
    k = gather.shape[0]
    width = gather.shape[1]
    n_vals = n_y + n_u + n_reg + 1
    vals = np.ones(n_vals)
    phi = np.empty(k)
    grad = np.zeros((max(n_reg, 1), ly))
    sv = np.empty(depth)
    sg = np.zeros((depth, ly))
    ys = np.empty(n)
    S = np.zeros((n, k))
    dy = np.zeros(ly)    # d yhat(t) / d yhat(t - 1 - l)
    for s in range(lag0):
        ys[s] = y[s]
    for t in range(lag0, n):
        _fill(y_lags, u_lags, u_cols, code, consts, start, ys, u, t, vals, grad, sv, sg, ly)
        acc = _value(gather, theta, vals, phi)
        ys[t] = acc
        if not (acc >= lo and acc <= hi):
            for s in range(t, lag0 + out.shape[0]):
                out[s - lag0] = np.nan
            return t
        out[t - lag0] = acc
        for j in range(ly):
            dy[j] = 0.0
        for i in range(k):
            for q in range(width):
                g = gather[i, q]
                if g >= n_y and g < n_y + n_u or g == n_vals - 1:
                    continue
                p = theta[i]
                for r in range(width):
                    if r != q:
                        p *= vals[gather[i, r]]
                if g < n_y:
                    dy[y_lags[g] - 1] += p
                else:
                    for j in range(ly):
                        if grad[g - n_y - n_u, j] != 0.0:
                            dy[j] += p * grad[g - n_y - n_u, j]
        for i in range(k):
            acc = phi[i]
            for j in range(ly):
                if dy[j] != 0.0 and t - 1 - j >= 0:
                    acc += dy[j] * S[t - 1 - j, i]
            S[t, i] = acc
            jac[t - lag0, i] = acc
    return -1


def _args(model) -> tuple:
    p = model.program
    return (model.gather, model.y_lags, model.u_lags, model.u_cols, p.code, p.consts,
            p.start, int(p.depth), int(model.y_reach))


def run_model_r(model, theta: np.ndarray, u: np.ndarray, y: np.ndarray, h: int, lag0: int,
                lo: float, hi: float, out: np.ndarray) -> int:
    """:func:`~.simulation.run_model`'s loop for a model with regressors."""
    return int(_run_r(*_args(model), np.ascontiguousarray(theta, dtype=float),
                      np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(y, dtype=float),
                      h, lag0, float(lo), float(hi), out))


def free_run_sensitivities_r(model, theta: np.ndarray, u: np.ndarray, y: np.ndarray,
                             lag0: int, lo: float, hi: float, out: np.ndarray,
                             jac: np.ndarray) -> int:
    """:func:`~.simulation.free_run_sensitivities`' loop for a model with regressors."""
    return int(_sens_r(*_args(model), np.ascontiguousarray(theta, dtype=float),
                       np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(y, dtype=float),
                       lag0, float(lo), float(hi), out, jac))
