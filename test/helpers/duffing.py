"""A discrete Duffing-like oscillator driven by filtered noise (a Silverbox in small).

A cubic spring: an odd nonlinearity that is a polynomial's case, not friction.
Written for the tests (no project code).
"""

from __future__ import annotations

import numpy as np

__all__ = ["duffing"]


def duffing(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Input and output (with 1e-3 measurement noise) of ``n`` samples."""
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.standard_normal(n), np.ones(4) / 4, mode="same")
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 1.6 * y[t - 1] - 0.8 * y[t - 2] + 0.1 * u[t - 1] - 0.2 * y[t - 1] ** 3
    return u, y + 1e-3 * rng.standard_normal(n)
