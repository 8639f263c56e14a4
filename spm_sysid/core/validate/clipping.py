"""An output held at exactly its largest or smallest value: a range limit in the record.

A sensor at the end of its range, an ADC at full scale, a tank that overflows, a
joint against its stop: the recorded output stays at one value while the true
one goes on. A polynomial NARX model follows such a limit only approximately,
and its free-run error there measures the limit as much as the model. The data
check says so (it changes nothing).

An end counts as clipped when the output sits at exactly that value on at least
:data:`CLIP_SHARE` of the samples, in at least :data:`CLIP_RUNS` separate runs,
and far more often than on the values just inside (:data:`CLIP_PILE` times the
samples of the band of :data:`CLIP_BAND` of the range, or of
:data:`CLIP_LEVELS` quantisation levels when those are coarser). A signal that
turns at its extremes (a sine dwells there) or is quantised coarsely spreads
over the levels below as well; a clipped one piles up on one value. Measured on
every shared and simulated record of the benchmarks: none clipped
(docs/results.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CLIP_SHARE", "Clipped", "clipped_ends", "describe_clipping"]

#: An end counts when at least this share of the samples sits exactly at it ...
CLIP_SHARE = 0.01

#: ... in at least this many separate runs ...
CLIP_RUNS = 3

#: ... and at least this many times as many samples as the band just inside holds:
CLIP_PILE = 3.0

#: the band is this share of the output's range ...
CLIP_BAND = 0.02

#: ... or this many of its quantisation levels, when that is wider.
CLIP_LEVELS = 5


@dataclass(frozen=True)
class Clipped:
    """One end of an output that holds its value (:func:`clipped_ends`)."""

    side: str
    value: float
    samples: int
    share: float
    runs: int
    longest: int


def clipped_ends(y: np.ndarray, segments=None) -> list[Clipped]:
    """The ends of ``y`` at which it is held (largest first; none: an empty list).

    Parameters
    ----------
    y : ndarray, shape (n,)
        The output (NaN samples are not looked at).
    segments : list of (start, stop), optional
        The samples to look at (default: all).
    """
    y = np.asarray(y, dtype=float)
    parts = [y[a:b] for a, b in segments] if segments else [y]
    x = np.concatenate(parts) if parts else y[:0]
    x = x[np.isfinite(x)]
    if len(x) < 100 or not np.ptp(x) > 0:
        return []
    found = []
    for side, value in (("largest", float(x.max())), ("smallest", float(x.min()))):
        end = _clipped(parts, x, side, value)
        if end is not None:
            found.append(end)
    return found


def _clipped(parts: list[np.ndarray], x: np.ndarray, side: str, value: float
             ) -> Clipped | None:
    at = int(np.count_nonzero(x == value))
    if at < CLIP_SHARE * len(x):
        return None
    inside = x[x != value]
    if inside.size == 0:
        return None
    nearest = float(inside.max() if side == "largest" else inside.min())
    width = max(CLIP_BAND * float(np.ptp(x)), CLIP_LEVELS * abs(value - nearest))
    band = int(np.count_nonzero(np.abs(inside - value) <= width))
    if at < CLIP_PILE * max(band, 1):
        return None
    runs, longest = 0, 0
    for part in parts:
        held = np.concatenate([[False], part == value, [False]])
        edges = np.flatnonzero(np.diff(held.astype(np.int8)))
        lengths = edges[1::2] - edges[::2]
        runs += len(lengths)
        longest = max(longest, int(lengths.max(initial=0)))
    if runs < CLIP_RUNS:
        return None
    return Clipped(side, value, at, at / len(x), runs, longest)


def describe_clipping(found: list[Clipped], name: str = "y") -> str:
    """The data check's warning for an output held at its ends ('' when it is not)."""
    if not found:
        return ""
    ends = " and ".join(f"its {c.side} value {c.value:.6g} on {c.share:.0%} of the samples "
                        f"({c.runs} runs, the longest {c.longest} samples)" for c in found)
    return (f"the output {name} holds exactly {ends}: a sensor's range, a full-scale "
            "reading, an overflow or a stop? While it is held, the recorded output is "
            "not what the system did: a model follows such a limit only approximately, "
            "and its errors there measure the limit as much as the model")
