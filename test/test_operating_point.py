"""Records far from zero: identified around their means, the model in the record's units."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.errors import SettingsError
from spm_sysid.core.identify import identify
from spm_sysid.core.jobs import JobSettings, run_job
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.operating_point import (
    OperatingPoint,
    choose_operating_point,
    in_record_units,
)
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.model.uncertainty import Uncertainty
from spm_sysid.core.record import Record

from .conftest import EQ1
from .helpers.joint import joint_record

#: The simulated joint's position, moved this far from zero (rad): ~140 of its
#: standard deviations, as an absolute encoder angle can be.
FAR = 30.0


def _model(space: TermSpace, names: list[str], coefficients, cov=None) -> NarxModel:
    index = {n: i for i, n in enumerate(space.term_names())}
    order = sorted(range(len(names)), key=lambda j: index[names[j]])
    theta = np.asarray(coefficients, dtype=float)[order]
    unc = None if cov is None else Uncertainty(np.asarray(cov)[np.ix_(order, order)], 100,
                                               1.0, "least squares")
    return NarxModel(space, [index[names[j]] for j in order], theta, uncertainty=unc)


def test_a_product_of_deviations_expands_into_the_record_terms_by_hand():
    """y~(t) = a y~(t-1) + b y~(t-1) u~(t-1), with y~ = y - y0, u~ = u - u0, written out."""
    a, b, y0, u0 = 0.7, 0.2, 5.0, -2.0
    space = TermSpace(ny=1, nu=1, degree=2)
    model = in_record_units(_model(space, ["y(t-1)", "y(t-1)*u(t-1)"], [a, b]),
                            OperatingPoint((u0,), y0, "test"))
    got = dict(zip(model.terms, model.coefficients))
    want = {"1": y0 - a * y0 + b * y0 * u0, "y(t-1)": a - b * u0, "u(t-1)": -b * y0,
            "y(t-1)*u(t-1)": b}
    assert got.keys() == want.keys()
    for name, value in want.items():
        assert got[name] == pytest.approx(value, rel=1e-14, abs=1e-14)
    assert model.metadata["operating_point"]["selected_terms"] == ["y(t-1)", "y(t-1)*u(t-1)"]
    assert model.metadata["operating_point"]["terms_added"] == 2


def test_the_expanded_model_predicts_and_simulates_as_the_model_of_deviations():
    """Cubes and products of two inputs; covariance mapped (output bands the same)."""
    rng = np.random.default_rng(3)
    space = TermSpace(ny=2, nu=2, degree=3, inputs=("a", "b"), output="y")
    names = ["y(t-1)", "y(t-2)", "a(t-1)*b(t-2)", "y(t-1)^3", "y(t-2)*a(t-1)^2"]
    theta = [0.5, -0.2, 0.1, -0.05, 0.02]
    root = rng.standard_normal((5, 5)) * 0.01
    dev = _model(space, names, theta, root @ root.T)
    point = OperatingPoint((3.0, -7.0), 12.0, "test")
    raw = in_record_units(_model(space, names, theta, root @ root.T), point)
    u = rng.standard_normal((300, 2)) * 0.3
    y = rng.standard_normal(300) * 0.3
    du, dy = u, y
    ru, ry = u + [3.0, -7.0], y + 12.0
    assert np.allclose(raw.predict(ru, ry), dev.predict(du, dy) + 12.0, rtol=0, atol=1e-9)
    sim_dev, sim_raw = dev.simulate(du, dy[:2]), raw.simulate(ru, ry[:2])
    assert np.allclose(sim_raw, sim_dev + 12.0, rtol=0, atol=1e-8)
    # the covariance maps with the coefficients: a linear function of the raw
    # coefficients that equals one of the deviation coefficients has its variance
    cov = raw.uncertainty.covariance
    assert cov.shape == (len(raw.term_indices),) * 2 and np.allclose(cov, cov.T)
    cube = raw.terms.index("y(t-1)^3")
    assert cov[cube, cube] == pytest.approx(dev.uncertainty.covariance[
        dev.terms.index("y(t-1)^3"), dev.terms.index("y(t-1)^3")], rel=1e-12)


def _joint_settings(around: str) -> JobSettings:
    return JobSettings.from_values({"focus": "simulation", "ny": 4, "nu": 4, "degree": 1,
                                    "constant": True, "criterion": "bic", "seed": 1,
                                    "operating_point": around})


def _free_run_rmse(model: NarxModel, tau: np.ndarray, q: np.ndarray) -> float:
    sim, _ = model.run(tau, q)
    return float(np.sqrt(np.mean((q[model.term_space.max_lag:][50:] - sim[50:]) ** 2)))


def test_a_joint_far_from_zero_gets_the_model_it_gets_near_zero():
    """The same physical record moved by 30 rad: same model; as recorded, a worse one."""
    tau, q = joint_record(20.0, seed=1)
    tau2, q2 = joint_record(20.0, seed=2)
    near = run_job(Record.from_samples(tau, q - q.mean(), source="near"),
                   _joint_settings("none")).model
    far = run_job(Record.from_samples(tau, q - q.mean() + FAR, source="far"),
                  _joint_settings("auto")).model
    as_recorded = run_job(Record.from_samples(tau, q - q.mean() + FAR, source="far"),
                          _joint_settings("none")).model
    shift = FAR - q.mean()
    e_near = _free_run_rmse(near, tau2, q2 - q.mean())
    e_far = _free_run_rmse(far, tau2, q2 + shift)
    e_as_recorded = _free_run_rmse(as_recorded, tau2, q2 + shift)
    point = far.metadata["operating_point"]
    assert point["output"]["y"] == pytest.approx(FAR, abs=1e-9)
    assert "standard deviations from zero" in point["reason"]
    assert e_far == pytest.approx(e_near, rel=1e-3)
    assert e_as_recorded > 2 * e_far
    assert "operating_point" not in as_recorded.metadata


def test_the_document_is_a_plain_narx_an_independent_simulation_reads(tmp_path):
    """The command as typed on a file 30 rad from zero; its document simulated by a loop."""
    tau, q = joint_record(20.0, seed=1)
    tau2, q2 = joint_record(20.0, seed=2)
    data, model_path = tmp_path / "far.csv", tmp_path / "far.json"
    np.savetxt(data, np.c_[tau, q + FAR], delimiter=",", header="tau,q", comments="")
    out = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "identify", "--data",
                          str(data), "--inputs", "tau", "--output", "q", "--focus",
                          "simulation", "--ny", "4", "--nu", "4", "--degree", "1", "--seed",
                          "1", "--json", str(model_path)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "identified around the estimation data's means (q = " in out.stdout
    doc = json.loads(model_path.read_text())
    lag = {}
    for name, c in zip(doc["terms"], doc["coefficients"]):
        m = re.fullmatch(r"(q|tau)\(t-(\d+)\)|1", name)
        assert m, f"a linear model's term {name}"
        lag[(m.group(1), int(m.group(2))) if m.group(1) else "1"] = c
    assert "1" in lag  # the operating point's constant
    y = q2 + FAR
    sim = y.copy()
    for t in range(4, len(y)):
        sim[t] = lag.get("1", 0.0) + sum(
            c * (sim[t - k] if s == "q" else tau2[t - k])
            for key, c in lag.items() if key != "1" for s, k in [key])
    ours, _ = NarxModel.from_dict(doc).run(tau2, y)
    assert np.allclose(sim[4:], ours, rtol=0, atol=1e-9)
    rmse = float(np.sqrt(np.mean((y[54:] - sim[54:]) ** 2)))
    assert rmse < 0.4 * float(np.std(q2))  # it simulates (about 0.9x as recorded)


def test_records_near_zero_are_identified_as_recorded(robot_arm):
    """The robot arm (the paper's numbers): auto leaves it as it is."""
    u, y = robot_arm
    point, why = choose_operating_point("auto", u, y, TermSpace())
    assert point is None and why is None


def test_a_regressor_of_the_signals_themselves_keeps_the_record_and_says_why():
    rng = np.random.default_rng(0)
    u = rng.standard_normal(400) + 10.0
    y = np.convolve(u, [0.0, 0.5, 0.2])[:400] + 0.01 * rng.standard_normal(400)
    moving = TermSpace(ny=1, nu=1, degree=1, regressors=("abs(u(t-1))",))
    point, why = choose_operating_point("auto", u, y, moving)
    assert point is None and "abs(u(t-1))" in why and "identified as it is" in why
    with pytest.raises(SettingsError, match="operating_point: mean: the regressor"):
        choose_operating_point("mean", u, y, moving)
    steps = TermSpace(ny=2, nu=1, degree=1, regressors=("sign(y(t-1)-y(t-2))",))
    point, why = choose_operating_point("auto", u, y, steps)
    assert point is not None and why is None
    result = identify(u=u, y=y, ny=1, nu=1, degree=1, regressors="abs(u(t-1))", seed=0,
                      generations=5, population_size=10)
    assert "identified as it is" in result.model.metadata["operating_point"]["reason"]


def test_the_python_api_identifies_around_the_means_too(robot_arm):
    u, y = robot_arm
    base = identify(u=u, y=y, seed=5, generations=30, operating_point="none")
    moved = identify(u=u + 40.0, y=y + 100.0, seed=5, generations=30)
    assert moved.model.metadata["operating_point"]["output"]["y"] == pytest.approx(
        100.0 + float(np.mean(y)))
    sim_base, _ = base.model.run(u, y)
    sim_moved, _ = moved.model.run(u + 40.0, y + 100.0)
    # the same deviations up to rounding: the same structure and free run
    assert moved.model.metadata["operating_point"]["selected_terms"] == base.model.terms
    assert np.allclose(sim_moved - 100.0, sim_base, rtol=0, atol=1e-6)


def test_the_paper_record_far_from_zero_gets_equation_1_certified(robot_arm, tmp_path):
    """The arm's acceleration moved by 1000: identify and certify as typed give eq. (1)."""
    u, y = robot_arm
    data = tmp_path / "moved.csv"
    np.savetxt(data, np.c_[u, y + 1000.0], delimiter=",", header="u,y", comments="",
               fmt="%.10g")
    cli = [sys.executable, "-m", "spm_sysid.apps.main"]
    out = subprocess.run([*cli, "identify", "--data", str(data), "--seed", "1", "--json",
                          str(tmp_path / "m.json")], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "certified optimal over all structures" in out.stdout
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["metadata"]["operating_point"]["selected_terms"] == EQ1
    assert doc["terms"] == ["1", *EQ1]
    assert doc["criterion"]["value"] == pytest.approx(-10744.785, abs=0.001)
    cert = subprocess.run([*cli, "certify", "--data", str(data), "--criterion", "aic",
                           "--seed", "1", "--quiet"], capture_output=True, text=True,
                          timeout=300)
    assert cert.returncode == 0, cert.stderr
    assert "around the estimation data's means (y = 1000" in cert.stdout
    assert "status: optimal" in cert.stdout and "value: -10744.78" in cert.stdout
    check = subprocess.run([*cli, "check-data", "--data", str(data)], capture_output=True,
                           text=True, timeout=300)
    assert check.returncode == 0, check.stderr
    assert "around the record's means (y = 1000" in check.stdout
    assert "no warning: the data can identify this space" in check.stdout
    raw = subprocess.run([*cli, "check-data", "--data", str(data), "--operating-point", "none"],
                         capture_output=True, text=True, timeout=300)
    assert "nearly combinations of others" in raw.stdout  # what identify no longer meets
    # a regressor that moves with an offset keeps the record: the space identify uses,
    # without the constant the deviations would add
    kept = subprocess.run([*cli, "check-data", "--data", str(data), "--regressors",
                           "abs(y(t-1))"], capture_output=True, text=True, timeout=300)
    assert kept.returncode == 0, kept.stderr
    assert "as recorded: y's mean" in kept.stdout and ", constant" not in kept.stdout
    as_recorded = subprocess.run([*cli, "certify", "--data", str(data), "--criterion", "aic",
                                  "--seed", "1", "--quiet", "--operating-point", "none",
                                  "--node-limit", "2000"], capture_output=True, text=True,
                                 timeout=300)
    assert as_recorded.returncode == 0, as_recorded.stderr
    assert "around" not in as_recorded.stdout and "value: -10744.78" not in as_recorded.stdout


def test_an_interrupted_jobs_best_model_so_far_is_written_in_the_record_units():
    """Ctrl-C writes the progress record's best model: mapped like the returned one."""
    from spm_sysid.core.jobs.single import _in_units
    from spm_sysid.core.progress import Progress

    space = TermSpace(ny=1, nu=1, degree=1)
    point = OperatingPoint((2.0,), 30.0, "test")
    seen = []
    report = _in_units(seen.append, point)
    report(Progress("search", best_model=lambda: _model(space, ["y(t-1)", "u(t-1)"],
                                                        [0.5, 0.1])))
    report(Progress("polish"))
    model = seen[0].best_model()
    assert dict(zip(model.terms, model.coefficients)) == pytest.approx(
        {"1": 30.0 - 0.5 * 30.0 - 0.1 * 2.0, "y(t-1)": 0.5, "u(t-1)": 0.1})
    assert seen[1].best_model is None
    report = seen.append
    assert _in_units(report, None) is report


def test_two_joints_far_from_zero_get_the_coupled_model_they_get_near_zero():
    """Each output's job and the coupled judgement work around the same point."""
    from .helpers.two_joints import two_joint_record

    names = {"input_names": ("t1", "t2"), "output_names": ("q1", "q2")}
    (u1, Y1), (u2, Y2) = two_joint_record(3000, seed=0), two_joint_record(3000, seed=1)
    shift = np.array([5.0, -3.0])
    settings = JobSettings.from_values({"focus": "simulation", "ny": 2, "nu": 2, "degree": 2,
                                        "criterion": "bic", "seed": 1})
    errors = []
    for moved in (0.0 * shift, shift):
        model = run_job(Record.from_samples(u1, Y1 + moved, source="arm", **names),
                        settings).model
        sim, diverged = model.simulate(u2, Y2 + moved)
        assert diverged == [None, None]
        errors.append(np.sqrt(np.mean((Y2[model.max_lag:] + moved - sim)[50:] ** 2, axis=0)))
    assert errors[1] == pytest.approx(errors[0], rel=0.02)
    points = [m.metadata["operating_point"] for m in model.models]
    assert points[0]["output"]["q1"] == pytest.approx(5.0 + Y1[:, 0].mean(), abs=1e-9)
    assert points[1]["inputs"]["q1"] == points[0]["output"]["q1"]


def test_lags_that_stand_in_for_one_another_are_reported_with_their_sum():
    """Each of y(t-1), y(t-2) spans zero; their sum (the pole near 1) does not."""
    from scipy import stats

    space = TermSpace(ny=2, nu=1, degree=1)
    names = ["y(t-1)", "y(t-2)", "u(t-1)"]
    var, cov = 4.0, -3.9999  # var of the sum: 4 + 4 - 2 * 3.9999 = 2e-4
    model = _model(space, names, [1.5, -0.499, 0.01],
                   [[var, cov, 0.0], [cov, var, 0.0], [0.0, 0.0, 1e-6]])
    (group,) = model.lags_together()
    se = np.sqrt(2e-4)
    half = stats.t.ppf(0.975, 100) * se
    assert group["signal"] == "y" and group["terms"] == ["y(t-1)", "y(t-2)"]
    assert group["sum"] == pytest.approx(1.001)
    assert group["standard_error"] == pytest.approx(se, rel=1e-9)
    assert np.allclose(group["interval"], (1.001 - half, 1.001 + half), rtol=1e-6)
    table = model.coefficient_table()
    assert "the 2 y(t-i) terms together" in table and "sum 1.001, std. error 0.0141" in table
    # uncorrelated lags: nothing stands in for anything, no line
    plain = _model(space, names, [1.5, -0.499, 0.01],
                   [[var, 0.0, 0.0], [0.0, var, 0.0], [0.0, 0.0, 1e-6]])
    assert plain.lags_together() == [] and "together" not in plain.coefficient_table()
