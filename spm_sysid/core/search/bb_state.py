"""The branch and bound's state: the problem's numbers, the open nodes, a worker's scratch.

Three named tuples that numba compiles like structs (:mod:`.branch_bound` works
on them): :class:`Data`, the problem's numbers; :class:`Heap`, the open nodes,
the incumbent and the counters (indexed by :data:`OPEN`, :data:`EXPANDED`, ...);
:class:`Work`, one worker's scratch arrays, allocated once (:func:`workspace`).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

__all__ = ["COUNTERS", "DONE", "EXPANDED", "FULL", "NEAR_BRANCHES", "OFFERED", "OPEN",
           "PAUSED", "PENDING", "Data", "Heap", "Work", "words_for", "workspace"]

#: :func:`expand` results.
DONE, PAUSED, FULL = 0, 1, 2

#: The counters of a :class:`Heap`, by position.
OPEN, EXPANDED, OFFERED, NEAR_BRANCHES, PENDING = range(5)
COUNTERS = ("open", "expanded", "offered", "near_branches", "pending")

#: The problem's numbers: ``gram`` (m + 1, m + 1) of the unit-norm candidates and the
#: target (last), ``r_ext`` their triangular factor, ``pen`` the penalty of each size,
#: ``n``/``scale``/``floor`` the rows, SSE scale and SSE floor, ``rank_tol`` the
#: smallest squared pivot of an identifiable structure, ``tol`` the pruning tolerance,
#: ``near`` the squared pivot below which the evaluator decides a candidate.
Data = namedtuple("Data", "gram r_ext pen n scale floor rank_tol tol near")

#: The open nodes (a binary heap on ``bound``; ``inside``/``free`` are term masks in
#: 64-bit words), the ``counts`` (see :data:`COUNTERS`), the incumbent ``best`` (1,)
#: and ``best_mask``, and ``pending``: candidates whose rank the evaluator decides.
Heap = namedtuple("Heap", "bound inside free counts best best_mask pending")

#: One worker's scratch space (see :func:`workspace`).
Work = namedtuple("Work", [
    "inside", "free", "child_in", "child_free", "members", "cols", "cand", "chain",
    "order", "L", "Lc", "piv", "Winv", "Hff", "pcost", "pairs", "Q", "At", "S", "cvec",
    "exact", "small", "chosen", "lrow", "wbuf", "gbuf", "pick", "edges", "deg", "gone",
    "theta", "theta2", "r", "g", "delta", "hdiag", "column", "drop", "prefmin", "wvals",
    "cored", "Ht"])


def workspace(m: int, rows: int, nw: int) -> Work:
    """Scratch arrays for a search over m terms (``rows``: rows of r_ext; ``nw`` words)."""
    z, e = np.zeros, np.empty
    i64 = np.int64
    return Work(
        inside=z(nw, np.uint64), free=z(nw, np.uint64), child_in=z(nw, np.uint64),
        child_free=z(nw, np.uint64), members=e(m, i64), cols=e(m + 1, i64),
        cand=e(m + 1, i64), chain=e(m + 1, i64), order=e(m + 1, i64), L=z((m + 1, m + 1)),
        Lc=z((m + 1, m + 1)), piv=z(m + 1), Winv=z((m, m)), Hff=z((m, m)),
        pcost=z((m, m)), pairs=z((m, m)), Q=z((rows, m + 1)), At=z((rows, m + 1)),
        S=z((m, m)), cvec=z(m), exact=z(m + 1), small=z(m + 1), chosen=z((m + 1, m + 1), i64),
        lrow=z((m + 1, m + 1)), wbuf=z(m + 1), gbuf=z(m + 1), pick=z(m + 1, i64),
        edges=e(max(m * m, 1)), deg=e(m, i64), gone=z(m, np.bool_), theta=e(m + 1),
        theta2=e(m + 1), r=e(rows), g=e(m + 1), delta=e(m), hdiag=e(m), column=e(m),
        drop=e(m + 1), prefmin=e(m + 1), wvals=e(m + 1), cored=z(m + 1, np.bool_),
        Ht=z((m + 1, rows)))


def words_for(m: int) -> int:
    """64-bit words of a term mask of m terms."""
    return max(1, (m + 63) // 64)
