"""The range of every signal a model was fitted on, and where new data leave it.

A polynomial model is a fit inside the region its estimation data covered;
outside, its squares and cubes grow without the data that would have tied them
down. On a short record whose input never went below -1.3, a model of
``y(t-1)^2*u(t-1)`` simulated a second record well until that record's input
held -2.4 for 20 samples, and then diverged; ``validate`` said "DIVERGED" and
nothing of why. The model document keeps each signal's smallest and largest
value on the estimation samples (``metadata.ranges``, in the record's units), and
``validate`` names each signal of the new data that goes beyond them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["BEYOND", "data_ranges", "range_notes"]

#: A signal is named when it goes beyond its fitted range by more than this share of
#: the range's width: a new draw of the same experiment crosses the edges by its noise.
BEYOND = 0.05


def _columns(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x[:, None] if x.ndim == 1 else x


def data_ranges(u: np.ndarray, y: np.ndarray, segments: Sequence[tuple[int, int]],
                inputs: Sequence[str], outputs: Sequence[str]) -> dict:
    """``{"inputs": {name: [low, high]}, "outputs": {...}}`` over the samples of ``segments``.

    NaN samples (never inside a segment a job uses) are ignored; a signal with no
    finite sample is left out.
    """
    rows = np.concatenate([np.arange(a, b) for a, b in segments]) if segments else \
        np.arange(len(y))

    def ranges(x: np.ndarray, names: Sequence[str]) -> dict:
        out = {}
        for name, col in zip(names, _columns(x)[rows].T):
            col = col[np.isfinite(col)]
            if col.size:
                out[str(name)] = [float(col.min()), float(col.max())]
        return out

    return {"inputs": ranges(u, inputs), "outputs": ranges(y, outputs)}


def range_notes(ranges: dict | None, u: np.ndarray, y: np.ndarray,
                segments: Sequence[tuple[int, int]] | None, inputs: Sequence[str],
                outputs: Sequence[str]) -> list[str]:
    """A sentence for each signal of new data that goes beyond the model's fitted range.

    Parameters
    ----------
    ranges : dict or None
        The document's ``metadata.ranges`` (None: an older document, no notes).
    u, y : ndarray
        The new data, in the record's units.
    segments : list of (start, stop) or None
        The samples validated (None: all).
    inputs, outputs : sequence of str
        The names of u's and y's columns.
    """
    if not ranges:
        return []
    segments = segments or [(0, len(y))]
    rows = np.concatenate([np.arange(a, b) for a, b in segments])
    notes = []
    for kind, x, names in (("input", u, inputs), ("output", y, outputs)):
        fitted = ranges.get(kind + "s") or {}
        for name, col in zip(names, _columns(x)[rows].T):
            if name not in fitted:
                continue
            low, high = fitted[name]
            col = col[np.isfinite(col)]
            margin = BEYOND * max(high - low, 1e-12 * max(abs(low), abs(high), 1.0))
            if not col.size or (col.min() >= low - margin and col.max() <= high + margin):
                continue
            share = float(np.mean((col < low) | (col > high)))
            ends = []
            if col.min() < low - margin:
                ends.append(f"down to {col.min():.4g}")
            if col.max() > high + margin:
                ends.append(f"up to {col.max():.4g}")
            notes.append(
                f"the {kind} {name} goes {' and '.join(ends)} on these data, beyond the "
                f"{low:.4g} to {high:.4g} the model was fitted on ({share:.0%} of the samples "
                "outside): the model extrapolates there, and a nonlinear model's free run "
                "may drift or diverge")
    return notes
