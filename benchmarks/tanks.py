"""A physical simulator of two cascaded water tanks with overflow (a benchmark's data).

Water is pumped into an upper tank; it drains through a small opening into a
lower tank, which drains freely (Torricelli: outflow proportional to the square
root of the level). When the upper tank is full it overflows; part of the
overflow falls into the lower tank. The lower tank's level is measured: a
sensor with about 40 dB signal-to-noise ratio and a 12-bit converter. The
input is the pump voltage, a random-phase multisine (a different phase draw for
the estimation and the test record, as in the cascaded-tanks benchmark of
Schoukens, Mattsson, Wigren and Noel). Nothing here is fitted to anything; it
only makes records with the features that make identification hard: a
square-root nonlinearity, a hard saturation, slow dynamics and noise.

::

    dx1/dt = -k1 sqrt(x1) + k4 u                       (x1 <= X1_MAX; overflow above)
    dx2/dt =  k2 sqrt(x1) - k3 sqrt(x2) + k5 overflow
    y      =  quantise(x2 + noise)
"""

from __future__ import annotations

import numpy as np

__all__ = ["SAMPLE_TIME", "multisine", "record", "simulate_tanks"]

#: Seconds between samples.
SAMPLE_TIME = 4.0

#: Upper tank capacity (volts of level sensor) above which it overflows.
X1_MAX = 10.0

K1, K2, K3, K4, K5 = 0.055, 0.055, 0.07, 0.034, 0.6

#: Integration steps per sample.
SUBSTEPS = 40


def multisine(n: int, seed: int, harmonics: int = 60, mean: float = 5.0,
              std: float = 1.6) -> np.ndarray:
    """A random-phase multisine of ``n`` samples: equal amplitudes, the first harmonics."""
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    phases = rng.uniform(0, 2 * np.pi, harmonics)
    u = np.sum([np.cos(2 * np.pi * (k + 1) * t / n + phases[k]) for k in range(harmonics)],
               axis=0)
    u = mean + std * u / np.std(u)
    return np.clip(u, 0.0, 10.0)


def simulate_tanks(u: np.ndarray, x0: tuple[float, float] = (4.0, 4.0)) -> np.ndarray:
    """The lower tank's true level at each sample, for the pump voltage ``u`` (RK4)."""
    dt = SAMPLE_TIME / SUBSTEPS
    x1, x2 = x0
    out = np.empty(len(u))

    def rates(x1, x2, v):
        return -K1 * np.sqrt(max(x1, 0.0)) + K4 * v, \
            K2 * np.sqrt(max(x1, 0.0)) - K3 * np.sqrt(max(x2, 0.0))

    for t, v in enumerate(u):
        out[t] = x2
        for _ in range(SUBSTEPS):
            a1, a2 = rates(x1, x2, v)
            b1, b2 = rates(x1 + 0.5 * dt * a1, x2 + 0.5 * dt * a2, v)
            c1, c2 = rates(x1 + 0.5 * dt * b1, x2 + 0.5 * dt * b2, v)
            d1, d2 = rates(x1 + dt * c1, x2 + dt * c2, v)
            x1 += dt * (a1 + 2 * b1 + 2 * c1 + d1) / 6
            x2 += dt * (a2 + 2 * b2 + 2 * c2 + d2) / 6
            if x1 > X1_MAX:  # overflow: part of it falls into the lower tank
                x2 += K5 * (x1 - X1_MAX)
                x1 = X1_MAX
            x1, x2 = max(x1, 0.0), max(x2, 0.0)
    return out


def record(seed: int, n: int = 1024, snr_db: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """One record ``(u, y)``: multisine pump voltage and the measured lower level.

    Noise at ``snr_db`` (power ratio of the level's variation to the noise), then a
    12-bit converter over 0..10 V. The first 200 samples' transient from the
    initial levels is simulated and dropped.
    """
    rng = np.random.default_rng(seed + 10_000)
    warm = 200
    u = multisine(n + warm, seed)
    x2 = simulate_tanks(u)[warm:]
    noise = rng.standard_normal(n) * np.std(x2) * 10 ** (-snr_db / 20)
    step = 10.0 / 4096
    y = np.clip(np.round((x2 + noise) / step) * step, 0.0, 10.0)
    return u[warm:], y
