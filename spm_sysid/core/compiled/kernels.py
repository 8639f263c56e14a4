"""Compiled inner loops: least-squares fits of many structures from one Gram matrix.

The GA scores a few dozen new structures per generation, each of its own size.
Done with numpy, every generation pays for gathering, padding to the largest
size and a dozen library calls; here one compiled call fits the whole batch,
each structure at its own size, and stops a factorisation at the first pivot
that shows the structure rank-deficient. The arithmetic is the evaluator's
(see :mod:`spm_sysid.core.fit.evaluator`): an up-looking Cholesky factor of the
structure's Gram sub-matrix with the target last, coefficients by back
substitution, and, where the Gram path may not be accurate enough, one step of
corrected semi-normal equations on the triangular factor of ``[P y]``.

``numba`` compiles the kernels (:mod:`spm_sysid.core.compiled.registry`: the
ahead-of-time build, else the JIT, cached on disk after the first use). It is
a required dependency: there is one numeric path. A missing or broken numba is
one clear error (:class:`~spm_sysid.core.errors.MissingDependencyError`) when
the kernels are first needed, never a silently slower fallback.
"""

from __future__ import annotations

import numpy as np

from .registry import jit, jit_exact

__all__ = ["GROUPED_FROM", "LANES", "cholesky_rows", "cholesky_solve", "csne_gathered", "csne_step",
           "fit_structures", "jit", "jit_exact", "pivoted_qr", "qr_structures"]


#: Rows of the Cholesky factor (columns of the QR) computed together: in their inner
#: loops each row of the factor (each reflector) read from memory serves this many of
#: them at once (the loops over the lanes are written out: LANES is 8 below).
LANES = 8


#: Rows of the Cholesky factor below this are computed one at a time (small
#: structures: the paper's are 5 to 20 terms), from it on in groups of LANES.
GROUPED_FROM = 32


@jit
def _diagonal(L, piv, j, d, tol, checked, first):  # pragma: no cover - compiled
    """Store row j's squared pivot d and its root on L's diagonal; the first weak row.

    A row below ``checked`` whose d is not above ``tol`` (NaN included), or any
    row whose d is not above 0, gets a zero diagonal; returns ``first`` updated
    to j when j is the first weak checked row.
    """
    piv[j] = d
    if d > (tol if j < checked else 0.0):
        L[j, j] = np.sqrt(d)
        return first
    L[j, j] = 0.0
    return j if j < checked and first < 0 else first


@jit
def cholesky_rows(gram, cols, start, stop, L, piv, tol, halt, checked):  # pragma: no cover
    """Rows start..stop-1 of the up-looking Cholesky factor of gram[cols, cols].

    Row j of L needs only rows 0..j-1, so a factor of a prefix extends row by
    row. ``piv[j]`` receives row j's squared pivot. For rows below ``checked``,
    a squared pivot not above ``tol`` (NaN included) leaves a zero diagonal
    (later rows then give that column 0); the first such row is returned (-1:
    none), and with ``halt`` the factorisation stops there. Rows from
    ``checked`` on (a target appended to the terms) have a zero diagonal only
    for a squared pivot not above 0. The evaluator's fits and the branch and
    bound's nodes both factorise with this routine.

    Rows from :data:`GROUPED_FROM` on go in groups of :data:`LANES`: each row
    of L read in the inner loop serves the whole group. Entry (j, i) is
    ``gram[cj, ci]`` less the dot product of rows j and i over columns < i,
    computed by one loop for every entry of a grouped row, so a row's numbers
    depend on its index only, never on the group it fell in (a test).
    """
    first = -1
    j0 = start
    while j0 < min(stop, GROUPED_FROM):  # one row at a time
        cj = cols[j0]
        for i in range(j0):
            acc = gram[cj, cols[i]]
            for p in range(i):
                acc -= L[j0, p] * L[i, p]
            L[j0, i] = acc / L[i, i] if L[i, i] > 0.0 else 0.0
        d = gram[cj, cj]
        for p in range(j0):
            d -= L[j0, p] * L[j0, p]
        first = _diagonal(L, piv, j0, d, tol, checked, first)
        if halt and first == j0:
            return first
        j0 += 1
    if j0 >= stop:
        return first
    W = np.zeros((LANES, stop))  # W[b, p] = L[j0 + b, p]: the group's rows, side by side
    s = np.zeros(LANES)
    while j0 < stop:
        nb = min(LANES, stop - j0)
        for i in range(j0 + nb):
            if i >= j0:  # row i has all its entries left of the diagonal: its pivot
                b = i - j0
                d = gram[cols[i], cols[i]]
                for p in range(i):
                    d -= W[b, p] * W[b, p]
                first = _diagonal(L, piv, i, d, tol, checked, first)
                if halt and first == i:
                    return first
                if i == j0 + nb - 1:
                    break
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
            for p in range(i):
                v = L[i, p]
                s0 += v * W[0, p]
                s1 += v * W[1, p]
                s2 += v * W[2, p]
                s3 += v * W[3, p]
                s4 += v * W[4, p]
                s5 += v * W[5, p]
                s6 += v * W[6, p]
                s7 += v * W[7, p]
            s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7] = s0, s1, s2, s3, s4, s5, s6, s7
            lii = L[i, i]
            for b in range(max(i - j0 + 1, 0), nb):
                x = (gram[cols[j0 + b], cols[i]] - s[b]) / lii if lii > 0.0 else 0.0
                W[b, i] = x
                L[j0 + b, i] = x
        j0 += nb
    return first


@jit
def cholesky_solve(L, g, k):  # pragma: no cover - compiled
    """``g`` <- (L L^T)^-1 g for the leading k x k block of a lower-triangular L."""
    for j in range(k):  # L w = g
        acc = g[j]
        for p in range(j):
            acc -= L[j, p] * g[p]
        g[j] = acc / L[j, j]
    for j in range(k - 1, -1, -1):  # L^T d = w
        acc = g[j]
        for p in range(j + 1, k):
            acc -= L[p, j] * g[p]
        g[j] = acc / L[j, j]


@jit
def csne_step(L, r_ext, cols, k, yi, theta, r, g):  # pragma: no cover - compiled
    """One corrected semi-normal step for the columns cols[:k] of r_ext.

    ``theta`` (k coefficients from the Cholesky factor L of their Gram matrix)
    is improved in place by ``(L L^T)^-1 A^T r``; ``r`` ends as the residual of
    the target (column yi) for the improved theta.
    """
    rows = r_ext.shape[0]
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
        cholesky_solve(L, g, k)
        for j in range(k):
            theta[j] += g[j]


@jit
def csne_gathered(L, A, ext, target, k, theta, r, g):  # pragma: no cover - compiled
    """:func:`csne_step` on gathered columns: the same step, contiguous memory.

    ``A[j, :ext[j]]`` holds column j of the structure (rows of a triangular
    factor below ``ext[j]`` are zero), ``target`` the target's column (zero
    beyond its own extent). Reading the columns once into rows of ``A`` (kept
    between structures that share a prefix) makes the three passes over them
    run on contiguous memory: about 4x faster than gathering from the factor
    in every pass (106 vs 26 us for 90 of 454 terms).
    """
    rows = r.shape[0]
    for rnd in range(2):
        for q in range(rows):
            r[q] = target[q]
        for j in range(k):
            th = theta[j]
            for q in range(ext[j]):
                r[q] -= A[j, q] * th
        if rnd == 1:
            break
        for j in range(k):
            acc = 0.0
            for q in range(ext[j]):
                acc += A[j, q] * r[q]
            g[j] = acc
        cholesky_solve(L, g, k)
        for j in range(k):
            theta[j] += g[j]


@jit
def fit_structures(gram, r_ext, idx, offsets, rank_tol, y_norm, n, refine_all,
                   sse, theta, bad, minpiv):  # pragma: no cover - compiled
    """Fit the structures ``idx[offsets[b]:offsets[b + 1]]`` for every b.

    Parameters
    ----------
    gram : ndarray, shape (m + 2, m + 2)
        Gram matrix of the unit-norm ``[P y]`` (target at index m).
    r_ext : ndarray, shape (rows, m + 2)
        Upper-triangular factor of ``[P y]`` (column c is zero below row c).
    idx : ndarray of int64
        The structures' term indices, concatenated, each in increasing order.
        Structures in lexicographic order of their index lists fit fastest (a
        prefix shared with the previous structure is not factorised again).
    offsets : ndarray of int64, shape (B + 1,)
        Where each structure starts in ``idx``.
    rank_tol : float
        Smallest squared pivot of an identifiable structure.
    y_norm : float
        Norm of the target (for the refinement test).
    n : int
        Number of regression rows (for the refinement test).
    refine_all : bool
        Refine every identifiable structure (criteria that use coefficients).
    sse : ndarray, shape (B,)
        Output: residual sum of squares (NaN where rank-deficient).
    theta : ndarray, shape (len(idx),)
        Output: coefficients of the unit-norm columns.
    bad : ndarray of bool, shape (B,)
        Output: rank-deficient (or empty) structures.
    minpiv : ndarray, shape (B,)
        Output: the smallest squared term pivot computed (the failing one when
        the factorisation stopped early).
    """
    m = gram.shape[0] - 2
    eps = 2.220446049250313e-16
    kmax = 0
    for b in range(len(offsets) - 1):
        kmax = max(kmax, offsets[b + 1] - offsets[b])
    L = np.zeros((kmax + 1, kmax + 1))
    piv = np.zeros(kmax + 1)
    cols = np.empty(kmax + 1, dtype=np.int64)
    rows = r_ext.shape[0]
    r = np.empty(rows)
    g = np.empty(kmax)
    A = np.empty((kmax, rows))  # the structure's columns of r_ext, gathered for CSNE
    ext = np.empty(kmax, dtype=np.int64)
    target = np.zeros(rows)
    for q in range(min(m + 1, rows)):
        target[q] = r_ext[q, m]
    valid = 0  # leading rows of L that hold the previous structure's factor
    gathered = 0  # leading rows of A that hold the previous structures' columns
    for b in range(len(offsets) - 1):
        s = offsets[b]
        k = offsets[b + 1] - s
        bad[b] = k == 0
        sse[b] = np.nan
        minpiv[b] = np.inf
        if k == 0:
            valid = 0
            gathered = 0
            continue
        # rows of L depend only on the terms up to them: a prefix shared with the
        # previous structure is already factorised (callers sort structures so)
        same = 0
        while same < min(k, valid) and cols[same] == idx[s + same]:
            same += 1
        gathered = min(gathered, same)
        for j in range(k):
            cols[j] = idx[s + j]
        cols[k] = m
        # the terms' rows and the target's (row k: its squared pivot is the SSE) in one call
        weak = cholesky_rows(gram, cols, same, k + 1, L, piv, rank_tol, True, k)
        last = k if weak < 0 else weak + 1
        for j in range(last):  # the reused rows' pivots count too
            if piv[j] < minpiv[b]:
                minpiv[b] = piv[j]
        if weak >= 0:  # a term reproduced by those before it (or NaN): rank-deficient
            bad[b] = True
            valid = weak
            minpiv[b] = piv[weak] if piv[weak] == piv[weak] else -np.inf
            continue
        valid = k
        # the target's row: its pivot is sqrt(SSE); at or below 0 an exact fit whose
        # SSE is lost in rounding (refined below), NaN a failure
        if not piv[k] == piv[k]:
            bad[b] = True
        if bad[b]:
            continue
        ssq = L[k, k] * L[k, k]
        # L = [[Ls, 0], [z^T, sqrt(SSE)]]: Ls^T theta = z
        tnorm = 0.0
        for j in range(k - 1, -1, -1):
            acc = L[k, j]
            for p in range(j + 1, k):
                acc -= L[p, j] * theta[s + p]
            theta[s + j] = acc / L[j, j]
            tnorm += theta[s + j] * theta[s + j]
        err = eps * (y_norm + np.sqrt(tnorm)) ** 2
        if refine_all or n * err > 1e-7 * ssq or ssq == 0.0:
            # corrected semi-normal equations on R_ext: theta += (Ls Ls^T)^-1 A^T r
            for j in range(gathered, k):
                c = cols[j]
                ext[j] = min(c + 1, rows)
                for q in range(ext[j]):
                    A[j, q] = r_ext[q, c]
            gathered = k
            csne_gathered(L, A, ext, target, k, theta[s:s + k], r, g)
            ssq = 0.0
            for q in range(rows):
                ssq += r[q] * r[q]
        sse[b] = ssq


@jit
def householder(alpha, nrm2):  # pragma: no cover - compiled
    """``(beta, tau, scale)`` of the reflector taking x to beta e_1.

    ``alpha`` is x's first entry, ``nrm2`` its squared norm (positive); the
    reflector is ``I - tau v v^T`` with ``v = [1, x[1:] * scale]``, and beta
    has the sign opposite to alpha (no cancellation).
    """
    beta = -np.sqrt(nrm2) if alpha >= 0.0 else np.sqrt(nrm2)
    return beta, (beta - alpha) / beta, 1.0 / (alpha - beta)


@jit
def qr_structures(r_ext, idx, offsets, rank_tol, sse, theta, bad):  # pragma: no cover
    """Fit the structures ``idx[offsets[b]:offsets[b + 1]]`` by Householder QR.

    The arbitration of structures whose Gram pivots come near ``rank_tol``
    (:meth:`~spm_sysid.core.fit.evaluator.StructureEvaluator._qr_fit` is the
    same for one structure): the QR factor of the structure's columns of
    ``r_ext`` (upper-triangular factor of ``[P y]``, target at column m) and
    of the target. A column c of ``r_ext`` is zero below row c, so each
    reflector spans only the rows down to the largest column so far, and the
    reflectors of a prefix shared with the previous structure are reused
    (structures in lexicographic order of their index lists fit fastest).
    Columns are reduced :data:`LANES` at a time (each reflector read once for
    them), and a reflector is applied in the same pass over them as the next
    reflector's dot products. Groups start at multiples of :data:`LANES`, so a
    column's numbers do not depend on how much its structure shared with the
    previous one.

    Outputs as :func:`fit_structures`: ``sse`` (NaN where rank-deficient),
    ``theta`` (coefficients of the unit-norm columns), ``bad`` (a squared
    diagonal entry of R below ``rank_tol``, or no terms).
    """
    m = r_ext.shape[1] - 2
    rows = r_ext.shape[0]
    kmax = 0
    for b in range(len(offsets) - 1):
        kmax = max(kmax, offsets[b + 1] - offsets[b])
    V = np.zeros((kmax + 1, rows))  # reflector j on rows j..span[j]-1 (V[j, j] = 1)
    tau = np.zeros(kmax + 1)
    span = np.zeros(kmax + 1, dtype=np.int64)
    Rt = np.zeros((kmax + 1, kmax + 1))  # Rt[j, i] = R[i, j]
    cols = np.empty(kmax + 1, dtype=np.int64)
    X = np.zeros((LANES, rows))  # the group's columns, side by side
    valid = 0  # leading reflectors that belong to the previous structure's prefix
    for b in range(len(offsets) - 1):
        st = offsets[b]
        k = offsets[b + 1] - st
        bad[b] = k == 0
        sse[b] = np.nan
        if k == 0:
            valid = 0
            continue
        same = 0
        while same < min(k, valid) and cols[same] == idx[st + same]:
            same += 1
        for j in range(k):
            cols[j] = idx[st + j]
        cols[k] = m
        ssq = 0.0
        j0 = same - same % LANES  # groups start at multiples of LANES (see above)
        while j0 <= k:
            nb = min(LANES, k + 1 - j0)
            X[:, :] = 0.0
            have = False
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
            for lane in range(nb):
                c = cols[j0 + lane]
                for q in range(min(c + 1, rows)):
                    X[lane, q] = r_ext[q, c]
            for i in range(j0 + nb):
                if i >= j0:  # column i has met every reflector before it
                    lane = i - j0
                    j = i
                    for p in range(min(j, rows)):
                        Rt[j, p] = X[lane, p]
                    top = min(cols[j] + 1, rows)
                    if j > 0:
                        top = max(top, span[j - 1])
                    if j == k:  # the target: what is left below row k is the residual
                        for q in range(k, top):
                            ssq += X[lane, q] * X[lane, q]
                        break
                    if j >= rows:  # more terms than rows
                        Rt[j, j] = 0.0
                        tau[j] = 0.0
                        span[j] = j
                    else:
                        end = max(top, j + 1)
                        nrm2 = 0.0
                        for q in range(j, end):
                            nrm2 += X[lane, q] * X[lane, q]
                        alpha = X[lane, j]
                        span[j] = end
                        V[j, j] = 1.0
                        if nrm2 == 0.0 or not nrm2 == nrm2:
                            Rt[j, j] = 0.0 if nrm2 == 0.0 else np.nan
                            tau[j] = 0.0
                            for q in range(j + 1, end):
                                V[j, q] = 0.0
                        else:
                            beta, tau[j], scale = householder(alpha, nrm2)
                            for q in range(j + 1, end):
                                V[j, q] = X[lane, q] * scale
                            Rt[j, j] = beta
                    if i == j0 + nb - 1:
                        break
                if i >= rows:
                    continue
                if not have:
                    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
                    for q in range(i, span[i]):
                        v = V[i, q]
                        s0 += v * X[0, q]
                        s1 += v * X[1, q]
                        s2 += v * X[2, q]
                        s3 += v * X[3, q]
                        s4 += v * X[4, q]
                        s5 += v * X[5, q]
                        s6 += v * X[6, q]
                        s7 += v * X[7, q]
                t = tau[i]
                s0 *= t
                s1 *= t
                s2 *= t
                s3 *= t
                s4 *= t
                s5 *= t
                s6 *= t
                s7 *= t
                have = i + 1 < j0 and i + 1 < rows
                if have:
                    u0 = u1 = u2 = u3 = u4 = u5 = u6 = u7 = 0.0
                    for q in range(i, span[i]):
                        v = V[i, q]
                        w = V[i + 1, q]
                        x0 = X[0, q] - s0 * v
                        x1 = X[1, q] - s1 * v
                        x2 = X[2, q] - s2 * v
                        x3 = X[3, q] - s3 * v
                        x4 = X[4, q] - s4 * v
                        x5 = X[5, q] - s5 * v
                        x6 = X[6, q] - s6 * v
                        x7 = X[7, q] - s7 * v
                        X[0, q] = x0
                        X[1, q] = x1
                        X[2, q] = x2
                        X[3, q] = x3
                        X[4, q] = x4
                        X[5, q] = x5
                        X[6, q] = x6
                        X[7, q] = x7
                        u0 += w * x0
                        u1 += w * x1
                        u2 += w * x2
                        u3 += w * x3
                        u4 += w * x4
                        u5 += w * x5
                        u6 += w * x6
                        u7 += w * x7
                    for q in range(span[i], span[i + 1]):
                        w = V[i + 1, q]
                        u0 += w * X[0, q]
                        u1 += w * X[1, q]
                        u2 += w * X[2, q]
                        u3 += w * X[3, q]
                        u4 += w * X[4, q]
                        u5 += w * X[5, q]
                        u6 += w * X[6, q]
                        u7 += w * X[7, q]
                    s0, s1, s2, s3, s4, s5, s6, s7 = u0, u1, u2, u3, u4, u5, u6, u7
                else:
                    for q in range(i, span[i]):
                        v = V[i, q]
                        X[0, q] -= s0 * v
                        X[1, q] -= s1 * v
                        X[2, q] -= s2 * v
                        X[3, q] -= s3 * v
                        X[4, q] -= s4 * v
                        X[5, q] -= s5 * v
                        X[6, q] -= s6 * v
                        X[7, q] -= s7 * v
            j0 += nb
        valid = k
        for j in range(k):
            d = Rt[j, j] * Rt[j, j]
            if not d >= rank_tol:  # small, or NaN
                bad[b] = True
                break
        if bad[b]:
            continue
        for j in range(k - 1, -1, -1):  # R[:k, :k] theta = R[:k, k]
            acc = Rt[k, j]
            for p in range(j + 1, k):
                acc -= Rt[p, j] * theta[st + p]
            theta[st + j] = acc / Rt[j, j]
        sse[b] = ssq


@jit
def reflector(At, j, nrm2):  # pragma: no cover - compiled
    """Turn row j of ``At`` (entries j on, squared norm ``nrm2`` > 0) into its reflector.

    Afterwards ``At[j, j]`` is beta and ``At[j, j+1:]`` holds v's tail (see
    :func:`householder`); returns ``(beta, tau)``.
    """
    beta, tau, scale = householder(At[j, j], nrm2)
    for q in range(j + 1, At.shape[1]):
        At[j, q] *= scale
    At[j, j] = beta
    return beta, tau


@jit
def reflect(At, j, tau, c):  # pragma: no cover - compiled
    """Apply the reflector in row j of ``At`` to row c (entries j on); returns At[c, j]."""
    rows = At.shape[1]
    acc = At[c, j]
    for q in range(j + 1, rows):
        acc += At[j, q] * At[c, q]
    acc *= tau
    At[c, j] -= acc
    for q in range(j + 1, rows):
        At[c, q] -= acc * At[j, q]
    return At[c, j]


@jit
def pivoted_qr(At, diag, piv):  # pragma: no cover - compiled
    """Householder QR with column pivoting of A = At.T: ``|R|``'s diagonal and the order.

    ``At`` (n, rows) holds A's columns as rows (overwritten). Step j takes the
    remaining column of largest norm (Businger and Golub, the choice of
    LAPACK's ``dgeqp3``); norms are downdated after each step and computed
    again where the downdate has lost most of the column's norm. Outputs
    ``diag[j] = |R[j, j]|`` and ``piv[j]``, the column of A in position j.
    """
    n, rows = At.shape
    norms = np.empty(n)
    ref = np.empty(n)  # the norm at the last exact computation
    for c in range(n):
        acc = 0.0
        for q in range(rows):
            acc += At[c, q] * At[c, q]
        norms[c] = acc
        ref[c] = acc
        piv[c] = c
    for j in range(n):
        diag[j] = 0.0
    for j in range(min(rows, n)):
        p = j
        for c in range(j + 1, n):
            if norms[c] > norms[p]:
                p = c
        if p != j:
            for q in range(rows):
                At[j, q], At[p, q] = At[p, q], At[j, q]
            norms[j], norms[p] = norms[p], norms[j]
            ref[j], ref[p] = ref[p], ref[j]
            piv[j], piv[p] = piv[p], piv[j]
        nrm2 = 0.0
        for q in range(j, rows):
            nrm2 += At[j, q] * At[j, q]
        if nrm2 == 0.0 or not nrm2 == nrm2:
            continue
        beta, tau = reflector(At, j, nrm2)
        diag[j] = abs(beta)
        for c in range(j + 1, n):
            r = reflect(At, j, tau, c)
            norms[c] -= r * r
            if norms[c] <= 1e-6 * ref[c]:  # cancellation: compute it again
                acc = 0.0
                for q in range(j + 1, rows):
                    acc += At[c, q] * At[c, q]
                norms[c] = acc
                ref[c] = acc
