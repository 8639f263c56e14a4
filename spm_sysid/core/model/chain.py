"""Compiled steps every prediction chain shares: where a chain starts, how divergence ends it.

A k-step-ahead prediction of output t runs one chain from the origin ``t - k``
(the measured outputs up to there); the free run is one chain for the whole
record. The polynomial simulation (:mod:`.simulation`) and the one with
regressors (:mod:`.regressor_sim`) take these two steps from here, so the two
agree on what a chain sees and on what a diverged output leaves behind.
"""

from __future__ import annotations

import numpy as np

from ..compiled.registry import jit_exact as jit

__all__ = ["chain_start", "mark_diverged"]


@jit
def mark_diverged(out, t, lag0):  # pragma: no cover - compiled
    """Rows t.. of ``out`` become NaN (a diverged chain predicts nothing after); returns t."""
    for s in range(t, lag0 + out.shape[0]):
        out[s - lag0] = np.nan
    return t


@jit
def chain_start(work, y, t, horizon, lag0, free):  # pragma: no cover - compiled
    """Start the chain that predicts output t; returns the first step it predicts.

    k steps ahead: one chain from origin ``o = t - horizon`` (or the start), the
    measured outputs up to o copied into ``work``. Free run (``free``): one chain
    for everything, extended by one step (measured outputs copied once, at the start).
    """
    if free:
        if t == lag0:
            for s in range(lag0):
                work[s] = y[s]
        return t
    o = max(t - horizon, lag0 - 1)
    for s in range(o - lag0 + 1 if o - lag0 + 1 > 0 else 0, o + 1):
        work[s] = y[s]
    return o + 1
