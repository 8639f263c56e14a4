"""Compiled branch and bound over term subsets (the engine of :mod:`.certify`).

A node fixes the terms I *in* and leaves the terms F *free*; its structures
are the S with ``I <= S <= T = I + F``. One call of :func:`expand` pops the
open node of the lowest bound (best first), factorises T once and then walks
its whole "in" chain without factorising again:

* T's Gram sub-matrix (I in index order first, then F) is factorised by an
  up-looking Cholesky. A failing pivot (squared pivot below ``rank_tol``) in I
  shows every structure of the node rank-deficient by the evaluator's own test
  (the pivot of a column can only shrink when columns are added before it), so
  the node is dropped; a failing pivot in F is branched on (in / out).
* ``SSE(T)`` from the residual on the triangular factor of ``[P y]`` after one
  corrected semi-normal step (accurate where the Gram matrix is ill-conditioned),
  the coefficients theta of T, ``H = (G_TT)^-1`` on F and the exact cost of
  leaving out one free term, ``delta_j = theta_j^2 / H_jj``.
* Leaving out any r free terms R costs at least ``D(r) = max(r-th smallest
  delta, (sum of the r smallest theta^2) / ||H_FF||_F)`` (the SSE of a subset is
  at least the SSE after leaving out any one of R; and ``theta_R' H_RR^-1
  theta_R >= ||theta_R||^2 / lambda_max(H_FF)``). A structure of ``|T| - r``
  terms therefore scores at least ``V(SSE(T) + D(r), |T| - r)``; the node's bound
  is the least of these over the sizes it allows.
* F is sorted by delta, largest first, and the chain "F[0] in, F[1] in, ..."
  is walked: chain node p fixes ``I + F[:p]``; its "out" child (``F[p]`` left
  out, ``SSE >= SSE(T) + delta_F[p]`` exactly) is pushed with its own bound; the
  chain stops where its bound reaches the incumbent. The chain's structures
  ``I + F[:p]`` (a greedy path by importance) are scored as incumbents; one that
  looks better is re-fitted accurately before it is accepted.

Values are ``n ln(max(SSE, floor) * scale / n) + pen[k]``, the evaluator's
formula. The heap lives in caller-owned arrays so a search can pause (after
``max_pops`` nodes) to report progress and go on, and grow when full.
"""

from __future__ import annotations

import numpy as np

from .kernels import jit

__all__ = ["DONE", "FULL", "PAUSED", "expand", "words_for"]

#: :func:`expand` results.
DONE, PAUSED, FULL = 0, 1, 2

#: Drop costs count this fraction of themselves (their rounding can be eps * cond).
DROP_SAFETY = 1.0 - 1e-6


def words_for(m: int) -> int:
    """64-bit words of a term mask of m terms."""
    return max(1, (m + 63) // 64)


@jit
def _value(sse, k, n, scale, floor, pen):  # pragma: no cover - compiled
    if k == 0:
        return np.inf
    return n * np.log(max(sse, floor) * scale / n) + pen[k]


@jit
def _push(heap_bound, heap_in, heap_free, size, bound, inside, free):  # pragma: no cover
    i = size
    heap_bound[i] = bound
    heap_in[i, :] = inside
    heap_free[i, :] = free
    while i > 0:
        parent = (i - 1) // 2
        if heap_bound[parent] <= heap_bound[i]:
            break
        heap_bound[parent], heap_bound[i] = heap_bound[i], heap_bound[parent]
        for w in range(heap_in.shape[1]):
            a, b = heap_in[parent, w], heap_free[parent, w]
            heap_in[parent, w], heap_free[parent, w] = heap_in[i, w], heap_free[i, w]
            heap_in[i, w], heap_free[i, w] = a, b
        i = parent
    return size + 1


@jit
def _pop(heap_bound, heap_in, heap_free, size, inside, free):  # pragma: no cover
    bound = heap_bound[0]
    inside[:] = heap_in[0, :]
    free[:] = heap_free[0, :]
    size -= 1
    if size == 0:
        return bound, size
    heap_bound[0] = heap_bound[size]
    heap_in[0, :] = heap_in[size, :]
    heap_free[0, :] = heap_free[size, :]
    i = 0
    while True:
        left = 2 * i + 1
        if left >= size:
            break
        child = left
        if left + 1 < size and heap_bound[left + 1] < heap_bound[left]:
            child = left + 1
        if heap_bound[i] <= heap_bound[child]:
            break
        heap_bound[child], heap_bound[i] = heap_bound[i], heap_bound[child]
        for w in range(heap_in.shape[1]):
            a, b = heap_in[child, w], heap_free[child, w]
            heap_in[child, w], heap_free[child, w] = heap_in[i, w], heap_free[i, w]
            heap_in[i, w], heap_free[i, w] = a, b
        i = child
    return bound, size


@jit
def _cholesky_rows(gram, cols, start, stop, L):  # pragma: no cover - compiled
    """Rows start..stop-1 of the up-looking Cholesky factor of gram[cols, cols].

    A non-positive pivot leaves a zero diagonal (its column then counts as
    dependent for the rows after it); returns the first such row, or -1.
    ``L[j, j] ** 2`` is the squared pivot of row j.
    """
    first = -1
    for j in range(start, stop):
        cj = cols[j]
        for i in range(j):
            acc = gram[cj, cols[i]]
            for p in range(i):
                acc -= L[j, p] * L[i, p]
            L[j, i] = acc / L[i, i] if L[i, i] > 0.0 else 0.0
        d = gram[cj, cj]
        for p in range(j):
            d -= L[j, p] * L[j, p]
        if d > 0.0:
            L[j, j] = np.sqrt(d)
        else:
            L[j, j] = 0.0
            if first < 0:
                first = j
    return first


@jit
def _refined_sse(L, r_ext, cols, k, yi, theta, r, g):  # pragma: no cover - compiled
    """SSE of the columns cols[:k] on r_ext (one corrected semi-normal step).

    theta: the coefficients, solved from the factor L (target row k), then refined.
    """
    rows = r_ext.shape[0]
    for j in range(k - 1, -1, -1):  # L^T theta = z (z: the target's row of L)
        acc = L[k, j]
        for p in range(j + 1, k):
            acc -= L[p, j] * theta[p]
        theta[j] = acc / L[j, j]
    for rnd in range(2):
        for q in range(rows):
            acc = r_ext[q, yi]
            for j in range(k):
                acc -= r_ext[q, cols[j]] * theta[j]
            r[q] = acc
        if rnd == 1:
            break
        for j in range(k):
            acc = 0.0
            for q in range(rows):
                acc += r_ext[q, cols[j]] * r[q]
            g[j] = acc
        for j in range(k):
            acc = g[j]
            for p in range(j):
                acc -= L[j, p] * g[p]
            g[j] = acc / L[j, j]
        for j in range(k - 1, -1, -1):
            acc = g[j]
            for p in range(j + 1, k):
                acc -= L[p, j] * g[p]
            g[j] = acc / L[j, j]
        for j in range(k):
            theta[j] += g[j]
    sse = 0.0
    for q in range(rows):
        sse += r[q] * r[q]
    return sse


@jit
def _set_bit(words, j):  # pragma: no cover - compiled
    words[j // 64] |= np.uint64(1) << np.uint64(j % 64)


@jit
def _clear_bit(words, j):  # pragma: no cover - compiled
    words[j // 64] &= ~(np.uint64(1) << np.uint64(j % 64))


@jit
def _members(words, m, out):  # pragma: no cover - compiled
    count = 0
    for j in range(m):
        if (words[j // 64] >> np.uint64(j % 64)) & np.uint64(1):
            out[count] = j
            count += 1
    return count


@jit
def expand(gram, r_ext, pen, n, scale, floor, rank_tol, tol, heap_bound, heap_in,
           heap_free, counts, best, best_mask, max_pops):  # pragma: no cover - compiled
    """Expand up to ``max_pops`` nodes, best first (see the module doc).

    Parameters
    ----------
    gram : ndarray, shape (m + 1, m + 1)
        Gram matrix of the unit-norm candidate columns and the target (last).
    r_ext : ndarray, shape (rows, m + 1)
        Triangular factor of the same ``[P y]``.
    pen : ndarray, shape (m + 1,)
        Penalty of each size.
    n, scale, floor : float
        Rows, SSE scale and SSE floor of the criterion (the evaluator's).
    rank_tol, tol : float
        Smallest squared pivot of an identifiable structure; pruning tolerance.
    heap_bound, heap_in, heap_free : ndarray
        The open nodes (a binary heap on the bound); in/free are term masks.
    counts : ndarray of int64, shape (3,)
        In/out: open nodes, nodes expanded so far, candidate structures scored.
    best : ndarray, shape (1,)
        In/out: the incumbent's value.
    best_mask : ndarray of bool, shape (m,)
        In/out: the incumbent.
    max_pops : int
        Nodes to expand in this call.

    Returns
    -------
    int
        :data:`DONE` (no open node can beat the incumbent: proved), :data:`PAUSED`
        or :data:`FULL` (the heap needs room).
    """
    m = gram.shape[0] - 1
    yi = m
    nw = heap_in.shape[1]
    cap = heap_bound.shape[0]
    rows = r_ext.shape[0]
    inside = np.zeros(nw, dtype=np.uint64)
    free = np.zeros(nw, dtype=np.uint64)
    child_in = np.zeros(nw, dtype=np.uint64)
    child_free = np.zeros(nw, dtype=np.uint64)
    members = np.empty(m, dtype=np.int64)
    cols = np.empty(m + 1, dtype=np.int64)
    chain = np.empty(m + 1, dtype=np.int64)
    L = np.zeros((m + 1, m + 1))
    L2 = np.zeros((m + 1, m + 1))
    Winv = np.zeros((m, m))
    theta = np.empty(m + 1)
    theta2 = np.empty(m + 1)
    r = np.empty(rows)
    g = np.empty(m + 1)
    delta = np.empty(m)
    hdiag = np.empty(m)
    dsort = np.empty(m)
    tsort = np.empty(m)
    drop = np.empty(m + 1)
    wvals = np.empty(m + 1)
    prefmin = np.empty(m + 1)
    pops = 0
    size = counts[0]
    while True:
        if size == 0 or heap_bound[0] >= best[0] - tol:
            counts[0] = size
            return DONE
        if pops >= max_pops:
            counts[0] = size
            return PAUSED
        if size + m + 2 > cap:
            counts[0] = size
            return FULL
        bound0, size = _pop(heap_bound, heap_in, heap_free, size, inside, free)
        if bound0 >= best[0] - tol:
            continue
        pops += 1
        counts[1] += 1
        k = _members(inside, m, members)
        for j in range(k):
            cols[j] = members[j]
        f = _members(free, m, members)
        for j in range(f):
            cols[k + j] = members[j]
        t = k + f
        cols[t] = yi
        # --- factorise T; rank-deficient I: nothing identifiable below this node
        _cholesky_rows(gram, cols, 0, t, L)
        weak = -1
        for j in range(t):
            if not L[j, j] * L[j, j] > rank_tol:
                weak = j
                break
        if 0 <= weak < k:
            continue
        if weak >= k:  # a free term nearly dependent on the others: branch on it
            c = cols[weak]
            child_in[:] = inside
            child_free[:] = free
            _clear_bit(child_free, c)
            size = _push(heap_bound, heap_in, heap_free, size, bound0, child_in, child_free)
            _set_bit(child_in, c)
            size = _push(heap_bound, heap_in, heap_free, size, bound0, child_in, child_free)
            continue
        _cholesky_rows(gram, cols, t, t + 1, L)
        sse_t = _refined_sse(L, r_ext, cols, t, yi, theta, r, g)
        # --- the cost of leaving out each free term: delta_j = theta_j^2 / H_jj
        if f > 0:
            for a in range(f):  # Winv = inverse of L's free block (lower triangular)
                for b in range(f):
                    Winv[a, b] = 0.0
            for b in range(f):
                Winv[b, b] = 1.0 / L[k + b, k + b]
                for a in range(b + 1, f):
                    acc = 0.0
                    for p in range(b, a):
                        acc -= L[k + a, k + p] * Winv[p, b]
                    Winv[a, b] = acc / L[k + a, k + a]
            frob = 0.0  # ||H_FF||_F, H_FF = Winv^T Winv
            for a in range(f):
                for b in range(a, f):
                    acc = 0.0
                    for p in range(b, f):
                        acc += Winv[p, a] * Winv[p, b]
                    if a == b:
                        hdiag[a] = acc
                        frob += acc * acc
                    else:
                        frob += 2.0 * acc * acc
            frob = np.sqrt(frob)
            for a in range(f):
                delta[a] = theta[k + a] * theta[k + a] / hdiag[a]
                dsort[a] = delta[a]
                tsort[a] = theta[k + a] * theta[k + a]
            dsort[:f].sort()
            tsort[:f].sort()
            # D(r): least SSE increase from leaving out r free terms
            drop[0] = 0.0
            cum = 0.0
            for q in range(1, f + 1):
                cum += tsort[q - 1]
                drop[q] = DROP_SAFETY * max(dsort[q - 1], cum / frob)
        else:
            drop[0] = 0.0
        # wvals[q]: the best any structure of t - q terms here could score
        best_q = np.inf
        for q in range(f + 1):
            wvals[q] = _value(sse_t + drop[q], t - q, n, scale, floor, pen)
            best_q = min(best_q, wvals[q])
            prefmin[q] = best_q
        # --- the chain, F by delta, largest first; its structures as incumbents
        order = np.argsort(-delta[:f])
        for a in range(f):
            chain[a] = cols[k + order[a]]
        for a in range(k):
            L2[a, :a + 1] = L[a, :a + 1]
        for a in range(f):
            cols[k + a] = chain[a]
        _cholesky_rows(gram, cols, k, t + 1, L2)
        good = t
        for j in range(k, t):
            if not L2[j, j] * L2[j, j] > 10.0 * rank_tol:
                good = j
                break
        ssq = gram[yi, yi]
        for j in range(k):
            ssq -= L2[t, j] * L2[t, j]
        for p in range(f + 1):  # structure I + chain[:p]
            kk = k + p
            if p > 0:
                ssq -= L2[t, kk - 1] * L2[t, kk - 1]
            if kk == 0 or kk > good:
                continue
            if _value(ssq, kk, n, scale, floor, pen) < best[0] - tol:
                # accurate fit of the prefix: its own factor, target row included
                for a in range(kk):
                    L[a, :a + 1] = L2[a, :a + 1]
                cols[kk] = yi
                _cholesky_rows(gram, cols, kk, kk + 1, L)
                value = _value(_refined_sse(L, r_ext, cols, kk, yi, theta2, r, g), kk,
                               n, scale, floor, pen)
                counts[2] += 1
                if value < best[0]:
                    best[0] = value
                    best_mask[:] = False
                    for a in range(kk):
                        best_mask[cols[a]] = True
                cols[kk] = chain[p] if p < f else yi
        # --- walk the chain: node p fixes I + chain[:p]
        child_in[:] = inside
        for p in range(f):
            bound_p = max(bound0, prefmin[f - p])
            if bound_p >= best[0] - tol:
                break
            # out child: chain[p] left out, chain[p+1:] free
            dp = DROP_SAFETY * delta[order[p]]
            ob = np.inf
            for q in range(1, f - p + 1):
                ob = min(ob, _value(sse_t + max(dp, drop[q]), t - q, n, scale, floor, pen))
            ob = max(ob, bound_p)
            if ob < best[0] - tol:
                child_free[:] = 0
                for a in range(p + 1, f):
                    _set_bit(child_free, chain[a])
                size = _push(heap_bound, heap_in, heap_free, size, ob, child_in, child_free)
            _set_bit(child_in, chain[p])
