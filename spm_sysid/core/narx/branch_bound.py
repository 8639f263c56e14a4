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
  the node is dropped; a failing pivot in F is branched on (in / out).
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
"""

from __future__ import annotations

import numpy as np

from .kernels import csne_step, jit

__all__ = ["DONE", "FULL", "PAUSED", "expand", "words_for"]

#: :func:`expand` results.
DONE, PAUSED, FULL = 0, 1, 2

#: Drop costs (from the Gram matrix of T, relative rounding about eps * cond) count
#: ``1 - DROP_MARGIN * eps * |T| * cond`` of themselves, cond estimated per node
#: from the smallest squared pivot and ||H_FF||_F; at least 1e-6 is taken off.
DROP_MARGIN = 1e3

#: Exact small sizes (projected explicitly, rounding about eps * SSE(I) / pivot)
#: count their SSE less this fraction of SSE(I).
SMALL_MARGIN = 1e-8


def words_for(m: int) -> int:
    """64-bit words of a term mask of m terms."""
    return max(1, (m + 63) // 64)


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
    csne_step(L, r_ext, cols, k, yi, theta, r, g)
    sse = 0.0
    for q in range(rows):
        sse += r[q] * r[q]
    return sse


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
def _small_sizes(S, c, zz, f, amax, exact, chosen, lrow, w, gsum,
                 pick):  # pragma: no cover - compiled
    """Exact least SSE of I + A for |A| = 0 .. amax, A among the free terms.

    Every A of up to amax terms is visited depth first, its factor grown one
    row at a time (``S``, ``c``, ``zz`` from :func:`_project_free`). A nearly
    dependent set counts as a perfect fit (a safe bound). ``chosen[a, :a]``
    receives the best A of each size (positions in F; -1 first when none).
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
        if not dd > tiny * S[e, e]:  # dependent: as if it fitted everything
            if zz > gsum[size]:
                gsum[size] = zz
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
def _consider(gram, r_ext, cand, kk, yi, rank_tol, near, n, scale, floor, pen, best,
              best_mask, pending, counts, Lc, theta, r, g):  # pragma: no cover - compiled
    """Offer the structure cand[:kk] as the incumbent.

    Its pivots are tested in index order, as the evaluator tests them: a
    squared pivot at or below ``rank_tol`` rules it out; one below ``near``
    leaves the verdict to the evaluator (the structure goes to ``pending``, for
    the caller); otherwise it is fitted accurately and kept if better.
    """
    _shell_sort(cand, kk)
    cand[kk] = yi
    _cholesky_rows(gram, cand, 0, kk + 1, Lc)
    smallest = np.inf
    for j in range(kk):
        smallest = min(smallest, Lc[j, j] * Lc[j, j])
    if not smallest > rank_tol:
        return
    if smallest < near:
        row = counts[4]
        if row < pending.shape[0]:
            pending[row, :] = 0
            for a in range(kk):
                _set_bit(pending[row], cand[a])
            counts[4] = row + 1
        return
    value = _value(_refined_sse(Lc, r_ext, cand, kk, yi, theta, r, g), kk, n, scale,
                   floor, pen)
    if value < best[0]:
        best[0] = value
        best_mask[:] = False
        for a in range(kk):
            best_mask[cand[a]] = True


@jit
def expand(gram, r_ext, pen, n, scale, floor, rank_tol, tol, heap_bound, heap_in,
           heap_free, counts, best, best_mask, pending, near, max_pops, budget,
           deep_budget):  # pragma: no cover - compiled
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
    counts : ndarray of int64, shape (5,)
        In/out: open nodes, nodes expanded so far, candidate structures offered,
        nodes branched on a nearly dependent free term, rows used in ``pending``.
    best : ndarray, shape (1,)
        In/out: the incumbent's value.
    best_mask : ndarray of bool, shape (m,)
        In/out: the incumbent.
    pending : ndarray of uint64, shape (rows, words)
        Out: candidates whose rank the evaluator must decide (squared pivot below
        ``near``); the caller scores them and empties it (``counts[4] = 0``).
    near : float
        See ``pending`` (the evaluator's ``NEAR_RANK * rank_tol``).
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
    cand = np.empty(m + 1, dtype=np.int64)
    chain = np.empty(m + 1, dtype=np.int64)
    order = np.empty(m + 1, dtype=np.int64)
    L = np.zeros((m + 1, m + 1))
    Lc = np.zeros((m + 1, m + 1))
    Winv = np.zeros((m, m))
    Hff = np.zeros((m, m))
    pcost = np.zeros((m, m))
    pairs = np.zeros((m, m))
    Q = np.zeros((rows, m + 1))
    At = np.zeros((rows, m + 1))
    S = np.zeros((m, m))
    cvec = np.zeros(m)
    exact = np.zeros(m + 1)
    small = np.zeros(m + 1)
    chosen = np.zeros((m + 1, m + 1), dtype=np.int64)
    lrow = np.zeros((m + 1, m + 1))
    wbuf = np.zeros(m + 1)
    gbuf = np.zeros(m + 1)
    pick = np.zeros(m + 1, dtype=np.int64)
    edges = np.empty(m * m)
    deg = np.empty(m, dtype=np.int64)
    gone = np.zeros(m, dtype=np.bool_)
    theta = np.empty(m + 1)
    theta2 = np.empty(m + 1)
    r = np.empty(rows)
    g = np.empty(m + 1)
    delta = np.empty(m)
    hdiag = np.empty(m)
    column = np.empty(m)
    drop = np.empty(m + 1)
    safety = 0.0
    prefmin = np.empty(m + 1)
    wvals = np.empty(m + 1)
    cored = np.zeros(m + 1, dtype=np.bool_)
    n_edges = 0
    pops = 0
    size = counts[0]
    while True:
        if size == 0 or heap_bound[0] >= best[0] - tol:
            counts[0] = size
            return DONE
        if pops >= max_pops or counts[4] + 2 * m + 2 > pending.shape[0]:
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
            counts[3] += 1
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
        # --- sizes |I| .. |I| + 3 exactly (leaving out many terms is what the drop
        # bounds see least); their best structures are incumbent candidates
        amax = max(min(2, f), _visits_for(f, budget))
        zz = _project_free(r_ext, cols, k, f, yi, Q, At, S, cvec)
        have_drops = False
        cut = False
        while True:
            _small_sizes(S, cvec, zz, f, amax, exact, chosen, lrow, wbuf, gbuf, pick)
            quick = np.inf
            for a in range(amax + 1):
                small[a] = _value(exact[a], k + a, n, scale, floor, pen)
                quick = min(quick, small[a])
                if ((a > 0 or k > 0) and small[a] < best[0] - tol
                        and (a == 0 or chosen[a, 0] >= 0)):
                    for j in range(k):
                        cand[j] = cols[j]
                    for j in range(a):
                        cand[k + j] = cols[k + chosen[a, j]]
                    counts[2] += 1
                    _consider(gram, r_ext, cand, k + a, yi, rank_tol, near, n, scale, floor,
                              pen, best, best_mask, pending, counts, Lc, theta2, r, g)
            if k + amax < t:  # larger sizes: at least SSE(T) and their penalty
                quick = min(quick, _value(sse_t, k + amax + 1, n, scale, floor, pen))
            if max(quick, bound0) >= best[0] - tol:
                cut = True
                break
            if amax == f:  # all sizes known exactly: closed if their best were offered
                cut = True
                for a in range(amax + 1):
                    if small[a] < best[0] - tol:
                        cut = False  # that size's best was ruled out or is pending
                if cut:
                    break
            # --- the cost of leaving out free terms, and the bound of each size t - q
            if not have_drops:
                minpiv = 1.0
                for j in range(t):
                    minpiv = min(minpiv, L[j, j] * L[j, j])
                safety = _drop_costs(L, theta, k, f, Winv, Hff, hdiag, pcost, pairs, delta,
                                     column, drop, minpiv)
                for q in range(f + 1):
                    cored[q] = False
                have_drops = True
                n_edges = 0
            lowest = np.inf
            for q in range(f + 1):
                wq = _value(sse_t + drop[q], t - q, n, scale, floor, pen)
                if f - q <= amax:
                    wq = max(wq, small[f - q])
                elif q >= 3 and wq < best[0] - tol and not cored[q]:
                    # could beat the incumbent: try the sharper pair bound (a core
                    # of the graph of cheap pairs)
                    cored[q] = True
                    if n_edges == 0:
                        for a in range(f):
                            for b in range(a + 1, f):
                                edges[n_edges] = pcost[a, b]
                                n_edges += 1
                        _shell_sort(edges, n_edges)
                    core = safety * _core_bound(pcost, f, q, edges, n_edges, deg, gone)
                    if core > drop[q]:
                        drop[q] = core
                        wq = _value(sse_t + core, t - q, n, scale, floor, pen)
                wvals[q] = wq
                lowest = min(lowest, wq)
                prefmin[q] = lowest
            if max(bound0, prefmin[f]) >= best[0] - tol:
                cut = True
                break
            # the next size up still alive: enumerate it too, if affordable
            q = f - amax - 1
            if (amax < f and wvals[q] < best[0] - tol
                    and _visits_for(f, deep_budget) > amax):
                amax += 1
                continue
            break
        if cut:
            continue
        # --- the chain, F by delta, largest first
        _order_descending(delta, f, order)
        for a in range(f):
            chain[a] = cols[k + order[a]]
        # --- walk the chain: node p fixes I + chain[:p]; push its "out" child
        child_in[:] = inside
        for p in range(f):
            bound_p = max(bound0, prefmin[f - p])
            if bound_p >= best[0] - tol:
                break
            dp = safety * delta[order[p]]
            ob = np.inf
            for q in range(1, f - p + 1):
                # chain[p] and q - 1 others: at least its (q-1)-th cheapest pair
                dq = max(dp, drop[q])
                if q >= 2:
                    dq = max(dq, safety * pairs[order[p], q - 2])
                vq = _value(sse_t + dq, t - q, n, scale, floor, pen)
                if f - q <= amax:
                    vq = max(vq, small[f - q])
                ob = min(ob, vq)
            ob = max(ob, bound_p)
            if ob < best[0] - tol:
                child_free[:] = 0
                for a in range(p + 1, f):
                    _set_bit(child_free, chain[a])
                size = _push(heap_bound, heap_in, heap_free, size, ob, child_in, child_free)
            _set_bit(child_in, chain[p])
