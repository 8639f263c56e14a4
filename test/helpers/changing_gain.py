"""A second-order plant whose input gain changes during the record (a payload picked up).

Shared by the tests (test_constancy.py) and ``make bench-unseen``.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter


def changing_gain(n: int, seed: int, before: float = 0.5, after: float = 0.6,
                  at: float = 0.5, noise: float = 1e-3):
    """Input and output of ``y(t) = 1.2y(t-1) - 0.5y(t-2) + g u(t-1) + 0.1u(t-1)^2``, g
    ``before`` up to the share ``at`` of the record and ``after`` from there; the input
    low-pass filtered noise of unit RMS, white noise on the output."""
    rng = np.random.default_rng(seed)
    u = lfilter([1.0], [1.0, -0.8], rng.standard_normal(n))
    u /= np.std(u)
    y = np.zeros(n)
    for t in range(2, n):
        g = before if t < at * n else after
        y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + g * u[t - 1] + 0.1 * u[t - 1] ** 2
    return u, y + noise * rng.standard_normal(n)
