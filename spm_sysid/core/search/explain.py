"""What holds a stopped certification's lower bound: its weakest open nodes, size by size.

A search that stops with ``limit`` proves ``lower_bound`` = the least bound of
its open nodes. To see why the gap stays, each of the weakest open nodes is
bounded once more on its own, as the search would bound it when popped
(:func:`~.branch_bound.expand` on a heap holding that node only, against the
same incumbent): the bound of every size ``|I| .. |T|`` it reaches, the size
whose bound is the least (what holds the node open), which sizes are known
exactly and how many still reach below the incumbent. A node that closes when
expanded was open only for want of time; one whose own bound stays low at some
size is where stronger per-size bounds would act.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .bb_state import NEAR_BRANCHES, OPEN
from .heaps import OpenNodes

__all__ = ["WeakNode", "explain_table", "weakest_nodes"]


@dataclass
class WeakNode:
    """One open node of a stopped search, bounded again on its own.

    Attributes
    ----------
    bound : float
        Its bound in the heap (from its parent): what the certificate's lower bound reads.
    inside, free : list of int
        The terms fixed in, and the free ones (the evaluator's columns).
    out : int
        Terms fixed out.
    own_bound : float
        The least bound of its sizes when bounded at the node, at least ``bound``
        (``inf``: it closes there).
    weakest_size : int or None
        The size whose bound is ``own_bound``.
    exact_up_to : int
        Sizes up to this one are enumerated (every subset; exact unless a subset is
        nearly dependent, which then counts as fitting down to a lower bound on SSE(T)).
    open_sizes : int
        Sizes whose bound is still below the incumbent.
    nearly_dependent : bool
        Its terms are nearly dependent (only the span bound holds its larger sizes).
    children_bound : float
        The least bound of the nodes its expansion opens (``inf``: none).
    size_bounds : list of float
        The bound of each size ``|I|, |I| + 1, ..`` at the node (``inf``: cut, it
        cannot beat the incumbent); the enumerated ones are exact.
    names : list of str
        The terms fixed in, by name (set by the caller that knows them).
    """

    bound: float
    inside: list
    free: list
    out: int
    own_bound: float
    weakest_size: int | None
    exact_up_to: int
    open_sizes: int
    nearly_dependent: bool
    children_bound: float
    size_bounds: list = field(default_factory=list)
    names: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready (the terms fixed in by name when :attr:`names` is set)."""
        def fin(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {"bound": fin(self.bound), "in": list(self.names or self.inside),
                "n_in": len(self.inside),
                "n_out": self.out, "n_free": len(self.free), "own_bound": fin(self.own_bound),
                "weakest_size": self.weakest_size, "exact_up_to": self.exact_up_to,
                "open_sizes": self.open_sizes, "nearly_dependent": self.nearly_dependent,
                "children_bound": fin(self.children_bound),
                "size_bounds": [fin(x) for x in self.size_bounds]}


def _members(words: np.ndarray, mu: int) -> list[int]:
    bits = np.unpackbits(words.view(np.uint8), bitorder="little")[:mu]
    return [int(j) for j in np.flatnonzero(bits)]


def _rebound(data, heap: OpenNodes, incumbent: tuple, bound: float, inside: np.ndarray,
             free: np.ndarray, budget: int, mu: int) -> WeakNode:
    """Bound one node alone on the scratch heap; read its sizes off the scratch space.

    ``incumbent``: (value, mask) of the stopped search, what every size is compared with.
    """
    heap.bound[0] = bound
    heap.inside[0] = inside
    heap.free[0] = free
    heap.counts[:] = 0
    heap.counts[OPEN] = 1
    best = float(incumbent[0])  # the certificate's value, whatever this expansion finds
    heap.best[0] = best
    heap.best_mask[:] = incumbent[1]
    work = heap.work
    work.small[:] = np.nan
    work.wvals[:] = np.nan
    heap.expand(data, 1, budget)
    ins, fr = _members(inside, mu), _members(free, mu)
    k, f = len(ins), len(fr)
    t = k + f
    per_size = np.full(t + 1, np.inf)  # an unknown size was cut: it cannot beat the incumbent
    exact = k - 1
    for a in range(f + 1):  # the small sizes, exactly
        if np.isfinite(work.small[a]):
            per_size[k + a] = work.small[a]
            exact = k + a
    for q in range(f + 1):  # size t - q from the drop and pair bounds (the exact value in)
        if np.isfinite(work.wvals[q]):
            per_size[t - q] = work.wvals[q]
    children = float(heap.bound[:heap.size].min()) if heap.size else np.inf
    near = bool(heap.counts[NEAR_BRANCHES])
    if near and exact < t:  # the larger sizes: the span bound on SSE(T) at the next size up
        per_size[exact + 1] = min(per_size[exact + 1], children)
    sizes = np.maximum(per_size[k:], bound)  # a node is never bounded below its parent's
    least = float(sizes.min())
    tol = data.tol
    return WeakNode(
        bound=float(bound), inside=ins, free=fr, out=mu - t,
        own_bound=least if least < best - tol else np.inf,
        weakest_size=int(k + np.argmin(sizes)) if least < best - tol else None,
        exact_up_to=exact, open_sizes=int(np.count_nonzero(sizes < best - tol)),
        nearly_dependent=near, children_bound=children,
        size_bounds=[float(x) for x in per_size[k:]])


def weakest_nodes(heaps: list[OpenNodes], data, usable: np.ndarray, budget: int,
                  count: int = 10) -> list[WeakNode]:
    """The ``count`` open nodes of the lowest bound, each bounded again on its own.

    ``heaps``, ``data`` and ``usable`` (the evaluator's columns the search runs on)
    are a stopped search's (:mod:`.certify`); they are not changed (each node is
    bounded in turn on one scratch heap, against the search's incumbent).
    """
    if count <= 0 or not any(h.size for h in heaps):
        return []
    bound = np.concatenate([h.bound[:h.size] for h in heaps])
    inside = np.concatenate([h.inside[:h.size] for h in heaps])
    free = np.concatenate([h.free[:h.size] for h in heaps])
    order = np.argsort(bound, kind="stable")[:count]
    top = min(heaps, key=lambda h: h.best[0])
    mu = data.gram.shape[0] - 1
    incumbent = (float(top.best[0]), top.best_mask.copy())
    scratch = OpenNodes(mu, data.r_ext.shape[0], incumbent[0], incumbent[1], 1)
    out = []
    for i in order:
        node = _rebound(data, scratch, incumbent, float(bound[i]), inside[i], free[i], budget,
                        mu)
        node.inside = [int(usable[j]) for j in node.inside]
        node.free = [int(usable[j]) for j in node.free]
        out.append(node)
    return out


def explain_table(nodes: list[dict], value: float) -> str:
    """The weakest open nodes as a short table with a one-line reading (``certify --explain``).

    ``nodes`` are :meth:`WeakNode.to_dict` documents (a certificate's ``weakest``),
    ``value`` the incumbent's criterion value.
    """
    if not nodes:
        return "explain: no open node (the search proved its result or never started)"

    def num(x: float | None) -> str:
        return "closes" if x is None else f"{x:.2f}"

    lines = ["weakest open nodes, each bounded again on its own (the lower bound is the "
             "least 'bound'; the incumbent is " f"{value:.2f}):",
             f"{'bound':>12} {'own bound':>12} {'in':>4} {'out':>4} {'free':>5} "
             f"{'weakest size':>12} {'enumerated':>10} {'open sizes':>10}"]
    for d in nodes:
        size = "-" if d["weakest_size"] is None else str(d["weakest_size"])
        lines.append(f"{num(d['bound']):>12} {num(d['own_bound']):>12} {d['n_in']:>4} "
                     f"{d['n_out']:>4} {d['n_free']:>5} {size:>12} {d['exact_up_to']:>10} "
                     f"{d['open_sizes']:>10}" + ("  nearly dependent" if d["nearly_dependent"]
                                                 else ""))
    closing = sum(d["own_bound"] is None for d in nodes)
    near = sum(d["nearly_dependent"] and d["own_bound"] is not None for d in nodes)
    above = sum(d["weakest_size"] == d["exact_up_to"] + 1 and not d["nearly_dependent"]
                for d in nodes)
    return "\n".join(lines + [
        f"reading: {closing} of {len(nodes)} close when expanded (open for want of time); "
        f"{near} hold nearly dependent terms (no drop bounds: sizes above the enumerated "
        "ones get only the span bound on all-in's SSE, and a dependent subset counts as "
        f"fitting down to it); in {above} the "
        "weakest size is the first above those enumerated (the drop and pair bounds from "
        "all-in down hold it there)"])
