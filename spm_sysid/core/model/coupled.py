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

:func:`refine_coupled` -- simulation focus for several outputs: the structures
stay those selected per output; their coefficients are refined **jointly**
(Levenberg-Marquardt over all outputs' coefficients at once) on the coupled
free-run error, each output's error over its standard deviation so that
outputs of different units weigh alike. A refinement that does not lower that
error, or diverges, is not taken.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..compiled.registry import jit_exact as jit
from .regressor_sim import coupled_program, regressors_at
from .regressors import Program
from .simulation import divergence_bounds
from .uncertainty import from_jacobian

__all__ = ["CoupledCompiled", "coupled_run", "refine_coupled"]


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


def refine_coupled(model, u: np.ndarray, Y: np.ndarray,
                   segments: list[tuple[int, int]] | None = None,
                   max_evaluations: int = 100):
    """All outputs' coefficients refined together on the coupled free-run error.

    Parameters
    ----------
    model : MimoModel
        The structures and the starting coefficients.
    u, Y : ndarray
        The estimation record(s).
    segments : list of (start, stop), optional
        Contiguous parts, each simulated from its own start (None: the whole record).
    max_evaluations : int
        Most cost evaluations of Levenberg-Marquardt (finite-difference
        Jacobian: each costs one coupled run per coefficient).

    Returns
    -------
    model : MimoModel
        With the refined coefficients (and their free-run Jacobian uncertainty),
        or the model given when refinement did not help.
    info : dict
        ``before``/``after`` (normalised coupled free-run SSE), ``evaluations``,
        ``taken`` and a ``message``.
    """
    from scipy.optimize import least_squares  # imported when a refinement runs

    run = _CoupledResiduals(model, u, Y, segments)
    theta0 = np.concatenate([np.asarray(m.coefficients, dtype=float) for m in model.models])
    r0 = run.residuals(theta0)
    before = float(r0 @ r0)
    info = {"before": before, "after": before, "evaluations": 1, "taken": False}
    if run.measured.size <= theta0.size:
        info["message"] = "too few rows to refine"
        return model, info
    try:
        sol = least_squares(run.residuals, theta0, method="lm", x_scale="jac",
                            max_nfev=max_evaluations)
    except (ValueError, FloatingPointError) as exc:  # pragma: no cover - numerical failure
        info["message"] = f"refinement failed ({exc})"
        return model, info
    sim, div = run.simulate(sol.x)
    after = float(sol.fun @ sol.fun)
    info.update(after=after, evaluations=int(sol.nfev))
    if div or not after < before:
        info["message"] = ("the refined coefficients diverge" if div else
                           "the coefficients given simulate best together; kept")
        return model, info
    info.update(taken=True, message=str(sol.message))
    return replace(model, models=run.refined_models(model, sol, sim)), info


class _CoupledResiduals:
    """The coupled free run of all outputs over the segments, and its scaled residuals.

    Residuals are divided by each output's spread; a sample past a divergence
    costs ten times its output's range.
    """

    def __init__(self, model, u: np.ndarray, Y: np.ndarray,
                 segments: list[tuple[int, int]] | None) -> None:
        u = np.asarray(u, dtype=float)
        self.u = u[:, None] if u.ndim == 1 else u
        self.Y = np.asarray(Y, dtype=float)
        self.q = q = self.Y.shape[1]
        self.cc = CoupledCompiled.from_models(model.models, self.u.shape[1])
        lag = self.cc.max_lag
        self.segs = [(a, b) for a, b in (segments or [(0, len(self.Y))]) if b - a > lag]
        self.bounds = [divergence_bounds(self.Y[:, i]) for i in range(q)]
        self.scale = np.array([float(np.std(self.Y[:, i])) or 1.0 for i in range(q)])
        self.measured = np.concatenate([self.Y[a + lag:b] for a, b in self.segs])  # (rows, q)
        self.sizes = np.cumsum((0,) + self.cc.n_terms)
        self.penalty = 10.0 * np.array([(hi - lo) for lo, hi in self.bounds]) / self.scale

    def split(self, theta: np.ndarray) -> list[np.ndarray]:
        """Each output's coefficients."""
        return [theta[self.sizes[i]:self.sizes[i + 1]] for i in range(self.q)]

    def simulate(self, theta: np.ndarray) -> tuple[np.ndarray, bool]:
        """The coupled free run over every segment, and whether any output diverged."""
        runs, diverged = [], False
        for a, b in self.segs:
            sim, div = coupled_run(self.cc, self.split(theta), self.u[a:b], self.Y[a:b],
                                   self.bounds)
            runs.append(sim)
            diverged |= any(d is not None for d in div)
        return np.concatenate(runs), diverged

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """Scaled free-run residuals of all outputs, one vector."""
        sim, _ = self.simulate(theta)
        r = (self.measured - sim) / self.scale
        return np.where(np.isfinite(r), r, self.penalty).ravel()

    def refined_models(self, model, sol, sim: np.ndarray) -> list:
        """Each output's model with its refined coefficients and their uncertainty.

        Each output's uncertainty comes from its rows and columns of the joint Jacobian.
        """
        jac = sol.jac.reshape(len(self.measured), self.q, -1)  # d(r)/d(theta)
        models = []
        for i, (m, th) in enumerate(zip(model.models, self.split(sol.x))):
            J = -jac[:, i, self.sizes[i]:self.sizes[i + 1]] * self.scale[i]  # d(sim_i)/d(th)
            e = self.measured[:, i] - sim[:, i]
            unc = from_jacobian(J, float(e @ e)) if np.all(np.isfinite(J)) else m.uncertainty
            meta = {**m.metadata, "coupled_refinement": True}
            models.append(replace(m, coefficients=np.array(th), uncertainty=unc, metadata=meta))
        return models
