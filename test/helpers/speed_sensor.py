"""A drive behind a sensor that reads |speed| (the coupled electric drives' kind of record).

Shared by the tests (test_ranges.py) and ``make bench-unseen``.
"""

from __future__ import annotations

import numpy as np


def speed_sensor(n: int, seed: int, low: float = -3.0, high: float = 3.0):
    """Input and output of a third-order plant seen through |speed|, driven by random levels
    in (low, high) held 5-39 samples each; noise 0.02."""
    rng = np.random.default_rng(seed)
    u = np.zeros(n)
    t = 0
    while t < n:
        hold = int(rng.integers(5, 40))
        u[t:t + hold] = rng.uniform(low, high)
        t += hold
    v = np.zeros(n)
    for t in range(3, n):
        v[t] = 1.6 * v[t - 1] - 0.8 * v[t - 2] + 0.1 * v[t - 3] + 0.08 * u[t - 1] + 0.04 * u[t - 2]
    return u, np.abs(v) + 0.02 * rng.standard_normal(n)
