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
from dataclasses import dataclass

import numpy as np

from ..compiled.aot import build_status
from ..compiled.registry import jit_available, jit_loaded
from ..cores import usable_cores
from ..defaults import MAX_JUDGED_TERMS
from ..fit.criteria import CERTIFIABLE, Criterion, get_criterion
from ..fit.evaluator import NEAR_RANK, StructureEvaluator
from ..fit.lstsq import DEFAULT_RANK_TOL
from ..memory import check_memory, memory_limit
from .branch_bound import (
    DONE,
    FULL,
    Data,
)
from .certificate import (
    Certificate,
    describe_certificate,
    mse_bounds,
    penalty_per_size,
    trivial_bound,
)
from .explain import weakest_nodes
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

__all__ = ["CERTIFIABLE", "Certificate", "certify", "check_certify_memory",
           "describe_certificate", "ensure_compiled", "penalty_per_size", "search_is_compiled"]


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
    P: np.ndarray, target: np.ndarray, criterion: str | Criterion = "bic", *,
    warm_start: np.ndarray | None = None, time_limit: float = 60.0,
    node_limit: int | None = None, sse_scale: float = 1.0, tolerance: float = 1e-6,
    rank_tol: float = DEFAULT_RANK_TOL, progress: Callable[[int, float, float], None] | None = None,
    evaluator: StructureEvaluator | None = None, enumeration_budget: int | None = None,
    threads: int | None = None, started: float | None = None, explain: int = 0,
    cutoff: float | None = None) -> Certificate:
    """Search all structures of the columns of ``P`` exactly (see the module doc).

    Parameters
    ----------
    P, target : ndarray
        As for :class:`StructureEvaluator` (None when ``evaluator`` is given).
    criterion : str or Criterion
        ``aic``, ``aicc`` or ``bic``.
    warm_start : ndarray of bool, optional
        A good structure (the GA's; default: forward selection's), polished first.
    time_limit, node_limit : float, int, optional
        Seconds, nodes before stopping with ``limit``.
    sse_scale, rank_tol, tolerance : float
        As for the evaluator; subtrees within ``tolerance`` of the incumbent are cut.
    progress, evaluator : callable, StructureEvaluator, optional
        ``progress(nodes, best, lower_bound)`` about every 0.5 s; the GA's evaluator
        (same data and criterion) to reuse its cache and numbers.
    enumeration_budget : int, optional
        Subsets of free terms a node enumerates (default :data:`ENUMERATION_BUDGET`).
    threads : int, optional
        Workers, each with its own open nodes (default: usable cores, at most 8; 1 with
        ``node_limit``; fewer when memory is short).
    started : float, optional
        ``time.perf_counter()`` when the caller's set-up began (default: now).
    explain : int, optional
        When stopped by a limit: its weakest open nodes, bounded again size by size
        (:attr:`Certificate.weakest`, :mod:`.explain`; after the time limit).
    cutoff : float, optional
        Seek only structures below this (a split space's other part, :mod:`.split`).

    Raises
    ------
    ValueError, MemoryLimitError
        An uncertifiable criterion (PMIC2), an impossible limit; memory past the bound.
    """
    ensure_compiled()
    t0 = time.perf_counter() if started is None else started
    deadline = t0 + time_limit
    _check_limits(time_limit, node_limit, threads)
    ev = _evaluator(evaluator, P, target, criterion, rank_tol=rank_tol, sse_scale=sse_scale)
    search = _Search.set_up(ev, ev.criterion, node_limit, threads, tolerance)
    best_full, best_value, warm_value = _incumbent(ev, search.usable, warm_start, deadline,
                                                   time_limit)
    if time.perf_counter() >= deadline:  # the set-up used the time: nothing searched
        return _unsearched(search, best_full, float(best_value), warm_value, t0=t0,
                           time_limit=time_limit)
    budget = ENUMERATION_BUDGET if enumeration_budget is None else int(enumeration_budget)
    heaps = search.heaps(best_value if cutoff is None else min(best_value, cutoff), best_full)
    status, reason = search.run(heaps, budget, deadline=deadline, time_limit=time_limit,
                                node_limit=node_limit, progress=progress)
    return _certificate(ev, search, heaps, status, reason, t0=t0, tolerance=tolerance,
                        warm_value=warm_value, explain=(explain, budget), cutoff=cutoff)


def _evaluator(given: StructureEvaluator | None, P: np.ndarray, target: np.ndarray,
               criterion: str | Criterion, *, rank_tol: float,
               sse_scale: float) -> StructureEvaluator:
    """The evaluator given (it must score ``criterion``), else that of ``P`` and ``target``.

    A new one is built once the memory bound holds its set-up.
    """
    crit = get_criterion(criterion)
    if given is not None:
        if given.criterion.name != crit.name:
            raise ValueError(f"the evaluator scores {given.criterion.name}, not {crit.name}")
        return given
    P = np.asarray(P)
    check_certify_memory(*P.shape)
    return StructureEvaluator(np.asarray(P, dtype=float), np.asarray(target, dtype=float),
                              crit, rank_tol=rank_tol, sse_scale=sse_scale)


def _unsearched(search: _Search, best_full: np.ndarray, value: float,
                warm_value: float | None, *, t0: float, time_limit: float) -> Certificate:
    """The set-up used the time: the incumbent with the trivial lower bound.

    The time limit holds in every phase: the local search and forward selection
    stop at the deadline, and nothing else is searched.
    """
    lower = min(search.trivial, value)
    return Certificate(status="limit", value=value, lower_bound=lower,
                       mask=best_full, nodes=0, seconds=time.perf_counter() - t0,
                       reason=f"time limit {time_limit:g} s (reached while setting the "
                              "search up)", warm_start=warm_value,
                       **mse_bounds(value, lower, best_full, search.pen, search.ev.n))


def _check_limits(time_limit: float, node_limit: int | None, threads: int | None) -> None:
    """A ValueError naming a limit no search can keep."""
    if not time_limit > 0:
        raise ValueError(f"time_limit must be > 0 seconds, got {time_limit}")
    if node_limit is not None and node_limit < 1:
        raise ValueError(f"node_limit must be at least 1, got {node_limit}")
    if threads is not None and threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")


def _incumbent(ev: StructureEvaluator, usable: np.ndarray, warm_start: np.ndarray | None,
               deadline: float, time_limit: float) -> tuple[np.ndarray, float, float | None]:
    """The first incumbent: the warm start (else forward selection's), polished.

    Returns its mask, its value and the warm start's own value (None when not finite).
    """
    if warm_start is None:
        from .forward import forward_selection

        _, warm_start = forward_selection(ev, max_terms=min(MAX_JUDGED_TERMS, len(usable)),
                                          deadline=deadline)
    warm = np.asarray(warm_start, dtype=bool)
    warm_value = ev.cached_score(warm) if warm.any() else np.inf
    best_full, best_value = polish(ev, warm, usable, seconds=min(5.0, 0.1 * time_limit),
                                   deadline=deadline)
    return best_full, best_value, float(warm_value) if np.isfinite(warm_value) else None


@dataclass
class _Search:
    """The branch and bound's shared data, its workers and the memory each may use."""

    ev: StructureEvaluator
    usable: np.ndarray
    pen: np.ndarray
    data: Data
    workers: int
    open_bytes: int
    trivial: float

    @classmethod
    def set_up(cls, ev: StructureEvaluator, crit: Criterion, node_limit: int | None,
               threads: int | None, tolerance: float) -> _Search:
        """Gram matrix and factor on the non-zero columns; workers the memory bound holds."""
        n, m = ev.n, ev.n_terms
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
        data = Data(gram, r_aug, pen, float(n), ev.sse_scale, ev.sse_floor, ev.rank_tol,
                    tolerance, NEAR_RANK * ev.rank_tol)
        return cls(ev, usable, pen, data, workers, open_bytes,
                   trivial_bound(r_aug, float(n), ev.sse_scale, ev.sse_floor, pen))

    def heaps(self, best_value: float, best_full: np.ndarray) -> list[OpenNodes]:
        """One heap of open nodes per worker, the root in the first."""
        mu = len(self.usable)
        heaps = [OpenNodes(mu, self.data.r_ext.shape[0], best_value, best_full[self.usable],
                           self.workers, self.open_bytes) for _ in range(self.workers)]
        heaps[0].push_root(mu)
        return heaps

    def run(self, heaps: list[OpenNodes], budget: int, *, deadline: float, time_limit: float,
            node_limit: int | None, progress: Callable | None) -> tuple[str, str | None]:
        """Expand the heaps in rounds until proved or a limit is met: (status, reason)."""
        rounds = _Rounds(self.workers)
        try:
            while True:
                started = time.perf_counter()
                results, busy = rounds.expand(heaps, self.data, budget, node_limit)
                for h in busy:
                    h.settle(self.ev, self.usable)
                share_best(heaps)
                if all(r == DONE for r in results):  # the incumbent only improves: stays proved
                    return "optimal", None
                now = self._restart(heaps, rounds, time_limit, deadline, node_limit)
                full = [h for h, r in zip(busy, results) if r == FULL]
                if any(not h.grow() for h in full):
                    return "limit", f"memory limit ({sum(h.size for h in heaps):,} open nodes)"
                if self.workers > 1:
                    balance(heaps)
                rounds.pace(now - started)
                if node_limit is not None and sum(h.nodes for h in heaps) >= node_limit:
                    return "limit", f"node limit {node_limit}"
                if now >= deadline:
                    return "limit", f"time limit {time_limit:g} s"
                rounds.report(heaps, now, progress)
        finally:
            rounds.close()

    def _restart(self, heaps: list[OpenNodes], rounds: _Rounds, time_limit: float,
                 deadline: float, node_limit: int | None) -> float:
        """Once, after PATH_AFTER s without a proof: restarts for a better incumbent."""
        now = time.perf_counter()
        if rounds.restarted or now - rounds.search_start < PATH_AFTER or node_limit is not None:
            return now
        rounds.restarted = True
        mask, value = path_incumbent(self.ev, self.usable,
                                     deadline=min(deadline, now + PATH_SHARE * time_limit))
        if mask is not None and value < heaps[0].best[0]:
            heaps[0].best[0] = value
            heaps[0].best_mask[:] = mask[self.usable]
            share_best(heaps)
        return time.perf_counter()


class _Rounds:
    """The search's rounds: how many nodes each pops, on one thread or several, and reports."""

    def __init__(self, workers: int) -> None:
        self.chunk = 64
        self.pool = ThreadPoolExecutor(workers) if workers > 1 else None
        self.search_start = time.perf_counter()
        self.last_report = self.search_start
        self.restarted = False
        # the ahead-of-time build holds the GIL: short searches run on it one heap after the
        # other, longer ones switch to numba's JIT (0.7 s to load) and run the heaps in parallel
        self.serial_for = PARALLEL_AFTER if build_status() and not jit_loaded() else 0.0

    def expand(self, heaps: list[OpenNodes], data: Data, budget: int,
               node_limit: int | None) -> tuple[list[int], list[OpenNodes]]:
        """One round over the heaps that hold nodes: their results, and those heaps."""
        done_nodes = sum(h.nodes for h in heaps)
        pops = self.chunk if node_limit is None else min(self.chunk, node_limit - done_nodes)
        elapsed = time.perf_counter() - self.search_start
        busy = [h for h in heaps if h.size]
        if (self.pool is not None and self.serial_for and elapsed >= self.serial_for
                and not jit_available()):  # a broken numba: the build, one thread
            self.close()
        if self.pool is None or len(busy) == 1 or elapsed < self.serial_for:
            return [h.expand(data, pops, budget) for h in busy], busy
        return list(self.pool.map(OpenNodes.expand_in_parallel, busy, [data] * len(busy),
                                  [pops] * len(busy), [budget] * len(busy))), busy

    def pace(self, seconds: float) -> None:
        """Rounds of about 0.1-0.4 s: limits and progress are checked between them."""
        if seconds < 0.1:
            self.chunk = min(self.chunk * 2, 1 << 16)
        elif seconds > 0.4:
            self.chunk = max(1, self.chunk // 2)

    def report(self, heaps: list[OpenNodes], now: float, progress: Callable | None) -> None:
        """``progress(nodes, best, lower bound)`` about every 0.5 s."""
        if progress is not None and now - self.last_report > 0.5:
            self.last_report = now
            progress(sum(h.nodes for h in heaps), float(heaps[0].best[0]), lower_bound(heaps))

    def close(self) -> None:
        """The thread pool ends (the rounds go on in this thread)."""
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None


def _certificate(ev: StructureEvaluator, search: _Search, heaps: list[OpenNodes], status: str,
                 reason: str | None, *, t0: float, tolerance: float, warm_value: float | None,
                 explain: tuple[int, int] = (0, 0), cutoff: float | None = None
                 ) -> Certificate:
    """The best structure re-scored by the evaluator, with its lower bound.

    ``explain``: (nodes, enumeration budget): a search stopped by a limit gets that many
    of its weakest open nodes bounded again (:func:`~.explain.weakest_nodes`).
    ``cutoff``: as for :func:`certify`; a proof that nothing is below it stays a proof
    when the best structure found is above it.
    """
    best = heaps[0].best
    nodes = sum(h.nodes for h in heaps)
    lower = float(best[0]) if status == "optimal" else max(lower_bound(heaps), search.trivial)
    mask = np.zeros(ev.n_terms, dtype=bool)
    mask[search.usable[heaps[0].best_mask]] = True
    value = ev.cached_score(mask) if mask.any() else np.inf
    below_cutoff = cutoff is None or best[0] < cutoff
    if value > best[0] + tolerance and status == "optimal" and below_cutoff:
        # the evaluator (the GA's numbers) disagrees with the search's accurate refit
        status = "limit"
        reason = "the best structure found is near rank-deficient; the evaluator scores it higher"
    lower = min(lower, float(value))
    cert = Certificate(status=status, value=float(value), lower_bound=lower,
                       mask=mask, nodes=int(nodes), seconds=time.perf_counter() - t0,
                       reason=reason, warm_start=warm_value,
                       **mse_bounds(float(value), lower, mask, search.pen, ev.n))
    if explain[0] and status == "limit":
        cert.weakest = weakest_nodes(heaps, search.data, search.usable, explain[1], explain[0])
    return cert

