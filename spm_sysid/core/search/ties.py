"""Exact ties: of the structures that fit a noise-free record exactly, the lowest degree.

A noise-free record is fitted exactly by several structures of one size: every
exact fit scores the SSE floor (:func:`~spm_sysid.core.fit.lstsq.sse_floor`), so
their criterion values are equal, and which of them a search meets first is
chance. A step response around its means fits with ``y(t-1)*u(t-1)`` as exactly
as with ``y(t-1)``: the product agrees with the plant on this record only. Of
such ties the lowest degree is taken. Noisy records have no exact fits, and
nothing here runs on them.

The moves' SSEs come from the evaluator's own fits: the rank-one formulas of the
polish's screen (:class:`~.neighbourhood.MoveScreen`) lose an SSE at the floor in
rounding.
"""

from __future__ import annotations

import numpy as np

__all__ = ["lowest_degree_of_ties"]

#: Swapped structures fitted at once (bounds the work of one step on a large space).
MAX_SWAPS = 20_000


def lowest_degree_of_ties(evaluator, mask: np.ndarray, degrees: np.ndarray,
                          max_steps: int = 100) -> np.ndarray:
    """``mask`` with terms swapped for lower-degree ones while the fit stays exact.

    Parameters
    ----------
    evaluator : StructureEvaluator
        Its fits (SSE and rank) and SSE floor; masks over its columns.
    mask : ndarray of bool
        The structure found.
    degrees : ndarray of int
        Each column's degree.
    max_steps : int
        Swaps at most (each lowers the degree: a structure of k terms takes at
        most its degree sum less k).

    Returns
    -------
    ndarray of bool
        ``mask`` itself unless it fits exactly; else the structure reached by
        swaps (one term out, one of lower degree in) each of which keeps the fit
        exact, the largest degree drop first. The size is kept, so a criterion of
        the SSE and the size keeps its value.
    """
    current = np.asarray(mask, dtype=bool).copy()
    if not _exact(evaluator, current[None, :])[0]:
        return current
    for _ in range(max_steps):
        inn, out = np.flatnonzero(current), np.flatnonzero(~current)
        drop, add = np.repeat(inn, len(out)), np.tile(out, len(inn))
        gain = degrees[drop] - degrees[add]
        order = np.argsort(-gain, kind="stable")[:MAX_SWAPS]
        order = order[gain[order] > 0]
        if not len(order):
            break
        swapped = np.repeat(current[None, :], len(order), axis=0)
        rows = np.arange(len(order))
        swapped[rows, drop[order]], swapped[rows, add[order]] = False, True
        exact = np.flatnonzero(_exact(evaluator, swapped))
        if not len(exact):
            break
        current = swapped[exact[0]]
    return current


def _exact(evaluator, masks: np.ndarray) -> np.ndarray:
    """Which structures fit exactly: full rank and an SSE at the evaluator's floor."""
    sse, _, bad = evaluator.fit_batch(masks)
    return ~np.asarray(bad, dtype=bool) & (np.asarray(sse) <= evaluator.sse_floor)
