"""A hard NARX space for searches: a smooth input, much noise, many structures nearly equal.

Written for the tests (no project code but the term space): certification and
its explanation are checked on it against brute force.
"""

from __future__ import annotations

import numpy as np


def smooth_narx_record(seed: int, n: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """u, y of a second-order NARX system driven by a strongly correlated (AR 0.95) input."""
    rng = np.random.default_rng(seed)
    e = rng.standard_normal(n + 50)
    u = np.zeros(n + 50)
    for k in range(1, n + 50):
        u[k] = 0.95 * u[k - 1] + e[k]
    u = u[50:] / np.abs(u[50:]).max()
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.2 * y[k - 1] - 0.5 * y[k - 2] + 0.4 * u[k - 1] + 0.1 * u[k - 2] * y[k - 1]
    return u, y + 0.3 * y.std() * rng.standard_normal(n)
