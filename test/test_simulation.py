"""Simulation kernel, k-step prediction, sensitivities, refinement, divergence, focus."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.fit.problem import fit_structure
from spm_sysid.core.fit.refine import (
    free_run_uncertainty,
    linear_radius,
    linear_stability_check,
    refine_simulation,
)
from spm_sysid.core.identify import identify
from spm_sysid.core.model import simulation
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.simulation import free_run_sensitivities, run_model
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.validate.validation import metrics, validate_model

from .conftest import ROOT


def _reference_chain(space, indices, theta, u, y, origin, stop):
    """Plain Python: measured outputs up to ``origin``, the model's own after it."""
    lin, terms = space.linear, space.terms
    u = space.inputs_2d(u)
    ys = list(y[:origin + 1])
    for t in range(origin + 1, stop):
        total = 0.0
        for i, c in zip(indices, theta):
            value = 1.0
            for f in terms[i]:
                src, lag = lin[f]
                value *= ys[t - lag] if src < 0 else u[t - lag, src]
            total += c * value
        ys.append(total)
    return np.array(ys)


def _reference_free_run(space, indices, theta, u, y):
    lag0 = space.max_lag
    return _reference_chain(space, indices, theta, u, y, lag0 - 1, len(y))[lag0:]


@pytest.fixture(scope="module")
def miso_model():
    rng = np.random.default_rng(2)
    n = 400
    u = rng.uniform(-1, 1, (n, 2))
    y = np.zeros(n)
    for t in range(3, n):
        y[t] = (0.6 * y[t - 1] - 0.2 * y[t - 3] + 0.5 * u[t - 1, 0] + 0.3 * u[t, 1]
                + 0.2 * y[t - 1] * u[t - 2, 0] - 0.1 * u[t, 1] ** 2 * y[t - 2])
    y += 0.01 * rng.standard_normal(n)
    space = TermSpace(ny=3, nu=(2, 1), delay=(1, 0), degree=3, inputs=("a", "b"))
    names = space.term_names()
    chosen = ["y(t-1)", "y(t-3)", "a(t-1)", "b(t)", "y(t-1)*a(t-2)", "y(t-2)*b(t)^2"]
    mask = np.zeros(space.n_terms, dtype=bool)
    mask[[names.index(c) for c in chosen]] = True
    return fit_structure(u, y, mask, space), u, y


def test_kernel_equals_a_plain_python_simulation(miso_model):
    model, u, y = miso_model
    ref = _reference_free_run(model.term_space, model.term_indices, model.coefficients, u, y)
    fast, at = run_model(model.compiled, model.coefficients, u, y)
    assert at is None and np.max(np.abs(fast - ref)) <= 1e-12 * np.max(np.abs(ref))
    # the uncompiled kernel (what runs without numba) gives the very same numbers
    cm = model.compiled
    out = np.empty(len(y) - model.term_space.max_lag)
    lo, hi = simulation.divergence_bounds(y)
    simulation._run.py_func(cm.gather, cm.y_lags, cm.u_lags, cm.u_cols, model.coefficients,
                            u, y, len(y), cm.max_lag, lo, hi, out)
    assert np.array_equal(out, fast)


def test_k_step_one_is_one_step_and_k_beyond_the_record_is_free_run(miso_model):
    model, u, y = miso_model
    one = model.predict(u, y, horizon=1)
    np.testing.assert_allclose(run_model(model.compiled, model.coefficients, u, y, 1)[0], one,
                               rtol=0, atol=1e-13)
    free = model.predict(u, y, horizon=None)
    assert np.array_equal(model.predict(u, y, horizon=len(y)), free)
    assert np.array_equal(model.predict(u, y, horizon=10 * len(y)), free)
    # k-step by hand at one sample: k chained steps from the measured outputs at t-k
    k, t = 5, 200
    chain = _reference_chain(model.term_space, model.term_indices, model.coefficients, u, y,
                             t - k, t + 1)
    k5 = model.predict(u, y, horizon=k)
    lag0 = model.term_space.max_lag
    assert k5[t - lag0] == pytest.approx(chain[-1], rel=1e-12)
    with pytest.raises(ValueError, match="horizon"):
        model.predict(u, y, horizon=0)


def test_sensitivity_jacobian_matches_finite_differences(miso_model):
    model, u, y = miso_model
    theta = model.coefficients
    yhat, jac, at = free_run_sensitivities(model.compiled, theta, u, y)
    assert at is None and np.array_equal(yhat, model.predict(u, y, horizon=None))
    for i in range(len(theta)):
        h = 1e-6 * max(1.0, abs(theta[i]))
        up, down = theta.copy(), theta.copy()
        up[i] += h
        down[i] -= h
        fd = (run_model(model.compiled, up, u, y)[0] - run_model(model.compiled, down, u, y)[0])
        fd /= 2 * h
        assert np.max(np.abs(fd - jac[:, i])) <= 1e-6 * np.max(np.abs(jac[:, i])) + 1e-9


def test_refinement_recovers_an_output_error_system():
    # output error: the noise is on the measurement only, so least squares on the
    # noisy lagged outputs is biased; minimising the simulation error is not
    rng = np.random.default_rng(7)
    n = 2000
    u = rng.uniform(-1, 1, n)
    x = np.zeros(n)
    for t in range(2, n):
        x[t] = 1.2 * x[t - 1] - 0.5 * x[t - 2] + 0.8 * u[t - 1] + 0.3 * u[t - 1] * x[t - 1]
    y = x + 0.1 * rng.standard_normal(n)
    space = TermSpace(ny=2, nu=1, degree=2)
    names = space.term_names()
    mask = np.zeros(space.n_terms, dtype=bool)
    mask[[names.index(c) for c in ("y(t-1)", "y(t-2)", "u(t-1)", "y(t-1)*u(t-1)")]] = True
    ls = fit_structure(u, y, mask, space)
    true = np.array([1.2, -0.5, 0.8, 0.3])
    assert np.max(np.abs(ls.coefficients - true)) > 0.05  # biased
    ref = refine_simulation(ls, u, y)
    assert ref.success and ref.sse < 0.7 * ref.sse_start
    np.testing.assert_allclose(ref.coefficients, true, atol=0.02)
    assert _free_run_sse(ls, u, y, ref.coefficients) == pytest.approx(ref.sse)
    assert linear_radius(space, ls.term_indices, ref.coefficients) < 1


def test_free_run_uncertainty_covers_the_truth_and_refuses_an_unstable_linearisation():
    """A Gauss-Newton covariance only where the free run's linearisation is bounded.

    The chaotic logistic map stays inside the measured range, but its sensitivities grow
    like e^(0.5 t): 400 samples overflow them, and the covariance would print standard
    errors of exactly zero. It is refused with the reason, and the table says it.
    """
    rng = np.random.default_rng(3)
    n = 3000
    u = rng.uniform(-1, 1, n)
    x = np.zeros(n)
    for t in range(1, n):
        x[t] = 0.7 * x[t - 1] + 0.5 * u[t - 1]
    y = x + 0.05 * rng.standard_normal(n)
    space = TermSpace(ny=1, nu=1, degree=1)
    ref = refine_simulation(NarxModel(space, [0, 1], np.array([0.6, 0.4])), u, y)
    found, why = free_run_uncertainty(NarxModel(space, [0, 1], ref.coefficients), u, y)
    assert why == "" and np.all(found.standard_errors > 0)
    assert np.all(np.abs(ref.coefficients - [0.7, 0.5]) < 4 * found.standard_errors)

    logistic = np.zeros(400)
    logistic[0] = 0.3
    for t in range(1, 400):
        logistic[t] = 3.9 * logistic[t - 1] * (1 - logistic[t - 1]) + 0.002 * u[t - 1]
    chaos = NarxModel(TermSpace(ny=1, nu=1, degree=2), [0, 1, 2], np.array([3.9, 0.002, -3.9]))
    assert np.isfinite(chaos.run(u[:400], logistic)[0]).all()  # it stays in range
    found, why = free_run_uncertainty(chaos, u[:400], logistic)
    assert found is None and "grow without bound" in why
    chaos.metadata = {"simulation": {"no_uncertainty": why}}
    assert f"(no coefficient uncertainty: {why})" in chaos.coefficient_table()


def test_the_growth_check_reads_the_largest_size_without_a_copy():
    """``max |J|`` from the Jacobian's own extremes equals numpy's of ``|J|``; NaN stays NaN.

    (The check used to copy a long record's Jacobian to take its absolute values.)
    """
    from spm_sysid.core.fit.refine import _largest_size

    rng = np.random.default_rng(8)
    for shape in [(7, 3), (1000, 5), (50, 1)]:
        jac = rng.standard_normal(shape) * rng.uniform(0.1, 10, shape[1])
        jac[rng.integers(shape[0]), 0] = -50.0  # the largest size negative
        assert _largest_size(jac) == float(np.max(np.abs(jac))) == 50.0
        jac[0, 0] = np.inf
        assert _largest_size(jac) == np.inf
        jac[1, -1] = np.nan
        assert np.isnan(_largest_size(jac))


def _free_run_sse(model: NarxModel, u, y, theta=None) -> float:
    """The free-run SSE of a model (or of its structure with ``theta``)."""
    if theta is not None:
        model = NarxModel(model.term_space, model.term_indices, np.asarray(theta))
    e = model.measured(y) - model.run(u, y)[0]
    return float(e @ e)


def _unstable_model() -> NarxModel:
    space = TermSpace(ny=1, nu=1, degree=1)
    return NarxModel(term_space=space, term_indices=[0, 1], coefficients=np.array([1.5, 1.0]),
                     criterion="aic", criterion_value=0.0, mse=1.0, n_samples=10)


def test_a_diverging_model_says_where_not_inf(robot_arm):
    u, y = robot_arm
    model = _unstable_model()
    sim, at = model.run(u, y)
    lo, hi = simulation.divergence_bounds(y)
    assert at is not None and np.all(np.isfinite(sim[:at - 1]))
    assert np.all(np.isnan(sim[at - 1:]))
    assert not lo <= model.simulate(u, np.r_[y[:1], np.zeros(len(y) - 1)])[at - 1] <= hi
    m = metrics(y[1:], sim, at)
    assert m["diverged_at"] == at and np.isnan(m["fit_percent"])
    report = validate_model(model, u, y)
    assert report.diverged_at == at and not report.passed and report.tests == []
    text = report.summary()
    assert f"free-run: DIVERGED at sample {at}" in text and "inf" not in text
    assert "correlation tests: not computed (the free-run simulation diverged" in text
    doc = report.to_dict()
    json.dumps(doc, allow_nan=False)  # strict JSON: no inf/NaN
    assert doc["diverged_at"] == at and doc["free_run"]["fit_percent"] is None


def test_diverging_model_on_the_command_line_and_in_figures(tmp_path):
    path = tmp_path / "unstable.json"
    _unstable_model().save(path)
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "validate", str(path),
                        "--horizon", "5", "--plots", str(tmp_path / "figs")],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "free-run: DIVERGED at sample" in r.stdout and "5-step:" in r.stdout
    assert "inf" not in r.stdout.replace("info", "")
    svg = (tmp_path / "figs" / "model_free_run.svg").read_text()
    assert "diverged at sample" in svg
    assert not (tmp_path / "figs" / "model_correlation.svg").exists()


def test_diverged_model_is_an_error_in_the_node_diagnostics():
    from spm_sysid.core.stream.diagnostics import ERROR, diagnostic_statuses

    doc = _unstable_model().to_dict()
    doc["metadata"]["validation"] = {"diverged_at": 17, "free_run": {"fit_percent": None},
                                     "correlation_tests": [],
                                     "correlation_tests_skipped": "the free-run simulation "
                                                                  "diverged at sample 17"}
    from spm_sysid.core.stream.buffer import SampleBuffer

    statuses = diagnostic_statuses("/n", SampleBuffer(10).stats_dict(), model=doc)
    ident = next(s for s in statuses if s.name.endswith("identification"))
    assert ident.level == ERROR and "DIVERGED at sample 17" in ident.message
    assert any("not computed" in s.message for s in statuses)


@pytest.mark.slow
def test_simulation_focus_meets_the_free_run_target_on_the_robot_arm(robot_arm):
    u, y = robot_arm
    # in-sample selection (the simulation criterion on all data): 11 terms, 85.5 %
    res = identify(u=u, y=y, criterion="bic", seed=1, focus="simulation",
                   selection="criterion")
    m = res.model
    fit = metrics(y[4:], m.simulate(u, y))["fit_percent"]
    assert fit >= 85.0  # the paper's eq. (2) simulates with about 11 %
    # the default (validated on held-out blocks) prefers the 8 linear terms, which the
    # held-out blocks cannot tell from the 11 (within one standard error): 84.9 %
    default = identify(u=u, y=y, criterion="bic", seed=1, focus="simulation").model
    assert default.metadata["selection"]["method"] == "validated"
    assert len(default.terms) <= len(m.terms)
    assert metrics(y[4:], default.simulate(u, y))["fit_percent"] >= 84.0
    assert m.metadata["focus"] == "simulation"
    assert "simulation error" in m.metadata["simulation"]["criterion_meaning"]
    assert linear_radius(m.term_space, m.term_indices, m.coefficients) < 1
    # the criterion value is BIC of the free-run SSE
    sse = _free_run_sse(m, u, y)
    n = len(y) - 4
    assert m.criterion_value == pytest.approx(n * np.log(sse / n) + len(m.terms) * np.log(n))


def test_the_fast_stability_check_agrees_with_the_roots():
    """Schur-Cohn step-down against numpy's roots, on random structures and scales."""
    ts = TermSpace(ny=4, nu=4, degree=2)
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(3000):
        idx = sorted(rng.choice(ts.n_terms, size=int(rng.integers(1, 12)),
                                replace=False).tolist())
        theta = rng.normal(0.0, rng.choice([0.3, 1.0, 3.0]), len(idx))
        radius = linear_radius(ts, idx, theta)
        if abs(radius - 1.0) < 1e-9:
            continue  # on the circle: either answer is rounding
        assert linear_stability_check(ts, idx)(theta) == (radius < 1.0), (idx, theta)
        checked += 1
    assert checked > 2900


def test_judging_skips_the_refinements_of_an_estimator_that_left_the_range(robot_arm,
                                                                            monkeypatch):
    """A finalist whose run left the range on one fold scores inf whatever the others give:
    the next folds skip its refinement, and every held-out error equals the full count's."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.select import finalists
    from spm_sysid.core.select.folds import informative_folds, sub_blocks

    u, y = robot_arm
    problem = Problem.from_signals(u, y)
    folds, _ = informative_folds(problem, 3, 3)
    label = sub_blocks(problem, folds)
    n_sub = int(label.max()) + 1
    refined = []
    real = finalists.refine_simulation
    monkeypatch.setattr(finalists, "refine_simulation",
                        lambda *a, **k: refined.append(1) or real(*a, **k))
    every = np.ones(problem.term_space.n_terms, dtype=bool)  # 44 terms: leaves the range
    linear = np.zeros_like(every)
    linear[[problem.term_space.terms.index((i,)) for i in range(8)]] = True
    for mask, diverges in ((every, True), (linear, False)):
        job = finalists.ValidatedSimulation.__new__(finalists.ValidatedSimulation)
        job.problem, job.folds = problem, folds
        refined.clear()
        skipped = job._fold_runs(mask, 30)
        calls_skipped = len(refined)
        full = [finalists.fold_runs(problem, fold, mask, 30) for fold in folds]
        assert len(refined) == calls_skipped + len(folds)  # the full count refines every fold
        for j in range(2):
            a = finalists.sub_block_errors([p[j] for p in skipped], label, n_sub)
            b = finalists.sub_block_errors([p[j] for p in full], label, n_sub)
            assert a == b
            assert np.all(np.isinf(a)) == diverges
        assert (calls_skipped < len(folds)) == diverges


def test_a_long_records_free_run_covariance_from_windows_matches_every_rows():
    """Windows' ``J'J`` scaled to all rows gives the covariance of the Jacobian of every row.

    A long record's free-run Jacobian (rows x terms) would be hundreds of MB; past
    ``FINAL_JACOBIAN_BYTES`` the covariance comes from the final refinement's windows.
    Here the budget is lowered so that 20 000 rows take that route: the standard
    errors agree with those of every row within 10 %, ``dof`` stays N - k, and the
    account says how many rows the Jacobian had.
    """
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.select import folds
    from spm_sysid.core.select.simulation import free_run_covariance

    rng = np.random.default_rng(11)
    n = 20000
    u = rng.uniform(-1, 1, n)
    x = np.zeros(n)
    for t in range(2, n):
        x[t] = 1.2 * x[t - 1] - 0.5 * x[t - 2] + 0.4 * u[t - 1] + 0.1 * u[t - 1] ** 2
    y = x + 0.05 * rng.standard_normal(n)
    space = TermSpace(ny=2, nu=1, degree=2)
    problem = Problem.from_signals(u, y, space)
    model = problem.model(np.isin(np.arange(space.n_terms), [0, 1, 2, 5]))
    whole, account = free_run_covariance(model, problem)
    assert account == {} and whole.dof == problem.rows - 4

    budget = folds.FINAL_JACOBIAN_BYTES
    try:
        folds.FINAL_JACOBIAN_BYTES = 8 * 4 * 4000  # 4 000 rows of 4 terms
        windowed, account = free_run_covariance(model, problem)
    finally:
        folds.FINAL_JACOBIAN_BYTES = budget
    assert 3000 < account["uncertainty_rows"] <= 4000
    assert windowed.dof == whole.dof and windowed.method == whole.method
    ratio = windowed.standard_errors / whole.standard_errors
    assert np.all(np.abs(ratio - 1) < 0.1), ratio
