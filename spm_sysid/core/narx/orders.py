"""Proposing the lags and the degree from the data, so a user need not guess.

Two scans, both on the same regression rows (those every candidate order has),
so their criterion values compare:

1. **order**: for n = 1 .. ``max_order``, the full linear model with output lags
   1..n and input lags delay..delay+n-1 (every input) is fitted by least squares;
   the order with the lowest criterion is proposed (BIC by default: it does not
   keep adding lags for tiny gains, as AIC tends to);
2. **degree**: at that order, for degree 1 .. ``max_degree``, a fast forward
   selection (greedy, orthogonalised: at each step the candidate term that
   lowers the SSE most, kept while the criterion improves) estimates the best
   criterion reachable with that degree; the degree with the lowest value is
   proposed. It is a screening device: the GA then searches that space.

Spaces beyond ``max_terms`` candidate terms are not scanned (reported).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .criteria import Criterion, get_criterion
from .lstsq import reference_fit
from .terms import TermSpace, power_of_two_scale

__all__ = ["OrderProposal", "forward_selection", "propose_orders"]


def forward_selection(P: np.ndarray, target: np.ndarray, criterion: Criterion,
                      max_terms: int = 60, patience: int = 3, sse_scale: float = 1.0,
                      deadline: float | None = None) -> tuple[float, list[int]]:
    """Greedy forward selection by SSE reduction; the best criterion value and its terms.

    Columns are orthogonalised against the chosen ones as the selection grows
    (modified Gram-Schmidt), so each step costs O(N M). ``sse_scale`` turns the
    SSE of scaled data back into the user's units. At ``deadline``
    (``time.perf_counter()``) it stops with the best found so far.
    """
    import time

    W = P / np.where(np.linalg.norm(P, axis=0) > 0, np.linalg.norm(P, axis=0), 1.0)
    r = target.astype(float).copy()
    n = len(target)
    chosen: list[int] = []
    best, best_terms, since = np.inf, [], 0
    for _ in range(min(max_terms, P.shape[1])):
        if deadline is not None and chosen and time.perf_counter() >= deadline:
            break
        norms = np.einsum("ij,ij->j", W, W)
        gain = np.where(norms > 1e-9, (W.T @ r) ** 2 / np.where(norms > 0, norms, 1.0), -1.0)
        gain[chosen] = -1.0
        j = int(np.argmax(gain))
        if gain[j] <= 0:
            break
        q = W[:, j] / np.sqrt(norms[j])
        r -= q * (q @ r)
        W -= np.outer(q, q @ W)
        chosen.append(j)
        k = len(chosen)
        value = float(criterion(np.array([(r @ r) * sse_scale]), n, np.array([k]), None)[0])
        if value < best:
            best, best_terms, since = value, list(chosen), 0
        else:
            since += 1
            if since >= patience:
                break
    return best, best_terms


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
    su = np.array([power_of_two_scale(c) for c in (u[:, None] if u.ndim == 1 else u).T])
    u = (u[:, None] if u.ndim == 1 else u) / su
    sy = power_of_two_scale(y)
    y = y / sy
    start = max(max_order, delay + max_order - 1)
    if len(y) - start <= (1 + m) * max_order + 1:
        raise ValueError(f"too few samples ({len(y)}) for orders up to {max_order}")

    def rows(space: TermSpace):
        P, target = space.regression(u, y)
        cut = start - space.max_lag  # the same rows for every space
        return P[cut:], target[cut:]

    scan = []
    for n in range(1, max_order + 1):
        space = TermSpace(ny=n, nu=n, degree=1, delay=delay, inputs=names)
        P, target = rows(space)
        fit = reference_fit(P, target, np.ones(space.n_terms, dtype=bool))
        value = np.inf if fit.rank_deficient else float(
            crit(np.array([fit.sse * sy * sy]), len(target), np.array([space.n_terms]),
                 None)[0])
        scan.append((n, value))
    order = min(scan, key=lambda item: item[1])[0]
    degrees, skipped = [], []
    for d in range(1, max_degree + 1):
        space = TermSpace(ny=order, nu=order, degree=d, delay=delay, inputs=names)
        if space.n_terms > max_terms:
            skipped.append((d, space.n_terms))
            continue
        P, target = rows(space)
        value, terms = forward_selection(P, target, crit, sse_scale=sy * sy)
        degrees.append((d, space.n_terms, value, len(terms)))
    degree = min(degrees, key=lambda item: item[2])[0] if degrees else 1
    return OrderProposal(order, degree, crit.name, scan, degrees, skipped)
