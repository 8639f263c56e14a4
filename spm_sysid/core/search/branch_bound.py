"""Compiled branch and bound over term subsets (the engine of :mod:`.certify`).

A node fixes the terms I *in* and leaves the terms F *free*; its structures
are the S with ``I <= S <= T = I + F``. One call of :func:`expand` pops open
nodes of the lowest bound (best first); for each it factorises T once, bounds
every size ``|I| .. |T|`` and walks its whole "in" chain without factorising
again:

* T's Gram sub-matrix (I in index order first, then F) is factorised by an
  up-looking Cholesky. A failing pivot (squared pivot below ``rank_tol``) in I
  shows every structure of the node rank-deficient by the evaluator's own test
  (the pivot of a column can only shrink when columns are added before it), so
  the node is dropped; a failing pivot in F is branched on (in / out) after
  the node is bounded without the factor: its small sizes exactly and larger
  ones by :func:`_sse_span` (a QR of T with no rank test), cut when that
  reaches the incumbent.
* ``SSE(T)`` from the residual on the triangular factor of ``[P y]`` after one
  corrected semi-normal step (accurate where the Gram matrix is ill-conditioned).
* **Small sizes exactly** (:func:`_project_free`, :func:`_small_sizes`): the
  least SSE of ``I + A`` for every ``|A| <= a``, a as large as ``budget``
  subsets allow (one size more, up to ``deep_budget``, when that size is the
  one left open); their best structures are incumbent candidates.
* **Larger sizes from T down** (:func:`_drop_costs`): leaving out r free terms
  costs at least the r-th smallest single cost ``delta_j = theta_j^2 / H_jj``
  (H: the inverse Gram matrix of T), the r smallest ``theta^2`` over
  ``||H_FF||_F``, and a pair bound (the r terms' dearest pair; each has r - 1
  partners no dearer, and where that size is still open a core of the graph of
  cheap pairs, :func:`_core_bound`, must hold them).
* F sorted by delta, largest first, gives the chain "F[0] in, F[1] in, ...":
  chain node p fixes ``I + F[:p]``; its "out" child (``F[p]`` left out, ``SSE >=
  SSE(T) + delta_F[p]`` exactly) is pushed with its own bound; the chain stops
  where its bound reaches the incumbent. Candidates are refitted accurately
  (:func:`_consider`) before they count.

Values are ``n ln(max(SSE, floor) * scale / n) + pen[k]``, the evaluator's
formula. The heap lives in caller-owned arrays so a search can pause (after
``max_pops`` nodes) to report progress and go on, and grow when full.

The state is :mod:`.bb_state`'s (the problem, the open nodes, a worker's scratch).
:func:`expand` pops nodes and runs the named steps on each:
:func:`_node_columns`, :func:`_factorise`, :func:`_branch_on`, :func:`_fit_all`,
:func:`_bound_sizes` (with :func:`_consider` for incumbents), :func:`_walk_chain`.
"""

from __future__ import annotations

import numpy as np

from ..compiled.kernels import cholesky_rows, csne_step, reflect, reflector
from ..compiled.registry import jit
from .bb_state import (  # noqa: F401 - the search's state, named here as before
    COUNTERS,
    DONE,
    EXPANDED,
    FULL,
    NEAR_BRANCHES,
    OFFERED,
    OPEN,
    PAUSED,
    PENDING,
    Data,
    Heap,
    Work,
    words_for,
    workspace,
)

__all__ = ["COUNTERS", "DONE", "Data", "FULL", "Heap", "PAUSED", "Work", "expand",
           "words_for", "workspace"]

#: Drop costs (from the Gram matrix of T, relative rounding about eps * cond) count
#: ``1 - DROP_MARGIN * eps * |T| * cond`` of themselves, cond estimated per node
#: from the smallest squared pivot and ||H_FF||_F; at least 1e-6 is taken off.
DROP_MARGIN = 1e3

#: Exact small sizes (projected explicitly, rounding about eps * SSE(I) / pivot)
#: count their SSE less this fraction of SSE(I).
SMALL_MARGIN = 1e-8


#: The angle :func:`_sse_span` allows between the span of a structure that passes the
#: rank test (squared pivots above 1e-9) and that of its columns moved by rounding:
#: eps |T| / its smallest singular value is below 1e-8 for 400 terms when that value
#: is a tenth of its smallest pivot.
SPAN_ANGLE = 1e-7


@jit
def _shell_sort(a, n):  # pragma: no cover - compiled
    """Sort a[:n] in place, ascending.

    One small routine instead of numba's sorts, which cost seconds of
    compilation each.
    """
    gap = 1
    while gap < n // 3:
        gap = 3 * gap + 1
    while gap >= 1:
        for i in range(gap, n):
            v = a[i]
            j = i
            while j >= gap and a[j - gap] > v:
                a[j] = a[j - gap]
                j -= gap
            a[j] = v
        gap //= 3


@jit
def _order_descending(key, n, out):  # pragma: no cover - compiled
    """out[:n] = the indices of key[:n], largest key first (a shell sort)."""
    for i in range(n):
        out[i] = i
    gap = 1
    while gap < n // 3:
        gap = 3 * gap + 1
    while gap >= 1:
        for i in range(gap, n):
            v = out[i]
            j = i
            while j >= gap and key[out[j - gap]] < key[v]:
                out[j] = out[j - gap]
                j -= gap
            out[j] = v
        gap //= 3


@jit
def _value(sse, k, n, scale, floor, pen):  # pragma: no cover - compiled
    if k == 0:
        return np.inf
    return n * np.log(max(sse, floor) * scale / n) + pen[k]


@jit
def _swap(heap_bound, heap_in, heap_free, i, j):  # pragma: no cover - compiled
    """Exchange open nodes i and j."""
    heap_bound[i], heap_bound[j] = heap_bound[j], heap_bound[i]
    for w in range(heap_in.shape[1]):
        a, b = heap_in[i, w], heap_free[i, w]
        heap_in[i, w], heap_free[i, w] = heap_in[j, w], heap_free[j, w]
        heap_in[j, w], heap_free[j, w] = a, b


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
        _swap(heap_bound, heap_in, heap_free, parent, i)
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
        _swap(heap_bound, heap_in, heap_free, child, i)
        i = child
    return bound, size


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
    csne_step(L, r_ext, cols, k, yi, theta, r, g)
    sse = 0.0
    for q in range(rows):
        sse += r[q] * r[q]
    return sse


@jit
def _sse_span(r_ext, cols, t, yi, Ht):  # pragma: no cover - compiled
    """A lower bound on the SSE of every identifiable S <= T = cols[:t].

    Householder QR of the gathered columns ``[r_ext[:, T] y]`` (rows of ``Ht``),
    no pivot test, so also where T is (nearly) rank-deficient: the residual c of
    y off every direction the columns reach. The QR is exact for columns moved
    by about eps; the moved columns of an S that passes the rank test span
    nearly S's span (within an angle of about eps |T| / its smallest singular
    value), so ``c <= SSE(S) + 2 sqrt(SSE(S)) d`` with ``d`` =
    :data:`SPAN_ANGLE` ||y||, and ``SSE(S) >= (sqrt(c + d^2) - d)^2``.
    """
    rows = r_ext.shape[0]
    for j in range(t + 1):
        src = cols[j] if j < t else yi
        for q in range(rows):
            Ht[j, q] = r_ext[q, src]
    yy = 0.0
    for q in range(rows):
        yy += Ht[t, q] * Ht[t, q]
    for j in range(min(t, rows)):
        nrm2 = 0.0
        for q in range(j, rows):
            nrm2 += Ht[j, q] * Ht[j, q]
        if not nrm2 > 0.0:
            continue
        _, tau = reflector(Ht, j, nrm2)
        for c in range(j + 1, t + 1):
            reflect(Ht, j, tau, c)
    sse = 0.0
    for q in range(min(t, rows), rows):
        sse += Ht[t, q] * Ht[t, q]
    d = SPAN_ANGLE * np.sqrt(yy)
    return (np.sqrt(sse + d * d) - d) ** 2


@jit
def _has_core(pcost, f, q, c, deg, gone):  # pragma: no cover - compiled
    """Whether q terms whose pairs all cost at most c may exist.

    A necessary test: the (q-1)-core of the graph of pairs costing <= c has q
    vertices.
    """
    for a in range(f):
        gone[a] = False
        d = 0
        for b in range(f):
            if b != a and pcost[a, b] <= c:
                d += 1
        deg[a] = d
    left = f
    changed = True
    while changed and left >= q:
        changed = False
        for a in range(f):
            if not gone[a] and deg[a] < q - 1:
                gone[a] = True
                left -= 1
                changed = True
                for b in range(f):
                    if not gone[b] and b != a and pcost[a, b] <= c:
                        deg[b] -= 1
    return left >= q


@jit
def _core_bound(pcost, f, q, edges, n_edges, deg, gone):  # pragma: no cover - compiled
    """Least c such that q terms with all pair costs <= c may exist (_has_core).

    Leaving out any q free terms costs at least this.
    """
    lo, hi = 0, n_edges - 1
    if not _has_core(pcost, f, q, edges[hi], deg, gone):
        return edges[hi]
    while lo < hi:
        mid = (lo + hi) // 2
        if _has_core(pcost, f, q, edges[mid], deg, gone):
            hi = mid
        else:
            lo = mid + 1
    return edges[lo]


@jit
def _project_off(Q, count, X, col):  # pragma: no cover - compiled
    """Remove from X[:, col] its components along Q[:, :count] (orthonormal), twice."""
    rows = Q.shape[0]
    for _ in range(2):
        for j in range(count):
            acc = 0.0
            for q in range(rows):
                acc += Q[q, j] * X[q, col]
            for q in range(rows):
                X[q, col] -= acc * Q[q, j]


@jit
def _project_free(r_ext, cols, k, f, yi, Q, At, S, c):  # pragma: no cover - compiled
    """The free columns and the target projected off span(I); returns SSE(I).

    I = cols[:k], F = cols[k:k + f]. Gram-Schmidt twice, on the triangular
    factor of [P y], so what :func:`_small_sizes` computes from ``S`` (Gram of
    the projected free columns) and ``c`` (their products with the projected
    target) is accurate where the Gram matrix of the data is not.
    """
    rows = r_ext.shape[0]
    for i in range(k):
        for q in range(rows):
            Q[q, i] = r_ext[q, cols[i]]
        _project_off(Q, i, Q, i)
        norm = 0.0
        for q in range(rows):
            norm += Q[q, i] * Q[q, i]
        norm = np.sqrt(norm)
        for q in range(rows):
            Q[q, i] /= norm
    for a in range(f + 1):  # column f: the target
        src = cols[k + a] if a < f else yi
        for q in range(rows):
            At[q, a] = r_ext[q, src]
        _project_off(Q, k, At, a)
    zz = 0.0
    for q in range(rows):
        zz += At[q, f] * At[q, f]
    for a in range(f):
        acc = 0.0
        for q in range(rows):
            acc += At[q, a] * At[q, f]
        c[a] = acc
        for b in range(a, f):
            acc = 0.0
            for q in range(rows):
                acc += At[q, a] * At[q, b]
            S[a, b] = acc
            S[b, a] = acc
    return zz


@jit
def _small_sizes(S, c, zz, f, amax, exact, chosen, lrow, w, gsum, pick,
                 floor_t):  # pragma: no cover - compiled
    """Exact least SSE of I + A for |A| = 0 .. amax, A among the free terms.

    Every A of up to amax terms is visited depth first, its factor grown one
    row at a time (``S``, ``c``, ``zz`` from :func:`_project_free`). A nearly
    dependent set, and every larger one holding it, counts as fitting down to
    ``floor_t`` (a lower bound on SSE(T): 0, or :func:`_sse_span`'s), a safe
    bound. ``chosen[a, :a]`` receives the best A of each size (positions in F;
    -1 first when none).
    """
    tiny = 1e-12
    for a in range(amax + 1):
        gsum[a] = 0.0  # here: the best gain of each size
        chosen[a, 0] = -1  # no set of that size found (yet)
    exact[0] = zz
    if amax == 0:
        return
    depth = 0
    pick[0] = -1
    while depth >= 0:
        pick[depth] += 1
        e = pick[depth]
        if e >= f:
            depth -= 1
            continue
        dd = S[e, e]
        for i in range(depth):
            acc = S[e, pick[i]]
            for p in range(i):
                acc -= lrow[depth, p] * lrow[i, p]
            lrow[depth, i] = acc / lrow[i, i]
            dd -= lrow[depth, i] * lrow[depth, i]
        size = depth + 1
        if not dd > tiny * S[e, e]:  # dependent, with all its supersets: as if they
            for s2 in range(size, amax + 1):  # fitted down to SSE(T)
                gsum[s2] = max(gsum[s2], zz - floor_t)
            continue
        lrow[depth, depth] = np.sqrt(dd)
        acc = c[e]
        for i in range(depth):
            acc -= lrow[depth, i] * w[i]
        w[depth] = acc / lrow[depth, depth]
        gain = w[depth] * w[depth]
        for i in range(depth):
            gain += w[i] * w[i]
        if gain > gsum[size]:
            gsum[size] = gain
            for i in range(size):
                chosen[size, i] = pick[i]
        if size < amax:
            depth += 1
            pick[depth] = e
    for a in range(1, amax + 1):
        exact[a] = max(0.0, zz - min(gsum[a], zz) - SMALL_MARGIN * zz)


@jit
def _visits_for(f, budget):  # pragma: no cover - compiled
    """Largest a such that all subsets of up to a of f terms number at most budget."""
    total, comb = 1, 1
    for a in range(1, f + 1):
        comb = comb * (f - a + 1) // a
        total += comb
        if total > budget:
            return a - 1
    return f


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
def _drop_costs(L, theta, k, f, Winv, Hff, hdiag, pcost, pairs, delta, column, drop,
                minpiv):  # pragma: no cover - compiled
    """Costs of leaving out free terms of T (factor L, coefficients theta).

    Fills ``delta`` (each term alone), ``pcost``/``pairs`` (each pair; rows of
    ``pairs`` sorted) and ``drop[q]``, a lower bound on the SSE increase of
    leaving out any q free terms: the largest of the q-th smallest delta, the q
    smallest theta^2 over ||H_FF||_F, and the q-th smallest over the terms a of
    a's (q-1)-th cheapest pair (each of q terms left out has q - 1 partners).
    Returns the fraction of these costs that counts (see :data:`DROP_MARGIN`;
    ``minpiv``: T's smallest squared pivot); ``drop`` has it applied already.
    """
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
    frob = 0.0  # ||H_FF||_F with H_FF = Winv^T Winv, the free block of (G_TT)^-1
    for a in range(f):
        for b in range(a, f):
            acc = 0.0
            for p in range(b, f):
                acc += Winv[p, a] * Winv[p, b]
            Hff[a, b] = acc
            Hff[b, a] = acc
            if a == b:
                hdiag[a] = acc
                frob += acc * acc
            else:
                frob += 2.0 * acc * acc
    frob = np.sqrt(frob)
    cond = max(1.0 / minpiv, frob)
    safety = min(1.0 - 1e-6, 1.0 - DROP_MARGIN * 2.220446049250313e-16 * (k + f) * cond)
    safety = max(safety, 0.0)
    for a in range(f):
        ta = theta[k + a]
        delta[a] = ta * ta / hdiag[a]
        q = 0
        for b in range(f):
            if b == a:
                continue
            tb = theta[k + b]
            det = hdiag[a] * hdiag[b] - Hff[a, b] * Hff[a, b]
            if det > 0.0:
                pcost[a, b] = (ta * ta * hdiag[b] - 2.0 * ta * tb * Hff[a, b]
                               + tb * tb * hdiag[a]) / det
            else:
                pcost[a, b] = 0.0
            pairs[a, q] = pcost[a, b]
            q += 1
        _shell_sort(pairs[a], f - 1)
    dsort = np.empty(f)
    tsort = np.empty(f)
    for a in range(f):
        dsort[a] = delta[a]
        tsort[a] = theta[k + a] * theta[k + a]
    _shell_sort(dsort, f)
    _shell_sort(tsort, f)
    drop[0] = 0.0
    cum = 0.0
    for q in range(1, f + 1):
        cum += tsort[q - 1]
        d = max(dsort[q - 1], cum / frob)
        if q >= 2:
            for a in range(f):
                column[a] = pairs[a, q - 2]
            _shell_sort(column, f)
            d = max(d, column[q - 1])
        drop[q] = max(safety * d, drop[q - 1])  # leaving out more never costs less
    return safety


@jit
def _consider(data, heap, work, kk):  # pragma: no cover - compiled
    """Offer the structure work.cand[:kk] as the incumbent.

    Its pivots are tested in index order, as the evaluator tests them: a
    squared pivot at or below ``rank_tol`` rules it out; one below ``near``
    leaves the verdict to the evaluator (the structure goes to ``pending``, for
    the caller); otherwise it is fitted accurately and kept if better.
    """
    m = data.gram.shape[0] - 1
    cand, Lc = work.cand, work.Lc
    _shell_sort(cand, kk)
    cand[kk] = m
    cholesky_rows(data.gram, cand, 0, kk + 1, Lc, work.piv, 0.0, False, kk + 1)
    smallest = np.inf
    for j in range(kk):
        smallest = min(smallest, Lc[j, j] * Lc[j, j])
    if not smallest > data.rank_tol:
        return
    counts = heap.counts
    if smallest < data.near:
        row = counts[PENDING]
        if row < heap.pending.shape[0]:
            heap.pending[row, :] = 0
            for a in range(kk):
                _set_bit(heap.pending[row], cand[a])
            counts[PENDING] = row + 1
        return
    sse = _refined_sse(Lc, data.r_ext, cand, kk, m, work.theta2, work.r, work.g)
    value = _value(sse, kk, data.n, data.scale, data.floor, data.pen)
    if value < heap.best[0]:
        heap.best[0] = value
        heap.best_mask[:] = False
        for a in range(kk):
            heap.best_mask[cand[a]] = True


@jit
def _node_columns(work, m):  # pragma: no cover - compiled
    """The popped node's columns: I (in index order), then F; returns (|I|, |F|)."""
    k = _members(work.inside, m, work.members)
    for j in range(k):
        work.cols[j] = work.members[j]
    f = _members(work.free, m, work.members)
    for j in range(f):
        work.cols[k + j] = work.members[j]
    work.cols[k + f] = m  # the target
    return k, f


@jit
def _factorise(data, work, t):  # pragma: no cover - compiled
    """Factorise T's Gram sub-matrix and the target's row; the first nearly dependent row, or -1.

    (work.cols[t] is the target: its row, computed with T's, is what :func:`_fit_all` uses.)
    """
    L = work.L
    cholesky_rows(data.gram, work.cols, 0, t + 1, L, work.piv, 0.0, False, t)
    for j in range(t):
        if not L[j, j] * L[j, j] > data.rank_tol:
            return j
    return -1


@jit
def _branch_on(heap, work, size, bound, c):  # pragma: no cover - compiled
    """Push the node's two children on the free term c: c out, then c in."""
    work.child_in[:] = work.inside
    work.child_free[:] = work.free
    _clear_bit(work.child_free, c)
    size = _push(heap.bound, heap.inside, heap.free, size, bound, work.child_in,
                 work.child_free)
    _set_bit(work.child_in, c)
    return _push(heap.bound, heap.inside, heap.free, size, bound, work.child_in,
                 work.child_free)


@jit
def _fit_all(data, work, t):  # pragma: no cover - compiled
    """SSE(T), all the node's terms in (the target's row from :func:`_factorise`, then CSNE)."""
    m = data.gram.shape[0] - 1
    return _refined_sse(work.L, data.r_ext, work.cols, t, m, work.theta, work.r, work.g)


@jit
def _bound_sizes(data, heap, work, k, f, sse_t, bound0, budget, deep_budget,
                 near):  # pragma: no cover - compiled
    """Bound every size |I| .. |T| of the node; returns (amax, safety, cut, quick).

    Sizes |I| .. |I| + amax exactly (their best structures offered as
    incumbents), larger ones from T down by the drop and pair bounds; amax
    grows by one where that size is the one left open and ``deep_budget``
    allows. ``cut``: no structure of the node can beat the incumbent. Leaves
    ``small``, ``drop``, ``prefmin``, ``delta``, ``pairs`` for :func:`_walk_chain`.
    ``near``: T is nearly rank-deficient (no factor to take drop costs from; ``sse_t``
    from :func:`_sse_span`): the exact small sizes and SSE(T) only, their least
    value in ``quick``.
    """
    w = work
    t = k + f
    best, tol = heap.best, data.tol
    n, scale, floor, pen = data.n, data.scale, data.floor, data.pen
    m = data.gram.shape[0] - 1
    amax = max(min(2, f), _visits_for(f, budget))
    zz = _project_free(data.r_ext, w.cols, k, f, m, w.Q, w.At, w.S, w.cvec)
    have_drops = False
    safety = 0.0
    n_edges = 0
    while True:
        _small_sizes(w.S, w.cvec, zz, f, amax, w.exact, w.chosen, w.lrow, w.wbuf, w.gbuf,
                     w.pick, sse_t if near else 0.0)
        quick = np.inf
        for a in range(amax + 1):
            w.small[a] = _value(w.exact[a], k + a, n, scale, floor, pen)
            quick = min(quick, w.small[a])
            if ((a > 0 or k > 0) and w.small[a] < best[0] - tol
                    and (a == 0 or w.chosen[a, 0] >= 0)):
                for j in range(k):
                    w.cand[j] = w.cols[j]
                for j in range(a):
                    w.cand[k + j] = w.cols[k + w.chosen[a, j]]
                heap.counts[OFFERED] += 1
                _consider(data, heap, work, k + a)
        if k + amax < t:  # larger sizes: at least SSE(T) and their penalty
            quick = min(quick, _value(sse_t, k + amax + 1, n, scale, floor, pen))
        if max(quick, bound0) >= best[0] - tol:
            return amax, safety, True, quick
        if amax == f:  # all sizes known exactly: closed if their best were offered
            closed = True
            for a in range(amax + 1):
                if w.small[a] < best[0] - tol:
                    closed = False  # that size's best was ruled out or is pending
            if closed:
                return amax, safety, True, quick
        if near:
            return amax, safety, False, quick
        # --- the cost of leaving out free terms, and the bound of each size t - q
        if not have_drops:
            minpiv = 1.0
            for j in range(t):
                minpiv = min(minpiv, w.L[j, j] * w.L[j, j])
            safety = _drop_costs(w.L, w.theta, k, f, w.Winv, w.Hff, w.hdiag, w.pcost, w.pairs,
                                 w.delta, w.column, w.drop, minpiv)
            for q in range(f + 1):
                w.cored[q] = False
            have_drops = True
            n_edges = 0
        lowest = np.inf
        for q in range(f + 1):
            wq = _value(sse_t + w.drop[q], t - q, n, scale, floor, pen)
            if f - q <= amax:
                wq = max(wq, w.small[f - q])
            elif q >= 3 and wq < best[0] - tol and not w.cored[q]:
                # could beat the incumbent: try the sharper pair bound (a core of the
                # graph of cheap pairs)
                w.cored[q] = True
                if n_edges == 0:
                    for a in range(f):
                        for b in range(a + 1, f):
                            w.edges[n_edges] = w.pcost[a, b]
                            n_edges += 1
                    _shell_sort(w.edges, n_edges)
                core = safety * _core_bound(w.pcost, f, q, w.edges, n_edges, w.deg, w.gone)
                if core > w.drop[q]:
                    w.drop[q] = core
                    wq = _value(sse_t + core, t - q, n, scale, floor, pen)
            w.wvals[q] = wq
            lowest = min(lowest, wq)
            w.prefmin[q] = lowest
        if max(bound0, w.prefmin[f]) >= best[0] - tol:
            return amax, safety, True, quick
        # the next size up still alive: enumerate it too, if affordable
        q = f - amax - 1
        if (amax < f and w.wvals[q] < best[0] - tol
                and _visits_for(f, deep_budget) > amax):
            amax += 1
            continue
        return amax, safety, False, quick


@jit
def _walk_chain(data, heap, work, k, f, sse_t, bound0, amax, safety,
                size):  # pragma: no cover - compiled
    """Walk the node's "in" chain (F by delta, largest first); push its "out" children.

    Chain node p fixes I + chain[:p]; its "out" child leaves chain[p] out and is
    pushed with its own bound; the walk stops where the chain's bound reaches
    the incumbent. Returns the new heap size.
    """
    w = work
    t = k + f
    best, tol = heap.best, data.tol
    n, scale, floor, pen = data.n, data.scale, data.floor, data.pen
    _order_descending(w.delta, f, w.order)
    for a in range(f):
        w.chain[a] = w.cols[k + w.order[a]]
    w.child_in[:] = w.inside
    for p in range(f):
        bound_p = max(bound0, w.prefmin[f - p])
        if bound_p >= best[0] - tol:
            break
        dp = safety * w.delta[w.order[p]]
        ob = np.inf
        for q in range(1, f - p + 1):
            # chain[p] and q - 1 others: at least its (q-1)-th cheapest pair
            dq = max(dp, w.drop[q])
            if q >= 2:
                dq = max(dq, safety * w.pairs[w.order[p], q - 2])
            vq = _value(sse_t + dq, t - q, n, scale, floor, pen)
            if f - q <= amax:
                vq = max(vq, w.small[f - q])
            ob = min(ob, vq)
        ob = max(ob, bound_p)
        if ob < best[0] - tol:
            w.child_free[:] = 0
            for a in range(p + 1, f):
                _set_bit(w.child_free, w.chain[a])
            size = _push(heap.bound, heap.inside, heap.free, size, ob, w.child_in,
                         w.child_free)
        _set_bit(w.child_in, w.chain[p])
    return size


@jit
def expand(data, heap, work, max_pops, budget, deep_budget):  # pragma: no cover - compiled
    """Expand up to ``max_pops`` nodes, best first (see the module doc).

    Parameters
    ----------
    data : Data
        The problem's numbers.
    heap : Heap
        In/out: the open nodes, the incumbent, the counters; ``pending`` is
        filled with candidates the evaluator must decide (the caller scores them
        and sets ``counts[PENDING] = 0``).
    work : Work
        Scratch space (:func:`workspace`).
    max_pops : int
        Nodes to expand in this call.
    budget : int
        Subsets of free terms a node enumerates exactly (its small sizes).
    deep_budget : int
        Up to this many when the next size up is the one the bounds leave open.

    Returns
    -------
    int
        :data:`DONE` (no open node can beat the incumbent: proved), :data:`PAUSED`
        or :data:`FULL` (the heap needs room).
    """
    m = data.gram.shape[0] - 1
    cap = heap.bound.shape[0]
    counts = heap.counts
    best, tol = heap.best, data.tol
    pops = 0
    size = counts[OPEN]
    while True:
        if size == 0 or heap.bound[0] >= best[0] - tol:
            counts[OPEN] = size
            return DONE
        if pops >= max_pops or counts[PENDING] + 2 * m + 2 > heap.pending.shape[0]:
            counts[OPEN] = size
            return PAUSED
        if size + m + 2 > cap:
            counts[OPEN] = size
            return FULL
        bound0, size = _pop(heap.bound, heap.inside, heap.free, size, work.inside, work.free)
        if bound0 >= best[0] - tol:
            continue
        pops += 1
        counts[EXPANDED] += 1
        k, f = _node_columns(work, m)
        t = k + f
        weak = _factorise(data, work, t)
        if 0 <= weak < k:  # rank-deficient I: nothing identifiable below this node
            continue
        if weak >= k:  # a free term nearly dependent on the others: bound, branch on it
            counts[NEAR_BRANCHES] += 1
            sse_t = _sse_span(data.r_ext, work.cols, t, m, work.Ht)
            _, _, cut, quick = _bound_sizes(data, heap, work, k, f, sse_t, bound0, budget,
                                            deep_budget, True)
            if not cut:
                size = _branch_on(heap, work, size, max(bound0, quick), work.cols[weak])
            continue
        sse_t = _fit_all(data, work, t)
        amax, safety, cut, _ = _bound_sizes(data, heap, work, k, f, sse_t, bound0, budget,
                                            deep_budget, False)
        if cut:
            continue
        size = _walk_chain(data, heap, work, k, f, sse_t, bound0, amax, safety, size)
