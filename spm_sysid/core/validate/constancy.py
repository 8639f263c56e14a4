"""Whether the system stayed the same over the record: its structure fitted on each half.

A payload picked up, a joint that warms up, a gain changed between two tests
glued into one file: a time-invariant model then fits neither part, and
nothing else says why (a second-order plant whose input gain went from 0.5 to
0.6 halfway got an order-1 model with a 90 % free-run fit and failed
correlation tests, no word of the change). The returned structure is fitted
by least squares on the first and on the second half of the estimation rows;
each half's one-step mean square error with the other half's coefficients,
against its own fit's (per degree of freedom), says how far the two fits
disagree. On one unchanged system the ratios stay near ``1 + terms / rows``:
measured 1.00-1.03 on the long records, and on the short real ones the
smaller of the two at most 1.75 (the robot arm's second half, 1.75 and 2.74;
one direction alone up to 4.3, the heat exchanger's first half, the other
1.28; docs/results.md); the gain change above gave 11 and 9. A warning needs both ratios at
:data:`CHANGED` or more and the Chow test's p-value (are the two halves'
coefficients the same?) below :data:`SIGNIFICANCE`: large, in both
directions, and not chance.

The rows are read a slice at a time into each half's triangular factor of
``[P t]`` (QR), so a record of 10^6 samples holds no more than a slice; every
error here is exact from those factors.
"""

from __future__ import annotations

import numpy as np

from ..fit.lstsq import sse_floor
from ..linalg import scaled_lstsq
from ..model.segments import normalise_segments
from ..model.uncertainty import stacked_factor

__all__ = ["CHANGED", "SIGNIFICANCE", "constancy", "constancy_warnings"]

#: Both halves' error with the other half's coefficients at least this many times their
#: own (mean squares per degree of freedom) for a warning.
CHANGED = 3.0

#: The Chow test's p-value below which the halves' coefficients differ beyond chance.
SIGNIFICANCE = 1e-3


def _halves(segments, n: int, lag: int) -> tuple[list, list, int] | None:
    """Each half's segments (rows split at their middle) and the sample they meet at."""
    segs = [(a, b) for a, b in normalise_segments(segments, n) if b - a > lag]
    rows = sum(b - a - lag for a, b in segs)
    if not segs or rows < 2:
        return None
    half, first, second, meet = rows // 2, [], [], None
    for a, b in segs:
        here = b - a - lag
        if half >= here:
            first.append((a, b))
        elif half <= 0:
            second.append((a, b))
        else:
            cut = a + lag + half
            first.append((a, cut))
            second.append((cut - lag, b))
            meet = cut
        half -= here
    return first, second, meet if meet is not None else second[0][0] + lag


def _factor(model, u, y, segments) -> tuple[np.ndarray, int]:
    """The triangular factor R of ``[P t]`` over ``segments``' rows, and how many rows."""
    rows = [0]

    def blocks():
        for P, t in model.regression_slices(u, y, segments):
            rows[0] += len(t)
            yield np.column_stack([P, t])
    r = stacked_factor(blocks(), len(model.term_indices) + 1)
    return r, rows[0]


def _fit(r: np.ndarray) -> np.ndarray:
    """The least-squares coefficients from the factor of ``[P t]``."""
    return scaled_lstsq(r[:, :-1], r[:, -1])


def _sse(r: np.ndarray, theta: np.ndarray) -> float:
    """||P theta - t||^2 from the factor of ``[P t]``, never below the rounding floor.

    A noise-free record fits exactly (1e-30, rounding): at the floor
    (:func:`~spm_sysid.core.fit.lstsq.sse_floor` of the target's norm, the
    factor's last column's) two exact fits compare as equal, not by rounding.
    """
    e = r[:, :-1] @ theta - r[:, -1]
    return max(float(e @ e), sse_floor(float(np.linalg.norm(r[:, -1]))))


def constancy(model, u: np.ndarray, y: np.ndarray, segments=None) -> dict | None:
    """The two halves' fits of ``model``'s structure, compared (None: too few rows).

    Returns ``{"at": sample where the halves meet, "ratios": [first, second],
    "p_value": the Chow test's, "changed": bool}``: ``ratios[i]`` is half i's
    one-step mean square error with the other half's least-squares coefficients
    over its own fit's (per degree of freedom). The p-value only where both
    ratios reach :data:`CHANGED` (None elsewhere: the ratios decide alone).
    """
    y = np.asarray(y, dtype=float)
    lag, p = model.term_space.max_lag, len(model.term_indices)
    split = _halves(segments, len(y), lag)
    if split is None:
        return None
    first, second, at = split
    (r1, m1), (r2, m2) = _factor(model, u, y, first), _factor(model, u, y, second)
    if min(m1, m2) < 3 * p:
        return None
    t1, t2 = _fit(r1), _fit(r2)
    own1, own2 = _sse(r1, t1), _sse(r2, t2)
    if own1 <= 0 or own2 <= 0:  # an output that is zero on a half
        return None
    ratios = [(_sse(r1, t2) / m1) / (own1 / (m1 - p)), (_sse(r2, t1) / m2) / (own2 / (m2 - p))]
    p_value = None
    if min(ratios) >= CHANGED:  # only then does the test decide (scipy loaded only then)
        from scipy import stats

        pooled = stacked_factor([r1, r2], r1.shape[1])
        dof = m1 + m2 - 2 * p
        f = max(_sse(pooled, _fit(pooled)) - own1 - own2, 0.0) / p / ((own1 + own2) / dof)
        p_value = float(stats.f.sf(f, p, dof))
    changed = p_value is not None and p_value < SIGNIFICANCE
    return {"at": int(at), "ratios": [float(x) for x in ratios], "p_value": p_value,
            "changed": bool(changed)}


def constancy_warnings(found: dict | None) -> list[str]:
    """The warning a changed system gets (none otherwise)."""
    if not found or not found["changed"]:
        return []
    (a, b), p = found["ratios"], found["p_value"]
    return ["the record's first and second halves fit different coefficients"
            f": each half's one-step error with the other half's is {a:.3g}x and "
            f"{b:.3g}x its own fit's (Chow test p {_p_text(p)}): the system may have changed "
            "during the record (a load, a temperature, wear, a drifting sensor), or the "
            "halves visit ranges that this structure does not describe alike; one model of "
            "both describes neither well: identify each part alone to compare"]


def _p_text(p: float) -> str:
    """``= 2.1e-05``; ``< 1e-300`` where the distribution's tail underflowed to 0."""
    return f"= {p:.2g}" if p > 0 else "< 1e-300"
