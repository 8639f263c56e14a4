"""A two-link planar arm simulated from its rigid-body equations (two torques, two angles).

    M(q) q'' + C(q, q') q' + K q + D q' = tau

with the standard two-link inertia matrix (point masses at the link centres
plus link inertias), the Coriolis/centrifugal terms, and joint springs and
dampers (position-controlled or elastic joints keep the arm near its rest
pose, so records stay bounded). Horizontal plane: no gravity. Integrated with
classical Runge-Kutta (4 substeps per sample), sampled at ``dt``; the outputs
are the joint angles q1, q2 with measurement noise. The coupling is physical:
the off-diagonal inertia m2 l1 lc2 cos(q2) moves joint 1 when joint 2 is
driven and back, so each angle's model needs the other joint's lags or torque.
"""

from __future__ import annotations

import numpy as np

__all__ = ["record"]

M1 = M2 = 1.0
L1 = 1.0
LC1 = LC2 = 0.5
I1 = I2 = 1.0 / 12.0
K = np.array([40.0, 30.0])   # joint stiffness, N m / rad
D = np.array([4.0, 3.0])     # joint damping, N m s / rad


def _accel(q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
    c2, s2 = np.cos(q[1]), np.sin(q[1])
    a = I1 + I2 + M1 * LC1 ** 2 + M2 * (L1 ** 2 + LC2 ** 2 + 2 * L1 * LC2 * c2)
    b = I2 + M2 * (LC2 ** 2 + L1 * LC2 * c2)
    d = I2 + M2 * LC2 ** 2
    h = M2 * L1 * LC2 * s2
    coriolis = np.array([-h * qd[1] * (2 * qd[0] + qd[1]), h * qd[0] ** 2])
    rhs = tau - coriolis - K * q - D * qd
    det = a * d - b * b
    return np.array([d * rhs[0] - b * rhs[1], -b * rhs[0] + a * rhs[1]]) / det


def _multisine(n: int, dt: float, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """Random-phase multisine over 0.1-3 Hz (below the arm's resonances and above)."""
    t = np.arange(n) * dt
    freqs = np.linspace(0.1, 3.0, 30)
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    x = np.sum(np.sin(2 * np.pi * freqs[:, None] * t + phases[:, None]), axis=0)
    return amplitude * x / np.std(x)


def record(n: int = 4000, seed: int = 0, dt: float = 0.02, noise: float = 2e-4,
           amplitude: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """One record: torques ``tau`` (n, 2) and measured angles ``q`` (n, 2).

    Torques are held over each sample (zero-order hold); ``noise`` is the
    angle measurement noise's standard deviation (rad).
    """
    rng = np.random.default_rng(seed)
    tau = np.column_stack([_multisine(n, dt, rng, amplitude),
                           _multisine(n, dt, rng, 0.75 * amplitude)])
    q, qd = np.zeros(2), np.zeros(2)
    out = np.zeros((n, 2))
    h = dt / 4
    for k in range(n):
        out[k] = q
        for _ in range(4):
            f = tau[k]
            k1q, k1v = qd, _accel(q, qd, f)
            k2q, k2v = qd + h / 2 * k1v, _accel(q + h / 2 * k1q, qd + h / 2 * k1v, f)
            k3q, k3v = qd + h / 2 * k2v, _accel(q + h / 2 * k2q, qd + h / 2 * k2v, f)
            k4q, k4v = qd + h * k3v, _accel(q + h * k3q, qd + h * k3v, f)
            q = q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
            qd = qd + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return tau, out + noise * rng.standard_normal(out.shape)
