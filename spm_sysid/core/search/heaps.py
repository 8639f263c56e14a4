"""The branch and bound's bookkeeping: open nodes per worker, shared incumbent, memory.

Each search worker keeps its open nodes in a heap of arrays that the compiled
search (:mod:`spm_sysid.core.search.branch_bound`) fills and drains; workers
share the best incumbent and are rebalanced when one runs short. The memory a
certification needs is known before anything is built.
"""

from __future__ import annotations

import numpy as np

from ..fit.evaluator import CACHE_ENTRY_BYTES, StructureEvaluator, cache_capacity
from ..memory import check_memory
from .branch_bound import (
    COUNTERS,
    EXPANDED,
    OPEN,
    PENDING,
    Data,
    Heap,
    expand,
    words_for,
    workspace,
)

__all__ = ["DEEP_FACTOR", "MAX_OPEN_BYTES", "OpenNodes", "balance", "cache_bytes",
           "check_certify_memory",
           "lower_bound", "settle", "setup_bytes", "share_best", "worker_bytes"]


#: A node may enumerate up to this many times its budget of subsets (certify.py,
#: ENUMERATION_BUDGET) where the next size up is left open.
DEEP_FACTOR = 4

#: Open nodes (all workers') may use at most this much memory before the search stops
#: with ``limit`` (less when the memory bound leaves less; :mod:`spm_sysid.core.memory`).
MAX_OPEN_BYTES = 1 << 30


def setup_bytes(rows: int, m: int) -> float:
    """Memory to set a certification of ``m`` candidates on ``rows`` rows up.

    The regression matrix and its scaled copy, the evaluator's ``[P y]`` and QR
    work space, its Gram matrix and triangular factor, and the search's copies of
    both.
    """
    r = min(rows, m + 1)
    return 8.0 * (4 * rows * (m + 1) + 2 * (m + 2) ** 2 + 2 * r * (m + 2))


def worker_bytes(rows: int, m: int) -> float:
    """Memory of one search worker's scratch space (about 14 (m+1)^2 + 3 r (m+1) numbers)."""
    r = min(rows, m + 1)
    return 8.0 * (14 * (m + 1) ** 2 + 3 * r * (m + 1))


def check_certify_memory(rows: int, m: int) -> None:
    """Refuse, before anything is built, a certification the memory bound cannot hold.

    Raises
    ------
    MemoryLimitError
        The set-up plus one search worker would exceed the bound.
    """
    check_memory(setup_bytes(rows, m) + worker_bytes(rows, m) + cache_bytes(m),
                 f"certifying {m} candidate terms on {rows} rows")


def cache_bytes(m: int) -> float:
    """Memory the evaluator's cache of scores may take (it is bounded: :func:`cache_capacity`)."""
    return float(cache_capacity(m) * (CACHE_ENTRY_BYTES + (m + 7) // 8))


def settle(ev: StructureEvaluator, usable: np.ndarray, rows: np.ndarray, best: np.ndarray,
            best_mask: np.ndarray) -> None:
    """Score the search's near rank-deficient candidates with the evaluator."""
    bits = np.unpackbits(rows.view(np.uint8).reshape(len(rows), -1), axis=1,
                         bitorder="little")[:, :len(usable)].astype(bool)
    masks = np.zeros((len(rows), ev.n_terms), dtype=bool)
    masks[:, usable] = bits
    scores = ev.score(masks)
    i = int(np.argmin(scores))
    if scores[i] < best[0]:
        best[0] = scores[i]
        best_mask[:] = bits[i]


class OpenNodes:
    """One worker of the search: open nodes, incumbent, counters, scratch space.

    The open nodes are a heap in arrays the compiled search fills; the counters
    are named in :data:`~.branch_bound.COUNTERS`.
    """

    def __init__(self, mu: int, rows: int, best: float, best_mask: np.ndarray, share: int = 1,
                 open_bytes: int = MAX_OPEN_BYTES) -> None:
        self.nw = words_for(mu)
        cap = 1 << 12
        self.bound = np.empty(cap)
        self.inside = np.zeros((cap, self.nw), dtype=np.uint64)
        self.free = np.zeros((cap, self.nw), dtype=np.uint64)
        self.counts = np.zeros(len(COUNTERS), dtype=np.int64)
        self.pending = np.zeros((max(4096, 4 * mu + 8), self.nw), dtype=np.uint64)
        self.best = np.array([best])
        self.best_mask = np.asarray(best_mask, dtype=bool).copy()
        self.max_open = open_bytes // share // (8 + 16 * self.nw)
        self.work = workspace(mu, rows, self.nw)

    @property
    def size(self) -> int:
        return int(self.counts[OPEN])

    @property
    def nodes(self) -> int:
        return int(self.counts[EXPANDED])

    @property
    def heap(self) -> Heap:
        """The arrays as the compiled search takes them (rebuilt after a resize)."""
        return Heap(self.bound, self.inside, self.free, self.counts, self.best,
                    self.best_mask, self.pending)

    def push_root(self, mu: int) -> None:
        self.bound[0] = -np.inf
        self.free[0] = 0
        for j in range(mu):
            self.free[0, j // 64] |= np.uint64(1) << np.uint64(j % 64)
        self.counts[OPEN] = 1

    def open_bound(self) -> float:
        return float(self.bound[0]) if self.size else np.inf

    def expand(self, data: Data, pops: int, budget: int) -> int:
        return expand(data, self.heap, self.work, pops, budget, DEEP_FACTOR * budget)

    def expand_in_parallel(self, data: Data, pops: int, budget: int) -> int:
        """The same on numba's JIT, which releases the GIL (heaps run on threads)."""
        return expand.jit(data, self.heap, self.work, pops, budget, DEEP_FACTOR * budget)

    def settle(self, ev: StructureEvaluator, usable: np.ndarray) -> None:
        """Near rank-deficient candidates: the evaluator decides."""
        if self.counts[PENDING]:
            settle(ev, usable, self.pending[:self.counts[PENDING]], self.best, self.best_mask)
            self.counts[PENDING] = 0

    def resize(self, cap: int) -> None:
        keep = self.size
        for name in ("bound", "inside", "free"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[:keep] = old[:keep]
            setattr(self, name, new)

    def grow(self) -> bool:
        """Double the room for open nodes; False past :data:`MAX_OPEN_BYTES`."""
        cap = len(self.bound)
        if 2 * cap > self.max_open:
            return False
        self.resize(2 * cap)
        return True


def share_best(heaps: list[OpenNodes]) -> None:
    """Every worker prunes with the best incumbent any has found."""
    top = min(heaps, key=lambda h: h.best[0])
    for h in heaps:
        if h is not top and top.best[0] < h.best[0]:
            h.best[0] = top.best[0]
            h.best_mask[:] = top.best_mask


def lower_bound(heaps: list[OpenNodes]) -> float:
    """No structure scores below this: the least open bound, or the incumbent."""
    return float(min([h.open_bound() for h in heaps] + [heaps[0].best[0]]))


def balance(heaps: list[OpenNodes]) -> None:
    """Deal the open nodes out again, best first, when a worker runs short."""
    sizes = [h.size for h in heaps]
    total = sum(sizes)
    if total < 2 * len(heaps) or min(sizes) * 4 >= max(sizes):
        return
    bound = np.concatenate([h.bound[:h.size] for h in heaps])
    inside = np.concatenate([h.inside[:h.size] for h in heaps])
    free = np.concatenate([h.free[:h.size] for h in heaps])
    order = np.argsort(bound, kind="stable")
    for i, h in enumerate(heaps):
        pick = order[i::len(heaps)]  # sorted: a valid heap
        need = len(pick) + 4096
        if len(h.bound) < need:
            h.resize(1 << int(np.ceil(np.log2(need))))
        h.bound[:len(pick)] = bound[pick]
        h.inside[:len(pick)] = inside[pick]
        h.free[:len(pick)] = free[pick]
        h.counts[OPEN] = len(pick)
