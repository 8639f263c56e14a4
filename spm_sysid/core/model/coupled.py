"""The coupled free run of several outputs, compiled, and its joint refinement.

Every output's model is a polynomial in lagged values of the inputs, its own
output and the other outputs (:mod:`spm_sysid.core.model.mimo`). In the coupled
free run all outputs step together: at each t every output's value is computed
from the simulated past of all of them, then written where the next step reads
it. One compiled loop (:func:`coupled_run`) runs any set of structures: the
signals are one matrix (inputs, then outputs), each output's linear values are
(column, lag) pairs into it, and its terms are rows of indices into those
values, padded with an index that points at a constant 1. Outputs whose term
spaces hold regressors (:mod:`.regressors`) have those among their values,
computed at each step from the simulated signals in the same kernel
(:func:`.regressor_sim.regressors_at`).

Divergence, as for one output: an output that is not finite or leaves its
measured range widened by ``DIVERGENCE_FACTOR`` spans is NaN from that sample
on (and so is every output that uses it).

:func:`coupled_sensitivities` -- the same run of structures without
regressors, with the derivatives of every simulated output with respect to
every output's coefficients (the sensitivity equations, stepped with the
run): the Jacobian of the joint refinement
(:mod:`spm_sysid.core.fit.refine_coupled`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..compiled.registry import jit_exact as jit
from .regressor_sim import coupled_program, regressors_at
from .regressors import Program
from .simulation import divergence_bounds

__all__ = ["CoupledCompiled", "coupled_run", "coupled_sensitivities"]


@dataclass(frozen=True)
class CoupledCompiled:
    """Several outputs' structures in the kernel's form."""

    lin_cols: np.ndarray  # (q, n_lin) int64: signal column of each linear value
    lin_lags: np.ndarray  # (q, n_lin) int64: its lag
    gather: np.ndarray    # (q, k_max, width) int64: value indices per term
    n_terms: tuple[int, ...]
    n_inputs: int
    max_lag: int
    program: Program  # the outputs' regressors (none: an empty program)

    @classmethod
    def from_models(cls, models, n_inputs: int) -> CoupledCompiled:
        """The kernel form of a :class:`~spm_sysid.core.model.mimo.MimoModel`'s models.

        Each output's values: its lagged signals (padded to the longest), its
        regressors (padded likewise), then the constant 1.
        """
        q = len(models)
        lins = [m.term_space.linear for m in models]
        n_lin = max(len(lin) for lin in lins)

        def column(i: int, src: int) -> int:  # output i's signal src in the signal matrix
            others = [j for j in range(q) if j != i]
            return (n_inputs + i if src < 0 else src if src < n_inputs
                    else n_inputs + others[src - n_inputs])

        cols = np.zeros((q, n_lin), dtype=np.int64)
        lags = np.ones((q, n_lin), dtype=np.int64)
        for i, lin in enumerate(lins):
            for j, (src, lag) in enumerate(lin):
                cols[i, j], lags[i, j] = column(i, src), lag
        # the regressors each output's terms use (the others are never computed)
        used = [sorted({f - len(lin) for t in m.term_indices for f in m.term_space.terms[t]
                        if f >= len(lin)}) for m, lin in zip(models, lins)]
        program = coupled_program(
            [([m.term_space.regressor_exprs[r] for r in rs], m.term_space.output,
              m.term_space.inputs) for m, rs in zip(models, used)], column)
        width = max([len(m.term_space.terms[t]) for m in models for t in m.term_indices]
                    + [1])
        k_max = max([len(m.term_indices) for m in models] + [1])
        one = n_lin + max(len(rs) for rs in used)  # the constant 1
        gather = np.full((q, k_max, width), one, dtype=np.int64)
        for i, m in enumerate(models):
            at = {len(lins[i]) + r: n_lin + k for k, r in enumerate(used[i])}
            for row, t in enumerate(m.term_indices):
                factors = [at.get(f, f) for f in m.term_space.terms[t]]
                gather[i, row, :len(factors)] = factors
        return cls(cols, lags, gather, tuple(len(m.term_indices) for m in models),
                   int(n_inputs), max(m.term_space.max_lag for m in models), program)

    def theta_matrix(self, thetas) -> np.ndarray:
        """Coefficients per output as one (q, k_max) array, zero-padded."""
        out = np.zeros(self.gather.shape[:2])
        for i, th in enumerate(thetas):
            out[i, :len(th)] = th
        return out


@jit
def _coupled(lin_cols, lin_lags, gather, theta, S, lag0, n_inputs, lo, hi, diverged, code,
             consts, start, depth):  # pragma: no cover - compiled
    """Step every output from lag0 on, writing into S's output columns.

    Each output's values: its lagged signals (padded to ``n_lin``), its
    regressors (padded to ``n_reg``: ``start[i]`` delimits output i's in
    ``code``, whose signal pushes all read ``S`` as op 1, column, lag), then the
    constant 1. Without regressors ``start`` is (q, 1) and none is computed.
    """
    q = gather.shape[0]
    n_lin = lin_cols.shape[1]
    n_reg = start.shape[1] - 1
    vals = np.ones(n_lin + n_reg + 1)
    new = np.empty(q)
    sv = np.empty(depth)
    sg = np.zeros((depth, 1))
    grad = np.zeros((max(n_reg, 1), 1))
    none = np.empty(1)
    for t in range(lag0, S.shape[0]):
        for i in range(q):
            for j in range(n_lin):
                vals[j] = S[t - lin_lags[i, j], lin_cols[i, j]]
            if n_reg > 0:
                regressors_at(code, consts, start[i], none, S, t, sv, sg, 0, vals, n_lin, grad)
            acc = 0.0
            for k in range(gather.shape[1]):
                p = 1.0
                for w in range(gather.shape[2]):
                    p *= vals[gather[i, k, w]]
                acc += theta[i, k] * p
            new[i] = acc
        for i in range(q):
            v = new[i]
            if diverged[i] < 0 and not (lo[i] <= v <= hi[i]):
                diverged[i] = t
            S[t, n_inputs + i] = v if diverged[i] < 0 else np.nan


@jit
def _coupled_sens(lin_cols, lin_lags, gather, n_terms, offsets, theta, S, lag0, n_inputs, lo,
                  hi, diverged, D):  # pragma: no cover - compiled
    """:func:`_coupled` without regressors, with the sensitivities of every output.

    ``D[t, i, :]``: d S[t, n_inputs + i] / d theta, theta all outputs' coefficients
    in one vector (output i's from ``offsets[i]``); zero on the measured start
    and from an output's divergence on (whose samples are NaN). Each term's
    derivative: its value (its own coefficient) plus its coefficient times the
    product of its other factors times each lagged output factor's sensitivity.
    """
    q = gather.shape[0]
    n_lin = lin_cols.shape[1]
    width = gather.shape[2]
    n_par = D.shape[2]
    vals = np.ones(n_lin + 1)
    out = np.full(n_lin + 1, -1)  # the output a value is a lag of (-1: an input, the 1)
    row = np.zeros(n_lin + 1, dtype=np.int64)  # its sample
    new = np.empty(q)
    dnew = np.zeros((q, n_par))
    for t in range(lag0, S.shape[0]):
        for i in range(q):
            for j in range(n_lin):
                c, lag = lin_cols[i, j], lin_lags[i, j]
                vals[j] = S[t - lag, c]
                out[j] = c - n_inputs if c >= n_inputs else -1
                row[j] = t - lag
            for p in range(n_par):
                dnew[i, p] = 0.0
            acc = 0.0
            for k in range(n_terms[i]):
                value = 1.0
                for w in range(width):
                    value *= vals[gather[i, k, w]]
                acc += theta[i, k] * value
                dnew[i, offsets[i] + k] += value
                for w in range(width):
                    g = gather[i, k, w]
                    if out[g] < 0:
                        continue
                    c = theta[i, k]
                    for w2 in range(width):
                        if w2 != w:
                            c *= vals[gather[i, k, w2]]
                    if c != 0.0:
                        src, o = row[g], out[g]
                        for p in range(n_par):
                            dnew[i, p] += c * D[src, o, p]
            new[i] = acc
        for i in range(q):
            v = new[i]
            if diverged[i] < 0 and not (lo[i] <= v <= hi[i]):
                diverged[i] = t
            ok = diverged[i] < 0
            S[t, n_inputs + i] = v if ok else np.nan
            for p in range(n_par):
                D[t, i, p] = dnew[i, p] if ok else 0.0


def coupled_run(cc: CoupledCompiled, thetas, u: np.ndarray, Y: np.ndarray,
                bounds: list[tuple[float, float]] | None = None
                ) -> tuple[np.ndarray, list[int | None]]:
    """Coupled free run from the first ``max_lag`` measured samples.

    Returns the simulated outputs for t = max_lag..n-1, shape (n - max_lag, q),
    and per output the sample where it diverged (None when it did not).
    """
    u = np.asarray(u, dtype=float)
    u = u[:, None] if u.ndim == 1 else u
    Y = np.asarray(Y, dtype=float)
    q = Y.shape[1]
    bounds = bounds or [divergence_bounds(Y[:, i]) for i in range(q)]
    S = np.ascontiguousarray(np.column_stack([u, Y]))
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    diverged = np.full(q, -1, dtype=np.int64)
    p = cc.program
    _coupled(cc.lin_cols, cc.lin_lags, cc.gather, cc.theta_matrix(thetas), S, cc.max_lag,
             cc.n_inputs, lo, hi, diverged, p.code, p.consts, p.start, int(p.depth))
    return (S[cc.max_lag:, cc.n_inputs:].copy(),
            [None if d < 0 else int(d) for d in diverged])


def coupled_sensitivities(cc: CoupledCompiled, thetas, u: np.ndarray, Y: np.ndarray,
                          bounds: list[tuple[float, float]]
                          ) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`coupled_run` with its sensitivities, for structures without regressors.

    Returns the simulated outputs for t = max_lag..n-1, shape (n - max_lag, q);
    their derivatives with respect to all outputs' coefficients (output 0's
    first), shape (n - max_lag, q, coefficients), zero where an output has
    diverged (NaN); and whether any output diverged.
    """
    if cc.program.start.shape[1] > 1:
        raise ValueError("coupled sensitivities need structures without regressors")
    u = np.asarray(u, dtype=float)
    u = u[:, None] if u.ndim == 1 else u
    Y = np.asarray(Y, dtype=float)
    q = Y.shape[1]
    S = np.ascontiguousarray(np.column_stack([u, Y]))
    n_terms = np.array(cc.n_terms, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(n_terms)[:-1]]).astype(np.int64)
    D = np.zeros((len(Y), q, int(n_terms.sum())))
    diverged = np.full(q, -1, dtype=np.int64)
    _coupled_sens(cc.lin_cols, cc.lin_lags, cc.gather, n_terms, offsets,
                  cc.theta_matrix(thetas), S, cc.max_lag, cc.n_inputs,
                  np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds]),
                  diverged, D)
    return (S[cc.max_lag:, cc.n_inputs:].copy(), D[cc.max_lag:], bool(np.any(diverged >= 0)))
