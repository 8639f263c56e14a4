"""Two coupled joints, each with a Coulomb-like sign term on its own last step (plain Python).

The record is made by the equations of :data:`TRUE`, so a coupled simulation
can be checked against the system itself and an identification against its
terms. Written for the tests (no project code).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SIGN", "TRUE", "two_joint_record"]

SIGN = ("sign(q1(t-1)-q1(t-2))", "sign(q2(t-1)-q2(t-2))")
TRUE = {"q1": {"q1(t-1)": 1.5, "q1(t-2)": -0.6, "q2(t-1)": 0.05, "t1(t-1)": 0.1, SIGN[0]: -0.02},
        "q2": {"q2(t-1)": 1.4, "q2(t-2)": -0.55, "q1(t-1)": 0.04, "t2(t-1)": 0.1,
               SIGN[1]: -0.015}}


def two_joint_record(n: int, seed: int, noise: float = 5e-4) -> tuple[np.ndarray, np.ndarray]:
    """Torques ``t1, t2`` (n, 2), held 10 samples, and the positions ``q1, q2`` (n, 2)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1, 1, (n // 10 + 1, 2)), 10, axis=0)[:n]
    Y = np.zeros((n, 2))
    for t in range(2, n):
        s1 = np.sign(Y[t - 1, 0] - Y[t - 2, 0])
        s2 = np.sign(Y[t - 1, 1] - Y[t - 2, 1])
        Y[t, 0] = 1.5 * Y[t - 1, 0] - 0.6 * Y[t - 2, 0] + 0.05 * Y[t - 1, 1] + 0.1 * u[t - 1, 0] \
            - 0.02 * s1
        Y[t, 1] = 1.4 * Y[t - 1, 1] - 0.55 * Y[t - 2, 1] + 0.04 * Y[t - 1, 0] \
            + 0.1 * u[t - 1, 1] - 0.015 * s2
    return u, Y + noise * rng.standard_normal(Y.shape)
