"""Local search over structures: one term added, removed or swapped at a time.

One routine serves every search that moves through structures by single-term
changes: the polish of a certification's incumbent (add, remove, swap), the
simulation-focused selection's search around the best refined structure
(add, remove), and forward selection (add only, greedy, with patience).

Each step scores every neighbour allowed by ``moves`` (in batches of bounded
memory), and moves to the best one:

* by default only while that improves the value (best improvement; a local
  optimum ends the search);
* with ``patience`` > 0 also when it does not, until ``patience`` steps in a
  row have brought no new best (forward selection's look-ahead); the best
  structure seen is returned.

The search stops at ``deadline`` (``time.perf_counter()``) between batches,
after ``max_steps`` steps, or when no neighbour is left.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..defaults import (
    POLISH_FLIPS,
    POLISH_HOME,
    POLISH_KICKS,
    POLISH_PATIENCE,
    POLISH_RESTART_FLIPS,
    POLISH_RESTARTS,
    POLISH_STEPS,
    POLISH_STRUCTURES,
    POLISH_TERMS,
)
from .neighbourhood import MOVES, MoveScreen

__all__ = ["MOVES", "POLISH_STEPS", "POLISH_STRUCTURES", "PolishResult", "SearchResult",
           "local_search", "neighbours", "polish"]


#: Neighbours scored at once (bounds memory: a batch of structures over M terms
#: takes BATCH_BITS / 8 bytes of masks).
BATCH_BITS = 1 << 25


@dataclass
class SearchResult:
    """Where a local search ended: the best structure seen and its value."""

    mask: np.ndarray
    value: float
    steps: int
    scored: int
    stopped: str  # "local optimum", "patience", "max steps", "deadline", "budget",
    #               "no neighbour"


def neighbours(mask: np.ndarray, allowed: np.ndarray, moves: Sequence[str] = MOVES,
               batch_bits: int | None = None):
    """Batches of the structures one move away from ``mask`` (empty structures left out).

    ``allowed`` marks the terms a move may add (and swap in).
    """
    mask = np.asarray(mask, dtype=bool)
    inn = np.flatnonzero(mask)
    out = np.flatnonzero(~mask & np.asarray(allowed, dtype=bool))
    drop, add = [], []
    if "remove" in moves:
        drop.append(inn)
        add.append(np.full(len(inn), -1))
    if "add" in moves:
        drop.append(np.full(len(out), -1))
        add.append(out)
    if "swap" in moves:
        drop.append(np.repeat(inn, len(out)))
        add.append(np.tile(out, len(inn)))
    drop = np.concatenate(drop) if drop else np.empty(0, dtype=int)
    add = np.concatenate(add) if add else np.empty(0, dtype=int)
    rows = max(1, (BATCH_BITS if batch_bits is None else batch_bits) // max(len(mask), 1))
    for start in range(0, len(drop), rows):
        d, a = drop[start:start + rows], add[start:start + rows]
        batch = np.repeat(mask[None, :], len(d), axis=0)
        r = np.arange(len(d))
        batch[r[d >= 0], d[d >= 0]] = False
        batch[r[a >= 0], a[a >= 0]] = True
        batch = batch[batch.any(axis=1)]
        if len(batch):
            yield batch


def local_search(
    score: Callable[[np.ndarray], np.ndarray], start: np.ndarray, allowed: np.ndarray, *,
    moves: Sequence[str] = MOVES, start_value: float | None = None, patience: int = 0,
    max_steps: int | None = None, deadline: float | None = None, min_steps: int = 0,
    max_scored: int | None = None, tolerance: float = 1e-9,
    on_step: Callable[[np.ndarray, float], None] | None = None,
) -> SearchResult:
    """Move from ``start`` by single-term changes while that helps (see the module doc).

    Parameters
    ----------
    score : callable
        ``score(masks) -> values`` for a (B, M) batch; lower is better (+inf: unusable).
    start, allowed : ndarray of bool, shape (M,)
        Where to begin (may be empty: then only additions); terms a move may bring in.
    moves, tolerance : sequence of str, float
        Among :data:`MOVES`; an improvement must exceed ``tolerance``.
    start_value : float, optional
        The start's value when known (else it is scored; an empty start is +inf).
    patience : int
        Steps in a row without a new best before stopping (0: at a local optimum).
    max_steps, min_steps : int
        Most steps; steps taken whatever the deadline (forward selection takes one).
    deadline : float, optional
        ``time.perf_counter()`` at which to stop, checked between batches.
    max_scored : int, optional
        Most neighbours scored in all (unlike ``deadline``, the same result on any
        machine); the best scored is still taken if it improves.
    on_step : callable, optional
        ``on_step(structure, value)`` after every step.
    """
    current, value = _start(score, start, start_value, moves)
    best, best_value = current.copy(), value
    steps = scored = since = 0
    while True:
        timed = deadline is not None and steps >= min_steps
        limit = _limit(steps, max_steps, deadline if timed else None)
        if limit:
            return SearchResult(best, best_value, steps, scored, limit)
        move, move_value, scored, spent = _best_neighbour(
            score, current, allowed, moves, scored, max_scored, deadline if timed else None)
        improves = move is not None and move_value < value - tolerance
        if spent and not improves:
            return SearchResult(best, best_value, steps, scored, "budget")
        if move is None or not np.isfinite(move_value):
            return SearchResult(best, best_value, steps, scored, "no neighbour")
        if not improves and patience == 0:
            return SearchResult(best, best_value, steps, scored, "local optimum")
        current, value = move, move_value
        steps += 1
        if on_step is not None:
            on_step(current, value)
        if value < best_value - tolerance:
            best, best_value, since = current.copy(), value, 0
        else:
            since += 1
        if spent:
            return SearchResult(best, best_value, steps, scored, "budget")
        if since and since >= patience:
            return SearchResult(best, best_value, steps, scored, "patience")


def _limit(steps: int, max_steps: int | None, deadline: float | None) -> str | None:
    """What stops the search before its next step ("max steps", "deadline"), if anything."""
    if max_steps is not None and steps >= max_steps:
        return "max steps"
    if deadline is not None and time.perf_counter() >= deadline:
        return "deadline"
    return None


def _start(score: Callable[[np.ndarray], np.ndarray], start: np.ndarray,
           start_value: float | None, moves: Sequence[str]) -> tuple[np.ndarray, float]:
    """The start (a copy) and its value (scored unless given; an empty start is +inf)."""
    unknown = set(moves) - set(MOVES)
    if unknown:
        raise ValueError(f"moves must be among {', '.join(MOVES)}, got {sorted(unknown)}")
    current = np.asarray(start, dtype=bool).copy()
    if start_value is None:
        start_value = float(score(current[None, :])[0]) if current.any() else np.inf
    return current, float(start_value)


def _best_neighbour(score: Callable[[np.ndarray], np.ndarray], current: np.ndarray,
                    allowed: np.ndarray, moves: Sequence[str], scored: int,
                    max_scored: int | None,
                    deadline: float | None) -> tuple[np.ndarray | None, float, int, bool]:
    """The best neighbour of ``current`` scored within the budget and the deadline.

    Returns it (None when none was scored), its value, the neighbours scored in
    all, and whether the budget ``max_scored`` is spent.
    """
    move, move_value, spent = None, np.inf, False
    for batch in neighbours(current, allowed, moves):
        if max_scored is not None:
            batch = batch[:max(max_scored - scored, 0)]
            spent = scored + len(batch) >= max_scored
            if not len(batch):
                break
        values = np.asarray(score(batch), dtype=float)
        scored += len(batch)
        i = int(np.argmin(values))
        if values[i] < move_value:
            move, move_value = batch[i].copy(), float(values[i])
        if spent or (deadline is not None and time.perf_counter() >= deadline):
            break
    return move, move_value, scored, spent


#: A kicked structure whose add/remove descent ends within this of the best so far is
#: searched with swaps too, while a swap step (k (n - k) structures) costs at most
#: 1 / POLISH_SWAP_SHARE of the budget; beyond, swap searches after every kick spend
#: the budget on a few kicks, and only the best is searched with swaps, at the end.
#: Measured: at 84 candidates (robot arm and dryer, AIC, 20 GA seeds each) swaps at
#: the end reach the best known structure on 8 and 3 seeds instead of 5 and 0 with the
#: same budget; on the paper's 44 candidates swaps after each kick reach it more often
#: (171 of 180 runs against 168 with swaps at the end), so they stay there.
POLISH_SLACK = 2.0
POLISH_SWAP_SHARE = 40


@dataclass
class PolishResult:
    """Where a polish ended: the structure, its value, and what it cost."""

    mask: np.ndarray
    value: float
    steps: int
    scored: int
    kicks: int
    moves: tuple[str, ...]
    stopped: str
    budget: int | None


#: ``progress(done, budget, best)``: the polish's work done of its budget, and its best.
PolishProgress = Callable[[int, int, float], None]


def polish(score: Callable[[np.ndarray], np.ndarray], mask: np.ndarray, allowed: np.ndarray,
           *, value: float | None = None, kick_terms: np.ndarray | None = None,
           usable_terms: int | None = None, deadline: float | None = None,
           screen: MoveScreen | None = None, progress: PolishProgress | None = None
           ) -> PolishResult:
    """Improve a structure by single-term moves, then by kicks: the one polish.

    Without ``kick_terms``: a local search (terms added, removed or swapped,
    :func:`local_search`) until no move helps or ``deadline`` -- the
    certification's incumbent. With ``kick_terms`` (the GA's best): within a
    budget of :data:`POLISH_STRUCTURES` scored structures (fewer for structures
    of more than :data:`POLISH_TERMS` terms; swaps only where they fit the
    budget, judged on ``usable_terms``), an iterated local search: the GA's
    best is usually a local optimum of single-term moves, so it is kicked
    (:data:`POLISH_FLIPS` terms of ``kick_terms`` flipped) and descended cheaply
    (additions and removals), keeping the best. Swaps: where a swap step is cheap
    (:data:`POLISH_SWAP_SHARE`), after each kick whose descent ends near the
    best (:data:`POLISH_SLACK`); in larger spaces only once, from the best the
    kicks found, on the quarter of the budget they leave. The kicks are drawn
    from the structure itself, so the polish is reproducible.

    With a ``screen`` as well (criteria of the SSE and the size:
    :meth:`~.neighbourhood.MoveScreen.usable`), every move of every descent is
    ranked from the least-squares factor instead, swaps included, and the
    search restarts when its kicks stop helping (:func:`_screened_polish`).

    ``progress(done, budget, best)`` is called after each kick's descent (work
    done of the budget: neighbourhoods ranked or structures scored).
    """
    if kick_terms is None:
        res = local_search(score, mask, allowed, start_value=value, deadline=deadline)
        return PolishResult(res.mask, float(res.value), res.steps, res.scored, 0, MOVES,
                            res.stopped, None)
    if screen is not None:
        return _screened_polish(score, mask, allowed, value, kick_terms, screen, deadline,
                                progress or _quiet)
    return _counted_polish(score, mask, allowed, value, kick_terms, usable_terms, deadline,
                           progress or _quiet)


def _quiet(done: int, budget: int, best: float) -> None:
    """No progress reports."""


def _counted_polish(score, mask, allowed, value, kick_terms, usable_terms, deadline,
                    progress: PolishProgress) -> PolishResult:
    """The iterated local search within a count of structures scored (see :func:`polish`)."""
    n = usable_terms if usable_terms is not None else int(allowed.sum())
    k = int(mask.sum())
    budget = min(POLISH_STRUCTURES, int(POLISH_STRUCTURES * (POLISH_TERMS / max(k, 1)) ** 2))
    # swaps are k (n - k) neighbours a step: in large spaces only additions and removals
    moves = ("remove", "add", "swap") if k * (n - k) <= budget // 4 else ("remove", "add")
    res = local_search(score, mask, allowed, moves=moves, start_value=value,
                       max_scored=budget, deadline=deadline)
    best_mask, best_value, steps, scored = res.mask, float(res.value), res.steps, res.scored
    rng = np.random.default_rng(zlib.crc32(np.packbits(mask).tobytes()))
    cheap = ("remove", "add")
    low, high = POLISH_FLIPS[0], min(POLISH_FLIPS[1], len(kick_terms) // 2 + 1)
    kicks, improved = 0, False
    # swaps after each promising kick while a swap step is cheap; else only at the end
    swap_each = moves != cheap and k * (n - k) <= budget // POLISH_SWAP_SHARE
    kick_budget = budget - (budget // 4 if moves != cheap and not swap_each else 0)
    while kicks < POLISH_KICKS and scored < kick_budget and high > low:
        kicks += 1
        start = best_mask.copy()
        flip = rng.choice(kick_terms, size=int(rng.integers(low, high)), replace=False)
        start[flip] = ~start[flip]
        if not start.any():
            continue
        r, cost = _descend(score, start, allowed, moves if swap_each else cheap, best_value,
                           kick_budget - scored, budget - scored, deadline)
        scored += cost
        if r.value < best_value - 1e-9:
            best_mask, best_value, steps, improved = r.mask, float(r.value), steps + r.steps, True
        progress(scored, budget, best_value)
    if improved and moves != cheap and not swap_each:
        r = local_search(score, best_mask, allowed, moves=moves, start_value=best_value,
                         max_scored=budget - scored, deadline=deadline)
        scored += r.scored
        if r.value < best_value - 1e-9:
            best_mask, best_value, steps = r.mask, float(r.value), steps + r.steps
    return PolishResult(best_mask, best_value, steps, scored, kicks, moves,
                        "budget" if scored >= budget else res.stopped, budget)


#: A screened descent's end is scored by the evaluator when its value from the
#: screen is within this of the best (the two agree to rounding on well-conditioned
#: structures; near the rank tolerance the evaluator has the last word).
SCREEN_MARGIN = 1e-3


def _screened_polish(score, mask, allowed, value, kick_terms, screen: MoveScreen,
                     deadline: float | None, progress: PolishProgress) -> PolishResult:
    """The iterated local search with every move ranked by ``screen``, restarted when stuck.

    Descents take the best of every addition, removal and swap by the screen's
    values (:meth:`~.neighbourhood.MoveScreen.descend`); an end that may beat
    the best is scored by the evaluator. Kicks (:data:`POLISH_FLIPS` terms
    flipped) start from the current structure, which moves to a kick's end when
    that is better; after :data:`POLISH_PATIENCE` kicks in a row that are not,
    a larger kick from the best (:data:`POLISH_RESTART_FLIPS`) becomes the
    current one, so the search leaves a basin the small kicks cannot. It stops
    after :data:`POLISH_RESTARTS` restarts in a row without a new best, after
    :data:`POLISH_HOME` descents in a row that lead back to the best itself, or
    after :data:`POLISH_STEPS` neighbourhoods ranked (fewer in large spaces:
    :meth:`~.neighbourhood.MoveScreen.step_budget`).
    """
    best_mask = np.asarray(mask, dtype=bool).copy()
    best_value = float(score(best_mask[None, :])[0]) if value is None else float(value)
    rng = np.random.default_rng(zlib.crc32(np.packbits(best_mask).tobytes()))
    search = _Kicks(rng, kick_terms)
    current, current_value = best_mask, np.inf  # the first descent starts at the GA's best
    budget = screen.step_budget(int(best_mask.sum()))
    left, scored, kicks, since, restarts, steps, home = budget, 0, 0, 0, 0, 0, 0
    start = best_mask.copy()
    while left > 0 and restarts <= POLISH_RESTARTS and home < POLISH_HOME:
        if deadline is not None and time.perf_counter() >= deadline:
            break
        end, approx, used = screen.descend(start, allowed, left)
        left -= used
        restarted = since >= POLISH_PATIENCE
        if restarted or approx < current_value - 1e-9:
            current, current_value, since = end, approx, 0
            restarts += restarted
        else:
            since += 1
        home = home + 1 if np.array_equal(end, best_mask) else 0
        if approx < best_value + SCREEN_MARGIN and not home:
            end_value = float(score(end[None, :])[0])
            scored += 1
            if end_value < best_value - 1e-9:
                best_mask, best_value, steps, restarts = end, end_value, steps + used, 0
        kicks += 1
        progress(budget - max(left, 0), budget, best_value)
        start = search.kick(best_mask if since >= POLISH_PATIENCE else current,
                            since >= POLISH_PATIENCE)
    stopped = "budget" if left <= 0 else "restarts" if home < POLISH_HOME else "home"
    return PolishResult(best_mask, best_value, steps, scored, kicks - 1, MOVES, stopped,
                        budget)


@dataclass
class _Kicks:
    """Random flips of a structure's terms, drawn reproducibly."""

    rng: np.random.Generator
    terms: np.ndarray

    def kick(self, mask: np.ndarray, large: bool) -> np.ndarray:
        """``mask`` with :data:`POLISH_FLIPS` (``large``: :data:`POLISH_RESTART_FLIPS`) flipped."""
        low, high = POLISH_RESTART_FLIPS if large else POLISH_FLIPS
        high = max(min(high, len(self.terms) // 2 + 1), low + 1)
        start = mask.copy()
        flip = self.rng.choice(self.terms, size=min(int(self.rng.integers(low, high)),
                                                    len(self.terms)), replace=False)
        start[flip] = ~start[flip]
        return start if start.any() else mask.copy()


def _descend(score, start: np.ndarray, allowed: np.ndarray, moves: Sequence[str],
             best_value: float, cheap_room: int, room: int, deadline: float | None
             ) -> tuple[SearchResult, int]:
    """A kicked structure descended by additions and removals, then maybe by swaps.

    Swaps when ``moves`` hold them and the first descent ended within
    :data:`POLISH_SLACK` of ``best_value``. Returns the search's end and the
    structures scored (at most ``cheap_room``, then ``room`` in all).
    """
    r = local_search(score, start, allowed, moves=("remove", "add"), max_scored=cheap_room,
                     deadline=deadline)
    scored = r.scored
    if "swap" in moves and r.value < best_value + POLISH_SLACK:
        r = local_search(score, r.mask, allowed, moves=moves, start_value=r.value,
                         max_scored=room - scored, deadline=deadline)
        scored += r.scored
    return r, scored
