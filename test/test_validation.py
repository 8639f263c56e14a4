"""Correlation tests, metrics, validation and figures."""

import numpy as np
import pytest
from PIL import Image

from spm_sysid.core.errors import DataError
from spm_sysid.core.fit.problem import fit_structure
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.validate.correlation import ccf, correlation_tests
from spm_sysid.core.validate.validation import metrics, split_segments, validate_model
from spm_sysid.tools.plots import plot_convergence, write_model_figures

from .conftest import eq1_model


def _direct_ccf(a, b, tau):
    a = np.asarray(a, float) - np.mean(a)
    b = np.asarray(b, float) - np.mean(b)
    total = 0.0
    for t in range(len(a)):
        if 0 <= t - tau < len(b):
            total += a[t] * b[t - tau]
    return total / np.sqrt(np.sum(a * a) * np.sum(b * b))


def test_ccf_equals_direct_computation():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=37), rng.normal(size=37)
    lags = np.arange(-6, 7)
    assert np.allclose(ccf(a, b, lags), [_direct_ccf(a, b, t) for t in lags], atol=1e-14)
    assert ccf(a, a, [0])[0] == pytest.approx(1.0)
    assert np.all(ccf(np.ones(10), b[:10], lags) == 0)


def test_white_noise_stays_inside_the_band_about_95_percent():
    rng = np.random.default_rng(1)
    fractions = []
    for _ in range(20):
        e, u = rng.normal(size=2000), rng.normal(size=2000)
        fractions += [t.fraction_inside for t in correlation_tests(e, u, 25)]
    assert 0.92 < np.mean(fractions) < 0.98


def test_missing_term_fails_the_residual_autocorrelation_test():
    rng = np.random.default_rng(2)
    n = 2000
    u = rng.normal(size=n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.6 * y[t - 1] - 0.4 * y[t - 2] + u[t - 1] + 0.05 * rng.normal()
    ts = TermSpace(ny=2, nu=1, degree=1)
    full = fit_structure(u, y, np.array([True, True, True]), ts)
    missing = fit_structure(u, y, np.array([True, False, True]), ts)  # no y(t-2)
    assert validate_model(full, u, y).test("ee").passed
    bad = validate_model(missing, u, y).test("ee")
    assert not bad.passed and abs(bad.worst_lag) in (1, 2)


def test_metrics_fit_percent():
    y = np.array([1.0, 2.0, 3.0, 4.0])
    m = metrics(y, y)
    assert m["fit_percent"] == 100.0 and m["mse"] == 0.0
    yhat = np.array([1.5, 2.0, 2.5, 4.0])
    m = metrics(y, yhat)
    expected = 100 * (1 - np.sqrt(0.5) / np.sqrt(5.0))
    assert m["fit_percent"] == pytest.approx(expected)
    assert m["max_abs"] == 0.5 and m["mean_abs"] == 0.25 and m["rmse"] == pytest.approx(
        np.sqrt(0.125))
    diverged = metrics(y, np.array([1, np.inf, 1, 1]))
    assert np.isnan(diverged["fit_percent"]) and np.isnan(diverged["mse"])
    assert diverged["diverged_at"] == 1


def test_validation_of_eq1_matches_the_paper(robot_arm):
    u, y = robot_arm
    model = eq1_model(robot_arm)
    rep = validate_model(model, u, y)
    assert rep.one_step_metrics["max_abs"] == pytest.approx(0.01467, abs=5e-5)
    assert rep.one_step_metrics["mean_abs"] == pytest.approx(0.004255, abs=5e-6)
    # free-run fits far worse than one-step, as the design notes warn
    assert rep.free_run_metrics["mse"] > 100 * rep.one_step_metrics["mse"]
    assert not rep.test("ee").passed  # as in the paper's Fig. 5
    doc = rep.to_dict()
    assert doc["one_step"]["mse"] == pytest.approx(2.6199e-05, rel=1e-4)
    assert {t["name"] for t in doc["correlation_tests"]} == {"ee", "ue", "e_eu", "u2_e",
                                                             "u2_e2"}


def test_holdout_split_keeps_initial_conditions(robot_arm):
    u, y = robot_arm
    [(a, b)], [(c, d)] = split_segments([(0, len(y))], len(y), 0.5, 4)
    ye, yv = y[a:b], y[c:d]
    assert len(ye) == 512 and len(yv) == 516
    assert np.array_equal(yv[4:], y[512:])
    with pytest.raises(ValueError):
        split_segments([(0, len(y))], len(y), 1.5, 4)


def test_figures_are_valid_images(robot_arm, tmp_path):
    u, y = robot_arm
    rep = validate_model(eq1_model(robot_arm), u, y)
    paths = write_model_figures(rep, tmp_path)
    paths += plot_convergence({"AIC, population 20": {0.0: [[3, 2, 1], [4, 2, 2]],
                                                       0.15: [[3, 1, 1], [2, 1, 1]]}},
                              tmp_path / "conv")
    assert len(paths) == 8
    for p in paths:
        assert p.stat().st_size > 1000
        if p.suffix == ".png":
            with Image.open(p) as im:
                im.verify()
            with Image.open(p) as im:
                assert im.size[0] > 300 and im.size[1] > 200
        else:
            assert p.read_text().lstrip().startswith(("<?xml", "<svg"))


def test_white_noise_passes_about_95_percent_of_the_time():
    rng = np.random.default_rng(4)
    passed = [t.passed for _ in range(100)
              for t in correlation_tests(rng.normal(size=1000), rng.normal(size=1000), 20)]
    assert 0.9 < np.mean(passed) <= 1.0


def test_errors_from_leaves_each_segments_first_samples_out(robot_arm):
    """The benchmarks' convention: the free run starts at once, errors count from sample k."""
    u, y = robot_arm
    model = eq1_model(robot_arm)
    segments = [(0, 500), (520, 1024)]
    rep = validate_model(model, u, y, segments=segments, errors_from=50, bands=False)
    lag = model.term_space.max_lag
    rows, sims = [], []
    for a, b in segments:  # independent: each segment's own free run, sliced by hand
        sim, _ = model.run(u[a:b], y[a:b])
        rows.append(y[a + 50:b])
        sims.append(sim[50 - lag:])
    e = np.concatenate(rows) - np.concatenate(sims)
    assert rep.free_run_metrics["rmse"] == pytest.approx(np.sqrt(np.mean(e * e)), rel=1e-12)
    assert rep.free_run_metrics["max_abs"] == pytest.approx(np.abs(e).max(), rel=1e-12)
    whole = validate_model(model, u, y, segments=segments, bands=False)
    assert len(rep.free_run) == len(whole.free_run)  # the arrays keep every row
    assert rep.free_run_metrics["rmse"] != whole.free_run_metrics["rmse"]
    assert rep.to_dict()["errors_from"] == 50
    assert "errors from sample 50 of each segment" in rep.summary()
    assert "RMSE " in rep.summary()
    # within the initial conditions: every row counts
    same = validate_model(model, u, y, segments=segments, errors_from=lag, bands=False)
    assert same.free_run_metrics == whole.free_run_metrics
    with pytest.raises(DataError, match="errors from sample 600 leave no sample to score: "
                                        "the longest segment has 504 samples"):
        validate_model(model, u, y, segments=segments, errors_from=600, bands=False)
