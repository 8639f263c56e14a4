"""Does an input act on the output within the sample? A hint for ``--delay`` before any search.

The candidate terms read each input from its delay on (``u(t-1)`` by default, as
in the paper). When the output moves with the input in the same sample (a static
map, an acceleration read beside the torque that causes it, a sensor sampled
after the command was applied), no lag from 1 on describes it: a record with
``y(t) = x(t) + 0.2x(t)^2``, ``x(t) = 0.5x(t-1) + 0.5u(t)`` got a free-run fit of
13 % and no word of why; with ``--delay 0`` its held-out error fell 2 500-fold.

:func:`within_sample` is a least-squares test: beside a linear ARX model of
order :data:`ORDERS` (the output's lags, a constant, each input's lags from its
delay on), how much of the one-step squared residual does the input one lag
earlier (``u(t)`` for delay 1) remove? The smaller share of the two orders
counts: at order 6 a periodic input's lags are nearly collinear and the robot
arm read 0.75, at 10 and 20 at most 0.001. Measured at order 10 and 20 (first
and second halves): the robot arm, the dryer, the two tanks, the speed loop,
the saturating loop and 21 kinds of ``make bench-unseen`` at most 0.08 (a heater
near 300 K); the heat exchanger 0.75 (``--delay 0`` simulated its second half at
0.197 against 0.480); the PD-controlled joint 0.65-0.66: a controller computes
the input from the output of the same sample, which this test cannot tell from
a plant's feedthrough, so the warning names both.

numpy only (the data check runs before every search).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model.presets import arx_columns

__all__ = ["FEEDTHROUGH_LEVEL", "FEEDTHROUGH_SHARE", "ORDERS", "Feedthrough",
           "describe_feedthrough", "within_sample"]

#: An input is said to act within the sample when its earlier lag removes this share ...
FEEDTHROUGH_SHARE = 0.5

#: ... significantly at this level (large-sample chi-square with one degree of freedom) ...
FEEDTHROUGH_LEVEL = 1e-3

#: ... beside a linear ARX model of each of these orders (the smaller share counts) ...
ORDERS = (10, 20)

#: ... read on at most this many rows, and on at least this many per column.
ROWS = 20_000
ROWS_PER_COLUMN = 10


@dataclass(frozen=True)
class Feedthrough:
    """One input's outcome (:func:`within_sample`)."""

    input: str
    lag: int          # the lag tested: one earlier than the input's delay
    share: float      # of the one-step squared residual it removes (the smaller of ORDERS)
    p_value: float    # the larger of ORDERS

    @property
    def acts(self) -> bool:
        return self.share >= FEEDTHROUGH_SHARE and self.p_value < FEEDTHROUGH_LEVEL


def within_sample(y: np.ndarray, u: np.ndarray, delays, names) -> list[Feedthrough]:
    """Each input's lag one earlier than its delay, tested beside a linear ARX (module doc).

    Parameters
    ----------
    y, u : ndarray
        One contiguous stretch of the output, shape (n,), and the inputs, (n,) or (n, m).
    delays : sequence of int
        Each input's delay (its smallest lag); inputs of delay 0 are not tested.
    names : sequence of str
        The inputs' names.

    Returns
    -------
    list of Feedthrough
        One per tested input; empty when the stretch is too short or not finite.
    """
    y = np.asarray(y, dtype=float)[:ROWS]
    u = np.asarray(u, dtype=float)
    u = u.reshape(len(u), -1)[:len(y)]
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        return []
    y, u = y / _size(y), u / np.array([_size(c) for c in u.T])  # 1e100 V or 1e-100 m alike
    tested = [j for j, d in enumerate(delays) if d >= 1 and np.ptp(u[:, j]) > 0]
    if not tested:
        return []
    tests = [_shares(y, u, delays, tested, n) for n in ORDERS]
    if any(t is None for t in tests):
        return []
    found = [Feedthrough(str(names[j]), int(delays[j]) - 1, min(t[j][0] for t in tests),
                         max(t[j][1] for t in tests)) for j in tested]
    return found


def describe_feedthrough(found: list[Feedthrough], output: str) -> str:
    """The data check's warning for the inputs that act within the sample ('' for none)."""
    acting = [f for f in found if f.acts]
    if not acting:
        return ""
    lag = min(f.lag for f in acting)
    terms = " and ".join(f"{f.input}({_lag(f.lag)})" for f in acting)
    shares = " and ".join(f"{f.share:.0%}" for f in acting)
    removes = "it removes" if len(acting) == 1 else "they remove"
    return (f"{output} moves with {terms} in the same step: beside linear ARX models of "
            f"orders {ORDERS[0]} and {ORDERS[1]} without it, {removes} at least {shares} of "
            "the one-step squared residual; either the plant responds within a sample (a "
            "static map, an acceleration beside its torque, a sensor read after the command "
            f"was applied): identify with --delay {lag}, or the input is computed from "
            f"this {output} in the same sample (a feedback controller's output): then keep "
            "the delay, a model with that term would describe the controller (docs/cli.md)")


def _lag(k: int) -> str:
    return "t" if k == 0 else f"t-{k}"


def _shares(y, u, delays, tested, order: int) -> dict[int, tuple[float, float]] | None:
    """Each tested input's (share removed, p-value) beside the linear ARX of ``order``.

    One QR factor of the ARX's columns (scaled to unit norm) serves every input: the
    squared residual a column removes is ``(r.z)^2 / z.z``, ``r`` the ARX's residual and
    ``z`` the column's part outside the ARX's columns.
    """
    inputs = [(str(i), tuple(range(max(int(d), 0), max(int(d), 0) + order)), u[:, i])
              for i, d in enumerate(delays)]
    lag0 = max([order] + [lags[-1] for _, lags, _ in inputs])
    if len(y) - lag0 < ROWS_PER_COLUMN * (order * (1 + len(inputs)) + 2):  # columns + 1
        return None
    cols, lag0 = arx_columns(y, inputs, order)
    target = y[lag0:]
    X = np.column_stack(cols)
    norms = np.linalg.norm(X, axis=0)
    q, _ = np.linalg.qr(X[:, norms > 0] / norms[norms > 0])
    r = target - q @ (q.T @ target)
    without = float(r @ r)
    dof = len(target) - q.shape[1] - 1
    out = {}
    for j in tested:
        d = int(delays[j])
        x = u[lag0 - d + 1:len(y) - d + 1, j]
        z = x - q @ (q.T @ x)
        zz = float(z @ z)
        if without <= 0 or zz <= 1e-12 * float(x @ x):
            out[j] = (0.0, 1.0)
            continue
        removed = min(float(r @ z) ** 2 / zz, without)
        left = without - removed
        chi2 = removed / (left / dof) if left > 0 else math.inf
        out[j] = (removed / without, math.erfc(math.sqrt(chi2 / 2)))
    return out


def _size(x: np.ndarray) -> float:
    """The largest magnitude, 1 for a signal of zeros (the test is scale-free)."""
    top = float(np.max(np.abs(x))) if x.size else 0.0
    return top if top > 0 else 1.0
