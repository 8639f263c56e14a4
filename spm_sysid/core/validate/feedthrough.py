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

from ..linalg import scaled_lstsq
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
ROWS = 50_000
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
    found = []
    for j, (d, name) in enumerate(zip(delays, names)):
        if d < 1 or np.ptp(u[:, j]) == 0:
            continue
        tests = [_share(y, u, delays, j, n) for n in ORDERS]
        if any(t is None for t in tests):
            return []
        found.append(Feedthrough(str(name), int(d) - 1, min(s for s, _ in tests),
                                 max(p for _, p in tests)))
    return found


def describe_feedthrough(found: list[Feedthrough], output: str) -> str:
    """The data check's warning for the inputs that act within the sample ('' for none)."""
    acting = [f for f in found if f.acts]
    if not acting:
        return ""
    lag = min(f.lag for f in acting)
    terms = " and ".join(f"{f.input}({_lag(f.lag)})" for f in acting)
    shares = " and ".join(f"{f.share:.0%}" for f in acting)
    return (f"{output} moves with {terms} in the same step: beside a linear ARX model of "
            f"order {ORDERS[0]} without it, it removes {shares} of the one-step squared "
            "residual; either the plant responds within a sample (a static map, an "
            "acceleration beside its torque, a sensor read after the command was "
            f"applied): identify with --delay {lag}, or the input is computed from "
            f"this {output} in the same sample (a feedback controller's output): then keep "
            "the delay, a model with that term would describe the controller (docs/cli.md)")


def _lag(k: int) -> str:
    return "t" if k == 0 else f"t-{k}"


def _share(y, u, delays, j: int, order: int) -> tuple[float, float] | None:
    """(share removed, p-value) of input ``j``'s earlier lag beside an ARX of ``order``."""
    inputs = [(str(i), tuple(range(max(int(d), 0), max(int(d), 0) + order)), u[:, i])
              for i, d in enumerate(delays)]
    cols, lag0 = arx_columns(y, inputs, order)
    target = y[lag0:]
    if len(target) < ROWS_PER_COLUMN * (len(cols) + 1):
        return None
    X = np.column_stack(cols)
    d = int(delays[j])
    extra = u[lag0 - d + 1:len(y) - d + 1, j]
    without, with_it = _sse(X, target), _sse(np.column_stack([X, extra]), target)
    if without <= 0:
        return 0.0, 1.0
    share = 1.0 - with_it / without
    if share <= 0:
        return 0.0, 1.0
    if with_it <= 0:
        return share, 0.0
    chi2 = (without - with_it) / (with_it / (len(target) - X.shape[1] - 1))
    return float(share), float(math.erfc(math.sqrt(chi2 / 2)))


def _sse(X: np.ndarray, target: np.ndarray) -> float:
    r = target - X @ scaled_lstsq(X, target)
    return float(r @ r)
