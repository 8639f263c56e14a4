"""What holds a stopped certification's bound (certify --explain), against brute force."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.fit.evaluator import StructureEvaluator
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.search.certify import certify
from spm_sysid.core.search.explain import explain_table

from .conftest import ROOT
from .helpers.narx import smooth_narx_record


def _narx_problem(seed: int, near: bool):
    """14 candidates of a smooth input's NARX space (many structures nearly equal); with
    ``near``, one more column within rounding distance of another (the span bound's case)."""
    u, y = smooth_narx_record(seed)
    rng = np.random.default_rng(seed + 100)
    ts = TermSpace(ny=2, nu=2, degree=2)
    P, t = ts.regression_matrix(u, y), ts.target(y)
    if near:
        P = np.column_stack([P, P[:, 3] + 2e-6 * rng.standard_normal(len(t))])
    return P, t


def _scores_of_all(ev: StructureEvaluator, m: int) -> tuple[np.ndarray, np.ndarray]:
    masks = ((np.arange(1, 2 ** m)[:, None] >> np.arange(m)) & 1).astype(bool)
    return masks, np.concatenate([ev.evaluate(masks[i:i + 4096])
                                  for i in range(0, len(masks), 4096)])


def _check_node(w, masks, scores, value, m):
    """No structure of the node (I <= S <= I + F) scores below what it claims."""
    inside = np.zeros(m, dtype=bool)
    inside[w.inside] = True
    allowed = inside.copy()
    allowed[w.free] = True
    assert len(w.inside) + len(w.free) + w.out == m
    mine = ((masks & inside).sum(axis=1) == inside.sum()) & ~(masks & ~allowed).any(axis=1)
    lowest = float(scores[mine].min()) if mine.any() else np.inf
    assert lowest >= w.bound - 1e-6
    if not np.isfinite(w.own_bound):  # closes: nothing in it beats the incumbent
        assert lowest >= value - 1e-6 and w.weakest_size is None
        return "closes"
    assert w.own_bound >= w.bound - 1e-9 and lowest >= w.own_bound - 1e-6
    assert len(w.inside) <= w.weakest_size <= len(w.inside) + len(w.free)
    sized = mine & (masks.sum(axis=1) == w.weakest_size)
    assert float(scores[sized].min()) >= w.own_bound - 1e-6 and w.open_sizes >= 1
    sizes = masks.sum(axis=1)
    for k, claim in enumerate(w.size_bounds, start=len(w.inside)):
        if not (mine & (sizes == k)).any():
            continue  # no structure of that size (the empty one)
        truth = float(scores[mine & (sizes == k)].min())
        assert truth >= min(claim, value) - 1e-6  # inf: cut, none beats the incumbent
        if k <= w.exact_up_to and not w.nearly_dependent and np.isfinite(truth):
            assert claim == pytest.approx(truth, abs=1e-4)  # enumerated: exact
    return "nearly dependent" if w.nearly_dependent else "open"


def test_each_weak_node_bounds_only_what_brute_force_allows():
    """Started from the true optimum and stopped early, every open node it explains is
    bounded validly: no structure of the node scores below its bound, its own bound,
    or its weakest size's bound; one that "closes" holds none better than the
    incumbent; the first holds the certificate's lower bound. All three kinds occur."""
    kinds = set()
    for near in (False, True):
        for seed in (1, 2):
            P, t = _narx_problem(seed, near)
            m = P.shape[1]
            masks, scores = _scores_of_all(StructureEvaluator(P, t, "aic"), m)
            best = masks[int(np.argmin(scores))]
            for nodes in (1, 2):
                cert = certify(P, t, "aic", warm_start=best, node_limit=nodes,
                               enumeration_budget=0, explain=5)
                assert cert.status == "limit"
                assert cert.value == pytest.approx(scores.min(), abs=1e-9)
                assert 1 <= len(cert.weakest) <= 5
                assert cert.weakest[0].bound == pytest.approx(cert.lower_bound, abs=1e-9)
                bounds = [w.bound for w in cert.weakest]
                assert bounds == sorted(bounds)
                kinds |= {_check_node(w, masks, scores, cert.value, m) for w in cert.weakest}
                doc = cert.to_dict()
                json.dumps(doc, allow_nan=False)
                assert len(doc["weakest"]) == len(cert.weakest)
                assert "reading:" in explain_table(doc["weakest"], cert.value)
    assert kinds == {"closes", "open", "nearly dependent"}


def test_a_proved_or_unexplained_search_has_no_weak_nodes():
    P, t = _narx_problem(0, False)
    assert certify(P, t, "bic", time_limit=600, explain=5).weakest == []
    cert = certify(P, t, "bic", node_limit=1, enumeration_budget=0)
    assert cert.status == "limit" and cert.weakest == [] and "weakest" not in cert.to_dict()
    assert "no open node" in explain_table([], 0.0)


def test_certify_explain_prints_the_weakest_nodes_with_term_names(tmp_path, robot_arm_path):
    def spm(*args):
        return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "certify", *args],
                              capture_output=True, text=True, cwd=ROOT, timeout=300)

    out = tmp_path / "c.json"
    r = spm("--data", str(robot_arm_path), "--no-ga", "--node-limit", "2", "--explain", "3",
            "--quiet", "--json", str(out))
    assert r.returncode == 0, r.stderr
    assert "status: limit (node limit 2)" in r.stdout
    lines = r.stdout.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("weakest open nodes"))
    assert lines[head + 1].split()[:2] == ["bound", "own"]
    rows = lines[head + 2:head + 5]
    doc = json.loads(out.read_text())
    assert len(doc["weakest"]) == 3
    assert float(rows[0].split()[0]) == pytest.approx(doc["lower_bound"], abs=0.01)
    names = TermSpace(ny=4, nu=4, degree=2).term_names()
    for row, node in zip(rows, doc["weakest"]):
        assert int(row.split()[2]) == node["n_in"] == len(node["in"])
        assert set(node["in"]) <= set(names)
        assert node["n_in"] + node["n_out"] + node["n_free"] <= len(names)
    assert lines[head + 5].startswith("reading: ")
    r = spm("--data", str(robot_arm_path), "--no-ga", "--node-limit", "2", "--quiet")
    assert r.returncode == 0 and "what holds the bound: run again with --explain" in r.stdout
    assert "weakest open nodes" not in r.stdout
    r = spm("--explain", "-1")
    assert r.returncode == 2 and "--explain must be 0 or more nodes, got -1" in r.stderr


@pytest.mark.slow
def test_bench_certify_scale_runs_the_84_candidate_space_and_says_what_holds_the_bound():
    """One run of `make bench-certify-scale` as its parent starts it (the robot arm's first
    half, (3,3,3) with the constant, BIC), stopped after 200 nodes whatever the machine's
    speed (a time limit may end on a busy machine before the search starts): explained."""
    case = {"file": "robot_arm.dat", "order": 3, "degree": 3, "criterion": "bic",
            "time_limit": 600, "node_limit": 200}
    r = subprocess.run([sys.executable, "-m", "benchmarks.certify_scale", "--one", "ours",
                        json.dumps(case)], capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["candidates"] == 84 and out["rows"] == 512 - 3
    assert out["status"] == "limit" and out["reason"] == "node limit 200" and out["gap"] > 0
    assert out["reading"].startswith("reading: ") and "of 5 close when expanded" in out["reading"]
