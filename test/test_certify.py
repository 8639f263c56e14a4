"""Certifying the optimum: branch and bound against brute force and the paper's models."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.narx.certify import certify, certify_data, penalty_per_size
from spm_sysid.core.narx.criteria import get_criterion
from spm_sysid.core.narx.evaluator import StructureEvaluator
from spm_sysid.core.narx.identify import identify
from spm_sysid.core.narx.terms import TermSpace

from .conftest import EQ1, EQ2, ROOT


def _all_masks(m: int) -> np.ndarray:
    return ((np.arange(1, 2 ** m)[:, None] >> np.arange(m)) & 1).astype(bool)


def _brute_force(P, t, criterion):
    ev = StructureEvaluator(P, t, criterion)
    masks = _all_masks(P.shape[1])
    scores = np.concatenate([ev.evaluate(masks[i:i + 4096])
                             for i in range(0, len(masks), 4096)])
    return float(scores.min()), masks[int(np.argmin(scores))]


def _problem(kind: str, seed: int, ny: int = 2, nu: int = 2):
    rng = np.random.default_rng(seed)
    n = 300
    if kind == "random":  # unstructured regressors, a sparse truth
        P = rng.standard_normal((n, 14))
        beta = np.where(rng.random(14) < 0.3, rng.normal(0, 1, 14), 0.0)
        return P, P @ beta + 0.5 * rng.standard_normal(n)
    if kind == "near-dependent":  # columns within rounding distance of the rank test
        P = rng.standard_normal((n, 14))
        P[:, 13] = P[:, 12] + 3e-4 * rng.standard_normal(n)  # squared pivot ~1e-7
        P[:, 11] = P[:, 10] - P[:, 9] + 1e-4 * rng.standard_normal(n)
        P[:, 8] = 2.0 * P[:, 7] + 5e-5 * rng.standard_normal(n)  # just above the test
        beta = np.zeros(14)
        beta[[0, 7, 12, 13, 10]] = [1.0, 0.5, 2.0, -1.9, 0.3]
        return P, P @ beta + 0.3 * rng.standard_normal(n)
    if kind == "offset":  # a level input and an output far from zero (a heater)
        level = np.repeat(rng.uniform(0.2, 0.8, n // 20 + 1), 20)[:n]
        u = level + 0.02 * rng.standard_normal(n)
        x = np.zeros(n)
        for k in range(2, n):
            x[k] = 1.5 * x[k - 1] - 0.6 * x[k - 2] + 0.1 * (u[k - 1] - 1.2 * u[k - 1] ** 2)
        y = 50.0 + 10.0 * x + 0.05 * rng.standard_normal(n)
        ts = TermSpace(ny=ny, nu=nu, degree=2)
        return ts.regression_matrix(u, y), ts.target(y)
    # structured and hard on purpose: a NARX space of a smooth (strongly correlated)
    # input with much noise, so many structures are nearly equal
    e = rng.standard_normal(n + 50)
    u = np.zeros(n + 50)
    for k in range(1, n + 50):
        u[k] = 0.95 * u[k - 1] + e[k]
    u = u[50:] / np.abs(u[50:]).max()
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.2 * y[k - 1] - 0.5 * y[k - 2] + 0.4 * u[k - 1] + 0.1 * u[k - 2] * y[k - 1]
    y += 0.3 * y.std() * rng.standard_normal(n)
    ts = TermSpace(ny=ny, nu=nu, degree=2)  # 14 candidate terms
    return ts.regression_matrix(u, y), ts.target(y)


@pytest.mark.parametrize("kind", ["random", "structured", "offset", "near-dependent"])
@pytest.mark.parametrize("criterion", ["aic", "bic"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_certify_equals_brute_force(kind, criterion, seed):
    P, t = _problem(kind, seed)
    truth, truth_mask = _brute_force(P, t, criterion)
    # budget 0: the tree does the work (nodes enumerate at most pairs exactly);
    # the default budget enumerates a 14-term problem at the root
    for budget in (0, None):
        cert = certify(P, t, criterion, time_limit=60, enumeration_budget=budget)
        assert cert.status == "optimal"
        assert cert.value == pytest.approx(truth, abs=1e-6)
        assert cert.lower_bound <= truth + 1e-6
        assert StructureEvaluator(P, t, criterion).cached_score(cert.mask) == pytest.approx(
            truth, abs=1e-6)
    # from a poor warm start (one term) too
    worst = np.zeros(P.shape[1], dtype=bool)
    worst[0] = True
    again = certify(P, t, criterion, warm_start=worst, time_limit=60, enumeration_budget=0)
    assert again.status == "optimal" and again.value == pytest.approx(truth, abs=1e-6)


def test_bounds_never_cut_the_optimum_on_collinear_offset_data():
    """18 candidate terms of an output with a large offset (columns nearly equal,
    the case the drop and pair bounds exist for), against all 2^18 structures."""
    P, t = _problem("offset", 7, ny=3, nu=3)
    assert P.shape[1] == 27
    P, t = P[:, :18], t
    for criterion in ("aic", "bic"):
        truth, _ = _brute_force(P, t, criterion)
        for budget, threads in ((0, 1), (0, 2), (300, 2)):
            worst = np.zeros(P.shape[1], dtype=bool)
            worst[0] = True
            cert = certify(P, t, criterion, warm_start=worst, time_limit=120,
                           enumeration_budget=budget, threads=threads)
            assert cert.status == "optimal" and cert.nodes > 1
            assert cert.value == pytest.approx(truth, abs=1e-6)


def test_a_limited_run_returns_a_valid_bound_and_gap():
    P, t = _problem("structured", 3)
    truth, _ = _brute_force(P, t, "aic")
    worst = np.zeros(P.shape[1], dtype=bool)
    worst[0] = True
    cert = certify(P, t, "aic", warm_start=worst, node_limit=3, enumeration_budget=0)
    assert cert.status == "limit" and cert.reason == "node limit 3" and cert.nodes == 3
    assert cert.lower_bound <= truth + 1e-9 <= cert.value + 1e-9
    assert cert.gap == pytest.approx(cert.value - cert.lower_bound) and cert.gap > 0
    doc = cert.to_dict()
    json.dumps(doc, allow_nan=False)
    assert doc["status"] == "limit" and doc["lower_bound"] <= doc["value"]


def test_invalid_limits_are_refused_with_their_name():
    P, t = _problem("random", 0)
    for kwargs, name in (({"time_limit": 0}, "time_limit"), ({"node_limit": 0}, "node_limit"),
                         ({"threads": 0}, "threads")):
        with pytest.raises(ValueError, match=name):
            certify(P, t, "aic", **kwargs)


def test_criteria_that_depend_on_coefficients_are_refused():
    with pytest.raises(ValueError, match="pmic2 cannot be certified"):
        penalty_per_size(get_criterion("pmic2"), 100, 10)
    P, t = _problem("random", 0)
    with pytest.raises(ValueError, match="cannot be certified"):
        certify(P, t, "pmic2")


@pytest.mark.parametrize("criterion, names", [("aic", EQ1), ("bic", EQ2)])
def test_the_papers_models_are_certified_optimal(robot_arm, criterion, names):
    u, y = robot_arm
    ts = TermSpace()
    cert = certify_data(u, y, term_space=ts, criterion=criterion, time_limit=60)
    assert cert.status == "optimal" and sorted(cert.terms) == sorted(names)
    res = identify(u=u, y=y, criterion=criterion, seed=1, certify_time_limit=60)
    doc = res.model.metadata["certificate"]
    assert doc["status"] == "optimal" and doc["gap"] == 0.0
    assert doc["value"] == pytest.approx(res.ga.best_score) and sorted(doc["terms"]) == sorted(
        names)
    assert doc["value"] == pytest.approx(cert.value, abs=1e-6)
    res = identify(u=u, y=y, criterion="pmic2", seed=1, certify_time_limit=60,
                   ga=__import__("spm_sysid").GAConfig(generations=20))
    assert res.model.metadata["certificate"]["status"] == "refused"


def test_certify_command_and_identify_certify(tmp_path):
    def spm(*args):
        return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                              capture_output=True, text=True, cwd=ROOT, timeout=300)

    r = spm("certify", "--data", str(ROOT.parent / "shared" / "data" / "robot_arm.dat"),
            "--criterion", "aic", "--json", str(tmp_path / "c.json"))
    assert r.returncode == 0, r.stderr
    assert "status: optimal" in r.stdout and "value: -10744.7850" in r.stdout
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["status"] == "optimal" and doc["value"] == doc["lower_bound"]
    assert sorted(doc["terms"]) == sorted(EQ1) and doc["nodes"] > 0 and doc["seconds"] >= 0
    r = spm("certify", "--criterion", "pmic2")
    assert r.returncode == 2 and "invalid choice: 'pmic2'" in r.stderr
    r = spm("certify", "--threads", "0")
    assert r.returncode != 0 and "--threads must be at least 1, got 0" in r.stderr
    r = spm("identify", "--certify", "--criterion", "bic", "--seed", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "certified optimal over all structures" in r.stdout


def test_bench_certify_prints_the_table():
    """The benchmark command as `make bench-certify` runs it, on one case and criterion."""
    r = subprocess.run([sys.executable, "-m", "spm_sysid.tools.bench_certify", "--cases",
                        "robot-arm", "--criteria", "bic", "--time-limit", "30"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    row = next(line for line in r.stdout.splitlines() if line.startswith("robot-arm"))
    fields = row.split()
    assert fields[1:4] == ["1024", "bic", "optimal"]
    assert float(fields[5]) == pytest.approx(-10707.48, abs=0.01)
    assert "certified 1 of 1" in r.stdout
    r = subprocess.run([sys.executable, "-m", "spm_sysid.tools.bench_certify", "--cases",
                        "nonsense"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 2 and "unknown case(s) nonsense" in r.stderr


def test_hard_cases_are_made_the_same_way_each_time():
    from spm_sysid.tools.bench_certify import CASES

    for name in ("dryer-0", "exchanger-1", "ar-0.97"):
        u1, y1 = CASES[name]()
        u2, y2 = CASES[name]()
        assert np.array_equal(u1, u2) and np.array_equal(y1, y2) and np.all(np.isfinite(y1))


def test_running_out_of_room_for_open_nodes_stops_with_a_valid_bound(monkeypatch):
    import spm_sysid.core.narx.certify as certify_module
    from spm_sysid.tools.bench_certify import CASES

    monkeypatch.setattr(certify_module, "MAX_OPEN_BYTES", 1)  # no room beyond the first block
    u, y = CASES["exchanger-0"]()
    cert = certify_data(u, y, term_space=TermSpace(), criterion="bic", time_limit=60)
    assert cert.status == "limit" and cert.reason.startswith("memory limit (")
    assert cert.lower_bound < cert.value and cert.gap > 0 and len(cert.terms) > 0
