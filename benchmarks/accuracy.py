"""Models on data they were not fitted on, against a linear ARX (make bench-accuracy).

For each record: estimate on the first half (a simulator: on its first
record), simulate the second half (its second record) in free run, and print
the second half's free-run RMSE and fit for

* the linear ARX model a user gets in one line (least squares, orders 1-10
  with a constant, the order chosen on the first half's own free run:
  :mod:`spm_sysid.core.validate.arx`);
* the default identification with the simulation focus (``--focus simulation
  --constant --criterion bic --seed 1``, the paper's space);
* the same with ``--orders auto`` (the lags and degree proposed from the first
  half, as ``propose-lags`` does);
* ``--focus simulation --orders auto`` as a user types it (AIC, no constant).

Then Silverbox and Wiener-Hammerstein at their real size (``../shared/data``):
identified on the estimation part by the command as typed, their test part
simulated in free run (the first 50 test samples initialise it, the benchmarks'
convention), beside the linear ARX and the published figures.

The joint is also identified at a fifth of its rate (``--decimate 5``), with
and without the friction preset, and the Coulomb force read from the friction
term on five records, at both rates; then the command as typed with and
without the friction preset on five record pairs, and how many are 3x better
with it (:func:`friction_ratios`).

Each record also gets the friction and the saturation presets
(``--regressors friction``, ``--regressors saturation``) beside the default
polynomial space, the lines under it.

Records: the robot arm, the dryer and the heat exchanger (``../shared/data``;
skipped with a line when missing), the two-tank simulator, the simulated joint
with Coulomb friction (``test/helpers/joint.py``: 20 s to identify, another
20 s to simulate; position out, so a free run drifts), the speed loop with
Coulomb friction (``test/helpers/velocity_loop.py``, 20 s each at 1 kHz: its
friction follows the output's own sign), the velocity loop whose
amplifier clips (``benchmarks/actuator.py``: 4 s at 1 kHz each), and the two-link
arm with two outputs (coupled free run, against a linear MIMO ARX fitted the
same way; both focuses, the given space and ``--orders auto``; the simulation
focus with the friction preset, every joint's bases in every output's space). Under each
NARX line: the linear/nonlinear call (the best nonlinear finalist's held-out
error against the best linear one's, and the paired test's p-value) and the
chosen model's held-out error with its standard error over the blocks.

Then the reliability of that call (``--calls`` seeds): how often a linear
system with noise gets a nonlinear model (it should not) and how often a
system with a clear nonlinear term gets one (it should), and one with a faint
nonlinear term in more noise (the power of the call), with 3 and 10
held-out blocks, and 3 blocks laid 3 times (the default). Figures, not assertions.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["main"]

#: Samples at the start of the held-out half left out of every error: the largest
#: ARX order tried (every model starts from measured samples there).
START = 10


def _shared(name: str) -> Path | None:
    from spm_sysid.core.io.datasets import find_robot_arm

    try:
        here = find_robot_arm().parent
    except ValueError:
        here = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    path = here / name
    return path if path.is_file() else None


def _records():
    """(name, (u1, y1), (u2, y2)) of every record that is here."""
    from spm_sysid.core.io.data import load_io

    from . import tanks

    for name, file in (("robot arm", "robot_arm.dat"), ("dryer", "dryer.dat"),
                       ("heat exchanger", "exchanger.dat")):
        path = _shared(file)
        if path is None:
            print(f"{name}: {file} not found beside the robot-arm data; skipped")
            continue
        u, y = load_io(path)
        h = len(y) // 2
        yield name, (u[:h], y[:h]), (u[h:], y[h:])
    yield "two tanks (simulator)", tanks.record(1), tanks.record(2)
    from .scale import _joint

    yield "joint with Coulomb friction (simulator)", _joint(20.0, 1), _joint(20.0, 2)
    from .scale import test_helper

    speed = test_helper("velocity_loop").velocity_record
    yield "speed loop with Coulomb friction (simulator)", speed(20.0, seed=1), speed(20.0, seed=2)
    from . import actuator

    yield "velocity loop, saturating amplifier (simulator)", actuator.record(4000, 0), \
        actuator.record(4000, 1)


def _narx(u1, y1, settings: dict):
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.record import Record

    names = {}
    if np.ndim(y1) == 2:  # the two-link arm's names; more joints numbered on
        names = {"input_names": tuple(f"tau{i + 1}" for i in range(np.shape(u1)[1])),
                 "output_names": tuple(f"q{i + 1}" for i in range(np.shape(y1)[1]))}
    record = Record.from_samples(u1, y1, source="first half", **names)
    t0 = time.perf_counter()
    result = run_job(record, JobSettings.from_values(settings))
    return result.model, time.perf_counter() - t0


def _narx_run(model, u2, y2) -> np.ndarray:
    """The model's free run of the held-out record, aligned with it (NaN before max_lag)."""
    if np.ndim(y2) == 2:  # coupled
        sim, _ = model.simulate(u2, y2)
        out = np.full(np.shape(y2), np.nan)
        out[model.max_lag:] = sim
        return out
    yhat, _ = model.run(u2, y2)
    out = np.full(len(y2), np.nan)
    out[model.term_space.max_lag:] = yhat
    return out


def _line(label: str, y2, sim, terms: str, seconds: float) -> str:
    from spm_sysid.core.validate.arx import fit_percent, rmse

    r, f = rmse(y2, sim, START), fit_percent(y2, sim, START)
    rs = ", ".join("diverged" if not np.isfinite(v) else f"{v:.5g}" for v in r)
    fs = ", ".join("-" if not np.isfinite(v) else f"{v:.1f}" for v in f)
    return f"  {label:<40} RMSE {rs:<20} fit % {fs:<12} {terms:<12} {seconds:6.1f} s"


def _call(model) -> str:
    """The linear/nonlinear call and the held-out error of a model's document."""
    sel = model.metadata.get("selection") or {}
    call = sel.get("linear_or_nonlinear") or {}
    coupled = model.metadata.get("coupled_selection")
    if coupled:
        call = coupled
        held, se = coupled.get("held_out_error"), coupled.get("held_out_stderr")
        what = f"{coupled.get('chosen')} ({coupled.get('fitted')})"
    else:
        held, se = sel.get("held_out_mse"), sel.get("held_out_stderr")
        what = f"{call.get('choice', sel.get('method'))}"
    text = f"    chose {what}"
    if call.get("p_value") is not None:
        text += (f"; best nonlinear {call['ratio']:.2f}x the best linear's held-out error, "
                 f"p = {call['p_value']:.3g}")
    if held is not None and se is not None:
        blocks = sel.get("folds", call.get("folds"))
        text += f"; held-out {held:.3g} +- {se:.2g} ({se / held:.0%}) over {blocks} blocks"
    if call.get("fallback"):
        text += f"; {call['fallback']}"
    if coupled and coupled.get("removed_by_guard"):
        text += f"; removed by the guard: {len(coupled['removed_by_guard'])} finalist(s)"
    loop = model.metadata.get("open_loop") if hasattr(model, "term_space") else None
    if loop and not loop.get("free_run_applies", True):
        text += f"; {loop['kind']}: judged on the {loop.get('horizon')}-step prediction"
    return text


def _systems(kind: str, seed: int, n: int = 800):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    x = np.zeros(n)
    if kind == "linear":  # ARX(2), equation noise
        e = 0.3 * rng.standard_normal(n)
        for t in range(2, n):
            x[t] = 1.2 * x[t - 1] - 0.5 * x[t - 2] + 0.7 * u[t - 1] + 0.3 * u[t - 2] + e[t]
        return u, x
    gain = 0.4 if kind == "nonlinear" else 0.1  # a clear nonlinear term, or a faint one
    for t in range(2, n):
        x[t] = (0.6 * x[t - 1] + 0.5 * u[t - 1] + gain * u[t - 1] ** 2
                - gain / 2 * x[t - 1] * u[t - 1])
    return u, x + (0.05 if kind == "nonlinear" else 0.1) * rng.standard_normal(n)


def calls(seeds: int) -> None:
    """How reliable the linear/nonlinear call is, by the number of held-out blocks."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.identify import identify_problem
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.options import SearchOptions

    space = TermSpace(ny=2, nu=2, degree=2, constant=True)
    print(f"the linear/nonlinear call over {seeds} seeds (800 samples, (2, 2, 2) with a "
          "constant, BIC, simulation focus)")
    for k, repeats in ((3, 1), (10, 1), (3, 3)):
        counts = {}
        for kind in ("linear", "nonlinear", "faint"):
            hits = 0
            for seed in range(seeds):
                u, y = _systems(kind, seed)
                model = identify_problem(Problem.from_signals(u, y, space), SearchOptions(
                    criterion="bic", seed=0, focus="simulation", simulation_folds=k,
                    simulation_repeats=repeats)).model
                hits += model.metadata["selection"]["linear_or_nonlinear"]["choice"] \
                    == "nonlinear"
            counts[kind] = hits
        scheme = f"{k} blocks" + (f" laid {repeats} times" if repeats > 1 else "")
        print(f"  {scheme:<21}: a nonlinear model for the linear system {counts['linear']} of "
              f"{seeds} (should be few), for the clear nonlinear one {counts['nonlinear']} "
              f"(should be all), for the faint one {counts['faint']}")
        sys.stdout.flush()


def record_rows(name: str, first, second, base: dict) -> None:
    """One record's lines, estimated on ``first`` and scored on ``second``.

    The linear ARX, the default space and its presets, the orders chosen from the
    data, and the command as typed.
    """
    from spm_sysid.core.validate.arx import choose_arx

    (u1, y1), (u2, y2) = first, second
    print(name)
    t0 = time.perf_counter()
    arx = choose_arx(u1, y1)
    print(_line(f"linear ARX (order {arx.order}, first half)", y2, arx.simulate(u2, y2),
                f"{arx.theta.shape[0]} params", time.perf_counter() - t0))
    model, seconds = _narx(u1, y1, base)
    print(_line("default, --focus simulation", y2, _narx_run(model, u2, y2),
                f"{len(model.terms)} terms", seconds))
    print(_call(model))
    model, seconds = _narx(u1, y1, {**base, "regressors": "friction"})
    print(_line("default + --regressors friction", y2, _narx_run(model, u2, y2),
                f"{len(model.terms)} terms", seconds))
    print(_call(model) + _regressor_terms(model))
    model, seconds = _narx(u1, y1, {**base, "regressors": "saturation"})
    print(_line("default + --regressors saturation", y2, _narx_run(model, u2, y2),
                f"{len(model.terms)} terms", seconds))
    print(_call(model) + _regressor_terms(model))
    model, seconds = _narx(u1, y1, {**base, "orders": "auto"})
    o = model.metadata["orders"]
    print(_line(f"--orders auto (chose {o['ny']}, {o['nu']}, {o['degree']})", y2,
                _narx_run(model, u2, y2), f"{len(model.terms)} terms", seconds))
    print(_call(model))
    model, seconds = _narx(u1, y1, TYPED)
    o = model.metadata["orders"]
    print(_line(f"as typed, AIC (chose {o['ny']}, {o['nu']}, {o['degree']})", y2,
                _narx_run(model, u2, y2), f"{len(model.terms)} terms", seconds))
    print(_call(model))
    sys.stdout.flush()


def run(args) -> None:
    from spm_sysid.core.validate.arx import choose_arx

    from . import two_link

    base = {"focus": "simulation", "constant": True, "criterion": "bic", "seed": 1}
    print("second-half free-run RMSE (each record's units) and fit, estimated on the first "
          f"half; errors from sample {START} of the held-out part")
    for name, first, second in _records():
        record_rows(name, first, second, base)
    joint_rates()
    benchmarks()
    tau1, q1 = two_link.record(args.samples, seed=0)
    tau2, q2 = two_link.record(args.samples, seed=1)
    print(f"two-link arm, two outputs (record 1 -> record 2, {args.samples} samples, coupled "
          "free run; values per output q1, q2)")
    t0 = time.perf_counter()
    arx = choose_arx(tau1, q1)
    print(_line(f"linear MIMO ARX (order {arx.order})", q2, arx.simulate(tau2, q2),
                f"{arx.theta.size} params", time.perf_counter() - t0))
    for focus in ("prediction", "simulation"):
        for orders in ("given", "auto"):
            settings = {**base, "focus": focus, "ny": 2, "nu": 2, "orders": orders}
            model, seconds = _narx(tau1, q1, settings)
            terms = "+".join(str(len(m.terms)) for m in model.models) + " terms"
            o = model.metadata.get("orders")
            label = (f"--focus {focus} (2, 2, 2)" if o is None else
                     f"--focus {focus} --orders auto ({o['ny']}, {o['nu']}, {o['degree']})")
            print(_line(label, q2, _narx_run(model, tau2, q2), terms, seconds))
            print(_call(model))
            sys.stdout.flush()
    model, seconds = _narx(tau1, q1, {**base, "ny": 2, "nu": 2, "regressors": "friction"})
    terms = "+".join(str(len(m.terms)) for m in model.models) + " terms"
    print(_line("--focus simulation (2, 2, 2) + --regressors friction", q2,
                _narx_run(model, tau2, q2), terms, seconds))
    print(_call(model) + "".join(f" [{m.term_space.output}]" + _regressor_terms(m)
                                 for m in model.models))
    if args.calls:
        calls(args.calls)


#: The joint's decimation in :func:`joint_rates` (1 kHz to 200 Hz).
DECIMATE = 5


def joint_rates(seeds: int = 5) -> None:
    """The simulated joint at 1/``DECIMATE`` of its rate, and the Coulomb force read from it.

    The held-out record is decimated as the first was, so its RMSE is over the
    decimated samples; the default space without regressors, with the friction
    preset, and with the sign of the velocity at t-1 (``VELOCITY_SIGN``). Then
    the force (the sign term over the input terms' sum, as docs/cli.md reads it)
    of ``--ny 2 --nu 2 --degree 1 --regressors friction --criterion bic`` on 20 s
    records of several seeds, at both rates, at the record's rate with the
    coefficients fitted to the free run (``--focus simulation --selection
    criterion``: the noise on the lagged outputs no longer biases them), and at
    the slower rate with the sign of the velocity at t-1 instead (the preset's
    sign is the previous block's motion's).
    """
    from spm_sysid.core.record import Record

    from .scale import _joint

    (u1, y1), (u2, y2) = _joint(20.0, 1), _joint(20.0, 2)
    held = Record.from_samples(u2, y2, source="second record").decimated(DECIMATE)
    print(f"joint with Coulomb friction at 1/{DECIMATE} of its rate (--decimate {DECIMATE}; "
          "the second record decimated alike)")
    base = {"focus": "simulation", "constant": True, "criterion": "bic", "seed": 1,
            "decimate": DECIMATE}
    for label, regressors, sign in (("default", "", SIGN),
                                    ("default + friction", "friction", SIGN),
                                    ("default + velocity sign", VELOCITY_SIGN, VELOCITY_SIGN)):
        model, seconds = _narx(u1, y1, {**base, "regressors": regressors})
        print(_line(f"{label}, --decimate {DECIMATE}", held.y,
                    _narx_run(model, held.u, held.y), f"{len(model.terms)} terms", seconds))
        force = _coulomb(model, sign)
        print(_call(model) + _regressor_terms(model)
              + (f"; Coulomb force {force:.3f} N m (true 0.3)" if force else ""))
    settings = {"ny": 2, "nu": 2, "degree": 1, "regressors": "friction", "criterion": "bic",
                "seed": 1}
    simulation = {"focus": "simulation", "selection": "criterion"}
    for label, extra, sign in (
            ("--decimate 1", {}, SIGN),
            ("--decimate 1 --focus simulation --selection criterion", simulation, SIGN),
            (f"--decimate {DECIMATE}", {"decimate": DECIMATE}, SIGN),
            (f"--decimate {DECIMATE}", {"decimate": DECIMATE, "regressors": VELOCITY_SIGN},
             VELOCITY_SIGN)):
        forces = [_coulomb(_narx(*_joint(20.0, s), {**settings, **extra})[0], sign)
                  for s in range(seeds)]
        what = "friction" if sign == SIGN else f'"{sign}"'
        within = sum(f is not None and abs(f - 0.3) <= 0.03 for f in forces)
        print(f"  Coulomb force, {label}, --regressors {what}, seeds 0-{seeds - 1} (N m, "
              "true 0.3): " + ", ".join("none" if f is None else f"{f:.3f}" for f in forces)
              + f"; within 10 %: {within} of {seeds}")
    sys.stdout.flush()
    friction_ratios(seeds)


#: Other joint recordings every pair's models are scored on too (seeds; the mean RMSE):
#: an integrating output's free run over one recording is one drift.
OTHER_RECORDINGS = (100, 101, 102)


def friction_ratios(pairs: int = 5) -> None:
    """Issue 42's 3x: the command as typed with ``--regressors friction``, on record pairs.

    For each pair of 20 s joint records (seeds 1 -> 2, 3 -> 4, ...): the best
    free run without friction terms (the command as typed at 1 kHz, and at
    ``--decimate 5``) over the one with the friction preset (1 kHz: as typed, and
    in the joint's own small space fitted to the free run, :data:`FRICTION_COMMANDS`),
    all scored on the second record's samples at the slower rate's block starts
    from sample 50 (the same samples for every model); and the same ratio of
    the mean errors over :data:`OTHER_RECORDINGS`.
    """
    from .scale import _joint

    print(f"joint, the command as typed (--focus simulation --orders auto, AIC) with and "
          f"without --regressors friction, {pairs} record pairs (free-run RMSE, rad; "
          f"'others': the mean over recordings of seeds {OTHER_RECORDINGS})")
    others = [_joint(20.0, k) for k in OTHER_RECORDINGS]
    met, met_others = [0, 0], [0, 0]
    for seed in range(1, 2 * pairs, 2):
        first, held = _joint(20.0, seed), [_joint(20.0, seed + 1), *others]
        plain, _ = _pair_score(first, held, {})
        slower, _ = _pair_score(first, held, {"decimate": DECIMATE})
        best = min(plain[0], slower[0])
        best_others = min(float(np.mean(plain[1:])), float(np.mean(slower[1:])))
        print(f"  records {seed} -> {seed + 1}: without {plain[0]:.4g} (1 kHz), {slower[0]:.4g} "
              f"(--decimate {DECIMATE}); on the others {np.mean(plain[1:]):.4g}, "
              f"{np.mean(slower[1:]):.4g}")
        for k, (label, settings) in enumerate(FRICTION_COMMANDS):
            scores, terms = _pair_score(first, held, settings)
            ratio, ratio_others = best / scores[0], best_others / float(np.mean(scores[1:]))
            met[k] += ratio >= 3.0
            met_others[k] += ratio_others >= 3.0
            print(f"    with friction, {label}: {scores[0]:.4g}{terms}; ratio {ratio:.2f}; on "
                  f"the others {np.mean(scores[1:]):.4g}: ratio {ratio_others:.2f}")
        sys.stdout.flush()
    for k, (label, _) in enumerate(FRICTION_COMMANDS):
        print(f"  at least 3x better with the friction terms, {label}: {met[k]} of {pairs} "
              f"pairs on the second record, {met_others[k]} of {pairs} on the others")


#: The commands with friction terms :func:`friction_ratios` scores (over :data:`TYPED`):
#: as typed, and the joint's own small space fitted to the free run (docs/cli.md).
FRICTION_COMMANDS = (
    ("as typed", {"regressors": "friction"}),
    ("--ny 2 --nu 2 --degree 1 --criterion bic --selection criterion",
     {"regressors": "friction", "orders": "given", "ny": 2, "nu": 2, "degree": 1,
      "criterion": "bic", "selection": "criterion"}),
)


def _pair_score(first, held: list, settings: dict) -> tuple[list[float], str]:
    """Free-run RMSE on each ``held`` record of the command as typed on ``first``; its regressors.

    Scored at the block starts of ``--decimate 5`` from sample 50, whatever the model's
    rate; a run that fails scores inf.
    """
    from spm_sysid.core.record import Record

    u1, y1 = first
    try:
        model, _ = _narx(u1, y1, {**TYPED, **settings})
    except Exception as exc:  # a failed run counts as no model
        return [float("inf")] * len(held), f" (failed: {str(exc)[:60]}...)"
    out = []
    for u2, y2 in held:
        at = np.arange(0, len(y2), DECIMATE)
        if settings.get("decimate"):
            slow = Record.from_samples(u2, y2, source="held-out record").decimated(DECIMATE)
            sim = _narx_run(model, slow.u, slow.y)
        else:
            sim = _narx_run(model, u2, y2)[at]
        e = (y2[at] - sim)[at >= 50]
        out.append(float(np.sqrt(np.nanmean(e * e))))
    return out, _regressor_terms(model)


#: The friction preset's sign term, and the sign of the velocity at t-1 (second order).
SIGN = "sign(y(t-1)-y(t-2))"
VELOCITY_SIGN = "sign(3*y(t-1)-4*y(t-2)+y(t-3))"


def _coulomb(model, sign: str = SIGN) -> float | None:
    """The Coulomb force a joint model's ``sign`` term says (None without the term)."""
    th = dict(zip(model.terms, model.coefficients))
    if sign not in th:
        return None
    return -th[sign] / sum(v for k, v in th.items() if k.startswith("u("))


#: ``spm-sysid identify --focus simulation --orders auto``, as a user types it (AIC, no
#: constant), with a seed so that the figures repeat.
TYPED = {"focus": "simulation", "orders": "auto", "seed": 1}

#: Published free-run RMSE on the test parts (mV; Champneys et al. 2024, arXiv
#: 2405.10779, first 50 test samples initialise): linear, polynomial NARX, best.
PUBLISHED = {"Silverbox": (6.96, 0.64, "0.26-0.30"), "Wiener-Hammerstein": (43.4, 27.3, "0.24")}

#: Test samples that may initialise the simulation (the benchmarks' convention).
SKIP = 50


def benchmarks() -> None:
    """Silverbox and Wiener-Hammerstein: estimation part, then the test part's free run."""
    from spm_sysid.core.io.data import load_io
    from spm_sysid.core.validate.arx import choose_arx, rmse

    for name, stem in (("Silverbox", "silverbox"), ("Wiener-Hammerstein", "wh")):
        est, val = _shared(f"{stem}_est.dat"), _shared(f"{stem}_val.dat")
        if est is None or val is None:
            print(f"{name}: {stem}_est.dat / {stem}_val.dat not found; skipped")
            continue
        u1, y1 = load_io(est)
        u2, y2 = load_io(val)
        lin, narx, best = PUBLISHED[name]
        print(f"{name} ({len(y1)} samples to identify, {len(y2)} to test; test free-run RMSE "
              f"in mV from test sample {SKIP}; published: linear {lin}, polynomial NARX "
              f"{narx}, best {best})")
        t0 = time.perf_counter()
        arx = choose_arx(u1, y1)
        r = 1e3 * rmse(y2, arx.simulate(u2, y2), SKIP)[0]
        label = f"linear ARX (order {arx.order})"
        print(f"  {label:<40} RMSE {r:8.3f} mV"
              f"{'':22}{time.perf_counter() - t0:6.1f} s")
        model, seconds = _narx(u1, y1, TYPED)
        o = model.metadata["orders"]
        r = 1e3 * rmse(y2, _narx_run(model, u2, y2), SKIP)[0]
        verdict = "at most" if r <= narx else "ABOVE"
        label = f"as typed (chose {o['ny']}, {o['nu']}, {o['degree']})"
        print(f"  {label:<40} RMSE "
              f"{r:8.3f} mV  {len(model.terms):3d} terms   {seconds:6.1f} s  ({verdict} the "
              f"published polynomial NARX's {narx} mV)")
        print(_call(model))
        model, seconds = _narx(u1, y1, {**TYPED, "regressors": "friction"})
        r = 1e3 * rmse(y2, _narx_run(model, u2, y2), SKIP)[0]
        print(f"  {'as typed + --regressors friction':<40} RMSE {r:8.3f} mV  "
              f"{len(model.terms):3d} terms   {seconds:6.1f} s")
        print(_call(model) + _regressor_terms(model))
        sys.stdout.flush()


def _regressor_terms(model) -> str:
    """The selected terms that hold a regressor (a preset's), in a few words."""
    names = [t for t in model.terms if any(r in t for r in model.term_space.regressors)]
    return f"; regressor terms selected: {', '.join(names) if names else 'none'}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=4000, help="two-link arm record length")
    p.add_argument("--calls", type=int, default=10,
                   help="seeds of the linear/nonlinear call's reliability (0: skip)")
    run(p.parse_args(argv))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
