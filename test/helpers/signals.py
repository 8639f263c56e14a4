"""Test inputs shared by the tests and the benchmarks."""

from __future__ import annotations

import numpy as np


def multisine(n: int, rng: np.random.Generator, top: float, k: int = 20) -> np.ndarray:
    """Sum of ``k`` unit sines, frequencies drawn in (0.001, ``top``) cycles/sample, then
    phases; unit RMS."""
    t = np.arange(n)
    f, ph = rng.uniform(0.001, top, k), rng.uniform(0, 2 * np.pi, k)
    return np.sin(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]).sum(0) / np.sqrt(k / 2)


def second_order(u: np.ndarray, extra=lambda u, t: 0.0, a=(1.2, -0.5), b=0.5) -> np.ndarray:
    """``y(t) = a0 y(t-1) + a1 y(t-2) + b u(t-1) + extra(u, t)``, noise-free, from rest."""
    y = np.zeros(len(u))
    for t in range(2, len(u)):
        y[t] = a[0] * y[t - 1] + a[1] * y[t - 2] + b * u[t - 1] + extra(u, t)
    return y


def squared(gain: float):
    """The ``extra`` of :func:`second_order` for ``gain u(t-1)^2``."""
    return lambda u, t: gain * u[t - 1] ** 2


def through_sine(u: np.ndarray) -> np.ndarray:
    """``y(t) = 0.8 y(t-1) + sin(2 u(t-1))``, noise-free: no low-degree polynomial of u."""
    y = np.zeros(len(u))
    for t in range(1, len(u)):
        y[t] = 0.8 * y[t - 1] + np.sin(2.0 * u[t - 1])
    return y
