"""Running a model whose terms include regressors (:mod:`.regressors`).

The same runs as :mod:`.simulation` (k-step prediction, free-run, and the
free run's sensitivities) for a structure whose bases include regressors: at
each step the regressors are computed from the outputs and inputs before it
(the model's own outputs in a free run) by their postfix code, with their
derivatives with respect to the lagged outputs, so the sensitivity equations
stay exact. Models without regressors never come here (their kernels are
unchanged). The coupled model of several outputs computes its regressors with
:func:`regressors_at` in its own kernel (:mod:`.coupled`). Built ahead of time
with the other kernels.
"""

from __future__ import annotations

import numpy as np

from ..compiled.registry import jit_exact as jit
from .chain import chain_start, mark_diverged
from .regressors import OPS, Program, program

__all__ = ["coupled_program", "free_run_sensitivities_r", "regressors_at", "run_model_r"]


@jit
def regressors_at(code, consts, start, ys, u, t, sv, sg, ly, vals, first,
                   grad):  # pragma: no cover - compiled
    """Every regressor at t into ``vals[first + r]``, its gradient into ``grad[r]``.

    The gradient is over y(t-1..t-ly). A stack machine over ``code[start[r]:start[r + 1]]``,
    in one function: a compiled call per operation cost more than the operation.
    """
    for r in range(start.shape[0] - 1):
        top = -1
        for k in range(start[r], start[r + 1]):
            op = code[k, 0]
            if op <= 2:  # a lagged output (gradient 1 at its lag), a lagged input, a number
                top += 1
                for j in range(ly):
                    sg[top, j] = 0.0
                if op == 0:
                    sv[top] = ys[t - code[k, 1]]
                    sg[top, code[k, 1] - 1] = 1.0
                else:
                    sv[top] = u[t - code[k, 2], code[k, 1]] if op == 1 else consts[code[k, 1]]
            elif op >= 7 and op <= 10:  # neg, sign, abs, tanh; the chain rule
                x = sv[top]
                s = 1.0 if x > 0 else (-1.0 if x < 0 else 0.0)
                if op == 10:
                    v = np.tanh(x)
                    d = 1.0 - v * v
                else:
                    v, d = (-x, -1.0) if op == 7 else ((s, 0.0) if op == 8 else (abs(x), s))
                sv[top] = v
                for j in range(ly):
                    sg[top, j] = d * sg[top, j] if sg[top, j] != 0.0 else 0.0
            else:  # + - * / min max sat deadzone: the gradient dx g_x / div + dy g_y
                top -= 1
                x, y2, dx, dy, div = sv[top], sv[top + 1], 1.0, 0.0, 1.0
                v = x
                if op == 3 or op == 4:
                    dy, v = (1.0, x + y2) if op == 3 else (-1.0, x + -1.0 * y2)
                elif op == 5:
                    v, dx, dy = x * y2, y2, x
                elif op == 6:
                    v, div = x / y2, y2
                elif op == 11 or op == 12:
                    if (y2 < x) if op == 11 else (y2 > x):
                        v, dx, dy = y2, 0.0, 1.0
                elif op == 13:  # sat(x, lim)
                    lim = abs(y2)
                    if x > lim or x < -lim:
                        v, dx = (lim if x > lim else -lim), 0.0
                elif abs(x) <= y2:  # deadzone(x, w), inside
                    v, dx = 0.0, 0.0
                else:  # deadzone, outside
                    dy = -1.0 if x > 0 else 1.0
                    v = x + dy * y2
                sv[top] = v
                for j in range(ly):
                    sg[top, j] = dx * sg[top, j] / div + dy * sg[top + 1, j]
        vals[first + r] = sv[0]
        for j in range(ly):
            grad[r, j] = sg[0, j]


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
    regressors_at(code, consts, start, ys, u, t, sv, sg, ly, vals, n_y + n_u, grad)


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
def sens_kernel_r(gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly, theta, u, y,
                  lag0, lo, hi, out, jac):  # pragma: no cover - compiled
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
            return mark_diverged(out, t, lag0)
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
    return int(sens_kernel_r(*_args(model), np.ascontiguousarray(theta, dtype=float),
                       np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(y, dtype=float),
                       lag0, float(lo), float(hi), out, jac))


# -- several outputs: the coupled free run with regressors ----------------------------------

def coupled_program(regressors: list, column) -> Program:
    """Every output's regressors as one program over the coupled signal matrix.

    ``regressors[i]``: output i's regressors (a list of
    :class:`~.regressors.Expr`), its term space's output and inputs;
    ``column(i, src)``: the matrix column of output i's signal ``src`` (-1: its
    own output; else its term space's input index). ``start`` is (q, n_reg + 1):
    output i's regressor r is ``code[start[i, r]:start[i, r + 1]]`` (empty when
    it has fewer). Without any, ``start`` is (q, 1): no regressor is computed.
    """
    n_reg = max(len(exprs) for exprs, _, _ in regressors)
    code, consts, depth = [], [], 1
    start = np.zeros((len(regressors), n_reg + 1), dtype=np.int64)
    for i, (exprs, output, inputs) in enumerate(regressors):
        own = program(list(exprs), output, tuple(inputs))
        for op, a, b in own.code[:own.start[-1]]:
            if op == OPS["y"]:
                op, a, b = OPS["u"], column(i, -1), a
            elif op == OPS["u"]:
                a = column(i, a)
            elif op == OPS["num"]:
                a += len(consts)
            code.append((op, a, b))
        consts += list(own.consts) if own.start[-1] else []
        starts = len(code) - own.start[-1] + own.start
        start[i, :len(starts)] = starts
        start[i, len(starts):] = starts[-1]
        depth = max(depth, int(own.depth))
    return Program(np.array(code or [(0, 0, 0)], dtype=np.int64).reshape(-1, 3),
                   np.array(consts or [0.0]), start, depth)
