import json

import numpy as np
import pytest

from spm_sysid.core.errors import ModelFormatError
from spm_sysid.core.fit.problem import fit_structure
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace

from .conftest import EQ1, eq1_model


def test_equation_reads_like_the_paper(robot_arm):
    m = eq1_model(robot_arm)
    assert m.terms == EQ1
    assert m.equation() == (
        "y(t) = 3.158y(t-1) - 4.439y(t-2) + 3.130y(t-3) - 0.982y(t-4) + 0.019u(t-1) "
        "- 0.029u(t-2) + 0.055u(t-3) - 0.030u(t-4)")


def test_one_step_errors_match_the_papers_figure_6(robot_arm):
    u, y = robot_arm
    e = eq1_model(robot_arm).residuals(u, y)
    assert np.max(np.abs(e)) == pytest.approx(0.01467, abs=5e-5)
    assert np.mean(np.abs(e)) == pytest.approx(0.004255, abs=5e-6)
    assert np.mean(e ** 2) == pytest.approx(2.6199e-05, rel=1e-4)


def test_json_round_trip_then_predict_and_simulate_on_new_data(robot_arm, tmp_path):
    u, y = robot_arm
    m = eq1_model(robot_arm)
    m.metadata["note"] = "test"
    path = m.save(tmp_path / "sub" / "model.json")
    doc = json.loads(path.read_text())
    assert doc["schema"] == "spm_sysid/narx-model" and doc["schema_version"] == 3
    assert doc["terms"] == EQ1 and doc["criterion"] == {"name": "aic", "value": -10744.78}
    unc = doc["uncertainty"]
    assert unc["method"] == "least squares" and unc["dof"] == 1020 - 8
    assert len(unc["standard_errors"]) == 8 and len(unc["intervals"]) == 8
    back = NarxModel.load(path)
    assert back.terms == m.terms and np.array_equal(back.coefficients, m.coefficients)
    assert back.term_space == m.term_space and back.metadata["note"] == "test"
    assert np.array_equal(back.uncertainty.covariance, m.uncertainty.covariance)
    # new data: the second half only
    u2, y2 = u[512:], y[512:]
    assert np.array_equal(back.predict(u2, y2), m.predict(u2, y2))
    assert np.array_equal(back.simulate(u2, y2), m.simulate(u2, y2))


def test_free_run_simulation_of_a_known_linear_system_is_exact():
    rng = np.random.default_rng(1)
    u = rng.normal(size=300)
    y = np.zeros(300)
    y[:2] = [0.3, -0.1]
    for t in range(2, 300):
        y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + 0.7 * u[t - 1] + 0.1 * u[t - 1] * u[t - 2]
    ts = TermSpace(ny=2, nu=2, degree=2)
    names = ts.term_names()
    idx = [names.index(n) for n in ("y(t-1)", "y(t-2)", "u(t-1)", "u(t-1)*u(t-2)")]
    model = NarxModel(ts, sorted(idx), np.array([1.2, -0.5, 0.7, 0.1]))
    # feeding back its own predictions reproduces the system exactly
    assert np.allclose(model.simulate(u, y[:2]), y[2:], rtol=0, atol=1e-12)
    # and the least-squares fit recovers the coefficients of noise-free data
    mask = np.zeros(ts.n_terms, dtype=bool)
    mask[idx] = True
    fit = fit_structure(u, y, mask, ts)
    assert np.allclose(fit.coefficients, [1.2, -0.5, 0.7, 0.1], atol=1e-10)
    with pytest.raises(ValueError, match="initial"):
        model.simulate(u, y[:1])


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(schema="other"), "not a spm_sysid model"),
    (lambda d: d.update(schema_version=99), "version 99"),
    (lambda d: d.pop("coefficients"), "incomplete"),
    (lambda d: d.update(terms=["u(t-1)"] * 8), "do not match"),
    (lambda d: d.update(term_indices=[0, 1, 2, 3, 4, 5, 6, 99]), "outside"),
    (lambda d: d.update(coefficients=[1.0]), "differ in length"),
])
def test_malformed_model_documents(robot_arm, tmp_path, mutate, message):
    doc = eq1_model(robot_arm).to_dict()
    mutate(doc)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFormatError, match=message):
        NarxModel.load(path)


def test_unreadable_model_files(tmp_path):
    with pytest.raises(ModelFormatError, match="not found"):
        NarxModel.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ModelFormatError, match="not valid JSON"):
        NarxModel.load(bad)


def test_fit_rejects_empty_and_dependent_structures():
    rng = np.random.default_rng(0)
    u = rng.normal(size=100)
    y = np.concatenate([[0.0], u[:-1]])
    ts = TermSpace(ny=2, nu=2, degree=1)
    with pytest.raises(ValueError, match="no terms"):
        fit_structure(u, y, np.zeros(4, dtype=bool), ts)
    with pytest.raises(ValueError, match="linearly dependent"):
        fit_structure(u, y, np.array([True, False, False, True]), ts)


def test_version_1_documents_still_load(robot_arm):
    u, y = robot_arm
    doc = eq1_model(robot_arm).to_dict()
    doc["schema_version"] = 1
    for key in ("inputs", "output"):
        del doc["term_space"][key]  # version 1 had neither
    m = NarxModel.from_dict(doc)
    assert m.terms == EQ1 and m.term_space.inputs == ("u",)
    assert np.array_equal(m.predict(u, y), eq1_model(robot_arm).predict(u, y))


def test_two_input_term_space_names_lags_and_products():
    ts = TermSpace(ny=1, nu=(2, 1), delay=(1, 0), degree=2, inputs=("torque", "cmd"))
    assert ts.n_inputs == 2 and ts.max_lag == 2
    assert [ts.term_names()[i] for i in range(4)] == ["y(t-1)", "torque(t-1)", "torque(t-2)",
                                                      "cmd(t)"]
    assert "y(t-1)*cmd(t)" in ts.term_names() and "torque(t-1)*cmd(t)" in ts.term_names()
    assert ts.n_terms == 4 + 10
    assert TermSpace(nu=2, inputs=("a", "b")).nus == (2, 2)  # one value for all inputs
    assert TermSpace(nu=(1, 1)).inputs == ("u1", "u2")        # unnamed inputs
    with pytest.raises(ValueError, match="delay gives 2 values for 3 inputs"):
        TermSpace(nu=(1, 1, 1), delay=(1, 1))
    back = TermSpace.from_dict(ts.to_dict())
    assert back == ts and back.term_names() == ts.term_names()


def test_two_input_system_with_a_cross_product_is_recovered_exactly():
    from spm_sysid.core.identify import identify

    rng = np.random.default_rng(3)
    n = 800
    u = rng.uniform(-1, 1, (n, 2))
    y = np.zeros(n)
    for t in range(2, n):  # y(t) = 0.5 y(t-1) + 0.7 u1(t-1) - 0.4 u2(t) + 0.3 u1(t-2) u2(t)
        y[t] = (0.5 * y[t - 1] + 0.7 * u[t - 1, 0] - 0.4 * u[t, 1]
                + 0.3 * u[t - 2, 0] * u[t, 1])
    y += 1e-3 * rng.standard_normal(n)
    ts = TermSpace(ny=2, nu=(2, 2), delay=(1, 0), degree=2, inputs=("u1", "u2"))
    res = identify(u=u, y=y, term_space=ts, criterion="bic", seed=1)
    assert sorted(res.model.terms) == sorted(["y(t-1)", "u1(t-1)", "u2(t)", "u1(t-2)*u2(t)"])
    coef = dict(zip(res.model.terms, res.model.coefficients))
    assert coef["y(t-1)"] == pytest.approx(0.5, abs=2e-3)
    assert coef["u1(t-2)*u2(t)"] == pytest.approx(0.3, abs=5e-3)
    # the free-run simulation with both inputs reproduces the system
    sim = res.model.simulate(u, y)
    assert np.sqrt(np.mean((sim - y[ts.max_lag:]) ** 2)) < 5e-3
    doc = res.model.to_dict()
    assert doc["term_space"]["inputs"] == ["u1", "u2"] and doc["term_space"]["nu"] == [2, 2]
    assert NarxModel.from_dict(doc).terms == res.model.terms
