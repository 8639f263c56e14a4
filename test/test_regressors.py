"""Regressors beside the polynomial terms: the grammar, the columns, the runs, the search.

Numbers are checked against independent computations: numpy on the signals for
columns and runs, finite differences for sensitivities, every subset by numpy's
least squares for the certified optimum.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.fit.criteria import get_criterion
from spm_sysid.core.identify import identify
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.presets import expand_presets
from spm_sysid.core.model.regressors import (
    FUNCTIONS,
    MAX_DEPTH,
    RegressorError,
    canonical,
    parse,
)
from spm_sysid.core.model.simulation import free_run_sensitivities
from spm_sysid.core.model.terms import TermSpace

from .conftest import ROOT
from .helpers.duffing import duffing
from .helpers.joint import Joint, joint_record

EVERY_FUNCTION = ["sign(y(t-1)-y(t-2))", "abs(u(t))", "tanh((y(t-1)-y(t-2))/0.05)",
                  "min(y(t-1),0.5*u(t-2))", "max(-y(t-2),u(t-1))", "sat(y(t-1),0.3)",
                  "deadzone(u(t-1),0.2)", "-(y(t-1)+2.5e-3)*u(t-1)/4"]


def _signals(n=600, seed=0):
    """A stable nonlinear system with a dead zone and Coulomb-like friction."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = (1.2 * y[t - 1] - 0.4 * y[t - 2] + 0.5 * u[t - 1]
                - 0.05 * np.sign(y[t - 1] - y[t - 2]) + 0.01 * rng.standard_normal())
    return u, y


def test_every_function_round_trips_through_its_text_and_the_model_document():
    assert {f for text in EVERY_FUNCTION for f in FUNCTIONS if f + "(" in text} == set(FUNCTIONS)
    for text in EVERY_FUNCTION:
        e = parse(text, "y", ("u",))
        assert parse(canonical(e), "y", ("u",)) == e
        assert canonical(parse(canonical(e), "y", ("u",))) == canonical(e)
    u, y = _signals()
    ts = TermSpace(ny=2, nu=2, degree=1, delay=0, regressors=tuple(EVERY_FUNCTION))
    mask = np.ones(ts.n_terms, dtype=bool)
    from spm_sysid.core.fit.problem import fit_structure

    model = fit_structure(u, y, mask, ts)
    back = NarxModel.from_dict(json.loads(model.to_json()))
    assert back.term_space == ts and back.terms == model.terms
    assert np.array_equal(back.predict(u, y), model.predict(u, y))
    assert np.array_equal(back.run(u, y)[0], model.run(u, y)[0])


@pytest.mark.parametrize("text, names", [
    ("__import__('os')", "'__import__'"),
    ("y(t-1).__class__", "'.'"),
    ("y" * 1_000_000, "1000000 characters"),
    ("(" * (MAX_DEPTH + 1) + "y(t-1)" + ")" * (MAX_DEPTH + 1), "nested deeper"),
    ("z(t-1)", "'z'"),
    ("y(t+1)", "y(t+...) reads the future"),
    ("y(t)", "y(t) is the output being predicted"),
    ("u(t-1)/y(t-1)", "divides by something other than a non-zero number"),
    ("sign(y(t-1), u(t-1))", "sign takes 1 argument(s), got 2"),
    ("y(t-1.5)", "whole number"),
    ("3", "reads no signal"),
])
def test_a_hostile_or_wrong_expression_is_refused_with_one_line_naming_it(text, names):
    with pytest.raises(RegressorError) as err:
        TermSpace(ny=2, nu=2, regressors=(text,))
    message = str(err.value)
    assert names in message and "\n" not in message and len(message) < 400


def test_the_command_line_refuses_a_bad_regressor_with_one_error_line():
    out = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "identify",
                          "--regressors", "sign(y(t-1)-y(t-2))", "__import__('os')"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 2
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert errors == [errors[0]] and "'__import__'" in errors[0]


def test_columns_runs_and_sensitivities_equal_independent_computations():
    u, y = _signals()
    texts = ("sign(y(t-1)-y(t-2))", "tanh((y(t-1)-y(t-3))/0.2)", "abs(u(t-1))*y(t-2)",
             "deadzone(y(t-1),0.1)")
    ts = TermSpace(ny=2, nu=2, degree=2, regressors=texts)
    assert ts.max_lag == 3 and ts.n_terms == 8 + 36
    lag = ts.max_lag
    ref = {  # numpy on the signals, by hand
        texts[0]: np.sign(y[lag - 1:-1] - y[lag - 2:-2]),
        texts[1]: np.tanh((y[lag - 1:-1] - y[lag - 3:-3]) / 0.2),
        texts[2]: np.abs(u[lag - 1:-1]) * y[lag - 2:-2],
        texts[3]: np.sign(y[lag - 1:-1]) * np.maximum(np.abs(y[lag - 1:-1]) - 0.1, 0.0),
    }
    P = ts.regression_matrix(u, y)
    names = ts.term_names()
    for text, column in ref.items():
        assert np.array_equal(P[:, names.index(text)], column)
    j = names.index(f"u(t-1)*{texts[0]}")
    assert np.array_equal(P[:, j], u[lag - 1:-1] * ref[texts[0]])

    picks = [names.index(n) for n in ("y(t-1)", "y(t-2)", "u(t-1)", texts[0], texts[1],
                                      f"u(t-1)*{texts[0]}", texts[3])]
    theta = np.array([1.1, -0.35, 0.5, -0.04, 0.02, 0.01, 0.03])
    model = NarxModel(term_space=ts, term_indices=sorted(picks),
                      coefficients=theta[np.argsort(picks)])
    # one step: the columns times the coefficients
    assert np.allclose(model.predict(u, y), P[:, model.term_indices] @ model.coefficients,
                       rtol=0, atol=1e-13)
    # free run: a plain Python loop on the model's own outputs
    sim = y.copy()
    for t in range(lag, len(y)):
        row = ts.regression_matrix(u[t - lag:t + 1], sim[t - lag:t + 1], model.term_indices)
        sim[t] = float(row[0] @ model.coefficients)
    free, at = model.run(u, y)
    assert at is None and np.allclose(free, sim[lag:], rtol=0, atol=1e-12)
    # k steps ahead: one step is the prediction; two steps chain one prediction
    assert np.allclose(model.run(u, y, horizon=1)[0], model.predict(u, y), rtol=0, atol=1e-13)
    chained = y.copy()
    chained[lag:] = model.predict(u, y)  # y(t) from y(t-1) predicted, y(t-2..) measured
    two_step = model.run(u, y, horizon=2)[0]
    t = len(y) - 1
    row = ts.regression_matrix(u[t - lag:t + 1],
                               np.r_[y[t - lag:t - 1], chained[t - 1], y[t]],
                               model.term_indices)
    assert two_step[-1] == pytest.approx(float(row[0] @ model.coefficients), abs=1e-12)
    # sensitivities: central finite differences of the free run
    out, jac, _ = free_run_sensitivities(model.compiled, model.coefficients, ts.inputs_2d(u), y)
    assert np.allclose(out, free, rtol=0, atol=1e-12)
    for i in range(len(theta)):
        step = 1e-6
        hi = model.with_coefficients(model.coefficients + step * np.eye(len(theta))[i])
        lo = model.with_coefficients(model.coefficients - step * np.eye(len(theta))[i])
        fd = (hi.run(u, y)[0] - lo.run(u, y)[0]) / (2 * step)
        assert np.allclose(jac[:, i], fd, rtol=1e-4, atol=1e-6), i


def test_the_online_predictor_predicts_as_the_model_does():
    from spm_sysid.core.online.predictor import OnlinePredictor

    u, y = _signals()
    res = identify(u=u, y=y, ny=2, nu=2, degree=2, regressors="friction", criterion="bic",
                   seed=1)
    model = res.model
    assert any(t.startswith("sign(") for t in model.terms)
    online = OnlinePredictor(model)
    got = [r[0] for k in range(len(y)) if (r := online.step(u[k], y[k])) is not None]
    assert np.allclose(got, model.predict(u, y), rtol=0, atol=1e-12)


@pytest.mark.parametrize("criterion", ["aic", "bic"])
def test_the_certified_optimum_with_regressors_equals_every_subset_by_least_squares(criterion):
    """Every subset of the candidate terms (products of two regressors are none)."""
    from spm_sysid.core.search.split import certify_data

    u, y = _signals(n=400, seed=3)
    ts = TermSpace(ny=1, nu=1, degree=2,
                   regressors=("sign(y(t-1)-y(t-2))", "tanh(u(t-1)/0.5)"))
    assert ts.n_terms == 14
    # products of two regressors are no candidates (one expression if a user wants one)
    names = ts.term_names()
    assert sorted(names[j] for j in np.flatnonzero(ts.regressor_products)) == sorted(
        ["sign(y(t-1)-y(t-2))^2", "sign(y(t-1)-y(t-2))*tanh(u(t-1)/0.5)",
         "tanh(u(t-1)/0.5)^2"])
    offered = [j for j in range(ts.n_terms) if not ts.regressor_products[j]]
    P, target = ts.regression(u, y)
    crit = get_criterion(criterion)
    n = len(target)
    best = np.inf
    for code in range(1, 2 ** len(offered)):
        cols = [j for i, j in enumerate(offered) if code >> i & 1]
        A = P[:, cols]
        coef, *_ = np.linalg.lstsq(A, target, rcond=None)
        if np.linalg.matrix_rank(A) < len(cols):
            continue
        r = target - A @ coef
        best = min(best, float(crit(np.array([r @ r]), n, np.array([len(cols)]), None)[0]))
    cert = certify_data(u, y, term_space=ts, criterion=criterion, time_limit=120)
    assert cert.status == "optimal"
    assert cert.value == pytest.approx(best, rel=1e-9, abs=1e-6)
    from spm_sysid.core.fit.problem import Problem

    assert not Problem.from_signals(u, y, ts).usable[ts.regressor_products].any()
    meta = identify(u=u, y=y, term_space=ts, criterion=criterion, seed=0).model.metadata
    assert meta["excluded_regressor_products"] == 3


def test_the_friction_preset_finds_the_sign_term_of_a_joint_with_coulomb_friction():
    """The simulated joint of the benchmarks (position out, torque in, PD at 1 kHz).

    The sign of the last position step is selected, and it opposes the motion:
    read as a force (the sign term over the input terms' sum, Ts^2/J) it is the
    joint's Coulomb friction to within a factor of two on this 20 s record (the
    position's encoder noise biases it; see the closing note of the friction issue).
    """
    tau, q = joint_record(20.0, seed=1)
    res = identify(u=tau, y=q, ny=2, nu=2, degree=1, regressors="friction", criterion="bic",
                   seed=1)
    th = dict(zip(res.model.terms, res.model.coefficients))
    step = "sign(y(t-1)-y(t-2))"
    assert step in th and th[step] < 0
    force = -th[step] / sum(v for k, v in th.items() if k.startswith("u("))
    assert 0.5 * Joint().coulomb < force < 2.0 * Joint().coulomb
    without = identify(u=tau, y=q, ny=2, nu=2, degree=1, criterion="bic", seed=1).model
    assert not any("sign" in t for t in without.terms)


def test_presets_take_their_scale_from_the_output():
    u, y = _signals()
    texts = expand_presets(["friction", "abs(u(t-1))"], "y", y)
    median_step = float(np.median(np.abs(np.diff(y))))
    assert texts[:2] == ["sign(y(t-1)-y(t-2))", "abs(y(t-1)-y(t-2))"]
    scale = float(texts[2].split("/")[1].rstrip(")"))
    assert scale == pytest.approx(median_step, rel=1e-2) and texts[3] == "abs(u(t-1))"


def test_the_friction_preset_reads_a_velocity_outputs_own_sign():
    """A velocity loop (speed out, torque in, PI at 1 kHz, Coulomb friction 0.15 N m).

    Its friction follows the speed's own sign, not the sign of the speed's last
    step: the preset adds ``sign(y(t-1))`` and its tanh for it, and for no output
    whose own sign says nothing (the joint's position, the robot arm's acceleration,
    samples taken around a mean). The model with it simulates a new record far
    better, and its friction read as a force (the own-sign terms over the input
    term, Ts/J) is the motor's to within 10 %.
    """
    from spm_sysid.core.io.datasets import load_robot_arm

    from .helpers.velocity_loop import Motor, velocity_record

    tau, v = velocity_record(20.0, seed=1)
    texts = expand_presets(["friction"], "y", v, [("u", (1,), tau)], ny=1)
    scale = texts[2].split("/")[1].rstrip(")")
    assert texts[3:] == ["sign(y(t-1))", f"tanh(y(t-1)/{scale})"], texts
    assert len(expand_presets(["friction"], "y", v, [("u", (1,), tau)], 1, own_sign=False)) == 3
    q_tau, q = joint_record(20.0, seed=1)
    u, y = load_robot_arm()
    for signal, inputs in ((q, [("u", (1, 2), q_tau)]), (y, [("u", (1, 2, 3, 4), u)])):
        assert len(expand_presets(["friction"], "y", signal, inputs, ny=2)) == 3
    for seed in range(20):  # 50 samples of noise: a sign that removes 5 % by chance is no friction
        noise = np.random.default_rng(seed).standard_normal(50)
        assert len(expand_presets(["friction"], "y", noise)) == 3
    settings = dict(u=tau, y=v, ny=1, nu=1, degree=1, criterion="bic", focus="simulation",
                    seed=1)
    model = identify(**settings, regressors="friction").model
    th = dict(zip(model.terms, model.coefficients))
    own = [k for k in th if k in texts[3:]]
    assert own and "u(t-1)" in th, th
    force = -sum(th[k] for k in own) / th["u(t-1)"]
    assert force == pytest.approx(Motor().coulomb, rel=0.1)
    without = identify(**settings).model
    tau2, v2 = velocity_record(20.0, seed=2)

    def free_run_rmse(m):
        sim, at = m.run(tau2, v2)
        assert at is None
        return float(np.sqrt(np.mean((v2[m.term_space.max_lag:] - sim) ** 2)))

    assert 10 * free_run_rmse(model) < free_run_rmse(without)  # 0.0083 against 0.395


def test_a_velocity_record_with_the_friction_preset_from_the_command_line(tmp_path):
    """``identify --regressors friction --json`` on a speed record, then ``validate`` on a
    new record: the document holds the own-sign regressors and simulates from them."""
    from .helpers.velocity_loop import velocity_record

    for seed, name in ((1, "speed.csv"), (2, "new.csv")):
        np.savetxt(tmp_path / name, np.column_stack(velocity_record(10.0, seed=seed)),
                   delimiter=",", header="torque,speed", comments="", fmt="%.10g")
    run = [sys.executable, "-m", "spm_sysid.apps.main"]
    out = subprocess.run([*run, "identify", "--data", "speed.csv", "--regressors", "friction",
                          "--ny", "1", "--nu", "1", "--degree", "1", "--criterion", "bic",
                          "--focus", "simulation", "--json", "m.json"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    model = NarxModel.load(tmp_path / "m.json")
    own = {r for r in model.term_space.regressors if r.startswith(("sign(y(t-1))", "tanh(y(t-1)/"))}
    assert len(own) == 2 and own & set(model.terms), (model.term_space.regressors, model.terms)
    again = subprocess.run([*run, "validate", "m.json", "--data", "new.csv"],
                           capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr
    line = next(ln for ln in again.stdout.splitlines() if ln.strip().startswith("free-run:"))
    assert float(line.split("RMSE ")[1].split(",")[0]) < 0.05, line  # 0.40 without


def test_the_friction_test_against_an_independent_least_squares_and_f_test():
    """The share and p-value of ``friction_sign``: numpy's least squares on the columns
    the docs name, scipy's chi-square (the large-sample form of the F test, which agrees)."""
    from scipy.stats import chi2
    from scipy.stats import f as f_distribution

    from spm_sysid.core.validate.friction import FRICTION_LEVEL, friction_sign

    from .helpers.velocity_loop import velocity_record

    tau, v = velocity_record(2.0, seed=3)
    found = friction_sign(v, tau, ny=2, nu=2)
    n, t = len(v), np.arange(2, len(v))
    step = v[t - 1] - v[t - 2]
    base = np.column_stack([v[t - 1], v[t - 2], np.ones(n - 2), tau[t - 1], tau[t - 2],
                            v[t - 1] ** 2, v[t - 1] ** 3, step ** 3, tau[t - 1] ** 2,
                            tau[t - 1] ** 3])
    full = np.column_stack([base, np.sign(step), np.sign(v[t - 1])])

    def sse(A):
        r = v[t] - A @ np.linalg.lstsq(A, v[t], rcond=None)[0]
        return r @ r

    s0, s1 = sse(base), sse(full)
    assert found.signs == ("sign(y(t-1)-y(t-2))", "sign(y(t-1))") and found.rows == n - 2
    assert found.share == pytest.approx(1 - s1 / s0, rel=1e-6)
    dof = n - 2 - full.shape[1]
    statistic = (s0 - s1) / 2 / (s1 / dof)
    assert found.p_value == pytest.approx(chi2.sf(2 * statistic, 2), rel=1e-6)
    assert f_distribution.sf(statistic, 2, dof) < FRICTION_LEVEL  # the exact test agrees
    assert friction_sign(v[:100], tau[:100]) is None  # too few rows for the test


def test_check_data_points_to_the_friction_preset_where_signs_explain_what_a_polynomial_cannot(
        tmp_path, robot_arm_path):
    """``spm-sysid check-data`` (and so every answer's warnings): a velocity loop and the
    1 kHz joint (read at the advised fifth of the rate) get the hint; with the preset
    asked for, none; a cubic spring, a plant behind a cubic of its input, steps held long at
    100x oversampling, the robot arm and a linear record with noise none."""
    from .helpers.velocity_loop import velocity_record

    rng = np.random.default_rng(4)
    lin_u = rng.standard_normal(5000)
    lin_y = np.zeros(5000)
    for k in range(2, 5000):
        lin_y[k] = 1.5 * lin_y[k - 1] - 0.7 * lin_y[k - 2] + lin_u[k - 1]
    cubic_u = np.sin(np.arange(20000)[:, None] * rng.uniform(0.005, 0.3, 20)
                     + rng.uniform(0, 6, 20)).sum(axis=1) / np.sqrt(10)
    cubic_y = np.zeros(20000)
    for k in range(2, 20000):  # Hammerstein: its input's cubic read as friction before
        cubic_y[k] = (1.3 * cubic_y[k - 1] - 0.45 * cubic_y[k - 2] + 0.4 * cubic_u[k - 1]
                      + 0.1 * cubic_u[k - 1] ** 3)
    held = np.repeat(rng.uniform(-1, 1, 20), 1000)  # steps held 1000 samples: 100x oversampled
    held_y = np.zeros(20000)
    for k in range(2, 20000):  # its steps are noise, whose sign the lagged outputs' noise reads
        held_y[k] = (1.5 * held_y[k - 1] - 0.56 * held_y[k - 2] + 0.05 * held[k - 1]
                     + 0.03 * held[k - 1] ** 3)
    records = {"speed.csv": velocity_record(20.0, seed=1), "joint.csv": joint_record(20.0, seed=2),
               "spring.csv": duffing(20000),
               "linear.csv": (lin_u, lin_y + rng.standard_normal(5000)),
               "cubic.csv": (cubic_u, cubic_y + 0.01 * rng.standard_normal(20000)),
               "held.csv": (held, held_y + 1e-3 * rng.standard_normal(20000))}
    for name, (u, y) in records.items():
        np.savetxt(tmp_path / name, np.column_stack([u, y]), delimiter=",", header="u,y",
                   comments="", fmt="%.10g")
    run = [sys.executable, "-m", "spm_sysid.apps.main", "check-data"]

    def hint(*args):
        out = subprocess.run([*run, *args], capture_output=True, text=True, cwd=tmp_path,
                             timeout=120)
        assert out.returncode == 0, out.stderr
        return [ln for ln in out.stdout.splitlines() if "--regressors friction" in ln]

    # the speed's own sign at the record's rate; the position's step at the advised one
    for name, rate, sign in (("speed.csv", "the record's rate", "warning: sign(y(t-1)) "),
                             ("joint.csv", "every 5th sample", "sign(y(t-1)-y(t-2))")):
        [line] = hint("--data", name)
        share = float(line.split(" explain ")[1].split("%")[0])
        assert share >= 5 and rate in line and sign in line, line
        assert not hint("--data", name, "--regressors", "friction")
    for name in ("spring.csv", "linear.csv", "cubic.csv"):
        assert not hint("--data", name), name
    assert not hint("--data", "held.csv", "--ny", "2", "--nu", "2")  # read 30 % before
    assert not hint("--data", str(robot_arm_path))


@pytest.mark.parametrize("how", ["input offset, auto", "mean asked for"])
def test_the_own_sign_and_an_operating_point(how):
    """An input far from zero is identified around its mean and the speed keeps its own
    sign; a mean asked for moves the speed too, and its sign is then not the record's:
    the preset leaves it out instead of refusing the point."""
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.record import Record

    from .helpers.velocity_loop import velocity_record

    tau, v = velocity_record(6.0, seed=1)
    point = "auto" if how.startswith("input") else "mean"
    settings = dict(ny=1, nu=1, degree=1, criterion="bic", seed=1, regressors="friction",
                    operating_point=point)
    job = run_job(Record.from_samples(tau + 5.0, v, source="speed"),
                  JobSettings.from_values(settings)).model  # the CLI's and the node's way
    for model in (identify(u=tau + 5.0, y=v, **settings).model, job):
        space = model.term_space
        own = {"sign(y(t-1))", *(r for r in space.regressors if r.startswith("tanh(y"))}
        assert "operating_point" in model.metadata
        if point == "auto":
            assert model.metadata["operating_point"]["output"] == {"y": 0.0}
            assert own & set(space.regressors) and own & set(model.terms), model.terms
        else:
            assert not own & set(space.regressors), space.regressors


def test_the_saturation_preset_finds_the_actuators_limit_and_its_model():
    """A velocity loop whose amplifier clips at 1.0 (benchmarks/actuator.py).

    The plant, written out: v(t) = 1.78 v(t-1) - 0.784 v(t-2) + 0.01 sat(u(t-2), 1).
    """
    from benchmarks.actuator import LIMIT, record
    from spm_sysid.core.model.presets import saturation_level

    u, y = record(2000, seed=0)
    u2, y2 = record(2000, seed=1)
    texts = expand_presets(["saturation"], "y", y, [("u", (1, 2), u)], ny=2)
    level = float(texts[0].split(",")[1].rstrip(")"))
    assert texts == [f"sat(u(t-1),{level!r})", f"sat(u(t-2),{level!r})"]
    assert level == pytest.approx(LIMIT, rel=0.02)  # not one of the command's own levels
    settings = dict(u=u, y=y, ny=2, nu=2, degree=1, criterion="bic", seed=1,
                    focus="simulation")
    model = identify(**settings, regressors="saturation").model
    assert sorted(model.terms) == sorted(["y(t-1)", "y(t-2)", f"sat(u(t-2),{level!r})"])
    th = dict(zip(model.terms, model.coefficients))
    assert th["y(t-1)"] == pytest.approx(1.78, abs=0.01)
    assert th["y(t-2)"] == pytest.approx(-0.784, abs=0.01)
    assert th[f"sat(u(t-2),{level!r})"] == pytest.approx(0.01, rel=0.1)
    without = identify(**settings).model

    def free_run_rmse(m):
        sim, at = m.run(u2, y2)
        assert at is None
        return float(np.sqrt(np.mean((y2[m.term_space.max_lag:] - sim) ** 2)))

    assert 5 * free_run_rmse(model) < free_run_rmse(without)
    # an input that never moves clips to nothing; an input at lag 0 is read at t
    assert expand_presets(["saturation"], "y", y, [("u", (1,), np.zeros(2000))]) == []
    assert saturation_level(y, [("u", (0,), u)], 0, ny=2) is not None
    assert expand_presets(["saturation"], "y", y, [("u", (0,), u)])[0].startswith("sat(u(t),")


@pytest.mark.slow
def test_identify_with_the_preset_then_validate_reads_the_document_back(tmp_path):
    """The commands a user types: ``identify --regressors friction --json``, then ``validate``."""
    doc = tmp_path / "model.json"
    run = [sys.executable, "-m", "spm_sysid.apps.main"]
    out = subprocess.run([*run, "identify", "--regressors", "friction", "--json", str(doc),
                          "--quiet"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    model = NarxModel.load(doc)
    assert len(model.term_space.regressors) == 3 and model.term_space.n_terms == 77
    again = subprocess.run([*run, "validate", str(doc)], capture_output=True, text=True,
                           cwd=ROOT, timeout=300)
    assert again.returncode == 0, again.stderr
    fit = model.metadata["validation"]["one_step"]["fit_percent"]
    assert f"fit {fit:.2f} %" in again.stdout


def test_the_simulation_focus_refines_a_structure_with_regressors():
    """The free-run refinement runs on the regressors' sensitivities and keeps the sign."""
    u, y = _signals(n=800, seed=5)
    res = identify(u=u, y=y, ny=2, nu=1, degree=1, regressors="sign(y(t-1)-y(t-2))",
                   criterion="bic", seed=1, focus="simulation")
    model = res.model
    assert model.metadata["focus"] == "simulation"
    assert "sign(y(t-1)-y(t-2))" in model.terms
    sign = model.coefficients[model.terms.index("sign(y(t-1)-y(t-2))")]
    assert sign == pytest.approx(-0.05, abs=0.02)  # the system's own -0.05
    free, at = model.run(u, y)
    assert at is None


def test_products_of_regressors_are_not_built_and_every_fit_is_the_full_matrix_one():
    """With the friction preset on (2, 2, 3) a third of the candidate matrix was products
    of two regressors, built and never used (on a 10-minute speed record at 1 kHz with
    the own sign, half: 528 of 1 056 MB); the problem now holds the others only."""
    from spm_sysid.core.fit.problem import Problem

    u, y = _signals(n=800, seed=4)
    ts = TermSpace(ny=2, nu=2, degree=3, constant=True,
                   regressors=tuple(expand_presets(["friction"], "y", y)))
    products = ts.regressor_products
    assert products.sum() == 40 and ts.n_terms == 120
    problem = Problem.from_signals(u, y, ts)
    assert problem.columns.shape == (problem.rows, 80)
    full, target = ts.regression(u / problem.u_scale, y / problem.y_scale,
                                 scales=(problem.u_scale, problem.y_scale, problem.r_scale))
    np.testing.assert_array_equal(problem.columns, full[:, ~products])
    rng = np.random.default_rng(0)
    usable = np.flatnonzero(problem.usable)
    for _ in range(5):
        mask = np.zeros(ts.n_terms, dtype=bool)
        mask[rng.choice(usable, 8, replace=False)] = True
        fit = problem.fit(mask)
        theta = np.linalg.lstsq(full[:, mask], target, rcond=None)[0]
        np.testing.assert_allclose(fit.coefficients, theta * problem._factors[mask], rtol=1e-8)
        score = problem.evaluator("bic").score(problem.restrict(mask)[None])[0]
        sse = float(np.sum((target - full[:, mask] @ theta) ** 2)) * problem.sse_scale
        assert score == pytest.approx(get_criterion("bic")(sse, problem.rows, 8)[0], rel=1e-9)
    mask = np.zeros(ts.n_terms, dtype=bool)
    mask[np.flatnonzero(products)[0]] = True
    with pytest.raises(ValueError, match="product of two regressors, which is no candidate"):
        problem.fit(mask)
    assert (problem.column_norms[products] == 0).all()
    assert (problem.column_norms[~products & ~problem.zero] > 0).all()
