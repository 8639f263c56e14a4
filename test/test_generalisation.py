"""Models that hold on new data: uncertainty, data check, validated selection, guards."""

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from benchmarks.tanks import record as tank_record
from spm_sysid.core.errors import DataError
from spm_sysid.core.fit.criteria import aicc
from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.identify import identify
from spm_sysid.core.jobs import describe_selection
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.model.uncertainty import output_band
from spm_sysid.core.search.certify import certify
from spm_sysid.core.select.folds import blocked_folds
from spm_sysid.core.select.guard import stress_check, surrogate_input
from spm_sysid.core.select.simulation import linear_orders
from spm_sysid.core.validate.excitation import check_problem, excitation_order

from .conftest import EQ1, ROOT, eq1_model, sine_record


def test_covariance_is_sigma2_inverse_gram_of_the_regressors(robot_arm):
    """Against the plain formula sigma^2 (P^T P)^-1 with numpy's own least squares."""
    u, y = robot_arm
    m = eq1_model(robot_arm)
    P = TermSpace().regression_matrix(u, y)[:, :8]
    t = TermSpace().target(y)
    theta, *_ = np.linalg.lstsq(P, t, rcond=None)
    e = t - P @ theta
    sigma2 = e @ e / (len(t) - 8)
    cov = sigma2 * np.linalg.inv(P.T @ P)
    assert m.terms == EQ1
    np.testing.assert_allclose(m.coefficients, theta, rtol=1e-8)
    np.testing.assert_allclose(m.uncertainty.covariance, cov, rtol=1e-6)
    assert m.uncertainty.dof == len(t) - 8
    # 95 % intervals: Student's t with N - k degrees of freedom
    half = stats.t.ppf(0.975, len(t) - 8) * np.sqrt(np.diag(cov))
    np.testing.assert_allclose(m.uncertainty.intervals(m.coefficients)[:, 1] - theta, half,
                               rtol=1e-6)


def test_the_95_percent_intervals_cover_the_true_coefficients():
    """300 replicates of a NARX system with known coefficients: coverage 93-97 %."""
    from benchmarks.generalise import coverage  # the benchmark's own computation

    pooled, per_coefficient = coverage(replicates=300, n=300, seed=2026)
    assert 0.93 <= pooled <= 0.97, pooled
    assert np.all(np.array(per_coefficient) >= 0.90), per_coefficient


def test_the_free_run_covariance_comes_from_the_jacobian(robot_arm):
    """Simulation focus: intervals from the Levenberg-Marquardt Jacobian, in the document."""
    u, y = robot_arm
    res = identify(u=u, y=y, criterion="bic", seed=0, focus="simulation")
    m = res.model
    assert m.uncertainty.method == "free-run Jacobian"
    assert m.uncertainty.dof == 1020 - len(m.terms)
    assert np.all(m.uncertainty.standard_errors > 0)
    doc = json.loads(m.to_json())
    back = NarxModel.from_dict(doc)
    np.testing.assert_array_equal(back.uncertainty.covariance, m.uncertainty.covariance)
    table = m.coefficient_table()
    assert "std. error" in table and "free-run Jacobian" in table


def test_the_answer_reports_the_linear_arx_on_the_same_held_out_blocks(robot_arm):
    """Issue 41: the free run is judged against the linear ARX's; the answer says what the
    one-line ARX fit (least squares, the best of its orders) scored on the same blocks."""
    u, y = robot_arm
    m = identify(u=u, y=y, criterion="bic", seed=0, focus="simulation").model
    call = m.metadata["selection"]["linear_or_nonlinear"]
    assert 1 <= call["linear_arx_order"] <= m.term_space.max_lag
    # the ARX of each order is a linear finalist: the best linear one is at least as good
    assert call["best_linear_held_out_mse"] <= call["linear_arx_held_out_mse"]
    assert call["linear_arx_held_out_stderr"] > 0
    text = describe_selection(m.metadata["selection"])
    assert (f"the linear ARX (least squares, order {call['linear_arx_order']}) had MSE "
            f"{call['linear_arx_held_out_mse']:.4g} on the same blocks") in text
    back = NarxModel.from_dict(json.loads(m.to_json()))  # the schema takes the fields
    assert back.metadata["selection"]["linear_or_nonlinear"] == call


def test_each_full_linear_structure_keeps_its_order_when_an_earlier_one_repeats():
    """Unusable terms can make order 2's structure order 1's: it is listed once, and the
    next one is still called order 3 (the answer names the ARX by its order)."""
    space = TermSpace(ny=3, nu=3, degree=1)
    names = space.term_names()
    usable = np.array([n not in ("y(t-2)", "u(t-2)") for n in names])
    got = [(k, [names[i] for i in np.flatnonzero(m)]) for k, m in linear_orders(space, usable)]
    assert got == [(1, ["y(t-1)", "u(t-1)"]), (3, ["y(t-1)", "y(t-3)", "u(t-1)", "u(t-3)"])]


def test_output_bands_contain_the_model_and_widen_with_noise(robot_arm):
    u, y = robot_arm
    m = eq1_model(robot_arm)
    one = output_band(m, u, y, horizon=1, draws=100)
    free = output_band(m, u, y, horizon=None, draws=50)
    yhat = m.predict(u, y)
    inside = (one.lower <= yhat) & (yhat <= one.upper)
    assert inside.mean() > 0.9 and one.diverged == 0.0
    assert free.mean_width > one.mean_width > 0  # errors accumulate when simulating
    assert output_band(m.with_coefficients(m.coefficients), u, y) is None  # no uncertainty


def test_a_sine_input_excites_two_lags_and_the_check_names_the_others():
    u, y = sine_record()
    assert excitation_order(u, [(0, 400)], 6) == 2
    white = np.random.default_rng(1).standard_normal(400)
    assert excitation_order(white, [(0, 400)], 6) == 6
    check = check_problem(Problem.from_signals(u, y, TermSpace(ny=4, nu=4, degree=1)))
    assert check.excitation == {"u": 2}
    # of u(t-1) .. u(t-4), two are combinations of the others
    assert len([n for n in check.collinear_terms if n.startswith("u(")]) == 2
    assert any("input u is persistently exciting of order 2 only: of its 4 lags only 2"
               in w for w in check.warnings)


def test_a_constant_input_is_named_and_its_lagged_terms_left_out():
    rng = np.random.default_rng(3)
    u = np.full(300, 2.0)
    y = np.cumsum(rng.standard_normal(300)) * 0.1
    check = check_problem(Problem.from_signals(u, y, TermSpace(ny=2, nu=3, degree=2)))
    assert check.excitation == {"u": 1}
    assert {"u(t-2)", "u(t-3)"} <= set(check.repeated_terms)
    assert any("input u is constant" in w for w in check.warnings)
    # with a constant term too, u(t-1) repeats the constant: nothing of u is identifiable
    with_c = check_problem(Problem.from_signals(u, y, TermSpace(ny=2, nu=3, degree=1,
                                                                constant=True)))
    assert {"u(t-1)", "u(t-2)", "u(t-3)"} <= set(with_c.repeated_terms)


def test_a_still_input_is_why_nothing_simulates(tmp_path):
    """The simulation focus said only that every structure diverged."""
    rng = np.random.default_rng(3)
    path = tmp_path / "still.csv"
    np.savetxt(path, np.column_stack([np.zeros(300), np.ones(300),
                                      np.cumsum(rng.standard_normal(300)) * 0.1]),
               delimiter=",", header="a,b,y", comments="")
    r = _cli("identify", "--data", str(path), "--inputs", "a,b", "--output", "y", "--focus",
             "simulation", "--orders", "auto", "--quiet")
    assert r.returncode == 2
    assert "no model simulates; the inputs a, b are constant (0, 1 throughout): nothing " \
           "excites the system" in r.stderr, r.stderr


def test_data_that_identify_nothing_are_refused_with_the_reason():
    u = np.zeros(200)
    y = np.r_[np.zeros(199), 1.0]  # every lagged output is 0, and so is the input
    with pytest.raises(DataError, match="no candidate term varies on this data"):
        check_problem(Problem.from_signals(u, y, TermSpace(ny=1, nu=1, degree=1)))


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)


def test_check_data_command_prints_the_report():
    """`spm-sysid check-data --ny 6 --nu 6 --degree 3`, as the README writes it."""
    r = _cli("check-data", "--ny", "6", "--nu", "6", "--degree", "3")
    assert r.returncode == 0, r.stderr
    assert "rows: 1018; candidate terms: 454 (454 usable); 2.2 rows per usable candidate" \
        in r.stdout
    assert "input u: persistently exciting of order >= 8 (6 lag(s) in the space)" in r.stdout
    assert "warning: 1018 rows for 454 candidate terms (fewer than 10 per candidate)" \
        in r.stdout
    assert "condition number of the candidate matrix" in r.stdout
    r = _cli("check-data")  # the paper's space: no warning
    assert r.returncode == 0 and "\nwarning:" not in r.stdout
    assert r.stdout.rstrip().endswith("no warning: the data can identify this space")
    assert "candidate terms: 44 (44 usable)" in r.stdout


def test_identify_validated_with_max_terms_as_the_readme_writes_it():
    r = _cli("identify", "--selection", "validated", "--max-terms", "20")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert out.index("data check: 1020 rows, 44 of 44 candidate terms usable") < out.index(
        "y(t) =")
    assert "selected by its one-step error on 3 held-out blocks" in out
    assert "std. error" in out and "least squares, " in out
    k = int(out.split(" terms, one-step MSE")[0].rsplit(", ", 1)[1])
    assert 1 <= k <= 20


def test_aicc_is_certified_against_brute_force_and_max_terms_respected():
    rng = np.random.default_rng(5)
    n = 40  # few rows: the correction matters
    u = rng.standard_normal(n)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 0.6 * y[k - 1] + 0.8 * u[k - 1] - 0.2 * u[k - 2] * y[k - 1]
    y += 0.05 * rng.standard_normal(n)
    ts = TermSpace(ny=2, nu=2, degree=2)  # 14 candidates
    P, t = ts.regression_matrix(u, y), ts.target(y)
    rows, m = P.shape

    def brute(limit):
        best = (np.inf, None)
        for k in range(1, limit + 1):
            for cols in itertools.combinations(range(m), k):
                A = P[:, cols]
                theta, *_ = np.linalg.lstsq(A, t, rcond=None)
                sse = float(np.sum((t - A @ theta) ** 2))
                # AICc = N ln(SSE/N) + 2k + 2k(k+1)/(N-k-1), written out here
                value = rows * np.log(sse / rows) + 2 * k + 2 * k * (k + 1) / (rows - k - 1)
                best = min(best, (value, cols))
        return best

    value, cols = brute(m)
    assert aicc(np.array([1.0]), 30, np.array([3]))[0] == pytest.approx(
        30 * np.log(1 / 30) + 6 + 24 / 26)
    cert = certify(P, t, "aicc", time_limit=600)
    assert cert.status == "optimal" and cert.value == pytest.approx(value, abs=1e-6)
    assert tuple(np.flatnonzero(cert.mask)) == cols
    small = brute(2)
    res = identify(u=u, y=y, term_space=ts, criterion="aicc", seed=0, max_terms=2,
                   certify_time_limit=30, selection="criterion")
    assert len(res.model.terms) <= 2
    assert res.model.criterion_value == pytest.approx(small[0], abs=1e-6)
    assert res.model.metadata["max_terms"] == 2


def test_blocked_folds_hold_out_each_block_once_and_never_train_across_it(robot_arm):
    u, y = robot_arm
    problem = Problem.from_signals(u, y)
    folds = blocked_folds(problem)
    assert len(folds) == 3
    covered = np.zeros(len(y), dtype=int)
    for f in folds:
        for c, d in f.held_out:
            covered[c:d] += 1
            for a, b in f.train_segments:  # no fit sees the held-out samples
                assert b <= c or a >= d
        assert 0.5 * problem.rows < f.train.sum() < problem.rows
    assert covered.max() == 1 and covered.sum() > 0.95 * len(y)


def test_random_phase_inputs_keep_the_spectrum_and_the_range():
    rng = np.random.default_rng(0)
    u = tank_record(1)[0][:, None]
    s = surrogate_input(u, rng)
    assert s.shape == u.shape and s.min() >= u.min() and s.max() <= u.max()
    assert abs(np.corrcoef(s[:, 0], u[:, 0])[0, 1]) < 0.2  # another order of the samples
    a, b = np.abs(np.fft.rfft(u[:, 0] - u.mean())), np.abs(np.fft.rfft(s[:, 0] - s.mean()))
    assert np.corrcoef(a, b)[0, 1] > 0.9  # clipping aside, the same spectrum


def test_the_guard_rejects_a_model_that_diverges_off_the_estimation_data():
    """A pole the estimation record hides: y(t) = 0.5 y(t-1) + 0.6 y(t-1) u(t-1).

    Stable while u < 0.83. The estimation input stays at 0.1; a record whose
    input later rises to 2 makes the same model explode when it is re-ordered.
    """
    ts = TermSpace(ny=1, nu=1, degree=2)
    names = ts.term_names()
    model = NarxModel(ts, [names.index("y(t-1)"), names.index("y(t-1)*u(t-1)")],
                      np.array([0.5, 0.6]))
    y = np.r_[1.0, np.full(399, 1e-3)]
    assert stress_check(model, np.full(400, 0.1), y, [(0, 400)]) is None
    reason = stress_check(model, np.r_[np.full(200, 0.1), np.full(200, 2.0)], y, [(0, 400)])
    assert reason is not None and "left the output's range" in reason


@pytest.mark.parametrize("order, degree", [(2, 2), (3, 3)])
def test_the_default_simulation_focus_never_returns_a_model_that_diverges_on_new_data(
        order, degree):
    """Two-tank cascade, constant, BIC: the issue's case (3, 3), and (2, 2) whose
    validated choice diverged on the test record until the guard drove it with
    random-phase inputs like the estimation input."""
    u, y = tank_record(1)
    u_test, y_test = tank_record(2)
    ts = TermSpace(ny=order, nu=order, degree=degree, constant=True)
    res = identify(u=u, y=y, term_space=ts, criterion="bic", seed=0, focus="simulation")
    m = res.model
    yhat, diverged_at = m.run(u_test, y_test, None)
    assert diverged_at is None
    assert np.all(np.isfinite(yhat))
    rmse = float(np.sqrt(np.mean((m.measured(y_test) - yhat) ** 2)))
    assert rmse < 0.5 * np.std(y_test)  # it simulates the test record, not just stays bounded
    sel = m.metadata["selection"]
    assert sel["method"] == "validated" and sel["what"] == "free-run"
    assert sel["held_out_mse"] is not None and sel["finalists"] >= 2
    # structures that explode off the data exist here: on held-out blocks or under the guard
    assert sel["removed_by_guard"] + sel["left_range_held_out"] >= 1
    assert m.criterion_value is not None


def test_the_arx_yardstick_is_plain_least_squares_and_finds_the_true_order():
    """Against an independent fit (normal equations, a loop over the rows)."""
    from spm_sysid.core.validate.arx import choose_arx, fit_arx, fit_percent, rmse

    rng = np.random.default_rng(4)
    n = 1500
    u = rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(2, n):  # an ARX(2) system with a constant, a little noise
        y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + 0.7 * u[t - 1] + 0.2 * u[t - 2] + 0.3
    y += 0.01 * rng.standard_normal(n)
    for order in (1, 2, 3):
        rows = []
        for t in range(order, n):
            rows.append([*(y[t - i] for i in range(1, order + 1)),
                         *(u[t - i] for i in range(1, order + 1)), 1.0])
        X = np.array(rows)
        expected = np.linalg.solve(X.T @ X, X.T @ y[order:])
        np.testing.assert_allclose(fit_arx(u, y, order).theta[:, 0], expected, rtol=1e-7,
                                   atol=1e-9)
    # regressors: y(t-1), y(t-2), u(t-1), u(t-2), then the constant
    np.testing.assert_allclose(fit_arx(u, y, 2).theta[:, 0], [1.2, -0.5, 0.7, 0.2, 0.3],
                               atol=0.05)
    model = choose_arx(u[:1000], y[:1000])
    assert model.order >= 2  # order 1 cannot simulate it
    sim = model.simulate(u[1000:], y[1000:])
    assert np.array_equal(sim[:model.order, 0], y[1000:1000 + model.order])  # measured start
    assert fit_percent(y[1000:], sim, 10)[0] > 98.0 and rmse(y[1000:], sim, 10)[0] < 0.05
    wild = fit_arx(u, y, 2)
    wild = type(wild)(2, wild.theta * 10.0)  # an unstable model: its run diverges
    assert np.isnan(wild.simulate(u, y)[-1, 0]) and rmse(y, wild.simulate(u, y))[0] == np.inf


def test_orders_auto_finds_the_true_lags_and_degree_and_says_why():
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.record import Record

    rng = np.random.default_rng(7)
    n = 1500
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for t in range(2, n):  # lags 2 and 2, degree 2
        y[t] = (0.5 * y[t - 1] - 0.2 * y[t - 2] + 0.8 * u[t - 1] + 0.3 * u[t - 2]
                + 0.25 * y[t - 1] * u[t - 1])
    y += 0.002 * rng.standard_normal(n)
    result = run_job(Record.from_samples(u, y, source="narx"),
                     JobSettings.from_values({"orders": "auto", "criterion": "bic", "seed": 0}))
    space = result.model.term_space
    assert (space.ny, space.nu, space.degree) == (2, 2, 2)
    orders = result.model.metadata["orders"]  # the document says what and why
    assert orders["mode"] == "auto" and (orders["ny"], orders["degree"]) == (2, 2)
    assert "order 2" in orders["reason"] and len(orders["order_scan"]) == 10
    assert "orders from the data: ny = nu = 2, degree 2" in result.summary("lines")
    assert set(result.model.terms) >= {"y(t-1)", "y(t-2)", "u(t-1)", "u(t-2)",
                                        "y(t-1)*u(t-1)"}
