"""Answers that say what happened: names, samples, defaults, limits and clocks as they are."""

import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

from spm_sysid.core.errors import DataError
from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.identify import identify
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.validate.open_loop import open_loop_check
from spm_sysid.core.validate.validation import describe_metrics, metrics

from .conftest import ROOT


def cli(*args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout, env=env)


def test_a_constant_output_is_named_by_its_own_name(robot_arm):
    u, _ = robot_arm
    with pytest.raises(DataError, match=r"the output q2 is constant \(0.25 throughout"):
        Problem.from_signals(u, np.full(len(u), 0.25), TermSpace(output="q2"))


def test_a_glitch_in_the_output_is_named_with_its_sample(robot_arm):
    u, y = robot_arm
    y = y.copy()
    y[512] = 1e4  # one bad read in a signal of unit size
    warnings = identify(u=u, y=y, seed=1).model.metadata["warnings"]
    assert warnings[0].startswith("the output y has 1 sample(s) far outside the rest "
                                  "(sample 512: 10000;"), warnings[0]
    clean = identify(u=u, y=robot_arm[1], seed=1).model.metadata.get("warnings") or []
    assert not any("far outside" in w for w in clean)


def test_a_wrapped_joint_angle_is_named_and_steps_and_slow_angles_are_not(tmp_path):
    """A continuous joint's position kept in [-pi, pi): the command as typed says so."""
    from spm_sysid.core.validate.excitation import wraps

    from .helpers.joint import joint_record

    tau, q = joint_record(5.0, seed=1)
    turns = 20.0 * q + 2.5  # several turns of a wheel, slow against its samples
    wrapped = (turns + np.pi) % (2 * np.pi) - np.pi
    jumps = int(np.sum(np.abs(np.diff(wrapped)) > np.pi))
    assert jumps > 0
    data = tmp_path / "wheel.csv"
    np.savetxt(data, np.c_[tau, wrapped], delimiter=",", header="tau,q", comments="")
    out = cli("identify", "--data", str(data), "--inputs", "tau", "--output", "q", "--seed",
              "1")
    assert out.returncode == 0, out.stderr
    assert (f"warning: the output q jumps by nearly a turn (2*pi) at {jumps} sample(s)"
            in out.stdout), out.stdout
    degrees = (np.degrees(turns) + 180.0) % 360.0 - 180.0
    assert wraps(degrees)[:2] == (360.0, "360")
    assert wraps(np.unwrap(wrapped)) is None and wraps(turns) is None
    step = np.where(np.arange(1000) < 500, 0.0, 6.0)  # a step test is not a wrap
    assert wraps(step) is None and wraps(np.where(step > 0, 2.0, -2.0)) is None


def test_a_constant_output_has_no_fit_percent_instead_of_minus_1e16():
    y = np.full(500, 0.25) + np.where(np.arange(500) % 2, 1e-17, 0.0)  # a mean that rounds
    m = metrics(y, np.full(500, 0.25))
    assert np.isnan(m["fit_percent"]) and m["mse"] < 1e-30
    assert "no fit % (the output does not vary here)" in describe_metrics("one-step", m)


@pytest.mark.parametrize("how", ["u equals y", "a second output twice the first"])
def test_an_input_that_repeats_the_output_does_not_read_as_instability(robot_arm, how):
    u, y = robot_arm
    n = len(y)
    inputs = y if how == "u equals y" else np.column_stack([u, 2.0 * y])
    alone = open_loop_check(u, y, [(0, n)], 4)
    check = open_loop_check(inputs, y, [(0, n)], 4)
    assert alone.kind == "stable" and check.kind == "stable", check  # was "pole 1.1355"
    assert abs(check.pole) < 1.0


def test_few_rows_per_term_warns_in_the_words_of_the_criterion_in_use(robot_arm):
    from spm_sysid.core.validate.excitation import check_problem

    u, y = robot_arm
    problem = Problem.from_signals(u[:306], y[:306], TermSpace(ny=6, nu=6, degree=2))
    for criterion, words in (("aic", "a criterion with a weak penalty (AIC)"),
                             ("bic", "even BIC may select too many terms")):
        few = [w for w in check_problem(problem, criterion=criterion).warnings
               if "rows for" in w]  # 90 candidates on 300 rows
        assert len(few) == 1 and words in few[0], few


def test_certify_certifies_what_identify_shows_by_default():
    r = cli("certify", "--help")
    assert "{aic,aicc,bic}" in r.stdout and "default aic" in r.stdout
    r = cli("certify", "--quiet", "--time-limit", "600")  # a proof, whatever the speed
    assert r.returncode == 0, r.stderr
    assert "status: optimal" in r.stdout and "value: -10744.7850" in r.stdout  # eq. (1)


def test_the_executables_print_their_usage_and_do_not_start():
    for exe, words in (("sysid_node", "usage: sysid_node"), ("bag_player", "usage: bag_player")):
        r = subprocess.run([str(ROOT / ".venv" / "bin" / exe) if (
            ROOT / ".venv" / "bin" / exe).exists() else exe, "--help"],
            capture_output=True, text=True, timeout=30)
        assert r.returncode == 0 and r.stdout.startswith(words), r.stdout + r.stderr


def test_a_stamp_is_the_nodes_clock_or_said_to_be_the_datas():
    import time

    from spm_sysid.ros.node.dashboard import describe_stamp
    from spm_sysid.ros.node.dashboard_server import host_name

    now = time.time_ns()
    assert describe_stamp(now, now).startswith(time.strftime("%Y-%m-%d"))
    assert describe_stamp(5 * 10**9, now) == ("5.000 s in the data's time (its stamps, e.g. "
                                             "a replayed bag's)")  # was 1970-01-01 00:00:05
    assert [host_name(h) for h in ("127.0.0.1:8765", "localhost", "[::1]:80", "::1")] == [
        "127.0.0.1", "localhost", "::1", "::1"]


def test_a_polish_neighbourhood_of_a_large_space_is_fitted_in_bounded_memory(robot_arm):
    """20 000 structures of 454 candidates at once: the fit works slice by slice."""
    u, y = robot_arm
    problem = Problem.from_signals(u, y, TermSpace(ny=6, nu=6, degree=3))
    ev = problem.evaluator(__import__("spm_sysid.core.fit.criteria",
                                      fromlist=["x"]).get_criterion("bic"))
    rng = np.random.default_rng(0)
    masks = rng.random((20_000, ev.n_terms)) < 0.1
    tracemalloc.start()
    values = ev.score(masks)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert np.isfinite(values).sum() > 1000
    assert peak < 120 * 2**20, peak / 2**20  # was about 400 MB
    assert ev.score(masks[:3]).tolist() == values[:3].tolist()  # the same numbers


def test_the_cache_of_scores_stays_within_its_capacity_and_keeps_the_best(robot_arm):
    from spm_sysid.core.fit.criteria import get_criterion

    u, y = robot_arm
    ev = Problem.from_signals(u, y, TermSpace()).evaluator(get_criterion("aic"))
    ev.cache_capacity = 1000
    rng = np.random.default_rng(1)
    masks = rng.random((3000, ev.n_terms)) < 0.3
    values = ev.score(masks)
    assert len(ev._cache) <= 1000 and ev.pruned >= 2000
    best = int(np.argmin(values))
    assert ev.ranked(1)[0].tolist() == masks[best].tolist()
    sizes = ev.best_per_size().sum(axis=1)
    assert sorted(sizes) == sorted(set(masks[np.isfinite(values)].sum(axis=1)))


def test_an_allocation_the_machine_refuses_is_one_error_line():
    script = (f"ulimit -v 2000000; exec {sys.executable} -m spm_sysid.apps.main certify "
              "--ny 100 --nu 100 --time-limit 20 --no-ga")
    env = dict(__import__("os").environ, SPM_SYSID_MAX_MEMORY="unlimited")
    r = subprocess.run(["bash", "-c", script], capture_output=True, text=True, cwd=ROOT,
                       timeout=120, env=env)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.startswith("error: out of memory") and "Traceback" not in r.stderr
