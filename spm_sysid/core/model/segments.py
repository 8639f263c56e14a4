"""Contiguous segments of a sampled record: gaps found from stamps, rows inside segments.

A lost, rejected or unpaired sample leaves a hole in a recording. Closing the
hole up and regressing across it would pair y(t) with samples that were never
one period apart, so every regression row here is built inside one contiguous
segment, never across a gap.

Rules (documented in ``docs/method.md``):

* the sampling period is given, or estimated as the median of the positive
  differences of consecutive stamps;
* a *gap* lies between two consecutive samples whose stamps differ by more than
  ``gap_factor`` (default 1.5) periods; the number of samples missing there is
  ``round(difference / period) - 1``;
* a stamp not later than the one before it (a replayed bag, a restarted clock)
  also starts a new segment (counted as a *restart*, not a gap);
* a segment with no more samples than the model's largest lag gives no
  regression row and is *skipped* (counted).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Segments",
    "SegmentInfo",
    "describe_data",
    "segment_report",
    "estimate_period_ns",
    "find_segments",
    "normalise_segments",
    "usable_segments",
]

DEFAULT_GAP_FACTOR = 1.5


def estimate_period_ns(stamps_ns: np.ndarray) -> int | None:
    """Median of the positive stamp differences, ns (None with fewer than 2 stamps)."""
    d = np.diff(np.asarray(stamps_ns, dtype=np.int64))
    d = d[d > 0]
    return int(np.median(d)) if d.size else None


@dataclass(frozen=True)
class SegmentInfo:
    """How a record splits into contiguous segments.

    Attributes
    ----------
    bounds : list of (start, stop)
        Index ranges ``[start, stop)`` of the segments, in order.
    period_ns : int or None
        Sampling period used to find gaps (None when there were no stamps).
    period_source : str
        ``"parameter"``, ``"estimated"`` or ``"index"`` (no stamps: one sample per index).
    gaps : int
        Holes inside the timeline (stamp difference above ``gap_factor`` periods).
    missing_samples : int
        Samples estimated missing in those holes.
    restarts : int
        Places where the stamps went back (a new timeline began).
    """

    bounds: list[tuple[int, int]]
    period_ns: int | None = None
    period_source: str = "index"
    gaps: int = 0
    missing_samples: int = 0
    restarts: int = 0

    @property
    def n_samples(self) -> int:
        return sum(b - a for a, b in self.bounds)

    def to_dict(self) -> dict:
        """Plain data for answers, documents and diagnostics."""
        return {
            "samples": self.n_samples,
            "segments": len(self.bounds),
            "gaps": self.gaps,
            "missing_samples": self.missing_samples,
            "restarts": self.restarts,
            "period_s": None if self.period_ns is None else self.period_ns / 1e9,
            "period_source": self.period_source,
        }


def find_segments(stamps_ns: np.ndarray, period_ns: int | None = None,
                  gap_factor: float = DEFAULT_GAP_FACTOR) -> SegmentInfo:
    """Split a record at its gaps and restarts, from the sample stamps.

    Parameters
    ----------
    stamps_ns : ndarray of int, shape (n,)
        Stamps in arrival (record) order.
    period_ns : int, optional
        Sampling period; estimated from the stamps when None or <= 0.
    gap_factor : float
        A difference above ``gap_factor * period`` is a gap.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps)
    if gap_factor <= 1.0:
        raise ValueError(f"gap_factor must be > 1, got {gap_factor}")
    source = "parameter"
    if period_ns is None or period_ns <= 0:
        period_ns, source = estimate_period_ns(stamps), "estimated"
    if n == 0:
        return SegmentInfo([], period_ns, source)
    d = np.diff(stamps)
    restart = d <= 0
    gap = ~restart & (d > gap_factor * period_ns) if period_ns else np.zeros_like(restart)
    cuts = np.flatnonzero(restart | gap) + 1
    edges = np.concatenate([[0], cuts, [n]])
    bounds = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]
    missing = int(np.sum(np.rint(d[gap] / period_ns) - 1)) if gap.any() else 0
    return SegmentInfo(bounds, period_ns, source, int(gap.sum()), missing, int(restart.sum()))


class Segments(list):
    """``[start, stop)`` ranges of a record of ``n`` samples, checked once.

    What :func:`normalise_segments` returns (a list of pairs, as before); handed
    to it again for the same record it is taken as checked, so the segments of
    a problem are checked where the problem is built and nowhere after.
    """

    def __init__(self, pairs, n: int) -> None:
        super().__init__(pairs)
        self.n = n


def normalise_segments(segments: Sequence[tuple[int, int]] | None, n: int
                       ) -> list[tuple[int, int]]:
    """Check ``[start, stop)`` index ranges against a record of ``n`` samples.

    None means one segment, the whole record. Ranges must be ordered and must not
    overlap. Returns :class:`Segments` (checked: not checked again).

    Raises
    ------
    ValueError
        Out-of-range, empty, unordered or overlapping ranges.
    """
    if isinstance(segments, Segments) and segments.n == n:
        return segments
    if segments is None:
        return Segments([(0, n)], n)
    out = []
    prev = 0
    for item in segments:
        try:
            a, b = (int(v) for v in item)
        except (TypeError, ValueError):
            raise ValueError(f"a segment must be a (start, stop) pair, got {item!r}") from None
        if not 0 <= a < b <= n:
            raise ValueError(f"segment ({a}, {b}) is empty or outside the {n} samples")
        if a < prev:
            raise ValueError(f"segments must be in order and not overlap; ({a}, {b}) "
                             f"starts before {prev}")
        out.append((a, b))
        prev = b
    if not out:
        raise ValueError("no segments given")
    return Segments(out, n)


def rows_segments(segments: Sequence[tuple[int, int]] | None, n: int, max_lag: int
                  ) -> Segments:
    """The checked segments of a record of ``n`` samples that give regression rows.

    (Longer than ``max_lag``.) Checked :class:`Segments` of this record are not
    checked again, and the result is :class:`Segments` too.
    """
    if segments is not None and not len(segments):
        return Segments([], n)  # nothing to check (a fold whose rest is empty, say)
    return Segments([(a, b) for a, b in normalise_segments(segments, n) if b - a > max_lag],
                    n)


def usable_segments(bounds: Sequence[tuple[int, int]], max_lag: int
                    ) -> tuple[list[tuple[int, int]], int, int]:
    """Segments long enough for one regression row; also (skipped count, skipped samples).

    Of checked :class:`Segments`, the ones kept are checked :class:`Segments` too.
    """
    keep = [(a, b) for a, b in bounds if b - a > max_lag]
    if isinstance(bounds, Segments) and keep:
        keep = Segments(keep, bounds.n)
    skipped = [(a, b) for a, b in bounds if b - a <= max_lag]
    return keep, len(skipped), sum(b - a for a, b in skipped)


def segment_report(info: SegmentInfo, max_lag: int, rejected: int = 0, unpaired: int = 0
                   ) -> tuple[list[tuple[int, int]], dict]:
    """The usable segments and a plain-data account of the data a fit will use.

    ``rejected`` counts samples dropped before segmenting (NaN/inf), ``unpaired``
    the input or output samples left without a partner.
    """
    bounds, skipped, skipped_samples = usable_segments(info.bounds, max_lag)
    return bounds, {**info.to_dict(), "used_samples": sum(b - a for a, b in bounds),
                    "used_segments": len(bounds), "skipped_segments": skipped,
                    "skipped_samples": skipped_samples, "rejected_samples": rejected,
                    "unpaired_samples": unpaired}


def describe_data(data: dict) -> str:
    """One phrase on what data a result used: samples, segments, gaps, skipped parts."""
    text = f"{data['used_samples']} samples"
    dropped = [f"{data[k]} {label}" for k, label in (
        ("rejected_samples", "rejected as NaN/inf"), ("unpaired_samples", "unpaired"),
        ("spike_samples", "left out as spikes"))
        if data.get(k)]
    if dropped:
        text += f" ({', '.join(dropped)})"
    if data["segments"] > 1 or data["gaps"]:
        text += (f" in {data['used_segments']} contiguous segment(s); {data['gaps']} gap(s) "
                 f"({data['missing_samples']} samples missing)")
        if data["restarts"]:
            text += f", {data['restarts']} restart(s) of the stamps"
        if data["skipped_segments"]:
            text += (f", {data['skipped_segments']} segment(s) too short to use "
                     f"({data['skipped_samples']} samples)")
    return text
