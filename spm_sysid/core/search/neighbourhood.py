"""Every single-term move's least-squares SSE at once, from the least-squares factor.

A local search over structures scores all neighbours of its current structure S
(k terms of n): k removals, n - k additions and k (n - k) swaps. Fitting each
costs O(k^3); from one QR factorisation of S's columns the residual sum of
squares of every move follows by rank-one algebra, all of them in
O(k^2 (n - k)). With ``P = (X_S' X_S)^-1``, ``beta`` S's coefficients:

* removing j: ``SSE + beta_j^2 / P_jj``;
* adding a: ``SSE - rho_a^2 / d_a``, with ``d_a`` the squared residual of
  column a against S and ``rho_a`` its products with the residual;
* swapping j for a: the addition's formula against S without j, where
  ``d_a`` grows by ``w_aj^2 / P_jj`` and ``rho_a`` by ``w_aj beta_j / P_jj``
  (``w_a = P X_S' x_a``).

The columns are the evaluator's triangular factor of ``[P y]`` (the same
least-squares problem in n + 1 rows), not its Gram matrix: where the SSE is a
small difference of large numbers (the dryer), the Gram matrix's values were
off by 4 in AIC, these agree with the fits to about 1e-11. The polish
(:func:`~spm_sysid.core.search.local.polish`) descends by these values and has
the evaluator score the ends that may beat its best: what it returns carries
the evaluator's own value.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..defaults import POLISH_STEP_WORK, POLISH_STEPS

__all__ = ["MOVES", "MoveScreen"]

#: The moves a step may take.
MOVES = ("remove", "add", "swap")


class MoveScreen:
    """Ranks the single-term moves of a structure by their criterion (see the module doc).

    Parameters
    ----------
    evaluator : StructureEvaluator
        Its triangular factor of the unit-norm columns and the target, criterion,
        row count, SSE scale and floor, rank tolerance and size limit are used.
    """

    def __init__(self, evaluator) -> None:
        self.ev = evaluator
        m = evaluator.n_terms
        # the triangular factor of [P y]: the least-squares problem in m + 1 rows
        self.factor = evaluator.factor[:, :m + 1]

    @staticmethod
    def usable(evaluator) -> bool:
        """Whether ranking suits the evaluator (else the polish that counts structures).

        Its criterion must depend on the SSE and the size only (AIC, AICc, BIC).
        """
        return not evaluator.criterion.needs_coefficients

    def step_budget(self, size: int) -> int:
        """Neighbourhoods a polish may rank from a structure of ``size`` terms.

        :data:`~spm_sysid.core.defaults.POLISH_STEPS`, fewer where a step's work
        ((n + 1) k (n - k)) passes :data:`~spm_sysid.core.defaults.POLISH_STEP_WORK`:
        the polish of a large space takes seconds, not minutes. At least one.
        """
        n = self.ev.n_terms
        work = (n + 1) * max(size, 1) * max(n - size, 1)
        return max(1, int(POLISH_STEPS * min(1.0, POLISH_STEP_WORK / work)))

    def sse(self, mask: np.ndarray, allowed: np.ndarray, moves: Sequence[str]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """The SSE of every move: (removed term or -1, added term or -1, SSE), and S's SSE.

        None when S is rank-deficient (a squared pivot of its columns below the
        evaluator's rank tolerance). Moves into a column that S (or S without
        the removed term) reproduces to that tolerance are left out.
        """
        inn = np.flatnonzero(mask)
        out = np.flatnonzero(~mask & allowed)
        k = len(inn)
        drop, add, sse = [], [], []
        X_out, target = self.factor[:, out], self.factor[:, -1]
        if k:
            q, r = np.linalg.qr(self.factor[:, inn])
            if np.min(np.abs(np.diag(r))) ** 2 < self.ev.rank_tol:
                return None
            r_inv = np.linalg.inv(r)
            diag = np.einsum("ij,ij->i", r_inv, r_inv)  # diag of (X_S' X_S)^-1
            qy = q.T @ target
            beta = r_inv @ qy
            residual = target - q @ qy
            qx = q.T @ X_out
            W = r_inv @ qx
            X_perp = X_out - q @ qx
        else:
            beta, diag = np.zeros(0), np.zeros(0)
            residual, W, X_perp = target, np.zeros((0, len(out))), X_out
        base = float(residual @ residual)
        d = np.einsum("ij,ij->j", X_perp, X_perp)
        rho = X_perp.T @ residual
        tol = self.ev.rank_tol
        if "remove" in moves and k > 1:
            drop.append(inn)
            add.append(np.full(k, -1))
            sse.append(base + beta ** 2 / diag)
        if "add" in moves and len(out):
            ok = d > tol
            drop.append(np.full(int(ok.sum()), -1))
            add.append(out[ok])
            sse.append(base - rho[ok] ** 2 / d[ok])
        if "swap" in moves and k and len(out):
            D = d[None, :] + W ** 2 / diag[:, None]
            R = rho[None, :] + W * (beta / diag)[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                S = base + (beta ** 2 / diag)[:, None] - R ** 2 / D
            ok = D > tol
            j, a = np.nonzero(ok)
            drop.append(inn[j])
            add.append(out[a])
            sse.append(S[ok])
        if not drop:
            return np.empty(0, dtype=int), np.empty(0, dtype=int), np.empty(0), base
        return (np.concatenate(drop), np.concatenate(add),
                np.maximum(np.concatenate(sse), 0.0), base)

    def values(self, mask: np.ndarray, allowed: np.ndarray, moves: Sequence[str] = MOVES):
        """Every move's criterion value: (removed or -1, added or -1, value), and S's own.

        None when S is rank-deficient. Moves past the size limit score +inf.
        """
        mask = np.asarray(mask, dtype=bool)
        moved = self.sse(mask, allowed, moves)
        if moved is None:
            return None
        drop, add, sse, base = moved
        ev = self.ev
        k = int(mask.sum()) + (add >= 0) - (drop >= 0)
        sse = np.append(sse, base)
        k = np.append(k, int(mask.sum()))
        with np.errstate(divide="ignore", invalid="ignore"):
            values = ev.criterion(np.maximum(sse, ev.sse_floor) * ev.sse_scale, ev.n, k)
        if ev.max_terms:
            values = np.where(k > ev.max_terms, np.inf, values)
        return drop, add, values[:-1], float(values[-1])

    def independent(self, mask: np.ndarray) -> np.ndarray:
        """``mask`` without each term its earlier terms reproduce to the rank tolerance.

        Terms are taken in index order, as :meth:`sse` factors them: a term stays
        when the squared norm of its column's part outside the span of the terms
        kept before it is at least the evaluator's rank tolerance (the pivot that
        QR would give it), so what is left passes :meth:`sse`'s test.
        """
        kept = np.asarray(mask, dtype=bool).copy()
        basis = np.zeros((self.factor.shape[0], 0))
        for j in np.flatnonzero(kept):
            column = self.factor[:, j]
            for _ in range(2):  # Gram-Schmidt twice: orthogonal to rounding
                column = column - basis @ (basis.T @ column)
            norm2 = float(column @ column)
            if norm2 < self.ev.rank_tol:
                kept[j] = False
            else:
                basis = np.column_stack([basis, column / np.sqrt(norm2)])
        return kept

    def descend(self, mask: np.ndarray, allowed: np.ndarray, max_steps: int,
                tolerance: float = 1e-9) -> tuple[np.ndarray, float, int]:
        """Best-improvement descent by additions, removals and swaps, ranked here.

        Returns where it ended, its value here, and the neighbourhoods ranked
        (at most ``max_steps``: the cost). It ends at a local optimum, after
        ``max_steps``, or at a rank-deficient structure (value +inf); a start
        whose terms are collinear first loses those its earlier terms reproduce
        (:meth:`independent`). Its value is the caller's to confirm with the
        evaluator.
        """
        current = np.asarray(mask, dtype=bool).copy()
        allowed = np.asarray(allowed, dtype=bool)
        value = np.inf
        for step in range(max_steps):
            moved = self.values(current, allowed)
            if moved is None and step == 0:  # a kick into collinear terms: drop those first
                current = self.independent(current)
                moved = self.values(current, allowed)
            if moved is None:
                return current, np.inf, step + 1
            drop, add, values, value = moved
            i = int(np.argmin(values)) if len(values) else -1
            if i < 0 or not values[i] < value - tolerance:
                return current, value, step + 1
            if drop[i] >= 0:
                current[drop[i]] = False
            if add[i] >= 0:
                current[add[i]] = True
            value = float(values[i])
        return current, value, max_steps
