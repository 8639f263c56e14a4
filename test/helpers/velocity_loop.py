"""A simulated velocity loop: a motor's speed with viscous and Coulomb friction, PI at 1 kHz.

The plant is ``J v' = tau - b v - Fc sign(v)`` (stiction: a motor at rest stays
there while the torque is below ``Fc``), integrated with five sub-steps per
sample. A PI controller at the sample rate tracks a multisine speed reference
(0.2-5 Hz, random phases) from the measured speed, a small random torque added;
the record is the applied torque (input, clipped at the amplifier's limit) and
the measured speed (output, with sensor noise). The speed does not integrate the
torque, and its own sign is the friction's: what velocity-controlled joints and
wheels give identification.

Written for the tests (no project code): the true parameters are known.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Motor", "velocity_record"]


@dataclass(frozen=True)
class Motor:
    """Parameters of the motor and its controller (SI units)."""

    inertia: float = 0.01          # J, kg m^2
    viscous: float = 0.02          # b, N m s / rad
    coulomb: float = 0.15          # Fc, N m
    kp: float = 0.5                # N m s / rad
    ki: float = 5.0                # N m / rad
    torque_limit: float = 1.0      # N m
    rate: float = 1000.0           # samples per second
    noise: float = 2e-3            # rad/s, standard deviation of the speed measurement
    peak: float = 3.0              # rad/s, of the reference
    dither: float = 0.05           # N m, standard deviation of the added torque


def velocity_record(seconds: float, seed: int = 0, motor: Motor = Motor()
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The torque and the measured speed of ``seconds`` of closed-loop tracking."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * motor.rate))
    ts = 1.0 / motor.rate
    t = np.arange(n) * ts
    freqs = np.linspace(0.2, 5.0, 10)
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    ref = np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases).sum(1)
    ref *= motor.peak / max(np.max(np.abs(ref)), 1e-12)
    tau, measured = np.zeros(n), np.zeros(n)
    v, integral, sub = 0.0, 0.0, 5
    for k in range(n):
        measured[k] = v + motor.noise * rng.standard_normal()
        error = ref[k] - measured[k]
        integral += error * ts
        tau[k] = np.clip(motor.kp * error + motor.ki * integral
                         + motor.dither * rng.standard_normal(),
                         -motor.torque_limit, motor.torque_limit)
        for _ in range(sub):
            v = _step(v, tau[k], ts / sub, motor)
    return tau, measured


def _step(v: float, tau: float, h: float, motor: Motor) -> float:
    """One explicit Euler step of the speed with Coulomb friction and stiction."""
    if v == 0.0 and abs(tau) <= motor.coulomb:
        return 0.0
    friction = motor.coulomb * np.sign(v if v != 0.0 else tau)
    after = v + h * (tau - motor.viscous * v - friction) / motor.inertia
    if v != 0.0 and np.sign(after) != np.sign(v) and abs(tau) <= motor.coulomb:
        return 0.0  # friction stops the motor; it does not push it back
    return after
