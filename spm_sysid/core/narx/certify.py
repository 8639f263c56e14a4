"""Certifying the optimum: branch and bound over all 2^M structures.

For AIC and BIC the criterion is ``N ln(SSE(S)/N) + pen(|S|)`` with ``pen``
increasing in the number of terms only, and the SSE never grows when terms are
added. A depth-first branch and bound over the terms can therefore prove that a
structure is the best of all (``optimal``) or, when time runs out, bound how
far the best found may be from the optimum (``limit``).

A node fixes some terms *in* (I) and some *out*; the rest (F) are free. Every
structure S of the node has ``I <= S <= T = I + F``. Two lower bounds on the
criterion of all of them are used, and the larger counts:

* **plain**: ``SSE(S) >= SSE(T)`` and ``|S| >= |I|``;
* **drop bound**: leaving out any r free terms R raises the SSE of T by
  ``theta_R' (H_RR)^-1 theta_R >= ||theta_R||^2 / lambda_max(H_FF)`` (theta:
  T's coefficients, H: the inverse of T's Gram matrix, unit-norm columns), so
  a structure with ``|I| + |F| - r`` terms has ``SSE >= SSE(T) + s_r /
  lambda_max(H_FF)`` with ``s_r`` the sum of the r smallest ``theta_j^2`` in F;
  the bound is the minimum over r of the criterion at that size.

Search order: best first -- the open node of the lowest bound is expanded
next, so the lower bound over all structures rises steadily and a stopped
search reports an honest gap. At each node the free term whose removal from T
costs the most SSE (``theta_j^2 / H_jj``) is branched on. The incumbent starts
from a warm start (the GA's result, else forward selection) and is improved by
the structures I and T met at every node. Node values are
the evaluator's (:class:`StructureEvaluator`, the GA's own numbers), so
"optimal" means: no structure scores lower than the result by more than
``tolerance`` (1e-6) on the criterion's scale. Rank-deficient structures
score +inf, as in the GA.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .branch_bound import DONE, FULL, expand, words_for
from .criteria import Criterion, get_criterion
from .evaluator import NEAR_RANK, StructureEvaluator
from .lstsq import DEFAULT_RANK_TOL

__all__ = ["CERTIFIABLE", "Certificate", "certify", "certify_data", "penalty_per_size"]

#: Criteria whose penalty depends on the number of terms only (certifiable).
CERTIFIABLE = ("aic", "bic")


@dataclass
class Certificate:
    """Outcome of :func:`certify`.

    Attributes
    ----------
    status : str
        ``optimal`` (proved) or ``limit`` (the time or node limit ran out).
    value : float
        Criterion value of the best structure found.
    lower_bound : float
        No structure scores below this (``value`` itself when optimal).
    mask : ndarray of bool
        The best structure found.
    nodes : int
        Branch-and-bound nodes explored.
    seconds : float
    bound : str
        The bounds used.
    reason : str or None
        What ran out (``limit``).
    warm_start : float or None
        The warm start's value (e.g. the GA's best).
    """

    status: str
    value: float
    lower_bound: float
    mask: np.ndarray
    nodes: int
    seconds: float
    bound: str = "plain + drop bound"
    reason: str | None = None
    warm_start: float | None = None
    terms: list[str] = field(default_factory=list)

    @property
    def gap(self) -> float:
        """``value - lower_bound`` (0 when optimal)."""
        return 0.0 if self.status == "optimal" else float(self.value - self.lower_bound)

    @property
    def improved(self) -> bool:
        """The search found a better structure than the warm start."""
        return self.warm_start is not None and self.value < self.warm_start - 1e-9

    def summary(self) -> str:
        """One line for people."""
        if self.status == "optimal":
            text = (f"certified optimal: {self.value:.2f} ({len(self.terms)} terms), "
                    f"{self.nodes} nodes, {self.seconds:.2f} s")
        else:
            text = (f"not certified ({self.reason}): best {self.value:.2f}, lower bound "
                    f"{self.lower_bound:.2f}, gap {self.gap:.2f}, {self.nodes} nodes, "
                    f"{self.seconds:.2f} s")
        if self.improved:
            text += f"; improved on the warm start ({self.warm_start:.2f})"
        return text

    def to_dict(self) -> dict:
        """JSON-ready (the ``certify --json`` document and ``metadata.certificate``)."""
        return {"status": self.status, "value": float(self.value),
                "lower_bound": float(self.lower_bound), "gap": float(self.gap),
                "terms": list(self.terms), "nodes": int(self.nodes),
                "seconds": round(float(self.seconds), 4), "bound": self.bound,
                "reason": self.reason, "warm_start": self.warm_start}


def penalty_per_size(criterion: Criterion, n: int, m: int) -> np.ndarray:
    """``pen(k)`` for k = 0..m, or a ValueError when the criterion is not certifiable.

    The criterion must be ``n ln(SSE/n) + pen(k)`` (checked numerically) with
    ``pen`` increasing.
    """
    if criterion.name not in CERTIFIABLE or criterion.needs_coefficients:
        raise ValueError(
            f"criterion {criterion.name} cannot be certified: its value depends on more "
            f"than the SSE and the number of terms (certifiable: {', '.join(CERTIFIABLE)})")
    k = np.arange(m + 1)
    pen = criterion(np.full(m + 1, float(n)), n, k, None)
    check = criterion(np.full(m + 1, float(n) * np.e), n, k, None)
    if not np.allclose(check - pen, n) or np.any(np.diff(pen) <= 0):
        raise ValueError(f"criterion {criterion.name} is not of the form N ln(SSE/N) + pen(k)")
    return pen


#: Open nodes may use at most this much memory before the search stops with ``limit``.
MAX_OPEN_BYTES = 1 << 30

#: Subsets of its free terms a node enumerates exactly (its smallest sizes).
ENUMERATION_BUDGET = 6000


def polish(ev: StructureEvaluator, mask: np.ndarray, usable: np.ndarray,
           seconds: float = 5.0) -> tuple[np.ndarray, float]:
    """Local search from ``mask``: add, remove or swap one term while that helps.

    A good incumbent lets the branch and bound cut more; this costs a few
    hundred evaluator calls per step.
    """
    t0 = time.perf_counter()
    mask = np.asarray(mask, dtype=bool).copy()
    value = ev.cached_score(mask) if mask.any() else np.inf
    m = len(mask)
    allowed = np.zeros(m, dtype=bool)
    allowed[usable] = True
    while time.perf_counter() - t0 < seconds:
        inn, out = np.flatnonzero(mask), np.flatnonzero(~mask & allowed)
        flips = np.repeat(mask[None, :], len(inn) + len(out), axis=0)
        flips[np.arange(len(inn)), inn] = False
        flips[len(inn) + np.arange(len(out)), out] = True
        swaps = np.repeat(mask[None, :], len(inn) * len(out), axis=0)
        rows = np.arange(len(swaps))
        swaps[rows, np.repeat(inn, len(out))] = False
        swaps[rows, np.tile(out, len(inn))] = True
        cands = np.concatenate([flips, swaps])
        cands = cands[cands.any(axis=1)]
        if not len(cands):
            break
        scores = ev.score(cands)
        i = int(np.argmin(scores))
        if not scores[i] < value - 1e-9:
            break
        mask, value = cands[i].copy(), float(scores[i])
    return mask, value


def _settle(ev: StructureEvaluator, usable: np.ndarray, rows: np.ndarray, best: np.ndarray,
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


def certify(
    P: np.ndarray,
    target: np.ndarray,
    criterion: str | Criterion = "bic",
    *,
    warm_start: np.ndarray | None = None,
    time_limit: float = 60.0,
    node_limit: int | None = None,
    sse_scale: float = 1.0,
    tolerance: float = 1e-6,
    rank_tol: float = DEFAULT_RANK_TOL,
    progress: Callable[[int, float, float], None] | None = None,
    evaluator: StructureEvaluator | None = None,
    enumeration_budget: int | None = None,
) -> Certificate:
    """Search all structures of the columns of ``P`` exactly (see the module doc).

    Parameters
    ----------
    P, target : ndarray
        Regression matrix and target, as for :class:`StructureEvaluator` (None
        when ``evaluator`` is given).
    criterion : str or Criterion
        ``aic`` or ``bic``.
    warm_start : ndarray of bool, optional
        A good structure (the GA's); default: forward selection's best. It is
        improved by a local search (one term added, removed or swapped) first.
    time_limit : float
        Seconds before stopping with ``limit``.
    node_limit : int, optional
        Nodes before stopping with ``limit``.
    sse_scale : float
        As for the evaluator (SSE of the data as given / SSE of ``target``).
    tolerance : float
        Subtrees whose bound is within this of the incumbent are not searched.
    rank_tol : float
        As for the evaluator: structures with a smaller squared pivot score +inf.
    progress : callable, optional
        ``progress(nodes, best, lower_bound)`` about every 0.5 s.
    evaluator : StructureEvaluator, optional
        Reuse the GA's (same data and criterion): its cache and numbers.
    enumeration_budget : int, optional
        Subsets of its free terms a node enumerates exactly (default
        :data:`ENUMERATION_BUDGET`; 0: only up to two terms).

    Raises
    ------
    ValueError
        A criterion that cannot be certified (e.g. PMIC2).
    """
    t0 = time.perf_counter()
    crit = get_criterion(criterion)
    if evaluator is None:
        evaluator = StructureEvaluator(np.asarray(P, dtype=float),
                                       np.asarray(target, dtype=float), crit,
                                       rank_tol=rank_tol, sse_scale=sse_scale)
    ev = evaluator
    n, m = ev.n, ev.n_terms
    if ev.criterion.name != crit.name:
        raise ValueError(f"the evaluator scores {ev.criterion.name}, not {crit.name}")
    pen = penalty_per_size(crit, n, m)
    # the evaluator's unit-norm Gram matrix of [P y] and triangular factor (the same
    # least-squares problem in min(n, m + 1) rows), on the non-zero columns
    usable = np.flatnonzero(~ev._zero_cols)
    keep = np.concatenate([usable, [m]])
    gram = np.ascontiguousarray(ev._gram[np.ix_(keep, keep)])
    r_aug = np.ascontiguousarray(ev._r_ext[:, keep])
    mu = len(usable)

    # incumbent: the warm start (else forward selection), then a local search
    if warm_start is None:
        from .orders import forward_selection

        _, chosen = forward_selection(r_aug[:, :mu], r_aug[:, mu], ev.criterion,
                                      max_terms=min(60, mu), sse_scale=ev.sse_scale)
        warm_start = np.zeros(m, dtype=bool)
        warm_start[usable[chosen]] = True
    warm = np.asarray(warm_start, dtype=bool)
    warm_value = ev.cached_score(warm) if warm.any() else np.inf
    best_full, best_value = polish(ev, warm, usable, seconds=min(5.0, 0.1 * time_limit))
    warm_value = float(warm_value) if np.isfinite(warm_value) else None

    # the heap of open nodes, owned here so the compiled search can pause and grow
    nw = words_for(mu)
    cap = 1 << 12
    max_open = MAX_OPEN_BYTES // (8 + 16 * nw)
    heap_bound = np.empty(cap)
    heap_in = np.zeros((cap, nw), dtype=np.uint64)
    heap_free = np.zeros((cap, nw), dtype=np.uint64)
    heap_bound[0] = -np.inf
    for j in range(mu):
        heap_free[0, j // 64] |= np.uint64(1) << np.uint64(j % 64)
    counts = np.array([1, 0, 0, 0, 0], dtype=np.int64)
    pending = np.zeros((4096, nw), dtype=np.uint64)
    near = NEAR_RANK * ev.rank_tol
    best = np.array([best_value if np.isfinite(best_value) else np.inf])
    best_mask = best_full[usable].copy()
    status, reason = "optimal", None
    budget = ENUMERATION_BUDGET if enumeration_budget is None else int(enumeration_budget)
    chunk, last_report = 64, t0
    while True:
        pops = chunk if node_limit is None else min(chunk, node_limit - int(counts[1]))
        started = time.perf_counter()
        result = expand(gram, r_aug, pen, float(n), ev.sse_scale, ev._sse_floor,
                        ev.rank_tol, tolerance, heap_bound, heap_in, heap_free, counts,
                        best, best_mask, pending, near, pops, budget)
        if counts[4]:  # near rank-deficient candidates: the evaluator decides
            _settle(ev, usable, pending[:counts[4]], best, best_mask)
            counts[4] = 0
        now = time.perf_counter()
        if result == DONE:
            break
        if result == FULL:
            if 2 * cap > max_open:
                status, reason = "limit", f"memory limit ({cap:,} open nodes)"
                break
            heap_bound = np.concatenate([heap_bound, np.empty(cap)])
            heap_in = np.concatenate([heap_in, np.zeros((cap, nw), dtype=np.uint64)])
            heap_free = np.concatenate([heap_free, np.zeros((cap, nw), dtype=np.uint64)])
            cap *= 2
            continue
        if now - started < 0.1:
            chunk = min(chunk * 2, 1 << 20)
        if node_limit is not None and counts[1] >= node_limit:
            status, reason = "limit", f"node limit {node_limit}"
            break
        if now - t0 > time_limit:
            status, reason = "limit", f"time limit {time_limit:g} s"
            break
        if progress is not None and now - last_report > 0.5:
            last_report = now
            progress(int(counts[1]), float(best[0]), float(min(heap_bound[0], best[0])))
    lower = float(best[0]) if status == "optimal" else float(min(heap_bound[0], best[0]))
    mask = np.zeros(m, dtype=bool)
    mask[usable[best_mask]] = True
    value = ev.cached_score(mask) if mask.any() else np.inf
    if value > best[0] + tolerance and status == "optimal":
        # the evaluator (the GA's numbers) disagrees with the search's accurate refit
        status = "limit"
        reason = "the best structure found is near rank-deficient; the evaluator scores it higher"
    return Certificate(status=status, value=float(value), lower_bound=min(lower, float(value)),
                       mask=mask, nodes=int(counts[1]), seconds=time.perf_counter() - t0,
                       reason=reason, warm_start=warm_value)


def certify_data(
    u: np.ndarray, y: np.ndarray, *, term_space, criterion: str = "bic",
    segments: list[tuple[int, int]] | None = None, warm_start: np.ndarray | None = None,
    time_limit: float = 60.0, node_limit: int | None = None,
    progress: Callable[[int, float, float], None] | None = None,
) -> Certificate:
    """:func:`certify` on measured signals (the term space's candidates of u, y).

    The data are scaled by powers of two as :func:`identify` scales them, so the
    values are the GA's; ``warm_start`` is a mask over all candidate terms.
    Terms whose regressor is zero on all rows are left out (they cannot be in an
    identifiable structure). The certificate's ``terms`` are the term names.
    """
    from .terms import power_of_two_scale

    u2 = term_space.inputs_2d(u)
    y = np.asarray(y, dtype=float)
    su = np.array([power_of_two_scale(c) for c in u2.T])
    sy = power_of_two_scale(y)
    P, target = term_space.regression(u2 / su, y / sy, segments)
    nonzero = np.any(P != 0, axis=0)
    warm = None if warm_start is None else np.asarray(warm_start, dtype=bool)[nonzero]
    cert = certify(P[:, nonzero], target, criterion, warm_start=warm, time_limit=time_limit,
                   node_limit=node_limit, sse_scale=sy * sy, progress=progress)
    full = np.zeros(term_space.n_terms, dtype=bool)
    full[np.flatnonzero(nonzero)] = cert.mask
    cert.mask = full
    names = term_space.term_names()
    cert.terms = [names[i] for i in np.flatnonzero(full)]
    return cert
