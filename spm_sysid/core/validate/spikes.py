"""Spikes in the output: samples that leave the signal and come back, found before any search.

A spike (a bad read, a dropped packet, an encoder glitch) is fitted by least
squares like any other sample. On a second-order system with spikes at 1 % of
its samples, each 20 standard deviations of the output, the command as typed
returned a static model of the input (free run on clean data 0.31 against 0.48
for the linear ARX); the same record with the spikes made gaps gave the true
structure (1.3e-4). The data check's glitch warning
(:func:`~.excitation.glitches`) finds samples far outside the whole signal's
range; spikes *within* its range are found here:

* the one-step error of a linear ARX model with cubic terms
  (:func:`~.friction.cubic_arx_design`, the friction test's columns) is more
  than :data:`SPIKE_Z` times the errors' robust standard deviation (1.4826 times
  their median absolute deviation; the model fitted again without such rows);
* and the output comes back: within :data:`SPIKE_WIDTH` samples it is back on
  the course it left (:func:`_returns`). A step, a hard stop or a change of mode
  does not come back, and is not a spike.

Measured (``ny = nu = 2``): the robot arm, the dryer, the heat exchanger,
Silverbox, Wiener-Hammerstein, the two tanks, the simulated joints, velocity
loops, a saturating loop, a hysteresis, a pendulum, a heater far from zero:
at most 8.5 robust deviations, no spike. Spikes of 3 to 20 output standard
deviations at 0.1 % or 1 % of the samples: every one found.

numpy only (the data check runs before every search); coefficients from at
most :data:`SPIKE_FIT_ROWS` rows of the longest segment, errors of every
segment in chunks of :data:`SPIKE_CHUNK` samples (memory stays small on 10^6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..linalg import scaled_lstsq
from .friction import cubic_arx_design

__all__ = ["SPIKE_ROUNDS", "SPIKE_WIDTH", "SPIKE_Z", "Spikes", "describe_spike_gaps",
           "describe_spikes", "output_spikes", "spikes_of_outputs", "without_spikes"]

#: A row is suspect when its one-step error exceeds this many robust standard deviations
#: (legitimate records measured at most 8.5; Gaussian noise never reaches it) ...
SPIKE_Z = 20.0

#: ... the output jumps there by this many typical steps (robust deviations of its
#: first difference) ...
SPIKE_STEP = 5.0

#: ... and a spike ends within this many samples (the output comes back).
SPIKE_WIDTH = 5

#: Output and input lags of the linear model (the screening's, not the space's: the
#: data check and ``--spikes gaps`` find the same spikes whatever the orders).
SPIKE_LAGS = 2

#: Rows the linear model is fitted on (the first of the longest segment).
SPIKE_FIT_ROWS = 50_000

#: Samples whose errors are computed at once.
SPIKE_CHUNK = 100_000

#: Least-squares fits, each without the rows the one before put beyond :data:`SPIKE_Z`
#: (many spikes inflate the first fit's deviation and hide the smaller ones).
SPIKE_FITS = 4

#: ``--spikes gaps`` looks again after leaving spikes out, at most this many times in all
#: (a spike next to a larger one, or hidden by many, shows once they are out).
SPIKE_ROUNDS = 3

#: Segments shorter than this many rows are not read (too short to fit, to tell).
SPIKE_MIN_ROWS = 200


@dataclass(frozen=True)
class Spikes:
    """The spikes found (:func:`output_spikes`)."""

    starts: tuple[int, ...]  # first sample of each spike (record indices)
    widths: tuple[int, ...]  # samples of each spike
    largest: float           # the largest one-step error, in robust standard deviations

    @property
    def samples(self) -> int:
        """Samples inside the spikes, in all."""
        return sum(self.widths)


def output_spikes(y: np.ndarray, u: np.ndarray, segments=None, ny: int = SPIKE_LAGS,
                  nu: int = SPIKE_LAGS) -> Spikes | None:
    """The output's spikes (module doc); None when there are none or too few rows to tell.

    Parameters
    ----------
    y, u : ndarray
        The output, shape (n,), and the inputs, (n,) or (n, m), of the whole record.
    segments : sequence of (start, stop), optional
        Contiguous stretches (no row crosses from one to the next); default: all.
    ny, nu : int
        Output lags (at least 2) and lags of each input of the linear model.
    """
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float).reshape(len(y), -1)
    ny, nu = max(int(ny), 2), max(int(nu), 1)
    bounds = [(int(a), int(b)) for a, b in (segments or [(0, len(y))])
              if b - a >= SPIKE_MIN_ROWS]
    if not bounds or not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        return None
    a, b = max(bounds, key=lambda s: s[1] - s[0])
    b = min(b, a + SPIKE_FIT_ROWS)
    X, target, _, scales = cubic_arx_design(y[a:b], u[a:b], ny, nu)
    theta, scale = _robust_fit(X, target)
    if theta is None:
        return None
    step = SPIKE_STEP * _robust_deviation(np.diff(y[a:b]))
    starts, widths, largest = [], [], 0.0
    for a, b in bounds:
        for t, z in _suspects(y, u, (a, b), (theta, scale, scales), ny, nu):
            largest = max(largest, z)
            width = _returns(y, t, b, max(z * scale / 2, step))
            if width and (not starts or t > starts[-1] + widths[-1]):  # t-1 not a spike's
                starts.append(t)
                widths.append(width)
    return Spikes(tuple(starts), tuple(widths), largest) if starts else None


def spikes_of_outputs(y: np.ndarray, u: np.ndarray, segments=None) -> Spikes | None:
    """:func:`output_spikes` of each output (columns of ``y``), together; None when none."""
    ys = np.asarray(y, dtype=float).reshape(len(y), -1)
    found = [f for f in (output_spikes(ys[:, j], u, segments) for j in range(ys.shape[1]))
             if f is not None]
    if not found:
        return None
    spans = sorted({(t, w) for f in found for t, w in zip(f.starts, f.widths)})
    return Spikes(tuple(t for t, _ in spans), tuple(w for _, w in spans),
                  max(f.largest for f in found))


def without_spikes(bounds, found: Spikes | None) -> list[tuple[int, int]]:
    """The segments ``bounds`` split around the spikes of ``found`` (their samples left out)."""
    if found is None:
        return [(int(a), int(b)) for a, b in bounds]
    cuts = sorted(zip(found.starts, found.widths))
    out = []
    for a, b in bounds:
        start = int(a)
        for t, w in cuts:
            if a <= t < b:
                out.append((start, t))
                start = max(start, t + w)
        out.append((start, int(b)))
    return [(a, b) for a, b in out if b > a]


def _robust_deviation(x: np.ndarray) -> float:
    """1.4826 times the median absolute deviation: the standard deviation of normal data."""
    return 1.4826 * float(np.median(np.abs(x - np.median(x)))) if len(x) else 0.0


def _robust_fit(X: np.ndarray, target: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Least squares, refitted without the rows beyond :data:`SPIKE_Z` (:data:`SPIKE_FITS`)."""
    keep = np.ones(len(target), dtype=bool)
    theta, scale = None, 0.0
    for _ in range(SPIKE_FITS):
        theta = scaled_lstsq(X[keep], target[keep])
        e = target - X @ theta
        scale = _robust_deviation(e[keep])
        if not scale > 0:
            return None, 0.0
        keep = np.abs(e) <= SPIKE_Z * scale
    return theta, scale


def _suspects(y, u, segment: tuple[int, int], fit, ny: int, nu: int):
    """(sample, deviations) of the rows of ``segment`` beyond :data:`SPIKE_Z`, in order.

    ``fit``: the coefficients, the errors' robust deviation, the columns' scales.
    """
    (a, b), (theta, scale, scales) = segment, fit
    lag0 = max(ny, nu)
    for start in range(a, b - lag0, SPIKE_CHUNK):
        lo, hi = max(a, start - lag0), min(b, start + SPIKE_CHUNK)
        X, target, first, _ = cubic_arx_design(y[lo:hi], u[lo:hi], ny, nu, scales)
        z = np.abs(target - X @ theta) / scale
        for i in np.flatnonzero(z > SPIKE_Z):
            yield lo + first + int(i), float(z[i])


def _returns(y: np.ndarray, t: int, stop: int, least: float) -> int:
    """The spike's width when the output leaves its course at sample ``t`` and comes back.

    For each width w up to :data:`SPIKE_WIDTH`: the line from ``y[t-1]`` to
    ``y[t+w]`` is the course; ``y[t]`` is off it by at least ``least`` (half the
    one-step error there: an impact on a stop is a large error after a small
    step; and :data:`SPIKE_STEP` typical steps: a dip of a fast signal is not a
    spike), and the course itself moves by at most half that (a step stays: it
    moves as far as it jumps). 0 when no width fits.
    """
    for width in range(1, SPIKE_WIDTH + 1):
        if t + width >= stop:
            return 0
        before, after = y[t - 1], y[t + width]
        off = abs(y[t] - (before + (after - before) / (width + 1)))
        if off >= least and abs(after - before) <= off / 2:
            return width
    return 0


def describe_spikes(found: Spikes | None, name: str = "y") -> str:
    """The spikes in words for the data check ('' when none)."""
    if found is None:
        return ""
    shown = ", ".join(str(t) for t in found.starts[:5])
    more = ", ..." if len(found.starts) > 5 else ""
    return (f"the output {name} has {len(found.starts)} spike(s) ({found.samples} "
            f"sample(s), at sample {shown}{more}): it jumps, up to {found.largest:.0f} times "
            "the typical one-step error of a linear ARX model, and comes back within "
            f"{SPIKE_WIDTH} samples. Least squares follows spikes (a model may lose its "
            "dynamics): --spikes gaps leaves them out (docs/cli.md)")


def describe_spike_gaps(doc: dict | None) -> str:
    """Spikes left out of a record (``metadata.spikes``) in words ('' when none)."""
    if not doc or not doc.get("spikes"):
        return ""
    shown = ", ".join(str(t) for t in (doc.get("at") or [])[:5])
    more = ", ..." if doc["spikes"] > 5 else ""
    return (f"{doc['spikes']} output spike(s) left out ({doc['samples']} sample(s), at sample "
            f"{shown}{more}; --spikes gaps): no regression row uses them")
