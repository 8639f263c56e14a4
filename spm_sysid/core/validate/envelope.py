"""The range of every signal a model was fitted on, and where new data leave it.

A polynomial model is a fit inside the region its estimation data covered;
outside, its squares and cubes grow without the data that would have tied them
down. On a short record whose input never went below -1.3, a model of
``y(t-1)^2*u(t-1)`` simulated a second record well until that record's input
held -2.4 for 20 samples, and then diverged; ``validate`` said "DIVERGED" and
nothing of why. The model document keeps each signal's smallest and largest
value on the estimation samples (``metadata.ranges``, in the record's units), and
``validate`` names each signal of the new data that goes beyond them; the node
counts the live samples beyond them (:class:`RangeWatch`, ``/diagnostics``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["BEYOND", "RangeWatch", "data_ranges", "range_notes"]

#: A signal is named when it goes beyond its fitted range by more than this share of
#: the range's width: a new draw of the same experiment crosses the edges by its noise.
BEYOND = 0.05


def _columns(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x[:, None] if x.ndim == 1 else x


def _rows(segments: Sequence[tuple[int, int]] | None, n: int) -> np.ndarray:
    """The sample indices of ``segments`` (None or empty: all ``n``)."""
    if not segments:
        return np.arange(n)
    return np.concatenate([np.arange(a, b) for a, b in segments])


def _edges(low: float, high: float) -> tuple[float, float]:
    """Beyond these a value counts as outside [low, high]: :data:`BEYOND` of its width."""
    margin = BEYOND * max(high - low, 1e-12 * max(abs(low), abs(high), 1.0))
    return low - margin, high + margin


def _ends(smallest: float, largest: float, edges: tuple[float, float]) -> list[str]:
    """``down to ...`` and ``up to ...`` for the extremes beyond ``edges``."""
    return ([f"down to {smallest:.4g}"] if smallest < edges[0] else []) + \
        ([f"up to {largest:.4g}"] if largest > edges[1] else [])


def data_ranges(u: np.ndarray, y: np.ndarray, segments: Sequence[tuple[int, int]],
                inputs: Sequence[str], outputs: Sequence[str]) -> dict:
    """``{"inputs": {name: [low, high]}, "outputs": {...}}`` over the samples of ``segments``.

    NaN samples (never inside a segment a job uses) are ignored; a signal with no
    finite sample is left out.
    """
    rows = _rows(segments, len(y))

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
    rows = _rows(segments, len(y))
    notes = []
    for kind, x, names in (("input", u, inputs), ("output", y, outputs)):
        fitted = ranges.get(kind + "s") or {}
        for name, col in zip(names, _columns(x)[rows].T):
            if name not in fitted:
                continue
            low, high = fitted[name]
            col = col[np.isfinite(col)]
            ends = _ends(col.min(), col.max(), _edges(low, high)) if col.size else []
            if not ends:
                continue
            share = float(np.mean((col < low) | (col > high)))
            notes.append(
                f"the {kind} {name} goes {' and '.join(ends)} on these data, beyond the "
                f"{low:.4g} to {high:.4g} the model was fitted on ({share:.0%} of the samples "
                "outside): the model extrapolates there, and a nonlinear model's free run "
                "may drift or diverge")
    return notes


class RangeWatch:
    """Counts live samples beyond the ranges a model was fitted on (the node's monitor).

    Parameters
    ----------
    ranges : dict or None
        The document's ``metadata.ranges`` (None or empty: nothing is watched).
    inputs, outputs : sequence of str
        The names of the values :meth:`update` is given, in that order.
    """

    def __init__(self, ranges: dict | None, inputs: Sequence[str],
                 outputs: Sequence[str]) -> None:
        self.names: list[str] = []
        limits = []
        for kind, names in (("inputs", inputs), ("outputs", outputs)):
            fitted = (ranges or {}).get(kind) or {}
            for name in names:
                low, high = fitted.get(name, (-np.inf, np.inf))
                limits.append((*_edges(low, high), low, high))
                self.names.append(name)
        self.limits = np.array(limits, dtype=float).reshape(-1, 4)
        self.count = 0
        self.low = np.full(len(self.names), np.inf)
        self.high = np.full(len(self.names), -np.inf)

    def update(self, u, y) -> str | None:
        """Check one sample (inputs u, outputs y); a sentence for the first one beyond."""
        x = np.concatenate([np.atleast_1d(np.asarray(u, dtype=float)),
                            np.atleast_1d(np.asarray(y, dtype=float))])
        if x.shape[0] != self.limits.shape[0]:
            return None
        out = (x < self.limits[:, 0]) | (x > self.limits[:, 1])
        if not out.any():
            return None
        self.count += 1
        self.low[out] = np.minimum(self.low[out], x[out])
        self.high[out] = np.maximum(self.high[out], x[out])
        if self.count > 1:
            return None
        i = int(np.flatnonzero(out)[0])
        return (f"{self.names[i]} = {x[i]:.4g}, beyond the {self.limits[i, 2]:.4g} to "
                f"{self.limits[i, 3]:.4g} the model was fitted on: its predictions there are "
                "extrapolations (counted in /diagnostics, beyond_fitted_range)")

    def values(self) -> dict:
        """The counts for ``/diagnostics``: samples beyond, and how far each signal went."""
        seen = []
        for i, name in enumerate(self.names):
            ends = _ends(self.low[i], self.high[i], tuple(self.limits[i, :2]))
            if ends:
                seen.append(f"{name} {' and '.join(ends)}")
        return {"beyond_fitted_range": self.count,
                "beyond_fitted_range_signals": "; ".join(seen)}
