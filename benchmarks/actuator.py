"""A velocity loop whose actuator saturates: the record the ``saturation`` preset is for.

A motor's velocity v is driven by the torque the amplifier delivers, which is
the commanded torque u clipped at the amplifier's limit (the controller asks
for more than the drive gives). Discretised at 1 kHz: a first-order motor with
viscous friction behind a first-order current loop, then velocity-sensor noise.
The command is a random staircase (levels held 20-200 ms, uniform in
±1.5 N m); the limit, 1.0 N m, is not one of the preset's levels (its
percentiles of |u|), as a user's would not be. Nothing here is fitted.

::

    i(t)  = 0.8 i(t-1) + 0.2 sat(u(t-1), LIMIT)         (the delivered torque)
    v(t)  = 0.98 v(t-1) + 0.05 i(t-1)                    (J dv/dt = i - b v)
    y(t)  = v(t) + noise
"""

from __future__ import annotations

import numpy as np

__all__ = ["LIMIT", "record"]

#: The amplifier's limit (N m).
LIMIT = 1.0

#: Velocity-sensor noise (standard deviation, rad/s).
NOISE = 0.01


def record(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(commanded torque, measured velocity): n samples of the loop from rest."""
    rng = np.random.default_rng(seed)
    u = np.empty(n)
    t = 0
    while t < n:
        hold = int(rng.integers(20, 201))
        u[t:t + hold] = rng.uniform(-1.5, 1.5)
        t += hold
    delivered = np.clip(u, -LIMIT, LIMIT)
    i = np.zeros(n)
    v = np.zeros(n)
    for t in range(1, n):
        i[t] = 0.8 * i[t - 1] + 0.2 * delivered[t - 1]
        v[t] = 0.98 * v[t - 1] + 0.05 * i[t - 1]
    return u, v + NOISE * rng.standard_normal(n)
