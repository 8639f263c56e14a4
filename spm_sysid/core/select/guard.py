"""The stability guard: a model must stay in range off the estimation data.

The chosen structure's model -- fitted on all data -- is simulated on every
segment, driven by the record's input itself, shifted by half its length,
reversed in time, and by :data:`~spm_sysid.core.defaults.SURROGATES` inputs with
the same amplitude spectrum and random phases (clipped to the measured range):
inputs like those it was fitted on, in orders the estimation never saw. A model
that leaves the output's range widened by
:data:`~spm_sysid.core.defaults.STRESS_FACTOR` spans fails
(:func:`stress_check`); a nonlinear one may hold with its nonlinear terms shrunk
(:func:`shrink_to_hold`).
"""

from __future__ import annotations

import numpy as np

from ..defaults import SHRINK_FACTORS, SIMULATION_FOLDS, STRESS_FACTOR, SURROGATES
from ..model.simulation import divergence_bounds, run_model

__all__ = ["shrink_to_hold", "stress_check", "stress_inputs", "surrogate_input"]


def stress_check(model, u: np.ndarray, y: np.ndarray, segments,
                 integrating: bool = False) -> str | None:
    """Why the model's simulation is not bounded off the estimation data, or None.

    Its free run on every segment, and driven by each segment's input shifted
    by half its length, reversed in time and with its phases randomised
    (:data:`SURROGATES` draws, :func:`surrogate_input`), from the segment's own
    initial outputs, must stay inside the measured output's range widened by
    :data:`STRESS_FACTOR` spans. An ``integrating`` output (a position driven by
    a torque) is checked on its own input only (driven by another order of the
    input it integrates to elsewhere, as the system itself would), over pieces
    as long as the held-out blocks it was judged on
    (:data:`~spm_sysid.core.defaults.SIMULATION_FOLDS` per segment), within the
    bounds of that judging (:func:`~spm_sysid.core.model.simulation.divergence_bounds`):
    any model's free run of an integrator drifts, and how far is its held-out
    error, already compared.
    """
    y = np.asarray(y, dtype=float)
    lo, hi = float(np.min(y)), float(np.max(y))
    span = max(hi - lo, 1e-300)
    bounds = (lo - STRESS_FACTOR * span, hi + STRESS_FACTOR * span)
    if integrating:  # the bounds of the held-out judging: a drift is an error, not a fault
        bounds = divergence_bounds(y)
    u2 = model.term_space.inputs_2d(u)
    lag = model.term_space.max_lag
    if integrating:
        segments = [(int(c), int(d)) for a, b in segments for c, d in zip(
            np.linspace(a, b, SIMULATION_FOLDS + 1)[:-1].round(),
            np.linspace(a, b, SIMULATION_FOLDS + 1)[1:].round())]
    for a, b in segments:
        if b - a <= lag:
            continue
        seg_y = y[a:b]
        for label, uu in stress_inputs(u2[a:b])[:1 if integrating else None]:
            yy = seg_y.copy()
            yy[lag:] = 0.0  # only the initial conditions are measured
            yhat, at = run_model(model.compiled, model.coefficients, uu, yy, None, bounds)
            if at is not None or not np.all(np.isfinite(yhat)):
                return f"its simulation driven by {label} left the output's range"
    return None


def stress_inputs(u: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The guard's inputs for one segment's input ``u`` (n, m), each with its description.

    The input itself, shifted by half its length, reversed in time, and
    :data:`SURROGATES` random-phase inputs like it (fixed seed: repeatable).
    """
    rng = np.random.default_rng(0)
    out = [("the estimation input", u),
           ("the input shifted by half its length", np.roll(u, len(u) // 2, axis=0)),
           ("the input reversed in time", u[::-1])]
    out += [(f"an input with the estimation input's spectrum and random phases "
             f"(draw {i + 1} of {SURROGATES})", surrogate_input(u, rng))
            for i in range(SURROGATES)]
    return out


def surrogate_input(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An input like ``u`` (n, m): each column's amplitude spectrum, random phases.

    The result is clipped to each column's measured range, so it excites the
    model at the frequencies and amplitudes of the estimation data but in an
    order the estimation never saw (a second multisine phase draw, a second run
    of a random signal).
    """
    out = np.empty_like(u, dtype=float)
    n = len(u)
    for j in range(u.shape[1]):
        col = u[:, j]
        mean = col.mean()
        spectrum = np.fft.rfft(col - mean)
        phases = rng.uniform(0.0, 2.0 * np.pi, len(spectrum))
        phases[0] = 0.0
        if n % 2 == 0:
            phases[-1] = 0.0  # the Nyquist bin stays real
        out[:, j] = np.clip(np.fft.irfft(np.abs(spectrum) * np.exp(1j * phases), n) + mean,
                            col.min(), col.max())
    return out


def shrink_to_hold(model, u, y, segments, linear_sse: float, integrating: bool = False
                   ) -> tuple[float, np.ndarray] | None:
    """The factor and coefficients that make a model whose nonlinear terms diverge hold.

    The nonlinear coefficients are scaled by each of
    :data:`~spm_sysid.core.defaults.SHRINK_FACTORS` in turn (the linear ones kept:
    they carry the dynamics); the first factor whose model passes the guard and
    still simulates the estimation data better than the best linear finalist
    (``linear_sse``) is returned with its coefficients. None when none does. The
    model given is not changed.
    """
    degree = model.term_space.term_degrees[list(model.term_indices)]
    nonlinear = degree > 1
    for factor in SHRINK_FACTORS:
        trial = model.with_coefficients(np.where(nonlinear, model.coefficients * factor,
                                                 model.coefficients))
        if stress_check(trial, u, y, segments, integrating) is not None:
            continue
        e = trial.measured(y, segments) - trial.run(u, y, None, segments)[0]
        if np.all(np.isfinite(e)) and float(e @ e) < linear_sse:
            return factor, trial.coefficients
    return None
