"""Certifying the optimum: branch and bound against brute force and the paper's models."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.fit.criteria import get_criterion
from spm_sysid.core.fit.evaluator import StructureEvaluator
from spm_sysid.core.identify import identify
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.search.certify import certify, penalty_per_size
from spm_sysid.core.search.split import certify_data

from .conftest import EQ1, EQ2, ROOT
from .helpers.narx import smooth_narx_record


def _all_masks(m: int) -> np.ndarray:
    return ((np.arange(1, 2 ** m)[:, None] >> np.arange(m)) & 1).astype(bool)


def _brute_force(P, t, criterion):
    ev = StructureEvaluator(P, t, criterion)
    masks = _all_masks(P.shape[1])
    scores = np.concatenate([ev.evaluate(masks[i:i + 4096])
                             for i in range(0, len(masks), 4096)])
    return float(scores.min()), masks[int(np.argmin(scores))]


def _problem(kind: str, seed: int, ny: int = 2, nu: int = 2, degree: int = 2):
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
        ts = TermSpace(ny=ny, nu=nu, degree=degree)
        return ts.regression_matrix(u, y), ts.target(y)
    # structured and hard on purpose: a NARX space of a smooth (strongly correlated)
    # input with much noise, so many structures are nearly equal
    u, y = smooth_narx_record(seed, n)
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
        cert = certify(P, t, criterion, time_limit=600, enumeration_budget=budget)
        assert cert.status == "optimal"
        assert cert.value == pytest.approx(truth, abs=1e-6)
        assert cert.lower_bound <= truth + 1e-6
        assert StructureEvaluator(P, t, criterion).cached_score(cert.mask) == pytest.approx(
            truth, abs=1e-6)
    # from a poor warm start (one term) too
    worst = np.zeros(P.shape[1], dtype=bool)
    worst[0] = True
    again = certify(P, t, criterion, warm_start=worst, time_limit=600, enumeration_budget=0)
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
    cert = certify_data(u, y, term_space=ts, criterion=criterion, time_limit=600)
    assert cert.status == "optimal" and sorted(cert.terms) == sorted(names)
    res = identify(u=u, y=y, criterion=criterion, seed=1, certify_time_limit=600)
    doc = res.model.metadata["certificate"]
    assert doc["status"] == "optimal" and doc["gap"] == 0.0
    assert doc["value"] == pytest.approx(res.ga.best_score) and sorted(doc["terms"]) == sorted(
        names)
    assert doc["value"] == pytest.approx(cert.value, abs=1e-6)
    res = identify(u=u, y=y, criterion="pmic2", seed=1, certify_time_limit=600,
                   ga=__import__("spm_sysid").GAConfig(generations=20))
    assert res.model.metadata["certificate"]["status"] == "refused"


def test_certify_command_and_identify_certify(tmp_path, robot_arm_path):
    def spm(*args):
        return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                              capture_output=True, text=True, cwd=ROOT, timeout=300)

    r = spm("certify", "--data", str(robot_arm_path),
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
    r = subprocess.run([sys.executable, "-m", "benchmarks.certify", "--cases",
                        "robot-arm", "--criteria", "bic", "--time-limit", "30"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    row = next(line for line in r.stdout.splitlines() if line.startswith("robot-arm"))
    fields = row.split()
    assert fields[1:4] == ["1024", "bic", "optimal"]
    assert float(fields[5]) == pytest.approx(-10707.48, abs=0.01)
    assert "certified 1 of 1" in r.stdout
    r = subprocess.run([sys.executable, "-m", "benchmarks.certify", "--cases",
                        "nonsense"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 2 and "unknown case(s) nonsense" in r.stderr


def test_hard_cases_are_made_the_same_way_each_time():
    from benchmarks.certify import CASES

    for name in ("dryer-0", "exchanger-1", "ar-0.97"):
        u1, y1 = CASES[name]()
        u2, y2 = CASES[name]()
        assert np.array_equal(u1, u2) and np.array_equal(y1, y2) and np.all(np.isfinite(y1))


def test_running_out_of_room_for_open_nodes_stops_with_a_valid_bound(monkeypatch):
    import spm_sysid.core.search.certify as certify_module
    from benchmarks.certify import CASES

    monkeypatch.setattr(certify_module, "MAX_OPEN_BYTES", 1)  # no room beyond the first block
    u, y = CASES["exchanger-0"]()
    cert = certify_data(u, y, term_space=TermSpace(), criterion="bic", time_limit=600)
    assert cert.status == "limit" and cert.reason.startswith("memory limit (")
    assert cert.lower_bound < cert.value and cert.gap > 0 and len(cert.terms) > 0


# -- issue 17: the memory bound and the time limit hold in every phase --------------------

_MAXRSS = ("import resource, sys\n"
           "from spm_sysid.apps.main import main\n"
           "code = main(sys.argv[1:])\n"
           "print('maxrss', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n"
           "sys.exit(code)\n")


@pytest.mark.parametrize("extra", [[], ["--no-ga"]])
def test_a_20000_term_certification_is_refused_within_the_bound(extra):
    """The review's case grew to 23.5 GB and was killed; with 2G it allocated 23 GiB."""
    env = dict(__import__("os").environ, SPM_SYSID_MAX_MEMORY="2G")
    r = subprocess.run([sys.executable, "-c", _MAXRSS, "certify", "--ny", "100", "--nu", "100",
                        "--time-limit", "20", *extra], capture_output=True, text=True, cwd=ROOT,
                       timeout=120, env=env)
    assert r.returncode == 2 and "20300 candidate terms" in r.stderr, r.stderr
    assert "limit of 2.0 GB (SPM_SYSID_MAX_MEMORY)" in r.stderr
    maxrss_kb = int(r.stderr.split("maxrss")[1].split()[0])
    assert maxrss_kb < 2 * 2**20  # nothing near the bound was ever allocated


def test_ulimit_v_bounds_the_memory_too():
    script = (f"ulimit -v 4000000; exec {sys.executable} -m spm_sysid.apps.main certify "
              "--ny 100 --nu 100 --time-limit 20 --no-ga")
    env = {k: v for k, v in __import__("os").environ.items() if k != "SPM_SYSID_MAX_MEMORY"}
    r = subprocess.run(["bash", "-c", script], capture_output=True, text=True, cwd=ROOT,
                       timeout=120, env=env)
    assert r.returncode == 2 and "address space left under ulimit -v" in r.stderr, r.stderr


def test_certify_refuses_a_problem_beyond_the_bound_before_building_it(monkeypatch):
    from spm_sysid.core.errors import MemoryLimitError

    monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", "64M")
    P = np.ones((400, 3000))
    with pytest.raises(MemoryLimitError, match="certifying 3000 candidate terms on 400 rows"):
        certify(P, P[:, 0], "bic", time_limit=5)


def test_a_search_stopped_in_its_set_up_reports_a_finite_bound(robot_arm):
    """The time limit counts from the caller's start; the trivial bound is still valid."""
    import time

    u, y = robot_arm
    cert = certify_data(u, y, term_space=TermSpace(), criterion="bic", time_limit=1.0,
                        started=time.perf_counter() - 5.0)
    assert cert.status == "limit" and "setting the search up" in cert.reason
    assert cert.nodes == 0 and np.isfinite(cert.lower_bound) and cert.lower_bound < cert.value
    json.dumps(cert.to_dict(), allow_nan=False)
    assert cert.lower_bound <= -10707.48  # below the certified BIC optimum


def test_the_local_search_in_small_batches_finds_the_same(monkeypatch):
    import spm_sysid.core.search.certify as certify_module
    import spm_sysid.core.search.local as search_module

    P, t = _problem("structured", 2)
    start = np.zeros(P.shape[1], dtype=bool)
    start[:2] = True
    usable = np.arange(P.shape[1])
    whole = certify_module.polish(StructureEvaluator(P, t, "aic"), start, usable)
    monkeypatch.setattr(search_module, "BATCH_BITS", 3 * P.shape[1])
    batched = certify_module.polish(StructureEvaluator(P, t, "aic"), start, usable)
    assert np.array_equal(whole[0], batched[0]) and whole[1] == pytest.approx(batched[1])
    ev = StructureEvaluator(P, t, "aic")
    assert whole[1] <= ev.cached_score(start)  # never worse than where it started


def test_a_control_group_limit_bounds_the_memory(tmp_path):
    """A container's (or systemd unit's) memory limit, not only the machine's free memory."""
    import os
    import uuid

    name = f"spm_sysid_test_{uuid.uuid4().hex[:8]}"
    for base, limit_file in (("/sys/fs/cgroup/memory", "memory.limit_in_bytes"),
                             ("/sys/fs/cgroup", "memory.max")):
        group = os.path.join(base, name)
        try:
            os.mkdir(group)
        except OSError:
            continue
        try:
            with open(os.path.join(group, limit_file), "w") as f:
                f.write(str(2**30))
        except OSError:
            os.rmdir(group)
            continue
        break
    else:
        pytest.skip("no writable cgroup memory controller here (needs root)")
    env = {k: v for k, v in os.environ.items() if k != "SPM_SYSID_MAX_MEMORY"}
    try:
        r = subprocess.run(
            ["sh", "-c", f"echo $$ > {group}/cgroup.procs && exec {sys.executable} -m "
             "spm_sysid.apps.main certify --ny 40 --nu 40 --time-limit 20 --no-ga"],
            capture_output=True, text=True, cwd=ROOT, timeout=120, env=env)
    finally:
        os.rmdir(group)
    assert r.returncode == 2, r.stderr
    assert "memory its control group may still take" in r.stderr, r.stderr


@pytest.mark.parametrize("collinear", [False, True])
def test_every_drop_bound_stays_below_the_true_cost_of_leaving_terms_out(collinear):
    """drop[q] <= min over q free terms R of SSE(T - R) - SSE(T), by brute force: the
    single costs, the q smallest theta^2 over ||H_FF||_F, and the pairs."""
    from itertools import combinations

    from spm_sysid.core.search.branch_bound import _drop_costs

    for seed in range(40):
        rng = np.random.default_rng(seed)
        n, k, f = 40, int(rng.integers(0, 3)), int(rng.integers(2, 8))
        t = k + f
        X = rng.standard_normal((n, t))
        if collinear:  # nearly equal columns and a common offset, as NARX products make
            X = X * rng.uniform(0.01, 0.2, t) + rng.uniform(0.5, 2.0) * X[:, :1]
        beta = rng.normal(0, 1, t) * rng.uniform(0, 1, t).round()  # some terms absent
        y = X @ beta + rng.standard_normal(n) * rng.uniform(0.01, 1.0)

        def sse(cols, X=X, y=y):
            if not cols:
                return float(y @ y)
            A = X[:, list(cols)]
            r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
            return float(r @ r)

        L = np.linalg.cholesky(X.T @ X)
        theta = np.linalg.lstsq(X, y, rcond=None)[0]
        drop = np.zeros(f + 1)
        _drop_costs(L, theta, k, f, np.zeros((f, f)), np.zeros((f, f)), np.zeros(f),
                    np.zeros((f, f)), np.zeros((f, f)), np.zeros(f), np.zeros(f), drop,
                    float(np.min(np.diag(L)) ** 2))
        full = sse(range(t))
        for q in range(1, f + 1):
            true = min(sse([j for j in range(t) if j not in set(R)]) - full
                       for R in combinations(range(k, t), q))
            assert drop[q] <= true * (1 + 1e-9) + 1e-9 * full, (seed, q, drop[q], true)


def _offset_cubic(seed: int):
    """The offset problem in a cubic space (34 candidates): its products of nearly
    constant columns are nearly dependent in many ways, so the search meets nodes
    whose free terms cannot all be factorised."""
    return _problem("offset", seed, degree=3)


def _counting_heaps(monkeypatch):
    """The search's open-node stores, kept for their counters."""
    from spm_sysid.core.search import heaps

    made, init = [], heaps.OpenNodes.__init__

    def keep(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(heaps.OpenNodes, "__init__", keep)
    return made


@pytest.mark.parametrize("seed", [7, 1])
def test_nearly_dependent_spaces_are_certified_as_brute_force_finds(monkeypatch, seed):
    """20 candidates of a cubic space with an offset: nodes whose terms are nearly
    dependent are bounded (span bound, exact small sizes), not passed over."""
    from spm_sysid.core.search.branch_bound import NEAR_BRANCHES

    made = _counting_heaps(monkeypatch)
    P, t = _offset_cubic(seed)
    P = P[:, :20]
    for criterion in ("aic", "bic"):
        truth, _ = _brute_force(P, t, criterion)
        for budget in (0, None):
            cert = certify(P, t, criterion, time_limit=120, enumeration_budget=budget,
                           threads=1)
            assert cert.status == "optimal"
            assert cert.value == pytest.approx(truth, abs=1e-6)
        assert made[-1].counts[NEAR_BRANCHES] > 0  # the case this test is for


def test_the_bound_rises_past_the_trivial_one_where_terms_are_dependent():
    """34 cubic candidates with an offset: 300 nodes lift the lower bound well above
    "all terms' SSE, one term's penalty" (nodes with nearly dependent terms used to
    keep the bound of the root and hold the search's bound there)."""
    P, t = _offset_cubic(7)
    ev = StructureEvaluator(P, t, "bic")
    pen = penalty_per_size(get_criterion("bic"), ev.n, ev.n_terms, ev.max_terms)
    r = t - P @ np.linalg.lstsq(P, t, rcond=None)[0]
    trivial = ev.n * np.log(float(r @ r) / ev.n) + pen[1]
    cert = certify(P, t, "bic", node_limit=300, enumeration_budget=0)
    assert cert.status == "limit"
    assert cert.lower_bound > trivial + 10.0, (cert.lower_bound, trivial)
    assert cert.lower_bound <= cert.value


@pytest.mark.parametrize("kind", ["dependent", "nearly dependent", "offset"])
def test_span_and_small_size_bounds_stay_below_every_identifiable_structure(kind):
    """For I <= S <= T: the span bound (a QR of T without a rank test) and the exact
    small sizes with it as their floor are at most the SSE of every structure the
    evaluator accepts, by brute force over all S."""
    from itertools import combinations

    from spm_sysid.core.search.branch_bound import _project_free, _small_sizes, _sse_span

    for seed in range(30):
        rng = np.random.default_rng(seed)
        n, k, f = 40, int(rng.integers(0, 3)), int(rng.integers(3, 8))
        t = k + f
        X = rng.standard_normal((n, t))
        if kind == "dependent":  # one free column a combination of two others
            X[:, -1] = X[:, k] - 2.0 * X[:, 0 if k else 1]
        elif kind == "nearly dependent":
            X[:, -1] = X[:, k] + 10.0 ** rng.uniform(-7, -3) * rng.standard_normal(n)
        else:
            X = X * rng.uniform(0.001, 0.05, t) + 1.0
        y = X @ rng.normal(0, 1, t) + rng.standard_normal(n) * rng.uniform(0.01, 1.0)
        ev = StructureEvaluator(X, y, "aic")
        R = np.ascontiguousarray(ev.factor)
        cols = np.arange(t + 1, dtype=np.int64)
        rows = R.shape[0]

        def sse(members, R=R, t=t):
            A = R[:, list(members)]
            return float(np.sum((R[:, t] - A @ np.linalg.lstsq(A, R[:, t], rcond=None)[0]) ** 2))

        free = range(k, t)
        accepted = {}
        for a in range(f + 1):
            for A in combinations(free, a):
                S = list(range(k)) + list(A)
                mask = np.zeros(t, dtype=bool)
                mask[S] = True
                if S and np.isfinite(ev.cached_score(mask)):
                    accepted.setdefault(a, []).append(sse(S))
        Q, At = np.zeros((rows, t + 1)), np.zeros((rows, t + 1))
        Sg, c = np.zeros((t, t)), np.zeros(t)
        zz = _project_free(R, cols, k, f, t, Q, At, Sg, c)
        span = _sse_span(R, cols, t, t, np.zeros((t + 1, rows)))
        exact = np.zeros(f + 1)
        _small_sizes(Sg, c, zz, f, f, exact, np.zeros((f + 1, f + 1), np.int64),
                     np.zeros((f + 1, f + 1)), np.zeros(f + 1), np.zeros(f + 1),
                     np.zeros(f + 1, np.int64), span)
        for a, values in accepted.items():
            assert span <= min(values) * (1 + 1e-12), (seed, a, span, min(values))
            assert exact[a] <= min(values) * (1 + 1e-12), (seed, a, exact[a], min(values))


def test_a_limited_run_bounds_the_one_step_mse_at_its_size():
    """The certificate's one-step MSE is the residual MSE of its structure (numpy's
    lstsq), and no structure of at most that many terms has a lower MSE than its
    bound (brute force over all 2^14); the command line says it in a sentence."""
    from spm_sysid.core.search.certify import describe_certificate

    P, t = _problem("structured", 3)
    worst = np.zeros(P.shape[1], dtype=bool)
    worst[0] = True
    cert = certify(P, t, "bic", warm_start=worst, node_limit=3, enumeration_budget=0)
    assert cert.status == "limit"
    A = P[:, cert.mask]
    r = t - A @ np.linalg.lstsq(A, t, rcond=None)[0]
    assert cert.one_step_mse == pytest.approx(float(r @ r) / len(t), rel=1e-9)
    assert cert.mse_lower_bound == pytest.approx(
        cert.one_step_mse * np.exp(-cert.gap / len(t)), rel=1e-9)
    assert cert.mse_lower_bound < cert.one_step_mse
    k = int(cert.mask.sum())
    masks = _all_masks(P.shape[1])
    for mask in masks[masks.sum(axis=1) <= k]:
        B = P[:, mask]
        e = t - B @ np.linalg.lstsq(B, t, rcond=None)[0]
        assert float(e @ e) / len(t) >= cert.mse_lower_bound * (1 - 1e-9)
    doc = cert.to_dict()
    assert doc["size"] == k and doc["one_step_mse"] == cert.one_step_mse
    text = describe_certificate(doc)
    assert f"no structure of at most {k} terms below {cert.mse_lower_bound:.4g}" in text
    optimal = certify(P, t, "bic")
    assert optimal.status == "optimal"
    assert optimal.mse_lower_bound == pytest.approx(optimal.one_step_mse)


def test_restarts_along_forward_selection_give_a_scored_better_incumbent(monkeypatch):
    """path_incumbent polishes forward selection's structures of every 4th size: its
    value is the evaluator's score of its mask, and no worse than any start it
    polished (a polish only improves)."""
    import time

    from spm_sysid.core.search.certify import PATH_STRIDE, path_incumbent
    from spm_sysid.core.search.forward import forward_selection_path

    P, t = _problem("offset", 7, ny=3, nu=3)
    ev = StructureEvaluator(P, t, "bic")
    usable = np.flatnonzero(~ev.zero_columns)
    mask, value = path_incumbent(ev, usable, deadline=time.perf_counter() + 60)
    assert mask is not None and ev.cached_score(mask) == pytest.approx(value)
    path = forward_selection_path(ev, max_terms=min(60, len(usable)))
    starts = path[PATH_STRIDE - 1::PATH_STRIDE]
    assert len(starts) >= 3
    assert value <= min(ev.cached_score(s) for s in starts) + 1e-9
    # restarting at once (not after a second), the search still proves the optimum
    monkeypatch.setattr("spm_sysid.core.search.certify.PATH_AFTER", 0.0)
    truth, _ = _brute_force(P[:, :18], t, "bic")
    cert = certify(P[:, :18], t, "bic", warm_start=np.eye(18, dtype=bool)[0], time_limit=120,
                   enumeration_budget=0)
    assert cert.status == "optimal" and cert.value == pytest.approx(truth, abs=1e-6)
