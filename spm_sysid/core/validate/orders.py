"""Proposing the lags and the degree from the data, so a user need not guess.

Two scans, both on the same regression rows (those every candidate order has),
so their criterion values compare:

1. **order**: for n = 1 .. ``max_order``, the full linear model with output lags
   1..n and input lags delay..delay+n-1 (every input) is fitted by least squares;
   the order with the lowest criterion is proposed (BIC by default: it does not
   keep adding lags for tiny gains, as AIC tends to);
2. **degree**: at that order, for degree 1 .. ``max_degree``, forward selection
   (:func:`~spm_sysid.core.search.forward.forward_selection`: at each step the
   candidate term that lowers the criterion most, on past the last improvement
   by a few steps)
   estimates the best criterion reachable with that degree; the degree with
   the lowest value is proposed. It is a screening device: the GA then searches
   that space.

Each space is one :class:`~spm_sysid.core.fit.problem.Problem` over the rows
every order has, so their criterion values compare.

Spaces beyond ``max_terms`` candidate terms are not scanned (reported).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..fit.criteria import get_criterion
from ..fit.problem import Problem
from ..model.terms import TermSpace
from ..search.forward import forward_selection

__all__ = ["OrderProposal", "orders_from_data", "propose_orders"]


@dataclass
class OrderProposal:
    """What :func:`propose_orders` found."""

    order: int
    degree: int
    criterion: str
    order_scan: list[tuple[int, float]] = field(default_factory=list)
    degree_scan: list[tuple[int, int, float, int]] = field(default_factory=list)
    skipped_degrees: list[tuple[int, int]] = field(default_factory=list)

    def summary(self) -> str:
        lines = [f"order scan (full linear models, {self.criterion.upper()}):"]
        lines += [f"  n = {n:2d}: {v:.2f}" + ("   <- lowest" if n == self.order else "")
                  for n, v in self.order_scan]
        if self.order == self.order_scan[-1][0]:
            lines.append("  note: the lowest value is at the largest order tried; the data "
                         "may support more lags (raise --max-order)")
        lines.append(f"degree scan at n = {self.order} (forward selection):")
        lines += [f"  degree {d}: {m} candidate terms, best {v:.2f} with {k} terms"
                  + ("   <- lowest" if d == self.degree else "")
                  for d, m, v, k in self.degree_scan]
        lines += [f"  degree {d}: {m} candidate terms, not scanned (more than max_terms)"
                  for d, m in self.skipped_degrees]
        return "\n".join(lines)


def propose_orders(u: np.ndarray, y: np.ndarray, *, max_order: int = 10, max_degree: int = 3,
                   delay: int = 1, criterion: str = "bic", inputs: tuple[str, ...] = (),
                   max_terms: int = 2000) -> OrderProposal:
    """Propose ``ny = nu = order`` and ``degree`` for data u, y (see the module doc).

    Parameters
    ----------
    u : ndarray, shape (n,) or (n, m)
        Input samples (one column per input).
    y : ndarray, shape (n,)
        Output samples.
    max_order, max_degree : int
        Largest lag order and degree tried.
    delay : int
        Input delay of every candidate space.
    criterion : str
        ``aic`` or ``bic`` (criteria that need coefficients are not supported here).
    inputs : tuple of str
        Input names (their number must match u's columns).
    max_terms : int
        Degree-scan spaces with more candidate terms are skipped.
    """
    crit = get_criterion(criterion)
    if crit.needs_coefficients:
        raise ValueError(f"{crit.name} needs coefficients; propose lags with aic or bic")
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    m = 1 if u.ndim == 1 else u.shape[1]
    names = tuple(inputs) or (("u",) if m == 1 else tuple(f"u{i + 1}" for i in range(m)))
    start = max(max_order, delay + max_order - 1)
    if len(y) - start <= (1 + m) * max_order + 1:
        raise ValueError(f"too few samples ({len(y)}) for orders up to {max_order}")

    def problem(space: TermSpace) -> Problem:
        # the rows every candidate order has: each space's one segment starts where
        # its largest lag leaves the first row at `start`
        return Problem.from_signals(u, y, space, [(start - space.max_lag, len(y))])

    scan = []
    for n in range(1, max_order + 1):
        space = TermSpace(ny=n, nu=n, degree=1, delay=delay, inputs=names)
        ev = problem(space).evaluator(crit)
        scan.append((n, ev.cached_score(np.ones(ev.n_terms, dtype=bool))))
    order = min(scan, key=lambda item: item[1])[0]
    degrees, skipped = [], []
    for d in range(1, max_degree + 1):
        space = TermSpace(ny=order, nu=order, degree=d, delay=delay, inputs=names)
        if space.n_terms > max_terms:
            skipped.append((d, space.n_terms))
            continue
        value, mask = forward_selection(problem(space).evaluator(crit))
        degrees.append((d, space.n_terms, value, int(mask.sum())))
    degree = min(degrees, key=lambda item: item[2])[0] if degrees else 1
    return OrderProposal(order, degree, crit.name, scan, degrees, skipped)


def orders_from_data(u: np.ndarray, y: np.ndarray, segments, space: TermSpace,
                     criterion: str) -> tuple[TermSpace, dict]:
    """``orders: auto``: the space with the lags and degree proposed from the data, and why.

    The proposal (:func:`propose_orders`) runs on the longest of ``segments``, with
    ``criterion`` when it is AIC or BIC (else BIC): ``ny = nu`` = the order whose
    full linear model scores best, the degree whose forward selection scores best.

    Raises
    ------
    DataError
        No proposal can be made on these data.
    """
    from dataclasses import replace

    from ..errors import DataError

    a, b = max(segments, key=lambda seg: seg[1] - seg[0])
    crit = criterion if criterion in ("aic", "bic") else "bic"
    try:
        proposal = propose_orders(u[a:b], y[a:b], delay=min(space.delays), criterion=crit,
                                  inputs=space.inputs)
    except ValueError as exc:
        raise DataError(f"orders: auto cannot propose lags on this data ({exc}); give ny, nu "
                        "and degree") from None
    n, d = proposal.order, proposal.degree
    why = {"mode": "auto", "ny": n, "nu": n, "degree": d, "criterion": proposal.criterion,
           "samples": int(b - a),
           "reason": f"order {n}: the full linear model of lags 1..n scores best by "
                     f"{proposal.criterion.upper()} among 1..{len(proposal.order_scan)}; "
                     f"degree {d}: forward selection scores best among "
                     f"{', '.join(str(row[0]) for row in proposal.degree_scan)}",
           "order_scan": [[int(k), float(v)] for k, v in proposal.order_scan],
           "degree_scan": [[int(row[0]), int(row[1]), float(row[2]), int(row[3])]
                           for row in proposal.degree_scan]}
    return replace(space, ny=n, nu=n, degree=d), why
