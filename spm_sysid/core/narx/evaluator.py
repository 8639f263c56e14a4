"""Scoring model structures: a fast cached evaluator and a reference fit.

A GA run scores tens of thousands of chromosomes, most of them repeats. The fast
:class:`StructureEvaluator` therefore

* keys every structure by its bit pattern and never fits a structure twice in a
  run (a dictionary cache);
* shares work across structures: the Gram matrix of all candidate columns and
  the target, ``[P y]^T [P y]``, is formed once (columns scaled to unit norm).
  A structure's least-squares fit is then a Cholesky factorisation of its
  ``(k+1) x (k+1)`` sub-matrix, independent of the number of samples N: the
  last pivot of the factor is ``sqrt(SSE)``, the others give the coefficients;
* fits all new structures of a generation in one compiled call
  (:mod:`spm_sysid.core.narx.kernels`), each at its own size, stopping a
  factorisation at the first pivot that shows the structure rank-deficient
  (without numba: batched LAPACK calls over structures of similar size).

Rank handling (both paths use the same rule, so they agree): with unit-norm
columns, the squared Cholesky pivot of term j is ``1 - R^2`` of regressing that
column on the terms before it. A structure in which some pivot falls below
``rank_tol`` (default 1e-9, i.e. a term reproduced by the others to within a
relative residual of about 3e-5) is *rank-deficient*: its parameters are not
identifiable, and it gets the worst score, ``+inf``, as does the empty
structure. Such a structure is never the best: dropping the redundant term gives
the same SSE with fewer terms.

:func:`spm_sysid.core.narx.lstsq.reference_fit` is the slow, numerically
preferred path (Householder QR of the selected columns); it gives the final
model's coefficients and is the yardstick the fast path is tested against. The
benchmark's naive baseline lives with the benchmark (:mod:`spm_sysid.tools.bench`).
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from .criteria import Criterion, get_criterion
from .kernels import HAVE_NUMBA, fit_structures
from .lstsq import DEFAULT_RANK_TOL, sse_floor

#: Structures the Gram path accepts with a smallest squared pivot below
#: NEAR_RANK * rank_tol have their rank (and fit) decided by QR, as the reference fit
#: decides it: there the Gram matrix's squared condition number makes pivots unreliable.
NEAR_RANK = 10.0

#: Near-threshold structures scoring within this of the best value seen are decided by
#: QR in :meth:`StructureEvaluator.evaluate` (an Akaike roulette weight of exp(-25)).
ARBITRATION_WINDOW = 50.0

__all__ = ["StructureEvaluator", "size_groups", "structure_keys"]


def structure_keys(masks: np.ndarray) -> np.ndarray:
    """One hashable key per structure: its bits packed into bytes. Shape (B,).

    Any number of candidate terms (``ceil(M / 8)`` bytes per key); ``tolist()``
    gives ``bytes`` objects for dictionaries, ``np.unique`` works on the array.
    """
    masks = np.asarray(masks, dtype=bool)
    packed = np.ascontiguousarray(np.packbits(masks, axis=-1, bitorder="little"))
    return packed.view(np.dtype((np.void, packed.shape[-1]))).reshape(masks.shape[:-1])


class StructureEvaluator:
    """Scores structures on one data set with one criterion; cached and batched.

    Parameters
    ----------
    P : ndarray, shape (N, n_terms)
        Regression matrix (see :meth:`TermSpace.regression_matrix`).
    target : ndarray, shape (N,)
        y(t) for the regression rows.
    criterion : str, Criterion or callable
        See :func:`spm_sysid.core.narx.criteria.get_criterion`.
    rank_tol : float
        See the module docstring.
    sse_scale : float
        Factor from the SSE of ``target`` to the SSE in the user's units (when
        the caller scaled the data).
    compiled : bool, optional
        Fit with the compiled kernel (default: when numba is installed) or with
        the batched numpy path (the same arithmetic; results agree to rounding).

    Attributes
    ----------
    evaluations : int
        Structures actually fitted (cache misses).
    lookups : int
        Structures asked for, including repeats.
    """

    def __init__(
        self,
        P: np.ndarray,
        target: np.ndarray,
        criterion: str | Criterion = "aic",
        rank_tol: float = DEFAULT_RANK_TOL,
        sse_scale: float = 1.0,
        compiled: bool | None = None,
    ) -> None:
        P = np.asarray(P, dtype=float)
        target = np.asarray(target, dtype=float)
        self.criterion = get_criterion(criterion)
        # SSE of the data as the user gave it = SSE here * sse_scale (identify scales
        # u and y by powers of two, which is exact, so criteria see the user's units)
        self.sse_scale = float(sse_scale)
        self.n, self.n_terms = P.shape
        self.rank_tol = rank_tol
        self.compiled = HAVE_NUMBA if compiled is None else bool(compiled) and HAVE_NUMBA
        norms = np.linalg.norm(P, axis=0)
        self._zero_cols = norms == 0
        self._scale = np.where(norms > 0, norms, 1.0)
        self._y_norm = float(np.linalg.norm(target)) or 1.0
        self._sse_floor = sse_floor(float(np.linalg.norm(target)))
        aug = np.column_stack([P / self._scale, target])
        m = self.n_terms
        # Gram matrix of [P y] plus one all-zero "dummy" index (m + 1) used to pad
        # structures of different sizes into one batch.
        gram = np.zeros((m + 2, m + 2))
        gram[: m + 1, : m + 1] = aug.T @ aug
        self._gram = gram
        # Triangular factor of [P y] with a zero dummy column, for coefficients.
        r_aug = np.linalg.qr(aug, mode="r")
        self._r_ext = np.zeros((r_aug.shape[0], m + 2))
        self._r_ext[:, : m + 1] = r_aug
        self._cache: dict[int, float] = {}
        self._best = np.inf  # best settled value (see evaluate)
        self.evaluations = 0
        self.lookups = 0

    @property
    def cache_hit_rate(self) -> float:
        """Fraction of lookups answered from the cache."""
        return 1.0 - self.evaluations / self.lookups if self.lookups else 0.0

    def score(self, masks: np.ndarray, keys: np.ndarray | None = None) -> np.ndarray:
        """Criterion values for a population, shape (B,); fits only unseen structures.

        ``keys`` (from :func:`structure_keys`) may be passed when the caller has them.
        """
        masks = np.asarray(masks, dtype=bool)
        keys = structure_keys(masks) if keys is None else keys
        self.lookups += len(keys)
        cache = self._cache
        todo: dict[int, int] = {}
        for row, key in enumerate(keys.tolist()):
            if key not in cache and key not in todo:
                todo[key] = row
        if todo:
            rows = list(todo.values())
            values = self.evaluate(masks[rows])
            cache.update(zip(todo.keys(), values.tolist()))
            self.evaluations += len(rows)
        return np.fromiter((cache[k] for k in keys.tolist()), dtype=float, count=len(keys))

    def ranked(self, count: int) -> np.ndarray:
        """The ``count`` best distinct structures scored so far, best first (masks).

        Only structures with a finite score are listed.
        """
        items = sorted(((v, k) for k, v in self._cache.items() if np.isfinite(v)),
                       key=lambda item: item[0])[:max(0, int(count))]
        if not items:
            return np.zeros((0, self.n_terms), dtype=bool)
        packed = np.frombuffer(b"".join(k for _, k in items), dtype=np.uint8)
        bits = np.unpackbits(packed.reshape(len(items), -1), axis=1, bitorder="little")
        return bits[:, :self.n_terms].astype(bool)

    def cached_score(self, mask: np.ndarray) -> float:
        """Score of one structure (cached)."""
        return float(self.score(np.asarray(mask, dtype=bool)[None, :])[0])

    def evaluate(self, masks: np.ndarray) -> np.ndarray:
        """Criterion values for distinct structures without touching the cache.

        Structures the Gram path accepts with a pivot near ``rank_tol`` are refitted
        by QR (:meth:`_qr_fit`) when they score within ``ARBITRATION_WINDOW`` of
        the best value seen so far -- those that could be selected; further off,
        the Gram path's value stands (in a GA their roulette weight is nil anyway).
        """
        masks = np.asarray(masks, dtype=bool)
        k = masks.sum(axis=1)
        sse, beta, bad, near = self._fit(masks, arbitrate=False)
        values = self._values(sse, k, beta, bad)
        finite = np.isfinite(values)
        best = min(self._best, float(values[finite & ~near].min())
                   if (finite & ~near).any() else np.inf)
        redo = near & finite & (values < (best if np.isfinite(best) else np.inf)
                                + ARBITRATION_WINDOW)
        if not np.isfinite(best):  # nothing settled yet: arbitrate every near one
            redo = near & finite
        if redo.any():
            sse2, beta2, bad2, _ = self._fit(masks[redo], arbitrate=True)
            values[redo] = self._values(sse2, k[redo], beta2, bad2)
        settled = np.isfinite(values) & (~near | redo)
        if settled.any():
            self._best = min(best, float(values[settled].min()))
        return values

    def _values(self, sse, k, beta, bad) -> np.ndarray:
        sse = np.maximum(sse, self._sse_floor)  # exact fits: see lstsq.sse_floor
        with np.errstate(invalid="ignore", divide="ignore"):
            values = self.criterion(sse * self.sse_scale, self.n, k, beta)
        return np.where(bad | (k == 0) | ~np.isfinite(values), np.inf, values)

    def fit_batch(self, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """SSE, standardised coefficients and rank-deficiency flags for a batch.

        One compiled call (:func:`~spm_sysid.core.narx.kernels.fit_structures`)
        fits every structure at its own size; without numba, structures are fitted
        in numpy batches of similar size (see :func:`size_groups`), so one large
        structure does not pad a whole generation to its size. Every structure
        accepted with a pivot near ``rank_tol`` is decided by QR (as the reference).

        Returns
        -------
        sse : ndarray, shape (B,)  NaN where rank-deficient
        beta : ndarray, shape (B, n_terms), or None when the criterion needs none
        bad : ndarray of bool, shape (B,)  rank-deficient structures
        """
        return self._fit(np.asarray(masks, dtype=bool), arbitrate=True)[:3]

    def _fit(self, masks: np.ndarray, arbitrate: bool):
        """Return ``(sse, beta, bad, near)`` for a batch.

        ``near`` marks accepted structures near the rank threshold that were not
        decided by QR (all False with ``arbitrate``).
        """
        if self.compiled:
            return self._fit_compiled(masks, arbitrate)
        B = len(masks)
        sse, bad, near = np.empty(B), np.empty(B, dtype=bool), np.empty(B, dtype=bool)
        beta = np.zeros((B, self.n_terms)) if self.criterion.needs_coefficients else None
        for rows in size_groups(masks.sum(axis=1)):
            sse[rows], b, bad[rows], near[rows] = self._fit_numpy(masks[rows], arbitrate)
            if beta is not None:
                beta[rows] = b
        return sse, beta, bad, near

    def _fit_compiled(self, masks: np.ndarray, arbitrate: bool):
        # lexicographic order of the term lists: neighbours share factorised prefixes
        order = np.lexsort(~masks.T[::-1]) if len(masks) > 1 else np.arange(len(masks))
        sse, beta, bad, near = self._fit_sorted(masks[order], arbitrate)
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        return (sse[back], None if beta is None else beta[back], bad[back], near[back])

    def _fit_sorted(self, masks: np.ndarray, arbitrate: bool):
        rows, cols = np.nonzero(masks)
        offsets = np.zeros(len(masks) + 1, dtype=np.int64)
        np.cumsum(masks.sum(axis=1), out=offsets[1:])
        sse = np.empty(len(masks))
        theta = np.zeros(len(cols))
        bad = np.empty(len(masks), dtype=np.bool_)
        minpiv = np.empty(len(masks))
        fit_structures(self._gram, self._r_ext, cols.astype(np.int64), offsets,
                       float(self.rank_tol), self._y_norm, self.n,
                       self.criterion.needs_coefficients, sse, theta, bad, minpiv)
        # Gram-accepted structures near the threshold: QR has the last word (a structure
        # the Gram matrix rejects stays rejected -- it is never the one selected)
        near = ~bad & (minpiv < NEAR_RANK * self.rank_tol)
        if arbitrate:
            for b in np.flatnonzero(near):
                sl = slice(offsets[b], offsets[b + 1])
                sse[b], theta[sl], bad[b] = self._qr_fit(cols[sl])
            near[:] = False
        beta = None
        if self.criterion.needs_coefficients:
            beta = np.zeros(masks.shape)
            keep = ~bad[rows]
            beta[rows[keep], cols[keep]] = theta[keep] / self._y_norm
        return sse, beta, bad, near

    def _qr_fit(self, cols: np.ndarray) -> tuple[float, np.ndarray, bool]:
        """SSE, coefficients and rank flag of one structure by Householder QR.

        For structures whose Gram pivots come near ``rank_tol``: squaring the
        condition number in the Gram matrix makes those pivots unreliable, so
        the rank is decided as the reference fit decides it, on the triangular
        factor of ``[P y]`` (the same least-squares problem in fewer rows).
        """
        A = self._r_ext[:, cols]
        t = self._r_ext[:, self.n_terms]
        Q, R = np.linalg.qr(A)
        if np.min(np.diag(R) ** 2) < self.rank_tol:
            return np.nan, np.zeros(len(cols)), True
        th = linalg.solve_triangular(R, Q.T @ t, check_finite=False)
        r = t - A @ th
        return float(r @ r), th, False

    def _fit_numpy(self, masks: np.ndarray, arbitrate: bool = True):
        """The batched numpy path of :meth:`fit_batch` for structures of similar size."""
        masks = np.asarray(masks, dtype=bool)
        B, m = masks.shape
        k = masks.sum(axis=1)
        kmax = int(k.max()) if B else 0
        dummy = m + 1
        # idx[b] = selected terms, then dummy padding, then the target column (m).
        idx = np.full((B, kmax + 1), dummy, dtype=np.intp)
        order = np.argsort(~masks, axis=1, kind="stable")[:, :kmax]
        pos = np.arange(kmax)
        valid = pos[None, :] < k[:, None]
        idx[:, :kmax] = np.where(valid, order, dummy)
        idx[:, kmax] = m
        sub = self._gram[idx[:, :, None], idx[:, None, :]]
        pad = np.zeros((B, kmax + 1))
        pad[:, :kmax] = ~valid
        sub += pad[:, :, None] * np.eye(kmax + 1)
        bad = (masks & self._zero_cols).any(axis=1)
        sub[bad] = np.eye(kmax + 1)  # factorable placeholder; the row stays flagged
        L, failed = _batched_cholesky(sub)
        exact = np.zeros(B, dtype=bool)
        if failed.any():
            # The last pivot is the SSE: when the terms reproduce the target to rounding it
            # is lost (<= 0). Raising the target's diagonal moves only that pivot, so a
            # second factorisation tells an exact fit (its SSE then comes from the
            # refinement below) from terms that are not independent.
            again = sub[failed]
            again[:, kmax, kmax] += self._gram[m, m]
            L2, failed2 = _batched_cholesky(again)
            L[failed], exact[failed] = L2, ~failed2
            L[exact, kmax, kmax] = 0.0
            failed = failed & ~exact
        diag = np.diagonal(L, axis1=1, axis2=2)
        pivots = np.where(valid, diag[:, :kmax] ** 2, 1.0)
        bad |= failed | (pivots < self.rank_tol).any(axis=1)
        sse = diag[:, kmax] ** 2
        # Gram = L L^T with L = [[Ls, 0], [z^T, sqrt(SSE)]], so Ls^T theta_n = z.
        theta_n = _solve_triangular(np.swapaxes(L[:, :kmax, :kmax], 1, 2), L[:, kmax, :kmax],
                                    lower=False)
        if self.criterion.needs_coefficients:
            redo = ~bad
        else:
            # First-order error of the Gram path: eps * (||y|| + ||theta_n||)^2 in SSE.
            # Where that could move a log-SSE criterion by more than 1e-7, refine.
            err = np.finfo(float).eps * (self._y_norm + np.linalg.norm(theta_n, axis=1)) ** 2
            redo = ~bad & ((self.n * err > 1e-7 * sse) | exact)
        if redo.any():
            sse[redo], theta_n[redo] = self._refine(idx[redo], kmax, L[redo], theta_n[redo])
        near = ~bad & (k > 0) & (pivots < NEAR_RANK * self.rank_tol).any(axis=1)
        if arbitrate:
            for b in np.flatnonzero(near):  # as in the compiled path: QR decides
                sse[b], theta_n[b, :k[b]], bad[b] = self._qr_fit(idx[b, :k[b]])
            near[:] = False
        beta = None
        if self.criterion.needs_coefficients:
            beta = np.zeros((B, m))
            rows = np.repeat(np.arange(B), kmax)
            cols = idx[:, :kmax].ravel()
            keep = valid.ravel() & ~np.repeat(bad, kmax)
            # theta_n is for unit-norm columns (theta_n = theta * ||phi||): beta = theta_n/||y||
            beta[rows[keep], cols[keep]] = theta_n.ravel()[keep] / self._y_norm
        sse = np.where(bad, np.nan, sse)
        return sse, beta, bad, near

    def _refine(self, idx, kmax, L, theta_n, chunk: int = 64):
        """Accurate SSE and coefficients where the Gram path's SSE is not accurate enough.

        Corrected semi-normal equations: one step of iterative refinement of the
        Gram path's coefficients (with its Cholesky factor), then the SSE from the
        residual itself, whose error is second order in the coefficients' error.
        The residual is taken on ``R_aug`` (the triangular factor of the unit-norm
        ``[P y]``: the same least-squares problem in ``min(N, m + 1)`` rows), so a
        structure of k terms costs O(rows * k) instead of a QR's O(rows * k^2).
        """
        sse = np.empty(len(idx))
        theta = theta_n.copy()
        target = self._r_ext[:, self.n_terms]
        for s0 in range(0, len(idx), chunk):
            sl = slice(s0, s0 + chunk)
            A = np.moveaxis(self._r_ext[:, idx[sl, :kmax]], 1, 0)  # (b, rows, kmax)
            Lk = L[sl, :kmax, :kmax]
            th = theta[sl]
            r = target[None, :] - np.einsum("brk,bk->br", A, th)
            g = np.einsum("brk,br->bk", A, r)
            th = th + _solve_triangular(np.swapaxes(Lk, 1, 2),
                                        _solve_triangular(Lk, g, lower=True), lower=False)
            r = target[None, :] - np.einsum("brk,bk->br", A, th)
            sse[sl] = np.einsum("br,br->b", r, r)
            theta[sl] = th
        return sse, theta


def size_groups(k: np.ndarray, growth: float = 1.25, slack: int = 4) -> list[np.ndarray]:
    """Row indices grouped by structure size, for the batched numpy path.

    Each group's largest structure has at most ``growth * smallest + slack`` terms,
    so padding a group to its largest costs at most about 2x in flops.
    """
    order = np.argsort(k, kind="stable")
    groups, start = [], 0
    ks = k[order]
    while start < len(order):
        stop = int(np.searchsorted(ks, growth * ks[start] + slack, side="right"))
        groups.append(order[start:stop])
        start = stop
    return groups


def _solve_triangular(T: np.ndarray, b: np.ndarray, lower: bool) -> np.ndarray:
    """Solve a stack of triangular systems ``T x = b``; shapes (B, k, k), (B, k).

    Substitution vectorised over the stack: k steps of O(B k) work each, instead of
    B library calls (whose overhead dominates for the GA's many small systems).
    """
    B, k = b.shape
    x = np.zeros((B, k))
    steps = range(k) if lower else range(k - 1, -1, -1)
    for j in steps:
        if lower:
            acc = np.einsum("bi,bi->b", T[:, j, :j], x[:, :j])
        else:
            acc = np.einsum("bi,bi->b", T[:, j, j + 1:], x[:, j + 1:])
        x[:, j] = (b[:, j] - acc) / T[:, j, j]
    return x


try:  # numpy's batched Cholesky without the raise (one bad matrix must not cost a loop)
    from numpy.linalg._umath_linalg import cholesky_lo as _cholesky_lo
except ImportError:  # pragma: no cover - another numpy layout: the loop below is used
    _cholesky_lo = None


def _batched_cholesky(mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of a stack, and which ones failed.

    Matrices that are not positive definite are factorised as identity and flagged
    instead of failing the whole batch.
    """
    if _cholesky_lo is not None:  # numpy's own gufunc: NaN marks a failed matrix
        with np.errstate(invalid="ignore"):
            out = _cholesky_lo(mats, signature="d->d")
        failed = np.isnan(out).any(axis=(1, 2))
        if failed.any():
            out[failed] = np.eye(mats.shape[-1])
        return out, failed
    try:
        return np.linalg.cholesky(mats), np.zeros(len(mats), dtype=bool)
    except np.linalg.LinAlgError:
        out = np.empty_like(mats)
        failed = np.zeros(len(mats), dtype=bool)
        eye = np.eye(mats.shape[-1])
        for i, mat in enumerate(mats):
            try:
                out[i] = np.linalg.cholesky(mat)
            except np.linalg.LinAlgError:
                out[i] = eye
                failed[i] = True
        return out, failed
