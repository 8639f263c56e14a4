"""Scoring model structures: a fast cached evaluator over one least-squares problem.

A GA run scores tens of thousands of chromosomes, most of them repeats. The
:class:`StructureEvaluator` therefore

* keys every structure by its bit pattern and never fits a structure twice in a
  run (a dictionary cache, bounded: past :func:`cache_capacity` entries, a share
  of the memory bound, it keeps its better half and the best of every size);
* shares work across structures: the Gram matrix of all candidate columns and
  the target, ``[P y]^T [P y]``, is formed once (columns scaled to unit norm).
  A structure's least-squares fit is then a Cholesky factorisation of its
  ``(k+1) x (k+1)`` sub-matrix, independent of the number of samples N: the
  last pivot of the factor is ``sqrt(SSE)``, the others give the coefficients;
* fits all new structures of a generation in one compiled call
  (:mod:`spm_sysid.core.compiled.kernels`), each at its own size, stopping a
  factorisation at the first pivot that shows the structure rank-deficient.

Rank handling: with unit-norm columns, the squared Cholesky pivot of term j is
``1 - R^2`` of regressing that column on the terms before it. A structure in
which some pivot falls below ``rank_tol`` (default 1e-9, i.e. a term reproduced
by the others to within a relative residual of about 3e-5) is
*rank-deficient*: its parameters are not identifiable, and it gets the worst
score, ``+inf``, as does the empty structure. Such a structure is never the
best: dropping the redundant term gives the same SSE with fewer terms.

:func:`spm_sysid.core.fit.lstsq.reference_fit` is the slow, numerically
preferred path (Householder QR of the selected columns); it gives the final
model's coefficients and is the yardstick the evaluator is tested against. The
benchmark's naive baseline lives with the benchmark (:mod:`benchmarks.engine`).

The numbers behind the evaluator -- the Gram matrix :attr:`gram`, the
triangular factor :attr:`factor`, the SSE floor -- are public: the branch and
bound (:mod:`spm_sysid.core.search.certify`) searches over the same problem with
them, and :meth:`with_criterion` gives an evaluator of another criterion that
shares them (a :class:`~spm_sysid.core.fit.problem.Problem` computes them once).
"""

from __future__ import annotations

import copy
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..compiled.kernels import fit_structures, qr_structures
from ..cores import usable_cores
from ..defaults import FACTOR_SLICE_BYTES
from ..model.uncertainty import solve_upper
from .criteria import Criterion, get_criterion
from .lstsq import DEFAULT_RANK_TOL, column_norms, sse_floor

#: Structures the Gram path accepts with a smallest squared pivot below
#: NEAR_RANK * rank_tol have their rank (and fit) decided by QR, as the reference fit
#: decides it: there the Gram matrix's squared condition number makes pivots unreliable.
NEAR_RANK = 10.0

#: A batch whose fits cost more than this (sum over its structures of k^3 less the
#: cube of the prefix shared with the one before) is split
#: in two halves fitted on two threads (numba's JIT, which releases the GIL): with
#: hundreds of candidate terms a generation's fits take tens of milliseconds, and the
#: halves give the same numbers (each structure is factorised the same way whether
#: or not its prefix was shared). Small batches (the paper's space: ~4e4) stay on one.
PARALLEL_FIT_WORK = 5e6

#: Near-threshold structures scoring within this of the best value seen are decided by
#: QR in :meth:`StructureEvaluator.evaluate` (an Akaike roulette weight of exp(-25)).
ARBITRATION_WINDOW = 50.0

__all__ = ["StructureEvaluator", "key_mask", "mask_key", "structure_keys"]


def structure_keys(masks: np.ndarray) -> np.ndarray:
    """One hashable key per structure: its bits packed into bytes. Shape (B,).

    Any number of candidate terms (``ceil(M / 8)`` bytes per key); ``tolist()``
    gives ``bytes`` objects for dictionaries, ``np.unique`` works on the array.
    """
    masks = np.asarray(masks, dtype=bool)
    packed = np.ascontiguousarray(np.packbits(masks, axis=-1, bitorder="little"))
    return packed.view(np.dtype((np.void, packed.shape[-1]))).reshape(masks.shape[:-1])


def mask_key(mask: np.ndarray) -> bytes:
    """One structure's key for a dictionary: its bits packed (numpy's default bit order).

    The order of keys that tie on a value follows from these bytes (finalists
    are sorted by value, then key), so it must not change.
    """
    return np.packbits(mask).tobytes()


def key_mask(key: bytes, n_terms: int) -> np.ndarray:
    """The structure of a :func:`mask_key` (a bool mask of ``n_terms``)."""
    return np.unpackbits(np.frombuffer(key, dtype=np.uint8))[:n_terms].astype(bool)


#: Bytes one cached score takes besides its key (the bytes object's header, the float,
#: the dictionary's slot), measured with tracemalloc on CPython 3.11.
CACHE_ENTRY_BYTES = 140

#: The share of the memory bound the cache of scores may take.
CACHE_SHARE = 0.1

#: Entries the cache keeps at least (a bound of a few MB still leaves room for a GA run)
#: and at most.
CACHE_ENTRIES = (20_000, 2_000_000)


def cache_capacity(n_terms: int) -> int:
    """Scores the cache may hold: :data:`CACHE_SHARE` of the memory bound, within limits."""
    from ..memory import memory_limit

    limit, _ = memory_limit()
    per_entry = CACHE_ENTRY_BYTES + (n_terms + 7) // 8
    low, high = CACHE_ENTRIES
    return int(max(low, min(high, CACHE_SHARE * limit / per_entry)))


#: Bytes a batch's fit works in at a time (its index arrays, about 8 per term and
#: structure); larger batches are fitted slice by slice.
FIT_SLICE_BYTES = 8 << 20


def _factors(P: np.ndarray, target: np.ndarray, columns: np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The columns' norms, and the Gram matrix and triangular factor of unit-norm ``[P y]``.

    Slice by slice (:data:`~spm_sysid.core.defaults.FACTOR_SLICE_BYTES`: the Gram
    matrix summed, the triangular factor updated by the QR of the factor so far
    stacked on the next rows) for long records; a record of one
    slice takes the one-pass route of earlier versions, so its numbers are unchanged.
    """
    m = P.shape[1] if columns is None else len(columns)
    rows = max(m + 1, FACTOR_SLICE_BYTES // (8 * (m + 1)))

    def block(a: int, b: int) -> np.ndarray:
        return P[a:b] if columns is None else P[a:b][:, columns]

    if P.shape[0] <= rows:
        X = block(0, P.shape[0])
        norms = np.linalg.norm(X, axis=0)
        aug = np.column_stack([X / np.where(norms > 0, norms, 1.0), target])
        return norms, aug.T @ aug, np.linalg.qr(aug, mode="r")
    norms = column_norms(P) if columns is None else column_norms(P)[columns]
    inverse = 1.0 / np.where(norms > 0, norms, 1.0)
    gram = np.zeros((m + 1, m + 1))
    r = np.zeros((0, m + 1))
    for a in range(0, P.shape[0], rows):
        aug = np.column_stack([block(a, a + rows) * inverse, target[a:a + rows]])
        gram += aug.T @ aug
        r = np.linalg.qr(np.vstack([r, aug]), mode="r")
    return norms, gram, r


class StructureEvaluator:
    """Scores structures on one data set with one criterion; cached and batched.

    Parameters
    ----------
    P : ndarray, shape (N, n_terms)
        Regression matrix (see :meth:`TermSpace.regression_matrix`).
    target : ndarray, shape (N,)
        y(t) for the regression rows.
    criterion : str, Criterion or callable
        See :func:`spm_sysid.core.fit.criteria.get_criterion`.
    rank_tol : float
        See the module docstring.
    sse_scale : float
        Factor from the SSE of ``target`` to the SSE in the user's units (when
        the caller scaled the data).
    max_terms : int
        Structures of more terms score +inf (0: no limit).
    columns : ndarray of int, optional
        The columns of ``P`` to score (None: all), read a slice of rows at a
        time: no copy of the selected columns is made.

    Attributes
    ----------
    gram : ndarray, shape (n_terms + 2, n_terms + 2)
        Gram matrix of the unit-norm ``[P y]`` (target at index n_terms) and an
        all-zero dummy index (n_terms + 1) that pads structures in a batch.
    factor : ndarray, shape (min(N, n_terms + 1), n_terms + 2)
        Triangular factor of the same ``[P y]`` (the least-squares problem in
        fewer rows), with a zero dummy column.
    zero_columns : ndarray of bool, shape (n_terms,)
        Columns that are zero on every row (a structure using one is rank-deficient).
    column_norms : ndarray, shape (n_terms,)
        Norms of P's columns (1 for zero columns).
    target_norm : float
        Norm of the target (1 for a zero target).
    sse_floor : float
        SSE below which a fit counts as exact (:func:`~spm_sysid.core.fit.lstsq.sse_floor`).
    evaluations : int
        Structures actually fitted (cache misses).
    lookups : int
        Structures asked for, including repeats.
    cache_capacity : int
        Scores the cache holds at most (:func:`cache_capacity`); past it the
        better half is kept (:attr:`pruned` counts the scores let go).
    """

    def __init__(
        self,
        P: np.ndarray,
        target: np.ndarray,
        criterion: str | Criterion = "aic",
        rank_tol: float = DEFAULT_RANK_TOL,
        sse_scale: float = 1.0,
        max_terms: int = 0,
        columns: np.ndarray | None = None,
    ) -> None:
        P = np.asarray(P, dtype=float)
        target = np.asarray(target, dtype=float)
        self.criterion = get_criterion(criterion)
        # SSE of the data as the user gave it = SSE here * sse_scale (identify scales
        # u and y by powers of two, which is exact, so criteria see the user's units)
        self.sse_scale = float(sse_scale)
        self.n = P.shape[0]
        self.n_terms = P.shape[1] if columns is None else len(columns)
        self.rank_tol = rank_tol
        self.max_terms = int(max_terms)
        m = self.n_terms
        gram = np.zeros((m + 2, m + 2))
        norms, gram[: m + 1, : m + 1], r_aug = _factors(P, target, columns)
        self.zero_columns = norms == 0
        self.column_norms = np.where(norms > 0, norms, 1.0)
        self.target_norm = float(np.linalg.norm(target)) or 1.0
        self.sse_floor = sse_floor(float(np.linalg.norm(target)))
        self.gram = gram
        self.factor = np.zeros((r_aug.shape[0], m + 2))
        self.factor[:, : m + 1] = r_aug
        self._reset()

    def _reset(self) -> None:
        self._cache: dict[bytes, float] = {}
        self._best_of_size: dict[int, tuple[float, bytes]] = {}
        self._best = np.inf  # best settled value (see evaluate)
        self.evaluations = 0
        self.lookups = 0
        self.pruned = 0
        self.cache_capacity = cache_capacity(self.n_terms)

    def with_criterion(self, criterion: str | Criterion,
                       max_terms: int | None = None) -> StructureEvaluator:
        """An evaluator of another criterion (and size limit) on the same problem.

        The numbers (Gram matrix, factor) are shared; the cache is new.
        """
        other = copy.copy(self)
        other.criterion = get_criterion(criterion)
        if max_terms is not None:
            other.max_terms = int(max_terms)
        other._reset()
        return other

    def without(self, columns: np.ndarray) -> StructureEvaluator:
        """A copy with ``columns`` (a mask) left out of every search's moves.

        Marked as zero columns, which the branch and bound and forward selection
        leave out; scores are unchanged, so the cache is shared.
        """
        other = copy.copy(self)
        other.zero_columns = self.zero_columns | np.asarray(columns, dtype=bool)
        return other

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
            best = self._best_of_size
            for key, size, value in zip(todo.keys(), masks[rows].sum(axis=1).tolist(),
                                        values.tolist()):
                if np.isfinite(value) and (size not in best or value < best[size][0]):
                    best[size] = (value, key)
        out = np.fromiter((cache[k] for k in keys.tolist()), dtype=float, count=len(keys))
        if len(cache) > self.cache_capacity:
            self._prune()
        return out

    def _prune(self) -> None:
        """Keep the better half of the cache (the best of every size is kept apart)."""
        keep = sorted(self._cache.items(), key=lambda item: item[1])
        keep = keep[:self.cache_capacity // 2]
        self.pruned += len(self._cache) - len(keep)
        self._cache = dict(keep)

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

    def best_per_size(self) -> np.ndarray:
        """The best-scoring structure of every size scored so far, by size (masks)."""
        best = self._best_of_size
        if not best:
            return np.zeros((0, self.n_terms), dtype=bool)
        keys = [best[k][1] for k in sorted(best)]
        packed = np.frombuffer(b"".join(keys), dtype=np.uint8)
        bits = np.unpackbits(packed.reshape(len(keys), -1), axis=1, bitorder="little")
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
            sse2, beta2, bad2, _ = self._fit(masks[redo], arbitrate=True, all_near=True)
            values[redo] = self._values(sse2, k[redo], beta2, bad2)
        settled = np.isfinite(values) & (~near | redo)
        if settled.any():
            self._best = min(best, float(values[settled].min()))
        return values

    def _values(self, sse, k, beta, bad) -> np.ndarray:
        sse = np.maximum(sse, self.sse_floor)  # exact fits: see lstsq.sse_floor
        with np.errstate(invalid="ignore", divide="ignore"):
            values = self.criterion(sse * self.sse_scale, self.n, k, beta)
        too_big = (k > self.max_terms) if self.max_terms else False
        return np.where(bad | (k == 0) | too_big | ~np.isfinite(values), np.inf, values)

    def fit_batch(self, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """SSE, standardised coefficients and rank-deficiency flags for a batch.

        One compiled call (:func:`~spm_sysid.core.compiled.kernels.fit_structures`)
        fits every structure at its own size. Every structure accepted with a
        pivot near ``rank_tol`` is decided by QR (as the reference).

        Returns
        -------
        sse : ndarray, shape (B,)  NaN where rank-deficient
        beta : ndarray, shape (B, n_terms), or None when the criterion needs none
        bad : ndarray of bool, shape (B,)  rank-deficient structures
        """
        return self._fit(np.asarray(masks, dtype=bool), arbitrate=True)[:3]

    def _fit(self, masks: np.ndarray, arbitrate: bool, all_near: bool = False):
        """Return ``(sse, beta, bad, near)`` for a batch (see :meth:`_fit_sorted`).

        ``near`` marks accepted structures near the rank threshold that were not
        decided by QR (all False with ``arbitrate``). ``all_near``: the batch is
        structures a previous call marked ``near``; QR decides them all directly.
        """
        # lexicographic order of the term lists: neighbours share factorised prefixes
        order = np.lexsort(~masks.T[::-1]) if len(masks) > 1 else np.arange(len(masks))
        # in slices of bounded memory (a polish's neighbourhood of a large space holds tens
        # of thousands of structures); each structure is factorised the same way in any slice
        step = max(1, FIT_SLICE_BYTES // (8 * (masks.shape[1] + 1)))
        parts = [self._fit_sorted(masks[order[i:i + step]], arbitrate, all_near)
                 for i in range(0, len(order), step)] or [
            self._fit_sorted(masks[order], arbitrate, all_near)]
        sse, bad, near = (np.concatenate([p[j] for p in parts]) for j in (0, 2, 3))
        beta = None if parts[0][1] is None else np.concatenate([p[1] for p in parts])
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        return (sse[back], None if beta is None else beta[back], bad[back], near[back])

    def _fit_sorted(self, masks: np.ndarray, arbitrate: bool, all_near: bool = False):
        rows, cols = np.nonzero(masks)
        offsets = np.zeros(len(masks) + 1, dtype=np.int64)
        np.cumsum(masks.sum(axis=1), out=offsets[1:])
        sse = np.empty(len(masks))
        theta = np.zeros(len(cols))
        bad = np.empty(len(masks), dtype=np.bool_)
        minpiv = np.empty(len(masks))
        idx = cols.astype(np.int64)
        if all_near:  # known near the threshold (and Gram-accepted): QR decides
            near = np.ones(len(masks), dtype=bool)
        else:
            _batched(fit_structures, (self.gram, self.factor), idx, offsets, masks,
                     (float(self.rank_tol), self.target_norm, self.n,
                      self.criterion.needs_coefficients),
                     ((sse, "b"), (theta, "i"), (bad, "b"), (minpiv, "b")))
            # Gram-accepted structures near the threshold: QR has the last word (a
            # structure the Gram matrix rejects stays rejected -- never the one selected)
            near = ~bad & (minpiv < NEAR_RANK * self.rank_tol)
        if arbitrate and near.any():  # one compiled call (qr_structures), sorted as here
            which = np.flatnonzero(near)
            sizes = offsets[which + 1] - offsets[which]
            sub_offsets = np.zeros(len(which) + 1, dtype=np.int64)
            np.cumsum(sizes, out=sub_offsets[1:])
            take = np.concatenate([np.arange(offsets[b], offsets[b + 1]) for b in which])
            sub_sse, sub_theta = np.empty(len(which)), np.zeros(len(take))
            sub_bad = np.empty(len(which), dtype=np.bool_)
            _batched(qr_structures, (self.factor,), idx[take], sub_offsets, masks[which],
                     (float(self.rank_tol),),
                     ((sub_sse, "b"), (sub_theta, "i"), (sub_bad, "b")))
            sse[which], theta[take], bad[which] = sub_sse, sub_theta, sub_bad
            near[:] = False
        beta = None
        if self.criterion.needs_coefficients:
            beta = np.zeros(masks.shape)
            keep = ~bad[rows]
            beta[rows[keep], cols[keep]] = theta[keep] / self.target_norm
        return sse, beta, bad, near

    def _qr_fit(self, cols: np.ndarray) -> tuple[float, np.ndarray, bool]:
        """SSE, coefficients and rank flag of one structure by Householder QR.

        For structures whose Gram pivots come near ``rank_tol``: squaring the
        condition number in the Gram matrix makes those pivots unreliable, so
        the rank is decided as the reference fit decides it, on the triangular
        factor of ``[P y]`` (the same least-squares problem in fewer rows).
        """
        k = len(cols)
        # R of [A t] alone (no Q): its last diagonal entry is the residual's norm
        R = np.linalg.qr(np.column_stack([self.factor[:, cols], self.factor[:, self.n_terms]]),
                         mode="r")
        if np.min(np.diag(R)[:k] ** 2) < self.rank_tol:
            return np.nan, np.zeros(k), True
        th = solve_upper(R[:k, :k], R[:k, k])
        return float(R[k, k] ** 2) if R.shape[0] > k else 0.0, th, False


def _shared_prefix(masks: np.ndarray) -> np.ndarray:
    """Terms each structure shares, as a leading run, with the one before it (first: 0).

    What a kernel does not factorise again in a sorted batch (see :func:`_batched`).
    """
    shared = np.zeros(len(masks), dtype=np.int64)
    if len(masks) > 1:
        differ = masks[1:] != masks[:-1]
        first = np.where(differ.any(axis=1), differ.argmax(axis=1), masks.shape[1])
        before = np.zeros((len(masks) - 1, masks.shape[1] + 1), dtype=np.int64)
        np.cumsum(masks[1:], axis=1, out=before[:, 1:])
        shared[1:] = before[np.arange(len(first)), first]
    return shared


def _batched(kernel, leading: tuple, idx: np.ndarray, offsets: np.ndarray, masks: np.ndarray,
             trailing: tuple, outputs: tuple) -> None:
    """``kernel(*leading, idx, offsets, *trailing, *outputs)`` on a sorted batch.

    ``outputs`` are (array, "b") per structure or (array, "i") per entry of
    ``idx``; ``masks`` are the batch's structures (sorted). A batch worth
    more than :data:`PARALLEL_FIT_WORK` (k^3 less shared^3 per structure: the
    factorisation a kernel does) runs as two halves of about equal work on two
    threads (numba's JIT: it releases the GIL); each structure is computed the
    same way, so the numbers are the same.
    """
    n = len(offsets) - 1
    k3 = np.diff(offsets).astype(float) ** 3
    work = k3
    if n > 1 and k3.sum() > PARALLEL_FIT_WORK:  # (small batches: not worth counting)
        work = k3 - _shared_prefix(masks).astype(float) ** 3
    pool = _fit_pool() if n > 1 and work.sum() > PARALLEL_FIT_WORK else None
    if pool is None:
        kernel(*leading, idx, offsets, *trailing, *(a for a, _ in outputs))
        return
    # cut before structure c: the second half factorises structure c from scratch
    before = np.cumsum(work)[:-1]
    after = work.sum() - before - work[1:] + k3[1:]
    cut = int(np.argmin(np.maximum(before, after))) + 1
    lo = int(offsets[cut])
    halves = [(slice(0, cut), slice(0, lo), offsets[:cut + 1]),
              (slice(cut, n), slice(lo, int(offsets[-1])), offsets[cut:] - lo)]
    runs = [pool.submit(kernel.jit, *leading, idx[e], np.ascontiguousarray(o), *trailing,
                        *(a[b] if kind == "b" else a[e] for a, kind in outputs))
            for b, e, o in halves]
    for run in runs:
        run.result()


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _fit_pool() -> ThreadPoolExecutor | None:
    """Two threads for large batches (None on one core)."""
    global _POOL
    if usable_cores() < 2:
        return None
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(2, thread_name_prefix="spm-fit")
    return _POOL
