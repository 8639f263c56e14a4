"""Two coupled outputs of different orders: what ``--orders auto`` gives each its own space.

y1 is second order and reads y2's last sample; y2 is first order and reads y1's
through a product with its own input. Used by the coupled validation's test and
by ``benchmarks/unseen.py``.
"""

from __future__ import annotations

import numpy as np


def coupled_outputs(u: np.ndarray, rng: np.random.Generator, noise: float = 1e-3
                    ) -> np.ndarray:
    """The two outputs (n, 2) driven by the inputs ``u`` (n, 2), with measurement noise."""
    n = len(u)
    y = np.zeros((n, 2))
    for t in range(2, n):
        y[t, 0] = (1.2 * y[t - 1, 0] - 0.5 * y[t - 2, 0] + 0.3 * u[t - 1, 0]
                   + 0.1 * y[t - 1, 1] + 0.05 * u[t - 1, 0] ** 2)
        y[t, 1] = 0.7 * y[t - 1, 1] + 0.4 * u[t - 1, 1] - 0.1 * y[t - 1, 0] * u[t - 1, 1]
    return y + noise * rng.standard_normal((n, 2))
