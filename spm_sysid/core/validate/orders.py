"""Proposing the lags and the degree from the data, so a user need not guess.

The proposal scans the first :data:`~spm_sysid.core.defaults.SCAN_ROWS` samples
(of the longest segment) and keeps every space within a budget of candidate
terms (:data:`~spm_sysid.core.defaults.AUTO_MAX_TERMS`, fewer on short records:
one term per :data:`~spm_sysid.core.defaults.ROWS_PER_TERM` rows), so that what
follows -- the search, the screening, a certification -- stays quick whatever
the record. With many signals (six inputs and six coupled outputs: 12 lagged
signals) every quadratic space above order 1 exceeds that budget, and a
second-order plant with a squared input was fitted at order 1, 30-40x the noise
in free run; the budget then grows to the quadratic space of order 2
(:func:`automatic_budget`), the commonest nonlinear model of a mechanical joint.

1. **order** (both focuses): for n = 1 .. ``max_order``, the full linear model
   with output lags 1..n and input lags delay..delay+n-1 (every input) is fitted
   by least squares on the same rows; the order with the lowest criterion is
   the linear order (BIC by default: it does not keep adding lags for tiny
   gains, as AIC tends to). An order whose model cannot be fitted scores +inf
   (null in the document).
2. **space**, by focus:

   * *prediction*: for each degree 1 .. ``max_degree``, at the linear order (or
     the largest below it whose space fits the budget), forward selection
     (:func:`~spm_sysid.core.search.forward.forward_selection`) estimates the
     best criterion reachable; the degree with the lowest value is proposed;
   * *simulation*: a one-step criterion favours long lags (coloured noise) and
     says little of how a model simulates, so every space of the budget
     (degree d, order n) is judged by how it simulates: forward selection on the
     first :data:`~spm_sysid.core.defaults.SCAN_FIT_SHARE` of the scanned
     samples, least squares, then a free run of the rest from its own first
     samples; the best spaces by that are refined on their free-run error and
     run again, and so is each linear space whose least-squares model left
     the range with an integrator beyond 1 (:func:`_scan_spaces`). The space
     with the lowest held-out RMSE (of either fit) is proposed -- the smallest
     within :data:`~spm_sysid.core.defaults.SCAN_TOLERANCE` of it. The
     selection then judges linear and nonlinear structures of that space on
     held-out blocks as always.

Each space is one :class:`~spm_sysid.core.fit.problem.Problem` over the rows
every order has, so their values compare.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..defaults import (
    AUTO_MAX_TERMS,
    ROWS_PER_TERM,
    SCAN_FIT_SHARE,
    SCAN_REFINED,
    SCAN_ROWS,
    SCAN_TOLERANCE,
    SEARCH_STEPS,
)
from ..fit.criteria import get_criterion
from ..fit.problem import Problem
from ..fit.refine import refine_simulation, stabilised_start
from ..model.terms import TermSpace
from ..search.forward import forward_selection

__all__ = ["OrderProposal", "automatic_budget", "orders_from_data", "propose_orders"]


@dataclass
class OrderProposal:
    """What :func:`propose_orders` found.

    ``order_scan``: (n, criterion of the full linear model; inf: not fitted);
    ``degree_scan``: (degree, candidates, best criterion, terms, order) of the
    prediction focus, at the linear order (capped to the budget); ``space_scan``:
    (order, degree, candidates, held-out free-run RMSE of least squares, and
    refined; inf: diverged, not fitted or not refined) of the simulation focus;
    ``skipped``: (degree, order) spaces beyond the budget.
    """

    order: int
    degree: int
    criterion: str
    focus: str = "prediction"
    budget: int = AUTO_MAX_TERMS
    samples: int = 0
    linear_order: int = 0
    order_scan: list[tuple[int, float]] = field(default_factory=list)
    degree_scan: list[tuple[int, int, float, int]] = field(default_factory=list)
    space_scan: list[tuple[int, int, int, float, float]] = field(default_factory=list)
    skipped_degrees: list[tuple[int, int]] = field(default_factory=list)

    def summary(self) -> str:
        lines = [f"scanned the first {self.samples} samples; spaces of at most "
                 f"{self.budget} candidate terms",
                 f"order scan (full linear models, {self.criterion.upper()}):"]
        lines += [f"  n = {n:2d}: " + (f"{v:.2f}" if np.isfinite(v) else "not fitted")
                  + ("   <- lowest" if n == self.linear_order else "")
                  for n, v in self.order_scan]
        if self.order_scan and self.linear_order == self.order_scan[-1][0]:
            lines.append("  note: the lowest value is at the largest order tried; the data "
                         "may support more lags (raise --max-order)")
        if self.focus == "simulation":
            lines.append("space scan (forward selection on the first part, free run of the "
                         "rest; held-out RMSE):")
            lines += [f"  n = {n:2d}, degree {d}: {m:4d} candidate terms, least squares "
                      + (f"{r:.4g}" if np.isfinite(r) else "diverged or not fitted")
                      + (f", refined {rr:.4g}" if np.isfinite(rr) else "")
                      + ("   <- proposed" if (n, d) == (self.order, self.degree) else "")
                      for n, d, m, r, rr in self.space_scan]
        else:
            lines.append("degree scan (forward selection):")
            lines += [f"  degree {d} at n = {n}: {m} candidate terms, best {v:.2f} with "
                      f"{k} terms" + ("   <- lowest" if d == self.degree else "")
                      for d, m, v, k, n in self.degree_scan]
        lines += [f"  degree {d}: not scanned (order 1 has more than {self.budget} "
                  "candidate terms)" for d, _ in self.skipped_degrees]
        return "\n".join(lines)

    def reason(self) -> str:
        """Why this space, in a sentence (the document's ``orders.reason``)."""
        n, d = self.order, self.degree
        head = (f"the full linear model scores best by {self.criterion.upper()} at order "
                f"{self.linear_order} among 1..{len(self.order_scan)}")
        if self.focus == "simulation":
            return (f"order {n}, degree {d}: of the spaces of at most {self.budget} candidate "
                    "terms, the one whose forward-selected model, refined, simulates the last "
                    f"third of the first {self.samples} samples best (the smallest within "
                    f"{SCAN_TOLERANCE - 1:.0%} of the best); {head}")
        return (f"order {n}: {head}" + (f" (capped to fit {self.budget} candidate terms)"
                                        if n < self.linear_order else "")
                + f"; degree {d}: forward selection scores best among "
                + ", ".join(str(row[0]) for row in self.degree_scan))


def _space(n: int, d: int, delay: int, names) -> TermSpace:
    return TermSpace(ny=n, nu=n, degree=d, delay=delay, inputs=names)


def automatic_budget(inputs: int, delay: int = 1) -> int:
    """Candidate terms a proposed space may have when the user gives no cap.

    :data:`~spm_sysid.core.defaults.AUTO_MAX_TERMS`, or the quadratic space of
    order 2 when ``inputs`` (the inputs and, in a coupled model, the other outputs)
    make it larger: the scan then still tries a second-order plant's squares and
    products. One output and up to six inputs keep 120 (their (2, 2) space has at
    most 119 terms).
    """
    names = tuple(f"u{i + 1}" for i in range(inputs))
    return max(AUTO_MAX_TERMS, _space(2, 2, delay, names).n_terms)


def _largest_order(d: int, top: int, budget: int, delay: int, names) -> int:
    """The largest order <= top whose degree-d space fits the budget (0: none)."""
    for n in range(top, 0, -1):
        if _space(n, d, delay, names).n_terms <= budget:
            return n
    return 0


def propose_orders(u: np.ndarray, y: np.ndarray, *, max_order: int = 10, max_degree: int = 3,
                   delay: int = 1, criterion: str = "bic", inputs: tuple[str, ...] = (),
                   max_terms: int | None = None, focus: str = "prediction",
                   max_rows: int = SCAN_ROWS) -> OrderProposal:
    """Propose ``ny = nu = order`` and ``degree`` for data u, y (see the module doc).

    Parameters
    ----------
    u, y : ndarray, shapes (n,) or (n, m), and (n,)
        Input samples (one column per input) and output samples.
    max_order, max_degree, delay : int
        Largest lag order and degree tried; the input delay of every space.
    criterion : str
        ``aic`` or ``bic`` (criteria that need coefficients are not supported here).
    inputs : tuple of str
        Input names (their number must match u's columns).
    max_terms : int or None
        Candidate terms a proposed space may have (fewer on short records); None:
        :func:`automatic_budget`.
    focus : str
        ``prediction`` or ``simulation`` (how spaces are compared).
    max_rows : int
        Samples scanned at most (the first ones).
    """
    crit = get_criterion(criterion)
    if crit.needs_coefficients:
        raise ValueError(f"{crit.name} needs coefficients; propose lags with aic or bic")
    y = np.asarray(y, dtype=float)[:max_rows]
    u = np.asarray(u, dtype=float)[:max_rows]
    m = 1 if u.ndim == 1 else u.shape[1]
    names = tuple(inputs) or (("u",) if m == 1 else tuple(f"u{i + 1}" for i in range(m)))
    start = max(max_order, delay + max_order - 1)
    if len(y) - start <= (1 + m) * max_order + 1:
        raise ValueError(f"too few samples ({len(y)}) for orders up to {max_order}")
    if max_terms is None:
        max_terms = automatic_budget(m, delay)
    budget = max(min(max_terms, (len(y) - start) // ROWS_PER_TERM), 1 + m)

    def problem(space: TermSpace, stop: int = len(y)) -> Problem:
        # the rows every candidate order has: each space's one segment starts where
        # its largest lag leaves the first row at `start`
        return Problem.from_signals(u, y, space, [(start - space.max_lag, stop)])

    scan = _linear_scan(problem, crit, max_order, delay, names)
    finite = [item for item in scan if np.isfinite(item[1])]
    if not finite:
        raise ValueError(f"no linear model of orders 1..{max_order} can be fitted")
    linear = min(finite, key=lambda item: item[1])[0]
    out = OrderProposal(linear, 1, crit.name, focus, budget, len(y), linear, scan)
    for d in range(1, max_degree + 1):
        if _space(1, d, delay, names).n_terms > budget:
            out.skipped_degrees.append((d, 1))
    if focus == "simulation":
        _scan_spaces(out, u, y, problem, crit, start, max_order, max_degree, delay, names)
    else:
        _scan_degrees(out, problem, crit, max_degree, delay, names)
    return out


def _linear_scan(problem, crit, max_order: int, delay: int,
                 names: tuple[str, ...]) -> list[tuple[int, float]]:
    """The criterion of every linear ARX of order 1..max_order (+inf where none fits)."""
    scan = []
    for n in range(1, max_order + 1):
        ev = problem(_space(n, 1, delay, names)).evaluator(crit)
        try:
            value = float(ev.cached_score(np.ones(ev.n_terms, dtype=bool)))
        except (ValueError, np.linalg.LinAlgError):
            value = np.inf
        scan.append((n, value if np.isfinite(value) else np.inf))
    return scan


def _scan_degrees(out: OrderProposal, problem, crit, max_degree, delay, names) -> None:
    """The prediction focus: each degree at the linear order (capped); the best criterion."""
    best = None
    for d in range(1, max_degree + 1):
        n = _largest_order(d, out.linear_order, out.budget, delay, names)
        if not n:
            continue
        space = _space(n, d, delay, names)
        value, mask = forward_selection(problem(space).evaluator(crit))
        out.degree_scan.append((d, space.n_terms, float(value), int(mask.sum()), n))
        if best is None or value < best[0]:
            best = (value, n, d)
    if best is not None:
        out.order, out.degree = best[1], best[2]


def _scan_spaces(out: OrderProposal, u, y, problem, crit, start, max_order, max_degree,
                 delay, names) -> None:
    """The simulation focus: every space of the budget by its held-out free run.

    Each space's forward-selected structure, fitted by least squares on the first
    part, simulates the rest; the best of each degree and the
    :data:`~spm_sysid.core.defaults.SCAN_REFINED` best overall are then refined on the
    first part's free-run error (:data:`~spm_sysid.core.defaults.SEARCH_STEPS`
    evaluations) and simulate the rest again: least squares alone misjudges
    spaces whose models need the refinement (a Wiener-Hammerstein system).
    So does every linear space whose least-squares model left the range with an
    integrator beyond 1 (:func:`_integrator_beyond`): at 1 kHz least squares puts
    a joint's integrator there, and the plant's own order was never refined.
    """
    cut = start + int(SCAN_FIT_SHARE * (len(y) - start))
    tried = []
    for d in range(1, max_degree + 1):
        for n in range(1, max_order + 1):
            space = _space(n, d, delay, names)
            if space.n_terms > out.budget:
                break
            model, r = None, np.inf
            try:
                fitted = problem(space, cut)
                _, mask = forward_selection(fitted.evaluator(crit))
                model = fitted.model(fitted.expand(mask))
                r = _held_out_rmse(model, u, y, cut)
            except (ValueError, np.linalg.LinAlgError):
                model = None
            tried.append([n, d, space.n_terms, r, np.inf, model])
    good = sorted((row for row in tried if np.isfinite(row[3])), key=lambda row: row[3])
    drifting = [row for row in tried if _integrator_beyond(row)]
    if not good and not drifting:  # nothing simulates: the prediction focus's choice
        _scan_degrees(out, problem, crit, max_degree, delay, names)
        return
    chosen = {id(min((row for row in good if row[1] == d), key=lambda row: row[3]))
              for d in {row[1] for row in good}}
    chosen |= {id(row) for row in good[:SCAN_REFINED] + drifting}
    for row in tried:
        if id(row) in chosen:
            n, model = row[0], row[5]
            ref = refine_simulation(model, u, y, [(start - model.term_space.max_lag, cut)],
                                    max_evaluations=SEARCH_STEPS)
            if ref.success and np.isfinite(ref.sse):
                row[4] = _held_out_rmse(model.with_coefficients(ref.coefficients), u, y, cut)
    out.space_scan = [(n, d, m, r, rr) for n, d, m, r, rr, _ in tried]
    # a space's error: the better of its two fits (a refinement that fails or drifts
    # off the held-out samples leaves least squares' error)
    good = [row for row in tried if np.isfinite(min(row[3], row[4]))]
    if not good:  # nothing simulates: the prediction focus's choice
        _scan_degrees(out, problem, crit, max_degree, delay, names)
        return
    best = min(min(row[3], row[4]) for row in good)
    near = [row for row in good if min(row[3], row[4]) <= SCAN_TOLERANCE * best]
    pick = min(near, key=lambda row: (row[2], min(row[3], row[4])))
    out.order, out.degree = pick[0], pick[1]


def _integrator_beyond(row) -> bool:
    """A linear space whose least-squares model left the range with an integrator beyond 1.

    Its refinement starts again with the poles scaled inside
    (:func:`~spm_sysid.core.fit.refine.stabilised_start`). Linear spaces only: their
    orders are what the integrator's start decides; the measured cost of refining the
    nonlinear ones too was a (3, 3) space chosen on a 200 s joint, 20x the time of
    the command, for no better free run.
    """
    model = row[5]
    return (model is not None and row[1] == 1 and not np.isfinite(row[3])
            and stabilised_start(model.term_space, model.term_indices, model.coefficients)
            is not None)


def _held_out_rmse(model, u, y, cut: int) -> float:
    """RMSE of the model's free run of samples cut.. (from their own first samples)."""
    yhat, at = model.run(u, y, None, [(cut - model.term_space.max_lag, len(y))])
    if at is not None or not np.all(np.isfinite(yhat)):
        return np.inf
    e = y[cut:] - yhat
    return float(np.sqrt(np.mean(e * e)))


def orders_from_data(u: np.ndarray, y: np.ndarray, segments, space: TermSpace,
                     criterion: str, focus: str = "prediction") -> tuple[TermSpace, dict]:
    """``orders: auto``: the space with the lags and degree proposed from the data, and why.

    The constant is always a candidate of that space: on the records of
    ``make bench-accuracy`` an offset the space could not express cost up to
    1.6x the linear ARX's free-run error (the two tanks); where there is no
    offset the criterion leaves it out.

    The proposal (:func:`propose_orders`) runs on the longest of ``segments``, with
    ``criterion`` when it is AIC or BIC (else BIC), for ``focus``.

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
                                  inputs=space.inputs, focus=focus)
    except DataError:  # the data cannot be identified at all (a constant signal): as it is
        raise
    except ValueError as exc:
        raise DataError(f"orders: auto cannot propose lags on this data ({exc}); give ny, nu "
                        "and degree") from None
    n, d = proposal.order, proposal.degree

    def number(v: float) -> float | None:
        return float(v) if np.isfinite(v) else None

    why = {"mode": "auto", "ny": n, "nu": n, "degree": d, "constant": True,
           "criterion": proposal.criterion,
           "focus": focus, "samples": proposal.samples, "max_terms": proposal.budget,
           "reason": proposal.reason() + "; the constant a candidate (records with an offset "
                                         "need it; the selection decides whether it enters)",
           "order_scan": [[int(k), number(v)] for k, v in proposal.order_scan],
           "degree_scan": [[int(row[0]), int(row[1]), number(row[2]), int(row[3])]
                           for row in proposal.degree_scan],
           "space_scan": [[int(k), int(g), int(c), number(r), number(rr)]
                          for k, g, c, r, rr in proposal.space_scan]}
    return replace(space, ny=n, nu=n, degree=d, constant=True), why
