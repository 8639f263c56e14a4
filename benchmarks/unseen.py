"""Benchmark: the command as typed on kinds of record nobody here fitted.

``python -m benchmarks.unseen`` (``make bench-unseen``) draws each record twice
(seeds 1 and 2), identifies the first as ``spm-sysid identify --focus simulation
--orders auto`` does (seed 1), simulates the second in free run and prints its
RMSE from sample 50, the linear ARX's of
:func:`~spm_sysid.core.validate.arx.choose_arx` fitted on the same record, the
space the scan chose, the seconds, and what the data check said. The kinds are
the ones that found defects: a two-level input, an unused (constant) input, a
PRBS, spikes, an output held at the end of its range, steps held long, a
positioning drive with friction, two outputs of different orders, six inputs
and six coupled outputs (the scan's budget), a dead time beyond the scanned
lags (not found: ``--delay`` given by hand beside it), a short record of a
sensor that reads |speed|, a gain that changes halfway (said: "changed"); and a few
that did not (a hysteresis, a heater far from zero, a tiny record, a pendulum,
a drifting sensor, an offset of 1000). Figures, not assertions
(docs/results.md, "Records nobody here fitted").
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable

import numpy as np

__all__ = ["KINDS", "main"]

Draw = Callable[[int, int], tuple[np.ndarray, np.ndarray]]


def _multisine(n: int, rng, top: float) -> np.ndarray:
    """The tests' multisine (``test/helpers/signals.py``): 20 sines below ``top``."""
    from .scale import test_helper

    return test_helper("signals").multisine(n, rng, top)


def _second_order(u: np.ndarray, extra=lambda u, t: 0.0, a=(1.2, -0.5), b=0.5) -> np.ndarray:
    """The tests' second-order plant (``test/helpers/signals.py``)."""
    from .scale import test_helper

    return test_helper("signals").second_order(u, extra, a, b)


def two_level(n: int, seed: int):
    """A smooth input and a two-level one into a second-order plant, with their product."""
    rng = np.random.default_rng(seed)
    u = np.column_stack([_multisine(n, rng, 0.01), np.sign(_multisine(n, rng, 0.003))])
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = (1.5 * y[t - 1] - 0.56 * y[t - 2] + 0.05 * u[t - 1, 0] + 0.02 * u[t - 1, 1]
                + 0.01 * u[t - 1, 0] * u[t - 1, 1])
    return u, y + 1e-3 * rng.standard_normal(n)


def unused_input(n: int, seed: int):
    """A second input that stays constant (an actuator not driven in this test)."""
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.03)
    y = _second_order(u, lambda u, t: 0.1 * u[t - 1] ** 2)
    return np.column_stack([u, np.full(n, 2.5)]), y + 1e-3 * rng.standard_normal(n)


def prbs(n: int, seed: int, levels=(-1.0, 1.0)):
    """A PRBS (held 5 samples) into a Wiener system: linear, then a square at the output."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.choice(levels, n // 5 + 1), 5)[:n]
    x = _second_order(u, a=(1.6, -0.68), b=0.1)
    return u, x + 0.3 * x ** 2 + 0.01 * rng.standard_normal(n)


def spikes(n: int, seed: int):
    """A second-order NARX system whose output has spikes at 1 % of its samples.

    Only on the record identified (seed 1): the second draw is clean, so its errors
    are the model's.
    """
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.05)
    y = _second_order(u, lambda u, t: 0.2 * u[t - 1] ** 2)
    out = y + 0.01 * rng.standard_normal(n)
    if seed == 1:
        k = rng.choice(n, n // 100, replace=False)
        out[k] += 20 * np.std(y) * rng.choice([-1, 1], len(k))
    return u, out


def clipped(n: int, seed: int):
    """A linear plant behind a sensor clipped to +-2."""
    rng = np.random.default_rng(seed)
    u = 1.5 * _multisine(n, rng, 0.03)
    y = _second_order(u, a=(1.3, -0.45))
    return u, np.clip(y + 1e-3 * rng.standard_normal(n), -2, 2)


def held_steps(n: int, seed: int):
    """Steps held 2000 samples into a plant with a cubic input (100x oversampled)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1, 1, n // 2000 + 1), 2000)[:n]
    y = _second_order(u, lambda u, t: 0.03 * u[t - 1] ** 3, a=(1.5, -0.56), b=0.05)
    return u, y + 1e-3 * rng.standard_normal(n)


def drive(n: int, seed: int):
    """A positioning drive at 1 kHz, the force command in, the position out.

    P position and PI speed loops, Coulomb and viscous friction, a force limit; the
    position quantised to 1 um, the force measured with noise.
    """
    rng = np.random.default_rng(seed)
    ref, k = np.zeros(n), 0
    while k < n:
        s = int(rng.integers(800, 3000))
        ref[k:k + s], k = rng.uniform(0.02, 0.2), k + s
    ref = np.convolve(ref, np.ones(300) / 300, mode="same")
    ref[:300] = ref[300]
    dt, mass, viscous, coulomb = 1e-3, 95.0, 200.0, 20.0
    x, v, integral = ref[0], 0.0, 0.0
    u, y = np.zeros(n), np.zeros(n)
    for t in range(n):
        y[t] = np.round(x * 1e6) / 1e6
        e = 35 * (ref[t] - y[t]) - v
        integral += e * dt
        f = 15000 * e + 150000 * integral
        u[t] = np.clip(f, -300, 300)
        integral -= (f - u[t]) / 300000  # anti-windup
        for _ in range(5):
            a = (u[t] - viscous * v - coulomb * np.tanh(v / 1e-4)) / mass
            v, x = v + a * dt / 5, x + v * dt / 5
    return u + 0.5 * rng.standard_normal(n), y


def two_outputs(n: int, seed: int):
    """Two inputs, two coupled outputs of orders 2 and 1 (``test/helpers/two_orders.py``)."""
    from .scale import test_helper

    rng = np.random.default_rng(seed)
    u = np.column_stack([_multisine(n, rng, 0.03), _multisine(n, rng, 0.03)])
    return u, test_helper("two_orders").coupled_outputs(u, rng)


def six_joints(n: int, seed: int):
    """Six torques, six coupled joints of second order, each with its torque squared."""
    rng = np.random.default_rng(seed)
    u = np.column_stack([_multisine(n, rng, 0.02) for _ in range(6)])
    coupling = 0.05 * (np.ones((6, 6)) - np.eye(6))
    y = np.zeros((n, 6))
    for t in range(2, n):
        y[t] = (1.6 * y[t - 1] - 0.68 * y[t - 2] + coupling @ (y[t - 1] - y[t - 2])
                + 0.05 * u[t - 1] + 0.01 * u[t - 1] ** 2)
    return u, y + 1e-3 * rng.standard_normal((n, 6))


def dead_time(n: int, seed: int, delay: int = 30):
    """A second-order plant whose input acts after 30 samples (a transport delay)."""
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.05)
    y = np.zeros(n)
    for t in range(delay + 1, n):
        y[t] = 1.3 * y[t - 1] - 0.4 * y[t - 2] + 0.1 * u[t - delay] + 0.05 * u[t - delay] ** 2
    return u, y + 0.01 * rng.standard_normal(n)


def speed_sensor(n: int, seed: int):
    """A third-order drive behind a sensor that reads |speed| (``test/helpers/speed_sensor.py``)."""
    from .scale import test_helper

    return test_helper("speed_sensor").speed_sensor(n, seed)


def hysteresis(n: int, seed: int):
    """A tank behind a valve with play (a hysteresis) and a square."""
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.01)
    play, level, y = 0.0, 0.0, np.zeros(n)
    for t in range(n):
        play = min(max(play, u[t] - 0.3), u[t] + 0.3)
        level = 0.995 * level + 0.005 * (play + 0.3 * play ** 2)
        y[t] = level
    return u, y + 0.002 * rng.standard_normal(n)


def heater(n: int, seed: int):
    """A heater around 300 K driven 0-1000 W, with a quadratic loss."""
    rng = np.random.default_rng(seed)
    u = np.clip(500 + 400 * np.sign(_multisine(n, rng, 0.002)) + 50 * rng.standard_normal(n),
                0, 1000)
    x, y = 300.0, np.zeros(n)
    for t in range(n):
        x += 0.002 * (0.02 * u[t] - 0.05 * (x - 293) - 1e-4 * (x - 293) ** 2)
        y[t] = x
    return u, y + 0.01 * rng.standard_normal(n)


def pendulum(n: int, seed: int):
    """A pendulum swinging to large angles, torque in, angle out (100 Hz)."""
    rng = np.random.default_rng(seed)
    tau = 2.5 * _multisine(n, rng, 0.02)
    th = w = 0.0
    y = np.zeros(n)
    for t in range(n):
        for _ in range(10):
            w += (tau[t] - 9.81 * np.sin(th) - 0.5 * w) * 0.001
            th += w * 0.001
        y[t] = th
    return tau, y + 1e-3 * rng.standard_normal(n)


def drifting_sensor(n: int, seed: int):
    """A plant with a cubic input whose sensor drifts (a random walk) around 3."""
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.05)
    y = _second_order(u, lambda u, t: 0.1 * u[t - 1] ** 3, a=(1.3, -0.45), b=0.4)
    return u, 3 + y + np.cumsum(0.002 * rng.standard_normal(n)) + 0.01 * rng.standard_normal(n)


def gain_change(n: int, seed: int):
    """The input gain of a second-order plant goes from 0.5 to 0.6 halfway (a payload)."""
    from .scale import test_helper

    return test_helper("changing_gain").changing_gain(n, seed)


def far_from_zero(n: int, seed: int):
    """An output of 1000 +- 0.01."""
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.05)
    y = _second_order(u, lambda u, t: 0.2 * u[t - 1] ** 2)
    return u, 1000 + 0.01 * y + 1e-5 * rng.standard_normal(n)


def sine_input(n: int, seed: int):
    """y(t) = 0.8 y(t-1) + sin(2 u(t-1)), u of std 2: no low-degree polynomial describes it."""
    from .scale import test_helper

    rng = np.random.default_rng(seed)
    u = 2.0 * _multisine(n, rng, 0.05)
    return u, test_helper("signals").through_sine(u) + 0.01 * rng.standard_normal(n)


def held_output(n: int, seed: int):
    """A second-order plant's output read every 10th sample and held (a slow sensor's)."""
    rng = np.random.default_rng(seed)
    u = _multisine(n, rng, 0.02)
    y = _second_order(u, lambda u, t: 0.2 * u[t - 1] ** 2) + 0.002 * rng.standard_normal(n)
    return u, y[(np.arange(n) // 10) * 10]


def within_sample(n: int, seed: int):
    """y(t) = x(t) + 0.2 x(t)^2, x(t) = 0.5 x(t-1) + 0.5 u(t): the input acts within the sample.

    A white input (a multisine's next value follows from its last ones, and then
    the lags from 1 on stand in for u(t): 0.015 against 0.010, not said).
    """
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    x = np.zeros(n)
    for t in range(n):
        x[t] = 0.5 * x[t - 1] + 0.5 * u[t]
    return u, x + 0.2 * x ** 2 + 0.01 * rng.standard_normal(n)


#: name -> (draw, samples, settings beside the command's)
KINDS: dict[str, tuple[Draw, int, dict]] = {
    "two-level input": (two_level, 20_000, {}),
    "unused (constant) input": (unused_input, 10_000, {}),
    "PRBS -1/1, Wiener": (prbs, 20_000, {}),
    "PRBS 0/1, Wiener": (lambda n, s: prbs(n, s, (0.0, 1.0)), 20_000, {}),
    "spikes at 1 %": (spikes, 20_000, {}),
    "  the same, --spikes gaps": (spikes, 20_000, {"spikes": "gaps"}),
    "sensor clipped at +-2": (clipped, 20_000, {}),
    "steps held 2000 samples": (held_steps, 40_000, {}),
    "positioning drive, 1 kHz": (drive, 100_000, {}),
    "  the same, friction preset": (drive, 100_000, {"regressors": "friction"}),
    "two outputs, orders 2 and 1": (two_outputs, 20_000, {}),
    "hysteresis": (hysteresis, 20_000, {}),
    "heater near 300 K": (heater, 20_000, {}),
    "pendulum": (pendulum, 20_000, {}),
    "drifting sensor": (drifting_sensor, 20_000, {}),
    "output 1000 +- 0.01": (far_from_zero, 20_000, {}),
    "six inputs, six outputs": (six_joints, 10_000, {}),
    "dead time of 30 samples": (dead_time, 5_000, {}),
    "  the same, --delay 28": (dead_time, 5_000, {"delay": 28}),
    "|speed| sensor, 500 samples": (speed_sensor, 500, {}),
    "gain 0.5 then 0.6": (gain_change, 20_000, {}),
    "input through sin(2u)": (sine_input, 20_000, {}),
    "output held 10 samples": (held_output, 20_000, {}),
    "input acts within the sample": (within_sample, 20_000, {}),
    "  the same, --delay 0": (within_sample, 20_000, {"delay": 0}),
}

#: What the data check said, by a phrase of its warning.
SAID = (("holds exactly", "held at an end"), ("spike", "spikes"),
        ("Coulomb friction?", "friction?"), ("faster than they move", "oversampled"),
        ("integrates", "integrates"), ("is constant", "constant input"),
        ("halves fit different", "changed"), ("explains little", "explains little"),
        ("repeats each value", "held output"), ("in the same step", "acts within the sample"))

#: Samples at the start of the second record left out of the errors (the benchmarks').
START = 50


def _rmse(y: np.ndarray, sim: np.ndarray) -> str:
    """Free-run RMSE from sample START, per output ("diverged" where a run left)."""
    from spm_sysid.core.validate.arx import rmse

    return ", ".join("diverged" if not np.isfinite(v) else f"{v:.4g}"
                     for v in rmse(y, sim, START))


def row(name: str, draw: Draw, n: int, settings: dict) -> str:
    """One kind's line: free-run RMSE, the ARX's, the space, the seconds, the warnings."""
    from spm_sysid.core.validate.arx import choose_arx

    from .accuracy import _narx, _narx_run

    (u1, y1), (u2, y2) = draw(n, 1), draw(n, 2)
    model, seconds = _narx(u1, y1, {"focus": "simulation", "orders": "auto", "seed": 1,
                                    **settings})
    ours = _rmse(y2, _narx_run(model, u2, y2))
    try:
        arx = choose_arx(u1, y1)
        linear = f"{_rmse(y2, arx.simulate(u2, y2))} (order {arx.order})"
    except ValueError as exc:
        linear = f"none ({exc})"
    o = model.metadata.get("orders") or {}
    warnings = " ".join(model.metadata.get("warnings") or [])
    said = ", ".join(tag for phrase, tag in SAID if phrase in warnings) or "-"
    return (f"{name:<28} {n:>7} {ours:<22} {linear:<28} ({o.get('ny')}, {o.get('nu')}, "
            f"{o.get('degree')}) {seconds:6.1f} s  {said}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.unseen", description=__doc__)
    p.add_argument("--only", nargs="*", help="kinds to run (a word of their names)")
    p.add_argument("--scale", type=float, default=1.0, help="samples x this (e.g. 0.25)")
    args = p.parse_args(argv)
    print("the command as typed (--focus simulation --orders auto, seed 1) on the first "
          f"draw, free run of the second from sample {START}; linear ARX of choose_arx")
    print(f"{'record':<28} {'samples':>7} {'free-run RMSE':<22} {'linear ARX':<28} "
          "space, seconds, what the data check said")
    started = time.perf_counter()
    for name, (draw, n, settings) in KINDS.items():
        if args.only and not any(w.lower() in name.lower() for w in args.only):
            continue
        print(row(name, draw, max(int(n * args.scale), 200), settings))
        sys.stdout.flush()
    print(f"{time.perf_counter() - started:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
