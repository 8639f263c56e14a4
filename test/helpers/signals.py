"""Test inputs shared by the tests and the benchmarks."""

from __future__ import annotations

import numpy as np


def multisine(n: int, rng: np.random.Generator, top: float, k: int = 20) -> np.ndarray:
    """Sum of ``k`` unit sines, frequencies drawn in (0.001, ``top``) cycles/sample, then
    phases; unit RMS."""
    t = np.arange(n)
    f, ph = rng.uniform(0.001, top, k), rng.uniform(0, 2 * np.pi, k)
    return np.sin(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]).sum(0) / np.sqrt(k / 2)
