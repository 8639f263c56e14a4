"""Certifying a problem's space, split in two where its constant makes columns interchangeable.

:func:`certify_data` certifies the candidates of measured signals, as
:func:`~spm_sysid.core.identify.identify` builds them; :func:`certify_split`
certifies an evaluator's space, in two searches where that pays:

With the constant a candidate, a column that is another plus a number (a
two-level input's square, ``u^2 = (a + b) u - a b``) stands for that other
column in every structure holding the constant, and is a term of its own in
every structure without it. One branch and bound over the whole space meets the
structures with the constant under two names each, and its bounds cannot tell
them apart (the dryer's default space around its means: 10.8 s; the two halves
below 0.35 s and 6.2 s). So the space is searched as two:

* the structures without those columns (the constant free): every structure
  with the constant is one of them under another name, or rank-deficient;
* the structures without the constant (those columns free).

The whole space's optimum is the better of the two optima, its lower bound the
lesser of the two bounds. The first search may take half the time limit, the
second what is left, and it seeks only structures below the first's best
(``cutoff``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..fit.criteria import get_criterion
from ..model.segments import rows_segments
from .certificate import Certificate, mse_bounds
from .certify import certify, check_certify_memory, ensure_compiled, penalty_per_size

__all__ = ["certify_data", "certify_split"]


def certify_split(evaluator, split: tuple[int | None, np.ndarray], *,
                  warm_start: np.ndarray | None = None, time_limit: float = 60.0,
                  started: float | None = None, **options) -> Certificate:
    """:func:`~.certify.certify` of ``evaluator``'s space, split on the constant.

    Parameters
    ----------
    evaluator : StructureEvaluator
        The space's evaluator (its criterion is certified).
    split : (int or None, ndarray of int)
        :meth:`~spm_sysid.core.fit.problem.Problem.constant_split`: the constant's
        column and, per column, the column it is plus a number (-1: none). Without
        such columns this is one plain search.
    warm_start, time_limit, started, options
        As for :func:`~.certify.certify` (``node_limit`` holds for each search).
    """
    constant, source = split
    affine = np.asarray(source) >= 0
    crit = evaluator.criterion
    if constant is None or not affine.any():
        return certify(None, None, crit, evaluator=evaluator, warm_start=warm_start,
                       time_limit=time_limit, started=started, **options)
    t0 = time.perf_counter() if started is None else started
    warm = None if warm_start is None else np.asarray(warm_start, dtype=bool)
    no_constant = np.zeros(evaluator.n_terms, dtype=bool)
    no_constant[constant] = True
    # the first half may take half the time (a proof usually takes less), so that the
    # second always searches: unsearched, its bound would be the trivial one
    first = certify(None, None, crit, evaluator=evaluator.without(affine),
                    warm_start=_renamed(warm, source), time_limit=time_limit / 2, started=t0,
                    **options)
    # the second half need only prove that none of its structures beats the first's best
    second = certify(None, None, crit, evaluator=evaluator.without(no_constant),
                     warm_start=_without(warm, no_constant), time_limit=time_limit,
                     started=t0, cutoff=first.value, **options)
    return _joined(evaluator, [first, second], warm, t0)


def _renamed(warm: np.ndarray | None, source: np.ndarray) -> np.ndarray | None:
    """The warm start with each column that is another plus a number replaced by that other."""
    if warm is None:
        return None
    out = warm.copy()
    for j in np.flatnonzero(warm & (source >= 0)):
        out[j], out[source[j]] = False, True
    return out if out.any() else None


def _without(warm: np.ndarray | None, left_out: np.ndarray) -> np.ndarray | None:
    """The warm start without the columns left out (None when nothing is left)."""
    if warm is None:
        return None
    out = warm & ~left_out
    return out if out.any() else None


def _joined(evaluator, halves: list[Certificate], warm: np.ndarray | None,
            t0: float) -> Certificate:
    """One certificate of the whole space: the better half's structure, the lesser bound."""
    best = min(halves, key=lambda c: c.value)
    optimal = all(c.status == "optimal" for c in halves)
    lower = best.value if optimal else min(min(c.lower_bound for c in halves), best.value)
    warm_value = None
    if warm is not None and warm.any():
        value = evaluator.cached_score(warm)
        warm_value = float(value) if np.isfinite(value) else None
    pen = penalty_per_size(evaluator.criterion, evaluator.n, evaluator.n_terms,
                           evaluator.max_terms)
    cert = Certificate(
        status="optimal" if optimal else "limit", value=best.value, lower_bound=lower,
        mask=best.mask, nodes=sum(c.nodes for c in halves),
        seconds=time.perf_counter() - t0,
        bound=best.bound + "; searched as two spaces: with the constant (terms that are "
        "another plus a number left out) and without it",
        reason=next((c.reason for c in halves if c.reason), None), warm_start=warm_value,
        **mse_bounds(best.value, lower, best.mask, pen, evaluator.n))
    cert.weakest = [node for c in halves for node in c.weakest]
    return cert


def certify_data(
    u: np.ndarray, y: np.ndarray, *, term_space, criterion: str = "bic",
    segments: list[tuple[int, int]] | None = None, warm_start: np.ndarray | None = None,
    time_limit: float = 60.0, node_limit: int | None = None,
    progress: Callable[[int, float, float], None] | None = None,
    threads: int | None = None,
    started: float | None = None,
    explain: int = 0,
) -> Certificate:
    """:func:`~.certify.certify` on measured signals (the term space's candidates of u, y).

    The data are scaled by powers of two as :func:`identify` scales them, so the
    values are the GA's; ``warm_start`` is a mask over all candidate terms.
    Terms whose regressor is zero on all rows, or proportional to an earlier
    term's, are left out as :func:`identify` leaves them out. The certificate's
    ``terms`` are the term names.
    ``started`` (``time.perf_counter()``) is when the caller's work began, e.g. a
    warm-start GA: the time limit counts from there (default: now). ``explain``: as
    for :func:`~.certify.certify`, the weakest open nodes' terms fixed in by name.
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
    cert = certify_split(problem.evaluator(crit), problem.constant_split(), warm_start=warm,
                         time_limit=time_limit, node_limit=node_limit, progress=progress,
                         threads=threads, started=started, explain=explain)
    cert.mask = problem.expand(cert.mask)
    names = term_space.term_names()
    cert.terms = [names[i] for i in np.flatnonzero(cert.mask)]
    columns = np.flatnonzero(problem.usable)  # the evaluator's column j is term columns[j]
    for node in cert.weakest:
        node.names = [names[columns[j]] for j in node.inside]
    return cert
