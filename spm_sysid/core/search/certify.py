"""Certifying the optimum: branch and bound over all 2^M structures.

For AIC and BIC the criterion is ``N ln(SSE(S)/N) + pen(|S|)`` with ``pen``
increasing in the number of terms only, and the SSE never grows when terms are
added. A branch and bound over the terms can therefore prove that a structure
is the best of all (``optimal``) or, when time runs out, bound how far the best
found may be from the optimum (``limit``).

A node fixes some terms *in* (I) and some *out*; the rest (F) are free. Every
structure S of the node has ``I <= S <= T = I + F``. The search
(:mod:`.branch_bound`, compiled) is best first: the open node of the lowest
bound is expanded next, so the lower bound over all structures (the smallest
open bound) rises steadily and a stopped search reports an honest gap. At a
node it bounds every size ``|I| .. |T|`` separately and takes the least:

* the **small sizes** ``|I| + a`` exactly, for every a whose subsets of F fit
  a budget (:data:`ENUMERATION_BUDGET`; one size more where that is the size
  left open): F and the target projected off span(I), every subset visited;
* the **larger sizes** from T downwards: leaving out r free terms raises
  ``SSE(T)`` by at least the r-th smallest single-term cost, the r smallest
  ``theta^2`` over ``||H_FF||_F`` (H: the inverse Gram matrix of T), and a pair
  bound (every pair of the terms left out costs at most what they all cost;
  a core of the graph of cheap pairs must hold them);
* where T's terms are nearly dependent (no factor for the drop costs): the
  small sizes exactly and a span bound on SSE(T) (a QR without a rank test).

A stopped search's gap is also read as one-step MSE: ``value = N ln(MSE) +
pen(k)``, so no structure of at most the result's size has an MSE below
``MSE exp(-gap / N)`` (:attr:`Certificate.mse_lower_bound`).

Incumbents: the warm start (the GA's result, else forward selection), improved
by a local search (one term added, removed or swapped); when no proof came
within :data:`PATH_AFTER` seconds, the polish of forward selection's
structures of every 4th size (:func:`path_incumbent`); and each node's best
subset of each size it enumerates, refitted accurately before it counts.
Values match the evaluator's (:class:`StructureEvaluator`, the GA's own
numbers): candidates with a squared pivot within ``NEAR_RANK`` of the rank
tolerance are scored by the evaluator itself, and the result is re-scored by
it, so "optimal" means: no structure scores lower than the result by more than
``tolerance`` (1e-6) on the criterion's scale. Rank-deficient structures score
+inf, as in the GA.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..compiled.aot import build_status
from ..compiled.registry import jit_available, jit_loaded
from ..cores import usable_cores
from ..defaults import MAX_JUDGED_TERMS
from ..files import json_float
from ..fit.criteria import CERTIFIABLE, Criterion, get_criterion
from ..fit.evaluator import NEAR_RANK, StructureEvaluator
from ..fit.lstsq import DEFAULT_RANK_TOL
from ..memory import check_memory, memory_limit
from ..model.segments import rows_segments
from .branch_bound import (
    DONE,
    FULL,
    Data,
)
from .heaps import (
    MAX_OPEN_BYTES,
    OpenNodes,
    balance,
    check_certify_memory,
    lower_bound,
    share_best,
    worker_bytes,
)
from .local import polish as search_polish

__all__ = ["CERTIFIABLE", "Certificate", "certify", "certify_data", "check_certify_memory",
           "describe_certificate", "ensure_compiled", "penalty_per_size", "search_is_compiled"]



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
    one_step_mse : float or None
        The best structure's one-step mean squared error (the data's units).
    mse_lower_bound : float or None
        No structure of at most as many terms has a one-step MSE below this: the
        lower bound read at the best structure's size (``one_step_mse`` itself when
        optimal). For AIC, AICc and BIC ``value = N ln(MSE) + pen(k)``, so it is
        ``one_step_mse * exp(-gap / N)``.
    """

    status: str
    value: float
    lower_bound: float
    mask: np.ndarray
    nodes: int
    seconds: float
    bound: str = "exact small sizes + drop and pair bounds + span bound (nearly dependent terms)"
    reason: str | None = None
    warm_start: float | None = None
    terms: list[str] = field(default_factory=list)
    one_step_mse: float | None = None
    mse_lower_bound: float | None = None

    @property
    def gap(self) -> float:
        """``value - lower_bound`` (0 when optimal)."""
        return 0.0 if self.status == "optimal" else float(self.value - self.lower_bound)

    @property
    def improved(self) -> bool:
        """The search found a better structure than the warm start."""
        return self.warm_start is not None and self.value < self.warm_start - 1e-9

    def to_dict(self) -> dict:
        """JSON-ready (the ``certify --json`` document and ``metadata.certificate``)."""
        return {"status": self.status, "value": float(self.value),
                "lower_bound": float(self.lower_bound), "gap": float(self.gap),
                "terms": list(self.terms), "nodes": int(self.nodes),
                "seconds": round(float(self.seconds), 4), "bound": self.bound,
                "reason": self.reason, "warm_start": self.warm_start,
                "size": int(np.count_nonzero(self.mask)),
                "one_step_mse": json_float(self.one_step_mse),
                "mse_lower_bound": json_float(self.mse_lower_bound)}


def describe_certificate(doc: dict | None) -> str:
    """A certificate in a few words, for answers, logs and the command line ('' if none).

    ``doc`` is :meth:`Certificate.to_dict` (``model.metadata["certificate"]``).
    """
    if not doc:
        return ""
    if doc["status"] == "optimal":
        text = (f"certified optimal over all structures ({doc['nodes']} nodes, "
                f"{doc['seconds']:.2f} s)")
    elif doc["status"] == "limit":
        text = (f"NOT certified ({doc['reason']}): lower bound {doc['lower_bound']:.2f}, "
                f"gap {doc['gap']:.2f}")
        mse, low = doc.get("one_step_mse"), doc.get("mse_lower_bound")
        if mse and low is not None:
            text += (f"; one-step MSE {mse:.4g}: no structure of at most {doc['size']} terms "
                     f"below {low:.4g} (at most {100.0 * (1.0 - low / mse):.1f} % lower)")
    else:
        return f"not certifiable: {doc['reason']}"
    if doc.get("ga_value") is not None and doc["value"] < doc["ga_value"]:
        text += f"; the search improved on the GA's {doc['ga_value']:.2f}"
    elif doc.get("warm_start") is not None and doc["value"] < doc["warm_start"] - 1e-9:
        text += f"; improved on the warm start ({doc['warm_start']:.4f})"
    return text


def penalty_per_size(criterion: Criterion, n: int, m: int, max_terms: int = 0) -> np.ndarray:
    """``pen(k)`` for k = 0..m, or a ValueError when the criterion is not certifiable.

    The criterion must be ``n ln(SSE/n) + pen(k)`` (checked numerically) with
    ``pen`` increasing. Sizes the criterion rules out (AICc with no degrees of
    freedom left) and sizes above ``max_terms`` (when > 0) get ``+inf``: no
    structure of those sizes can be selected, nor certified.
    """
    if criterion.name not in CERTIFIABLE or criterion.needs_coefficients:
        raise ValueError(
            f"criterion {criterion.name} cannot be certified: its value depends on more "
            f"than the SSE and the number of terms (certifiable: {', '.join(CERTIFIABLE)})")
    k = np.arange(m + 1)
    with np.errstate(invalid="ignore"):
        pen = criterion(np.full(m + 1, float(n)), n, k, None)
        check = criterion(np.full(m + 1, float(n) * np.e), n, k, None)
    finite = np.isfinite(pen)
    usable = int(finite.sum())  # only the largest sizes may be ruled out
    head = slice(0, usable)
    if (usable == 0 or not finite[head].all() or not np.allclose(check[head] - pen[head], n)
            or np.any(np.diff(pen[head]) <= 0)):
        raise ValueError(f"criterion {criterion.name} is not of the form N ln(SSE/N) + pen(k)")
    if max_terms and max_terms < m:
        pen = pen.copy()
        pen[max_terms + 1:] = np.inf
    return pen


#: Subsets of its free terms a node enumerates exactly (its smallest sizes).
ENUMERATION_BUDGET = 3000


#: Seconds a search runs on the ahead-of-time build (one thread) before it loads numba's
#: JIT to run its heaps in parallel: most searches end before, and the JIT costs 0.7 s
#: (none when this process has loaded it already: then the heaps run in parallel at once).
PARALLEL_AFTER = 1.0


def polish(ev: StructureEvaluator, mask: np.ndarray, usable: np.ndarray,
           seconds: float = 5.0, deadline: float | None = None) -> tuple[np.ndarray, float]:
    """The polish (:func:`~spm_sysid.core.search.local.polish`) of ``mask``, for an incumbent.

    One term added, removed or swapped while that helps; a good incumbent lets
    the branch and bound cut more. It stops after ``seconds`` or at
    ``deadline``, whichever is first.
    """
    stop = time.perf_counter() + seconds
    allowed = np.zeros(len(mask), dtype=bool)
    allowed[usable] = True
    res = search_polish(ev.score, mask, allowed, deadline=stop if deadline is None
                        else min(stop, deadline))
    return res.mask, res.value


#: Seconds without a proof after which the search polishes structures along forward
#: selection's path (every :data:`PATH_STRIDE`-th size) for better incumbents, within
#: :data:`PATH_SHARE` of the time limit: on 164-candidate spaces a polish from the
#: GA's best stalls in a local optimum that a start of another size escapes.
PATH_AFTER = 1.0
PATH_STRIDE = 4
PATH_SHARE = 0.2


def path_incumbent(ev: StructureEvaluator, usable: np.ndarray, *, deadline: float,
                   seconds_each: float = 2.0) -> tuple[np.ndarray | None, float]:
    """The best polish of forward selection's structures of every PATH_STRIDE-th size.

    Restarts for the incumbent ("better incumbents early"): forward selection's
    path (one structure per size, up to 60 terms), each 4th polished (one term
    added, removed or swapped while that helps) until ``deadline``. Returns the
    best mask and its value (None, inf when none finished).
    """
    from .forward import forward_selection_path

    best_mask, best_value = None, np.inf
    path = forward_selection_path(ev, max_terms=min(MAX_JUDGED_TERMS, len(usable)))
    for i in range(PATH_STRIDE - 1, len(path), PATH_STRIDE):
        if time.perf_counter() >= deadline:
            break
        mask, value = polish(ev, path[i], usable, seconds=seconds_each, deadline=deadline)
        if value < best_value:
            best_mask, best_value = mask, float(value)
    return best_mask, best_value


_COMPILED = False


def search_is_compiled() -> bool:
    """True when the search is compiled in this process or cached on disk (fast start)."""
    import glob

    from . import branch_bound

    if _COMPILED or build_status():
        return True
    here = os.path.dirname(branch_bound.__file__)
    places = [os.path.join(here, "__pycache__")]
    if os.environ.get("NUMBA_CACHE_DIR"):
        places.append(os.environ["NUMBA_CACHE_DIR"])
    return any(glob.glob(os.path.join(p, "**", "branch_bound.expand-*.nbi"), recursive=True)
               for p in places)


def ensure_compiled() -> None:
    """Compile (the first time ever) or load the search before any clock starts.

    The first use on a machine compiles it (about 20 s here; cached on disk
    after); time limits are meant for the search, not for that.
    """
    global _COMPILED
    if _COMPILED:
        return
    _COMPILED = True
    rng = np.random.default_rng(0)
    P = rng.standard_normal((12, 3))
    certify(P, P @ np.array([1.0, 0.0, 0.5]) + 0.1 * rng.standard_normal(12), "aic",
            threads=1, time_limit=600.0)


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
    threads: int | None = None,
    started: float | None = None,
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
    threads : int, optional
        Workers searching at once, each with its own open nodes, sharing the
        incumbent and dealt nodes best first when one runs short (default: the
        usable cores, at most 8; one when ``node_limit`` is given; fewer when
        the memory bound does not hold more).
    started : float, optional
        ``time.perf_counter()`` when the caller's set-up began (the time limit
        counts from there; default: now).

    The time limit and the memory bound hold in every phase: the set-up's
    memory is checked before anything is built, the local search and forward
    selection stop at the deadline, and a search stopped before it began
    reports the trivial lower bound (all terms' SSE, one term's penalty).

    Raises
    ------
    ValueError
        A criterion that cannot be certified (e.g. PMIC2).
    MemoryLimitError
        The set-up, or one search worker, would exceed the memory bound.
    """
    ensure_compiled()
    t0 = time.perf_counter() if started is None else started
    deadline = t0 + time_limit
    if not time_limit > 0:
        raise ValueError(f"time_limit must be > 0 seconds, got {time_limit}")
    if node_limit is not None and node_limit < 1:
        raise ValueError(f"node_limit must be at least 1, got {node_limit}")
    if threads is not None and threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    crit = get_criterion(criterion)
    if evaluator is None:
        P = np.asarray(P)
        check_certify_memory(*P.shape)
        evaluator = StructureEvaluator(np.asarray(P, dtype=float),
                                       np.asarray(target, dtype=float), crit,
                                       rank_tol=rank_tol, sse_scale=sse_scale)
    ev = evaluator
    n, m = ev.n, ev.n_terms
    if ev.criterion.name != crit.name:
        raise ValueError(f"the evaluator scores {ev.criterion.name}, not {crit.name}")
    pen = penalty_per_size(crit, n, m, ev.max_terms)
    # the evaluator's unit-norm Gram matrix of [P y] and triangular factor (the same
    # least-squares problem in min(n, m + 1) rows), on the non-zero columns
    usable = np.flatnonzero(~ev.zero_columns)
    keep = np.concatenate([usable, [m]])
    rows_r = ev.factor.shape[0]
    mu = len(usable)
    # node_limit asks for an exact count: one worker then; fewer when memory is short
    cores = usable_cores()
    workers = 1 if node_limit is not None else max(1, min(int(threads or cores or 1), 8))
    limit, _ = memory_limit()
    copies = 8.0 * ((mu + 1) ** 2 + rows_r * (mu + 1))  # the search's gram and factor
    per_worker = worker_bytes(rows_r, mu)
    check_memory(copies + per_worker, f"the branch and bound over {mu} candidate terms")
    workers = max(1, min(workers, int((limit - copies) // per_worker)))
    open_bytes = int(min(MAX_OPEN_BYTES, max(limit - copies - workers * per_worker, 0) / 2))
    gram = np.ascontiguousarray(ev.gram[np.ix_(keep, keep)])
    r_aug = np.ascontiguousarray(ev.factor[:, keep])
    trivial = _trivial_bound(r_aug, float(n), ev.sse_scale, ev.sse_floor, pen)

    # incumbent: the warm start (else forward selection), then a local search
    if warm_start is None:
        from .forward import forward_selection

        _, warm_start = forward_selection(ev, max_terms=min(MAX_JUDGED_TERMS, mu),
                                          deadline=deadline)
    warm = np.asarray(warm_start, dtype=bool)
    warm_value = ev.cached_score(warm) if warm.any() else np.inf
    best_full, best_value = polish(ev, warm, usable, seconds=min(5.0, 0.1 * time_limit),
                                   deadline=deadline)
    warm_value = float(warm_value) if np.isfinite(warm_value) else None
    if time.perf_counter() >= deadline:  # the set-up used the time: nothing searched
        value = float(best_value)
        lower = min(trivial, value)
        return Certificate(status="limit", value=value, lower_bound=lower,
                           mask=best_full, nodes=0, seconds=time.perf_counter() - t0,
                           reason=f"time limit {time_limit:g} s (reached while setting the "
                                  "search up)", warm_start=warm_value,
                           **_mse_bounds(value, lower, best_full, pen, n))

    budget = ENUMERATION_BUDGET if enumeration_budget is None else int(enumeration_budget)
    heaps = [OpenNodes(mu, r_aug.shape[0], best_value, best_full[usable], workers,
                        open_bytes) for _ in range(workers)]
    heaps[0].push_root(mu)
    data = Data(gram, r_aug, pen, float(n), ev.sse_scale, ev.sse_floor, ev.rank_tol, tolerance,
                NEAR_RANK * ev.rank_tol)
    status, reason = "optimal", None
    chunk, last_report, restarted = 64, t0, False
    pool = ThreadPoolExecutor(workers) if workers > 1 else None
    search_start = time.perf_counter()
    # the ahead-of-time build holds the GIL: short searches run on it one heap after the
    # other, longer ones switch to numba's JIT (0.7 s to load) and run the heaps in parallel
    serial_for = PARALLEL_AFTER if build_status() and not jit_loaded() else 0.0
    try:
        while True:
            done_nodes = sum(h.nodes for h in heaps)
            pops = chunk if node_limit is None else min(chunk, node_limit - done_nodes)
            started = time.perf_counter()
            busy = [h for h in heaps if h.size]
            if (pool is not None and serial_for and started - search_start >= serial_for
                    and not jit_available()):  # a broken numba: the build, one thread
                pool.shutdown()
                pool = None
            if pool is None or len(busy) == 1 or started - search_start < serial_for:
                results = [h.expand(data, pops, budget) for h in busy]
            else:
                results = list(pool.map(OpenNodes.expand_in_parallel, busy,
                                        [data] * len(busy), [pops] * len(busy),
                                        [budget] * len(busy)))
            for h in busy:
                h.settle(ev, usable)
            share_best(heaps)
            now = time.perf_counter()
            if all(r == DONE for r in results):  # the incumbent only improves: stays proved
                break
            if not restarted and now - search_start >= PATH_AFTER and node_limit is None:
                restarted = True  # no proof yet: restarts for a better incumbent
                mask, value = path_incumbent(
                    ev, usable, deadline=min(deadline, now + PATH_SHARE * time_limit))
                if mask is not None and value < heaps[0].best[0]:
                    heaps[0].best[0] = value
                    heaps[0].best_mask[:] = mask[usable]
                    share_best(heaps)
                now = time.perf_counter()
            full = [h for h, r in zip(busy, results) if r == FULL]
            if any(not h.grow() for h in full):
                status = "limit"
                reason = f"memory limit ({sum(h.size for h in heaps):,} open nodes)"
                break
            if workers > 1:
                balance(heaps)
            # rounds of about 0.1-0.4 s: limits and progress are checked between them
            if now - started < 0.1:
                chunk = min(chunk * 2, 1 << 16)
            elif now - started > 0.4:
                chunk = max(1, chunk // 2)
            if node_limit is not None and sum(h.nodes for h in heaps) >= node_limit:
                status, reason = "limit", f"node limit {node_limit}"
                break
            if now >= deadline:
                status, reason = "limit", f"time limit {time_limit:g} s"
                break
            if progress is not None and now - last_report > 0.5:
                last_report = now
                progress(sum(h.nodes for h in heaps), float(heaps[0].best[0]),
                         lower_bound(heaps))
    finally:
        if pool is not None:
            pool.shutdown()
    best = heaps[0].best
    best_mask = heaps[0].best_mask
    nodes = sum(h.nodes for h in heaps)
    lower = float(best[0]) if status == "optimal" else max(lower_bound(heaps), trivial)
    mask = np.zeros(m, dtype=bool)
    mask[usable[best_mask]] = True
    value = ev.cached_score(mask) if mask.any() else np.inf
    if value > best[0] + tolerance and status == "optimal":
        # the evaluator (the GA's numbers) disagrees with the search's accurate refit
        status = "limit"
        reason = "the best structure found is near rank-deficient; the evaluator scores it higher"
    lower = min(lower, float(value))
    return Certificate(status=status, value=float(value), lower_bound=lower,
                       mask=mask, nodes=int(nodes), seconds=time.perf_counter() - t0,
                       reason=reason, warm_start=warm_value,
                       **_mse_bounds(float(value), lower, mask, pen, n))


def _mse_bounds(value: float, lower: float, mask: np.ndarray, pen: np.ndarray,
                n: float) -> dict:
    """The best structure's one-step MSE, and the least of any structure of its size or less.

    ``value = N ln(MSE) + pen(k)`` read backwards at k = its size.
    """
    k = int(np.count_nonzero(mask))
    if not (k and np.isfinite(value) and np.isfinite(pen[k])):
        return {}
    mse = float(np.exp((value - pen[k]) / n))
    low = float(np.exp((lower - pen[k]) / n)) if np.isfinite(lower) else 0.0
    return {"one_step_mse": mse, "mse_lower_bound": min(low, mse)}


def _trivial_bound(r_aug: np.ndarray, n: float, scale: float, floor: float,
                   pen: np.ndarray) -> float:
    """No structure scores below the SSE of all terms with the penalty of one term."""
    mu = r_aug.shape[1] - 1
    sse = float(r_aug[mu, mu] ** 2) if r_aug.shape[0] > mu else 0.0
    return float(n * np.log(max(sse, floor) * scale / n) + pen[1]) if mu else np.inf


def certify_data(
    u: np.ndarray, y: np.ndarray, *, term_space, criterion: str = "bic",
    segments: list[tuple[int, int]] | None = None, warm_start: np.ndarray | None = None,
    time_limit: float = 60.0, node_limit: int | None = None,
    progress: Callable[[int, float, float], None] | None = None,
    threads: int | None = None,
    started: float | None = None,
) -> Certificate:
    """:func:`certify` on measured signals (the term space's candidates of u, y).

    The data are scaled by powers of two as :func:`identify` scales them, so the
    values are the GA's; ``warm_start`` is a mask over all candidate terms.
    Terms whose regressor is zero on all rows, or proportional to an earlier
    term's, are left out as :func:`identify` leaves them out. The certificate's
    ``terms`` are the term names.
    ``started`` (``time.perf_counter()``) is when the caller's work began, e.g. a
    warm-start GA: the time limit counts from there (default: now).
    """
    from ..fit.problem import Problem

    ensure_compiled()  # the first use compiles; the time limit starts after
    started = time.perf_counter() if started is None else started
    n = len(np.asarray(y))
    lag = term_space.max_lag
    segs = rows_segments(segments, n, lag)
    check_certify_memory(max(sum(b - a - lag for a, b in segs), 0), term_space.n_terms)
    problem = Problem.from_signals(u, y, term_space, segments)
    crit = get_criterion(criterion)
    warm = None if warm_start is None else problem.restrict(
        np.asarray(warm_start, dtype=bool) & problem.usable)
    cert = certify(None, None, crit, warm_start=warm, time_limit=time_limit,
                   node_limit=node_limit, progress=progress, threads=threads, started=started,
                   evaluator=problem.evaluator(crit))
    cert.mask = problem.expand(cert.mask)
    names = term_space.term_names()
    cert.terms = [names[i] for i in np.flatnonzero(cert.mask)]
    return cert
