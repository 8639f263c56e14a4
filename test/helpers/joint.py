"""A simulated robot joint: a mass with viscous and Coulomb friction, PD-controlled at 1 kHz.

The plant is ``J q'' = tau - b q' - Fc sign(q')`` (stiction: the joint stays at
rest while the torque is below ``Fc``), integrated with ten sub-steps per
sample. A PD controller running at the sample rate tracks a multisine
reference (0.1-2 Hz, random phases) from the measured position, with a random
torque dither added (held 20 ms: the excitation closed-loop identification
needs beside the controller's own torque); the record is the applied torque
(input) and the measured position (output, with encoder noise). The position
integrates the torque in open loop (a pole at 1): what closed-loop positioning
drives give identification.

Written for the tests (no project code): the true parameters are known, so an
identified model can be checked against them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Joint", "joint_record"]


@dataclass(frozen=True)
class Joint:
    """Parameters of the joint and its controller (SI units)."""

    inertia: float = 0.05          # J, kg m^2
    viscous: float = 0.1           # b, N m s / rad
    coulomb: float = 0.3           # Fc, N m
    kp: float = 20.0               # N m / rad
    kd: float = 1.0                # N m s / rad
    torque_limit: float = 5.0      # N m
    rate: float = 1000.0           # samples per second
    noise: float = 1e-4            # rad, standard deviation of the position measurement
    amplitude: float = 0.3         # rad, of each reference sine
    dither: float = 0.5            # N m, random torque added to the controller's (held 20 ms)


def joint_record(seconds: float, seed: int = 0, joint: Joint = Joint()
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The torque and the measured position of ``seconds`` of closed-loop tracking.

    Returns
    -------
    tau, q : ndarray, shape (n,)
        The controller's torque at each sample (held until the next) and the
        position measured at that sample.
    """
    rng = np.random.default_rng(seed)
    n = int(round(seconds * joint.rate))
    ts = 1.0 / joint.rate
    t = np.arange(n) * ts
    freqs = np.linspace(0.1, 2.0, 8)
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    ref = joint.amplitude * np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases).sum(1)
    ref /= max(np.max(np.abs(ref)), 1e-12) / (2 * joint.amplitude)
    hold = max(int(round(0.02 * joint.rate)), 1)
    dither = np.repeat(rng.uniform(-joint.dither, joint.dither, n // hold + 1), hold)[:n]
    tau = np.zeros(n)
    q_meas = np.zeros(n)
    q, v, sub = 0.0, 0.0, 10
    h = ts / sub
    previous = 0.0
    for k in range(n):
        q_meas[k] = q + joint.noise * rng.standard_normal()
        rate = (q_meas[k] - previous) / ts if k else 0.0
        previous = q_meas[k]
        tau[k] = np.clip(joint.kp * (ref[k] - q_meas[k]) - joint.kd * rate + dither[k],
                         -joint.torque_limit, joint.torque_limit)
        for _ in range(sub):
            v, q = _step(v, q, tau[k], h, joint)
    return tau, q_meas


def _step(v: float, q: float, tau: float, h: float, joint: Joint) -> tuple[float, float]:
    """One semi-implicit Euler step with Coulomb friction and stiction."""
    if v == 0.0 and abs(tau) <= joint.coulomb:
        return 0.0, q  # stuck
    direction = np.sign(v) if v != 0.0 else np.sign(tau)
    a = (tau - joint.viscous * v - joint.coulomb * direction) / joint.inertia
    v_new = v + h * a
    if v != 0.0 and np.sign(v_new) != np.sign(v):
        v_new = 0.0  # friction stops the joint; it does not push it back
    return v_new, q + h * v_new
