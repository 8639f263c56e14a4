"""The free-run residuals of a structure and their Jacobian, and their refinement, compiled.

:class:`FreeRun` holds a structure, a record and its segments in the kernels'
form. The kernel :func:`residuals` gives the residuals ``y - ysim(theta)`` over
every segment (each simulated from its own initial conditions) and their
Jacobian; Levenberg-Marquardt
(:func:`~spm_sysid.core.fit.levenberg.refine_free_run`) calls it at each of
its steps without returning to Python, and
:func:`~spm_sysid.core.fit.levenberg.evaluate_free_run` once.

Rules of the evaluation (see :mod:`~spm_sysid.core.fit.refine`):

* **guard**: when set, coefficients whose linear part is unstable (the
  Schur-Cohn test of the output-lag polynomial) cost as much as a divergence
  at the first sample: every output on the range's edge farthest from the
  measured one, no gradient;
* beyond a divergence the simulation holds the range's edge nearest its last
  value, with no gradient.

Models with regressors run their own simulation kernel
(:mod:`~spm_sysid.core.model.regressor_sim`); the rest is shared.
"""

from __future__ import annotations

import numpy as np

from ..compiled.registry import jit_exact as jit
from ..model.regressor_sim import sens_kernel_r
from ..model.segments import rows_segments
from ..model.simulation import divergence_bounds, sens_kernel

__all__ = ["FreeRun", "residuals"]

_NO_CODE = np.zeros((0, 3), dtype=np.int64)
_NO_CONSTS = np.zeros(0)
_NO_START = np.zeros(1, dtype=np.int64)


class FreeRun:
    """A structure's free-run residuals on a record's segments, in the kernels' form.

    Parameters
    ----------
    model : NarxModel
        The structure (its compiled form and term space).
    u, y : ndarray
        The record.
    segments : list of (start, stop) or None
        Contiguous parts, each simulated from its own start; None: the whole record.
    guard : bool
        Whether unstable linear parts cost a divergence (see the module).
    """

    def __init__(self, model, u: np.ndarray, y: np.ndarray, segments, guard: bool) -> None:
        ts = model.term_space
        compiled = model.compiled
        y = np.ascontiguousarray(y, dtype=float)
        lag0 = ts.max_lag
        self.segs = list(rows_segments(segments, len(y), lag0))
        self.measured = np.concatenate([y[a + lag0:b] for a, b in self.segs])
        self.k = len(model.term_indices)
        p = compiled.program
        program = ((p.code, p.consts, p.start, int(p.depth), int(compiled.y_reach))
                   if p is not None else (_NO_CODE, _NO_CONSTS, _NO_START, 1, 0))
        part_pos, part_lag = _output_lags(ts, model.term_indices)
        lo, hi = divergence_bounds(y)
        self.args = (compiled.gather, compiled.y_lags, compiled.u_lags, compiled.u_cols,
                     *program, np.ascontiguousarray(ts.inputs_2d(u), dtype=float), y,
                     np.array([a for a, _ in self.segs], dtype=np.int64),
                     np.array([b for _, b in self.segs], dtype=np.int64), int(lag0),
                     float(lo), float(hi), bool(guard), part_pos, part_lag, int(ts.ny),
                     self.measured)


def _output_lags(term_space, term_indices) -> tuple[np.ndarray, np.ndarray]:
    """The positions of the terms ``y(t-l)`` alone in the structure, and their lags l."""
    lin, all_terms = term_space.linear, term_space.terms
    pos = [p for p, i in enumerate(term_indices)
           if len(all_terms[i]) == 1 and term_space.is_output_lag(all_terms[i][0])]
    lags = [lin[all_terms[term_indices[p]][0]][1] for p in pos]
    return np.array(pos, dtype=np.int64), np.array(lags, dtype=np.int64)


@jit
def residuals(args, theta, r, jac):  # pragma: no cover - compiled
    """The residuals and their Jacobian at theta into ``r``, ``jac``; first diverged or -1."""
    (gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly, u, y, seg_a, seg_b,
     lag0, lo, hi, guard, part_pos, part_lag, ny, measured) = args
    mid = 0.5 * (lo + hi)
    if guard and not _stable(theta, part_pos, part_lag, ny):
        for i in range(measured.shape[0]):
            r[i] = measured[i] - (lo if measured[i] >= mid else hi)
        jac[:] = 0.0
        return (seg_a[0] if seg_a.shape[0] > 0 else 0) + lag0
    first, off = -1, 0
    for s in range(seg_a.shape[0]):
        a, b = seg_a[s], seg_b[s]
        rows = b - a - lag0
        out, sens = r[off:off + rows], jac[off:off + rows]
        if code.shape[0] > 0:
            at = sens_kernel_r(gather, y_lags, u_lags, u_cols, code, consts, start, depth, ly,
                               theta, u[a:b], y[a:b], lag0, lo, hi, out, sens)
        else:
            at = sens_kernel(gather, y_lags, u_lags, u_cols, theta, u[a:b], y[a:b], lag0, lo,
                             hi, out, sens)
        if at >= 0:
            first = a + at if first < 0 else first
            _hold_edge(out, sens, at - lag0, y[a + lag0 - 1], lo, hi)
        for i in range(rows):
            out[i] = measured[off + i] - out[i]
        off += rows
    jac *= -1.0
    return first


@jit
def _hold_edge(out, sens, first, before, lo, hi):  # pragma: no cover - compiled
    """Rows ``first``.. of a diverged run: the range's edge nearest the last value, no gradient."""
    last = out[first - 1] if first > 0 else before
    edge = hi if last >= 0.5 * (lo + hi) else lo
    for i in range(first, out.shape[0]):
        out[i] = edge
        sens[i, :] = 0.0


@jit
def _stable(theta, part_pos, part_lag, ny):  # pragma: no cover - compiled
    """Whether the output-lag polynomial's roots lie inside the unit circle (Schur-Cohn).

    The step-down recursion: every reflection coefficient of modulus below 1.
    """
    a = np.zeros(ny + 1)
    a[0] = 1.0
    for j in range(part_pos.shape[0]):
        a[part_lag[j]] -= theta[part_pos[j]]
    n = ny
    while n > 0 and a[n] == 0.0:
        n -= 1
    while n > 0:
        k = a[n] / a[0]
        if not abs(k) < 1.0:
            return False
        scale = 1.0 - k * k
        b = np.empty(n)
        for j in range(n):
            b[j] = (a[j] - k * a[n - j]) / scale
        a[:n] = b
        n -= 1
    return True
