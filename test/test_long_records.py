"""Records at their real size (issue 41): progress off a terminal, Ctrl-C, long-record
judging, orders that cannot be fitted, the account of the model returned, a drive.

The commands run as users type them (``spm-sysid identify ...``) with stderr a
pipe, not a terminal: what a log, CI or ``| tee`` sees.
"""

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from spm_sysid.core.fit.free_run import FreeRun
from spm_sysid.core.fit.levenberg import refine_free_run
from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.fit.refine import linear_radius, refine_simulation, stabilised_start
from spm_sysid.core.jobs import JobSettings, describe_selection, run_job
from spm_sysid.core.model.mimo import read_model_document
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.options import SearchOptions
from spm_sysid.core.progress import PHASES, Progress
from spm_sysid.core.record import Record
from spm_sysid.core.select.call import Call
from spm_sysid.core.select.finalists import returned_account
from spm_sysid.core.select.folds import is_long, refinement_windows, sub_blocks
from spm_sysid.core.select.plan import plan_selection
from spm_sysid.core.validate.orders import propose_orders
from spm_sysid.tools.cli.progress import PhaseBars

sys.path.insert(0, str(Path(__file__).parent))
from helpers.duffing import duffing  # noqa: E402
from helpers.joint import Joint, joint_record  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).with_name("spm-sysid"))


# -- progress off a terminal ------------------------------------------------------------

def test_progress_off_a_terminal_is_a_line_per_phase_and_one_every_few_seconds():
    out = io.StringIO()  # not a terminal
    bars = PhaseBars(True, stream=out, every=0.3)
    try:
        bars(Progress("checking data"))
        for step in range(1, 5):
            bars(Progress("screening", step, 8, best=-1.0, elapsed=step * 0.1))
        time.sleep(1.0)  # a long step: nothing new comes
        bars(Progress("validation", elapsed=2.0))
    finally:
        bars.close()
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("checking data")
    assert lines[1].startswith("screening: step 1/8") and "12% of this phase" in lines[1]
    assert any("(still working on this step)" in x and "step 4/8" in x for x in lines)
    assert lines[-1].startswith("validation")
    assert not any("\r" in x for x in lines)  # lines, not a redrawn bar


def test_the_estimate_left_goes_by_the_steps_after_a_phases_first():
    """A dear first step (a cold cache) does not make the rest look as dear."""
    now = [0.0]
    out = io.StringIO()
    bars = PhaseBars(True, stream=out, every=1e9, clock=lambda: now[0])
    try:
        bars(Progress("held-out blocks", 0, 15))
        for step, at in ((1, 10.0), (2, 11.0), (3, 12.0)):
            now[0] = at
            bars(Progress("held-out blocks", step, 15))
            bars._print(bars._last, at)  # a line at each step
        now[0] = 14.0  # the fourth step under way for 2 s
        bars._print(bars._last, now[0], still=True)
    finally:
        bars.close()
    lines = out.getvalue().splitlines()[1:]
    assert "step 1/15" in lines[0] and "left" not in lines[0], lines  # no pace yet
    assert "step 2/15" in lines[1] and "about 13 s left in it" in lines[1], lines
    # 1 s a step after the first: 12 left, not 4 x 12 s = 48 s from the phase's start
    assert "step 3/15" in lines[2] and "about 12 s left in it" in lines[2], lines
    assert "still working" in lines[3] and "about 10 s left in it" in lines[3], lines


def test_identify_off_a_terminal_reports_its_phases_in_order(robot_arm_path):
    r = subprocess.run([EXE, "identify", "--focus", "simulation"], capture_output=True,
                       text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    phases = [line.split(":")[0].split(",")[0] for line in r.stderr.splitlines()
              if line.split(":")[0].split(",")[0] in PHASES]
    assert phases[0] == "checking data" and phases[-1] == "validation"
    assert {"search", "screening", "held-out blocks"} <= set(phases)
    assert [PHASES.index(p) for p in phases] == sorted(PHASES.index(p) for p in phases)


# -- Ctrl-C -------------------------------------------------------------------------------

def test_ctrl_c_ends_the_command_and_writes_the_best_model_so_far(tmp_path):
    u, y = duffing(60_000)
    data = tmp_path / "long.dat"
    np.savetxt(data, np.column_stack([u, y]))
    out = tmp_path / "model.json"
    p = subprocess.Popen([EXE, "identify", "--data", str(data), "--focus", "simulation",
                          "--json", str(out)], stderr=subprocess.PIPE, text=True, cwd=ROOT)
    seen = []
    for line in p.stderr:  # wait until the selection runs: the search has a best by then
        seen.append(line)
        if line.startswith(("screening", "held-out blocks")):
            break
    p.send_signal(signal.SIGINT)
    rest = p.stderr.read()
    assert p.wait(timeout=120) == 130, "".join(seen) + rest
    assert rest.strip().endswith("interrupted")
    assert "the best model so far" in rest and str(out) in rest
    model, doc = read_model_document(out)
    stop = doc["metadata"]["interrupted"]
    assert stop["phase"] in ("screening", "held-out blocks")
    assert "least squares" in stop["model"] and len(model.terms) >= 1


def test_ctrl_c_without_json_writes_nothing_and_says_interrupted(tmp_path):
    u, y = duffing(60_000)
    data = tmp_path / "long.dat"
    np.savetxt(data, np.column_stack([u, y]))
    p = subprocess.Popen([EXE, "identify", "--data", str(data), "--focus", "simulation"],
                         stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    for line in p.stderr:
        if line.startswith("screening"):
            break
    p.send_signal(signal.SIGINT)
    assert p.wait(timeout=120) == 130
    assert p.stderr.read().strip().endswith("interrupted")
    assert sorted(os.listdir(tmp_path)) == ["long.dat"]


# -- long records -------------------------------------------------------------------------

def test_a_long_record_is_judged_on_blocks_laid_once_and_cut_in_nine():
    u, y = duffing(30_000)
    problem = Problem.from_signals(u, y, TermSpace(ny=2, nu=2, degree=3), [(0, len(y))])
    assert is_long(problem)
    plan = plan_selection(problem, SearchOptions(focus="simulation"))
    assert len(plan.folds) == 3  # laid once, not three times
    label = sub_blocks(problem, plan.folds)
    assert set(np.unique(label[label >= 0])) == set(range(9))
    for i, fold in enumerate(plan.folds):  # each fold's held-out samples: three sub-blocks
        held = np.concatenate([np.arange(a, b) for a, b in fold.held_out])
        assert set(np.unique(label[held])) == {3 * i, 3 * i + 1, 3 * i + 2}
    # refinements fit on windows of a few thousand samples spread over the record
    windows = refinement_windows(problem.segments, 2)
    assert sum(b - a for a, b in windows) <= 5_000 and windows[-1][1] > 25_000
    short = Problem.from_signals(u[:5000], y[:5000], TermSpace(ny=2, nu=2, degree=3),
                                 [(0, 5000)])
    assert not is_long(short)
    assert len(plan_selection(short, SearchOptions(focus="simulation")).folds) == 9


def test_a_long_record_gets_a_model_that_simulates_new_data():
    u, y = duffing(30_000, seed=1)
    u2, y2 = duffing(5_000, seed=2)
    result = run_job(Record.from_samples(u, y, source="duffing"),
                     JobSettings.from_values({"focus": "simulation", "orders": "auto",
                                              "seed": 0}))
    m = result.model
    orders = m.metadata["orders"]
    assert orders["focus"] == "simulation" and orders["space_scan"]
    assert TermSpace(ny=orders["ny"], nu=orders["nu"],
                     degree=orders["degree"]).n_terms <= orders["max_terms"]
    yhat, diverged = m.run(u2, y2)
    assert diverged is None
    lag = m.term_space.max_lag
    rmse = float(np.sqrt(np.mean((y2[lag:] - yhat) ** 2)))
    assert rmse < 0.1 * np.std(y2)  # the cubic stiffness found: a linear model gets ~0.3
    assert m.metadata["selection"]["linear_or_nonlinear"]["choice"] == "nonlinear"


def test_a_long_record_polishes_the_best_screened_structure_into_the_finalists():
    """The one-step search missed the cubic stiffness (a wrong cubic term instead): on a
    long record, moves from the best screened nonlinear structure find the true one, and
    it is a finalist; a short record is judged on what was screened."""
    from spm_sysid.core.fit.criteria import get_criterion
    from spm_sysid.core.fit.evaluator import key_mask, mask_key
    from spm_sysid.core.select.finalists import ValidatedSimulation

    def mask_of(space, names):
        all_names = space.term_names()
        mask = np.zeros(space.n_terms, dtype=bool)
        mask[[all_names.index(t) for t in names]] = True
        return mask

    space = TermSpace(ny=2, nu=2, degree=3)
    truth = ["y(t-1)", "y(t-2)", "u(t-1)", "y(t-1)^3"]
    missed = mask_of(space, ["y(t-1)", "y(t-2)", "u(t-1)", "y(t-1)^2*y(t-2)"])
    for n, polished in ((30_000, True), (5_000, False)):
        u, y = duffing(n, seed=3)
        problem = Problem.from_signals(u, y, space, [(0, n)])
        plan = plan_selection(problem, SearchOptions(focus="simulation"))
        job = ValidatedSimulation(problem, plan.folds, get_criterion("aic"), 0,
                                  lambda p: None, time.perf_counter())
        finals = job.screen(missed[None, :])
        key = mask_key(mask_of(space, truth))
        assert (key in job.scorer.scored) == polished
        cubic = space.term_names().index("y(t-1)^3")
        found = [(v, k) for v, k in finals if key_mask(k, space.n_terms)[cubic]]
        assert bool(found) == polished  # where the moves ended is a finalist
        if polished:
            assert found[0][0] < job.scorer.scored[mask_key(missed)][0] - 100
    # a space of more than POLISH_SPACE terms: each move would try them all; not polished
    big = TermSpace(ny=4, nu=4, degree=3)
    assert big.n_terms > 100
    problem = Problem.from_signals(*duffing(30_000, seed=3), big, [(0, 30_000)])
    job = ValidatedSimulation(problem, [], get_criterion("aic"), 0, lambda p: None,
                              time.perf_counter())
    job.scorer(mask_of(big, ["y(t-1)", "y(t-2)", "u(t-1)", "y(t-1)^2*y(t-2)"]))
    assert job.polish() is None


# -- orders that cannot be fitted ---------------------------------------------------------

def test_an_order_scan_with_orders_that_cannot_be_fitted_still_gives_a_document(tmp_path):
    """One sine excites two input lags: the full linear models of order 3+ are singular."""
    n = 2000
    t = np.arange(n)
    u = np.sin(0.3 * t)
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.5 * y[k - 1] + 0.3 * u[k - 1]
    y += 1e-3 * np.random.default_rng(0).standard_normal(n)
    data, out = tmp_path / "sine.dat", tmp_path / "m.json"
    np.savetxt(data, np.column_stack([u, y]))
    r = subprocess.run([EXE, "identify", "--data", str(data), "--orders", "auto", "--json",
                        str(out), "--quiet"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    _, doc = read_model_document(out)
    scan = doc["metadata"]["orders"]["order_scan"]
    assert [row[1] is None for row in scan] == [False, False] + [True] * 8
    r = subprocess.run([EXE, "propose-lags", "--data", str(data)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0 and "n =  3: not fitted" in r.stdout, r.stderr


# -- the account describes the model returned --------------------------------------------

@pytest.mark.parametrize("fate", ["returned", "shrunk", "removed", "not better"])
def test_the_account_and_its_sentence_describe_the_model_returned(fate):
    call = Call([1, 0], "nonlinear" if fate != "not better" else "linear", linear=0,
                challenger=1, ratio=0.05, p_value=1e-6 if fate != "not better" else 0.3)
    decision = {"choice": call.choice, "ratio": 0.05, "p_value": call.p_value,
                "nonlinear_terms": 12, "best_linear_terms": 4}
    returned, terms, nonlinear, shrunk = {
        "returned": (1, 12, True, None), "shrunk": (1, 12, True, 0.5),
        "removed": (0, 4, False, None), "not better": (0, 4, False, None)}[fate]
    reasons = ["its simulation driven by the input reversed in time left the output's range"]
    account = returned_account(decision, call, returned, terms, nonlinear, shrunk,
                               reasons if fate == "removed" else [])
    assert account["choice"] == ("nonlinear" if nonlinear else "linear")
    assert account["terms"] == terms
    text = describe_selection({"method": "validated", "what": "free-run", "folds": 9,
                               "held_out_mse": 1e-3, "linear_or_nonlinear": account})
    assert f"a {account['choice']} model of {terms} terms" in text
    expected = {"returned": "more than the noise, returned",
                "shrunk": "scaled by 0.5 to pass the stability guard",
                "removed": "but removed by the stability guard (its simulation driven by the "
                           "input reversed in time",
                "not better": "not better than the best linear one by more than the noise: "
                              "linear kept"}[fate]
    assert expected in text
    if fate == "removed":
        assert "the model above was returned instead" in text
        assert "it simulates them better" not in text


def test_a_real_selection_describes_the_model_it_returns(robot_arm):
    u, y = robot_arm
    for settings in ({"focus": "simulation", "seed": 0},
                     {"focus": "simulation", "seed": 0, "degree": 1}):
        m = run_job(Record.from_samples(u, y, source="arm"),
                    JobSettings.from_values(settings)).model
        call = m.metadata["selection"]["linear_or_nonlinear"]
        degree = max(len(m.term_space.terms[i]) for i in m.term_indices)
        assert call["choice"] == ("nonlinear" if degree > 1 else "linear")
        assert call["terms"] == len(m.terms)


# -- a drive: the position integrates ----------------------------------------------------

@pytest.mark.slow
def test_a_pd_controlled_joint_with_friction_is_judged_and_beats_arx_on_its_free_run():
    """Issue 41, item 5: a mass with viscous and Coulomb friction, position output, PD at
    1 kHz with a multisine reference: judged on its free run, better than the ARX."""
    from spm_sysid.core.validate.arx import choose_arx

    joint = Joint()
    tau, q = joint_record(10.0, seed=0, joint=joint)
    tau2, q2 = joint_record(10.0, seed=1, joint=joint)
    result = run_job(Record.from_samples(tau, q, source="joint"),
                     JobSettings.from_values({"focus": "simulation", "seed": 0}))
    m = result.model
    assert m.metadata["open_loop"]["kind"] == "integrating"
    assert m.metadata["selection"]["what"] == "free-run"
    assert any("integrates" in w for w in m.metadata["warnings"])
    yhat, diverged = m.run(tau2, q2)
    assert diverged is None
    lag = m.term_space.max_lag
    ours = float(np.sqrt(np.mean((q2[lag:] - yhat) ** 2)))
    arx = choose_arx(tau, q)
    sim = arx.simulate(tau2, q2)
    theirs = float(np.sqrt(np.nanmean((q2[10:] - sim[10:]) ** 2)))
    assert ours < theirs, (ours, theirs)
    assert any(t.startswith("u(") for t in m.terms)  # a model of the torque's effect
    assert json.loads(json.dumps(m.to_dict(), allow_nan=False))


# -- an integrator that least squares puts beyond 1 -------------------------------------

def test_a_stabilised_start_scales_every_pole_and_keeps_the_structure():
    """An integrator's pole beyond 1 (real, positive) is scaled to 0.999 with every other
    pole; a resonance beyond 1 is not (a stable system's structure that fails stays lost)."""
    space = TermSpace(ny=3, nu=1, degree=1, constant=True)
    names = ["y(t-1)", "y(t-3)", "u(t-1)"]  # y(t-2) is not in the structure
    indices = [space.term_names().index(n) for n in names]
    theta = np.array([1.2, -0.19, 0.7])  # z^3 - 1.2 z^2 + 0.19: a pole beyond 1
    radius = linear_radius(space, indices, theta)
    assert radius > 1.0
    start = stabilised_start(space, indices, theta)
    assert linear_radius(space, indices, start) == pytest.approx(0.999, abs=1e-9)
    r = 0.999 / radius  # each y(t-l) times r**l (every pole times r), the input's as it was
    assert start == pytest.approx([1.2 * r, -0.19 * r ** 3, 0.7], rel=1e-12)
    assert stabilised_start(space, indices, np.array([0.5, -0.1, 0.7])) is None  # stable
    resonance = [space.term_names().index(n) for n in ("y(t-1)", "y(t-2)", "u(t-1)")]
    theta = np.array([1.0, -1.05, 0.7])  # z^2 - z + 1.05: a complex pair beyond 1
    assert linear_radius(space, resonance, theta) > 1.0
    assert stabilised_start(space, resonance, theta) is None  # not an integrator's pole


def test_an_integrator_least_squares_puts_beyond_one_is_refined_from_inside_the_circle():
    """At 1 kHz least squares puts a drive's integrator beyond 1 (1.005 here), and the
    refinement from there ended beyond 1 too: the structure was lost. It now starts again
    with the poles scaled inside, guarded, and keeps the integrator."""
    tau, q = joint_record(10.0, seed=0)
    space = TermSpace(ny=2, nu=2, degree=1, constant=True)
    model = Problem.from_signals(tau, q, space).model(np.ones(space.n_terms, dtype=bool))
    assert linear_radius(space, model.term_indices, model.coefficients) > 1.001
    plain = refine_free_run(FreeRun(model, tau, q, None, guard=False), model.coefficients, 30)
    assert linear_radius(space, model.term_indices, plain.x) > 1.0  # where it used to end
    ref = refine_simulation(model, tau, q, None, max_evaluations=30)
    assert ref.success and np.isfinite(ref.sse), ref.message
    assert "poles scaled inside the unit circle" in ref.message
    assert 0.999 <= linear_radius(space, model.term_indices, ref.coefficients) < 1.0
    yhat, diverged = model.with_coefficients(ref.coefficients).run(tau, q)
    assert diverged is None
    e = q[space.max_lag:] - yhat
    assert float(e @ e) == pytest.approx(ref.sse, rel=1e-9)
    assert ref.sse < 0.5 * float(np.sum((q - q.mean()) ** 2))  # it simulates the record


def test_the_order_scan_refines_a_linear_space_whose_integrator_least_squares_put_beyond_one():
    """The simulation focus's scan judged each space by its least-squares free run and
    refined only those that stayed in range: on a joint at 1 kHz ARX(2), the plant's own
    order, left the range (its integrator beyond 1) and was never refined, so the scan
    proposed other spaces (order 1, degree 3 on a 200 s record). It is now refined, with
    the stabilised start, and simulates the scan's held-out samples."""
    tau, q = joint_record(5.0, seed=0)
    proposal = propose_orders(tau, q, criterion="aic", focus="simulation")
    rows = {(n, d): (ls, refined) for n, d, _, ls, refined in proposal.space_scan}
    ls, refined = rows[(2, 1)]
    assert not np.isfinite(ls)  # least squares' free run left the range
    start = 10  # the scan's first row (orders up to 10, delay 1)
    cut = start + int(2 / 3 * (len(q) - start))
    assert np.isfinite(refined) and refined < 0.6 * float(np.std(q[cut:]))
    space = TermSpace(ny=2, nu=2, degree=1, constant=True)
    model = Problem.from_signals(tau[:cut], q[:cut], space).model(
        np.ones(space.n_terms, dtype=bool))
    assert stabilised_start(space, model.term_indices, model.coefficients) is not None


def test_many_inputs_widen_the_scan_to_the_quadratic_space_of_order_two():
    """Seven inputs (or six and the other outputs of a coupled model): every quadratic
    space above order 1 has more than the 120 candidate terms of the scan's budget,
    and a second-order plant with a squared input was proposed at order 1 (six inputs
    and six coupled outputs: 0.034 free run on a new draw, noise 0.001). The budget
    grows to the quadratic space of order 2, which the scan then proposes."""
    from spm_sysid.core.defaults import AUTO_MAX_TERMS
    from spm_sysid.core.validate.orders import automatic_budget

    rng = np.random.default_rng(3)
    n, m = 3000, 7
    u = rng.standard_normal((n, m))
    b = np.linspace(0.5, 0.2, m)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 1.5 * y[t - 1] - 0.6 * y[t - 2] + b @ u[t - 1] + 0.3 * u[t - 1, 0] ** 2
    y += 0.01 * rng.standard_normal(n)
    quadratic = TermSpace(ny=2, nu=2, degree=2, inputs=tuple(f"u{i}" for i in range(m)))
    assert [automatic_budget(k) for k in range(1, 7)] == [AUTO_MAX_TERMS] * 6
    assert automatic_budget(m) == quadratic.n_terms > AUTO_MAX_TERMS
    p = propose_orders(u, y, max_order=3, max_degree=2, criterion="aic", focus="simulation")
    scored = {(k, d): min(r, rr) for k, d, _, r, rr in p.space_scan}
    assert p.budget == quadratic.n_terms and (p.order, p.degree) == (2, 2)
    assert scored[2, 2] < 0.2 * min(r for (k, d), r in scored.items() if (k, d) != (2, 2))
    capped = propose_orders(u, y, max_order=3, max_degree=2, criterion="aic",
                            focus="simulation", max_terms=AUTO_MAX_TERMS)
    assert (2, 2) not in {(k, d) for k, d, *_ in capped.space_scan}
    assert (capped.order, capped.degree) != (2, 2)


@pytest.mark.slow
def test_a_long_joint_record_gets_a_model_that_integrates(tmp_path):
    """100 s of the joint at 1 kHz: every structure's refinement ended beyond 1 and the
    command as typed stopped with 'no finalist structure simulates within the output's
    range'. It returns a model that keeps the integrator and simulates another record."""
    tau, q = joint_record(100.0, seed=3)
    data = tmp_path / "joint.csv"
    np.savetxt(data, np.column_stack([tau, q]), delimiter=",", header="torque,q",
               comments="", fmt="%.9g")
    out = subprocess.run([EXE, "identify", "--data", str(data), "--inputs", "torque",
                          "--output", "q", "--focus", "simulation", "--orders", "auto",
                          "--seed", "1", "--json", str(tmp_path / "m.json")],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    m, _ = read_model_document(tmp_path / "m.json")
    assert m.metadata["open_loop"]["kind"] == "integrating"
    assert 0.99 < linear_radius(m.term_space, m.term_indices, m.coefficients) < 1.0
    assert any(t.startswith("torque(") for t in m.terms)
    tau2, q2 = joint_record(100.0, seed=5)
    yhat, diverged = m.run(tau2, q2)
    assert diverged is None
    rmse = float(np.sqrt(np.mean((q2[m.term_space.max_lag:] - yhat) ** 2)))
    assert rmse < 0.8 * float(np.std(q2)), rmse


def test_ctrl_c_while_a_command_still_imports_says_interrupted(tmp_path, monkeypatch, capsys):
    """A Ctrl-C in the first fraction of a second (numpy, scipy, rclpy still loading) ended
    spm-sysid with a KeyboardInterrupt traceback and status -2: the console scripts now
    import each command inside the guard (a module whose import is interrupted stands
    for those imports here)."""
    from spm_sysid.apps.launch import run_guarded

    (tmp_path / "slow_to_import.py").write_text("raise KeyboardInterrupt\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert run_guarded("slow_to_import", "main") == 130
    assert capsys.readouterr().err == "interrupted\n"
    for exe in ("spm-sysid", "sysid_node", "bag_player"):  # what users run goes through it
        script = Path(sys.executable).with_name(exe).read_text()
        assert "from spm_sysid.apps.launch import" in script, (exe, script)
