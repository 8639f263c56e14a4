"""The typed interface over real DDS: the Identify action, GetModel, typed topics.

A real sysid_node process; this test's rclpy node is the client. Goals read the
robot-arm bag directly (``bag_path``), so no replay is needed.
"""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import json
import math
import re
import signal
import subprocess
import sys

from action_msgs.msg import GoalStatus
from spm_sysid_interfaces.action import Identify
from spm_sysid_interfaces.msg import NarxModel as NarxModelMsg
from spm_sysid_interfaces.msg import ValidationReport
from std_msgs.msg import String

from spm_sysid.core.progress import PHASES

from .conftest import EQ1, ROOT
from .ros_harness import IdentifyClient, play_bag, start_node, stop

Code = Identify.Result
FACTOR = re.compile(r"^(\w+)\(t(?:-(\d+))?\)(?:\^(\d+))?$")


def factors_from_name(name: str) -> list[tuple[str, int, int]]:
    """An independent reading of a printed term name, e.g. ``y(t-1)*u(t-2)^2``."""
    if name == "1":
        return []
    out = []
    for part in name.split("*"):
        m = FACTOR.match(part)
        assert m, part
        out.append((m.group(1), int(m.group(2) or 0), int(m.group(3) or 1)))
    return out


@pytest.mark.slow
def test_goal_gives_feedback_in_order_and_a_typed_result_equal_to_the_document(
        ros_env, harness, arm_bag):
    node = start_node(ros_env, "seed:=1")
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        before = client.get_model()
        assert not before.available and "no model yet" in before.message

        feedback: list = []
        handle = client.send(feedback, bag_path=arm_bag)
        status, result = client.result(handle)
        assert status == GoalStatus.STATUS_SUCCEEDED, result.message
        assert result.error_code == Code.NONE
        assert "AIC -10744.78" in result.message and "certified optimal" in result.message

        # feedback: phases in the job's order, generations never going back
        phases = [f.phase for f in feedback]
        assert phases[0] == "checking data" and "search" in phases and phases[-1] == "validation"
        order = [PHASES.index(p) for p in phases]
        assert order == sorted(order)
        gens = [f.step for f in feedback if f.phase == "search"]
        assert gens == sorted(gens) and gens[-1] == 300
        assert all(f.elapsed >= 0 for f in feedback)
        assert any(f.structures_evaluated > 0 and math.isfinite(f.best_value) for f in feedback)

        # the typed model is the JSON document, term by term
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)
        assert json.loads(result.document) == doc
        m = result.model
        assert [t.name for t in m.terms] == doc["terms"] == EQ1
        assert [t.index for t in m.terms] == doc["term_indices"]
        assert list(m.coefficients) == doc["coefficients"]
        for term in m.terms:
            assert [(f.signal, f.lag, f.power) for f in term.factors] == \
                factors_from_name(term.name)
        unc = doc["uncertainty"]
        assert list(m.standard_errors) == unc["standard_errors"]
        assert [[a, b] for a, b in zip(m.interval_lower, m.interval_upper)] == unc["intervals"]
        assert m.criterion == "aic" and m.criterion_value == doc["criterion"]["value"]
        assert m.certification == NarxModelMsg.CERTIFICATION_OPTIMAL and m.gap == 0.0
        assert m.samples == 1024 and m.gaps == 0 and m.document_version == 3
        assert (m.output_name, list(m.input_names), m.ny, list(m.nu), m.degree) == \
            ("y", ["u"], 4, [4], 2)
        val = doc["metadata"]["validation"]
        assert m.free_run_fit_percent == pytest.approx(val["free_run"]["fit_percent"])
        assert m.diverged == (val["diverged_at"] is not None)

        r = result.report
        assert [t.name for t in r.correlation_tests] == [
            t["name"] for t in val["correlation_tests"]]
        assert [t.passed for t in r.correlation_tests] == [
            t["passed"] for t in val["correlation_tests"]]
        assert r.one_step.fit_percent == pytest.approx(val["one_step"]["fit_percent"])
        assert r.residual_count == val["n_samples"] - 4
        assert r.residual_rms == pytest.approx(val["one_step"]["rmse"], rel=1e-9)

        # the same model latched on the typed topics and from GetModel
        latched = harness.latched(NarxModelMsg, "/spm_sysid/narx_model")
        assert list(latched.coefficients) == doc["coefficients"]
        report = harness.latched(ValidationReport, "/spm_sysid/validation")
        assert report.n_samples == val["n_samples"]
        after = client.get_model()
        assert after.available and json.loads(after.document) == doc
        assert list(after.model.coefficients) == doc["coefficients"]

        # the Trigger service keeps working beside the action (the old contract)
        res = harness.call("/spm_sysid/identify")
        assert not res.success and "too few samples: 0 paired samples" in res.message
    finally:
        stop(node)


@pytest.mark.slow
def test_cancel_stops_a_long_search_and_keeps_the_model_a_second_goal_is_busy(
        ros_env, harness, arm_bag):
    node = start_node(ros_env, "seed:=1")
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        status, first = client.result(client.send(bag_path=arm_bag, generations=20))
        assert status == GoalStatus.STATUS_SUCCEEDED, first.message
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)

        feedback: list = []
        long_goal = client.send(feedback, bag_path=arm_bag, generations=100000)
        assert harness.spin_until(lambda: any(f.phase == "search" and f.step > 0
                                              for f in feedback), 60)
        # a second goal and a Trigger call while it runs: BUSY, with the reason
        status, busy = client.result(client.send(bag_path=arm_bag), 30)
        assert status == GoalStatus.STATUS_ABORTED and busy.error_code == Code.BUSY
        assert "already running" in busy.message
        assert "already running" in harness.call("/spm_sysid/identify").message

        cancel = long_goal.cancel_goal_async()
        assert harness.spin_until(cancel.done, 10)
        status, canceled = client.result(long_goal, 30)  # a search of 100 000 generations
        assert status == GoalStatus.STATUS_CANCELED and canceled.error_code == Code.CANCELED
        assert "previous model stays published" in canceled.message
        assert len(canceled.model.terms) == 0

        # the previous model is still the published one, on every topic and from GetModel
        assert json.loads(harness.latched(String, "/spm_sysid/model").data) == doc
        assert list(harness.latched(NarxModelMsg, "/spm_sysid/narx_model").coefficients) == \
            doc["coefficients"]
        assert json.loads(client.get_model().document) == doc
        # and the node goes on: the next goal runs on a fresh worker
        status, again = client.result(client.send(bag_path=arm_bag, generations=20), 60)
        assert status == GoalStatus.STATUS_SUCCEEDED and again.error_code == Code.NONE
    finally:
        stop(node)


def test_bad_goals_end_with_a_code_and_the_reason(ros_env, harness, tmp_path):
    node = start_node(ros_env)
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        cases = [
            ({"criterion": "xyz"}, "", Code.INVALID_SETTINGS, "unknown criterion 'xyz'"),
            ({"generations": "many"}, "", Code.INVALID_SETTINGS,
             "generations must be an integer"),
            ({"input_topic": "/other"}, "", Code.INVALID_SETTINGS,
             "input_topic is set when the node starts"),
            ({"no_such_setting": "1"}, "", Code.INVALID_SETTINGS, "unknown setting"),
            ({}, "", Code.TOO_FEW_SAMPLES, "too few samples: 0 paired samples"),
            ({}, tmp_path / "missing.mcap", Code.BAD_DATA, "missing.mcap"),
        ]
        for overrides, bag, code, words in cases:
            status, result = client.result(client.send(bag_path=bag, **overrides), 30)
            assert status == GoalStatus.STATUS_ABORTED, (overrides, result.message)
            assert result.error_code == code, (overrides, result.message)
            assert words in result.message, (overrides, result.message)
        assert not client.get_model().available  # nothing was published
        # a goal's override is checked by the parameters' schema: the same reason
        refused = harness.set_parameters("/spm_sysid", criterion="xyz")[0]
        assert not refused.successful
        status, result = client.result(client.send(criterion="xyz"), 30)
        assert result.message == f"invalid settings: {refused.reason}"
    finally:
        stop(node)


@pytest.mark.slow
def test_call_identify_uses_the_action_and_ctrl_c_cancels_the_goal(ros_env, harness, arm_bag):
    """``spm-sysid call identify`` as the README writes it: progress, then the answer."""
    node = start_node(ros_env, "seed:=1")
    call = [sys.executable, "-m", "spm_sysid.apps.main", "call", "identify"]
    try:
        harness.wait_ready()
        play_bag(ros_env, arm_bag)  # the README: replay, then call identify --show-model
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024)
        r = subprocess.run(call + ["--show-model"], capture_output=True,
                           text=True, env=ros_env, timeout=120, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        assert r.stdout.startswith("success: y(t) = 3.158y(t-1) - 4.439y(t-2)")
        # a summary to read (issue 30: it was 300 lines of JSON): equation, table, fits
        shown = r.stdout.splitlines()
        assert shown[1].startswith("y(t) = 3.158y(t-1)") and len(shown) < 30
        assert any(x.split()[:1] == ["y(t-1)"] and "[" in x for x in shown)  # interval
        assert any(x.startswith("fits: one-step fit") for x in shown)
        assert shown[-1].startswith("criterion: AIC -10744.78, certified optimal")
        progress = [p for p in r.stderr.splitlines()  # not a terminal: a line per phase
                    if not p.startswith("still waiting for")]
        assert progress[0].startswith("checking data") and any(
            p.startswith("search: generation ") for p in progress)
        assert not any(": 0, 0 structures" in p for p in progress), progress
        r = subprocess.run(call + ["--show-model", "--json", "--quiet"], capture_output=True,
                           text=True, env=ros_env, timeout=120, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        doc = json.loads(r.stdout.split("\n", 1)[1])
        assert doc["terms"] == EQ1

        # the example client of examples/, as its docstring says to run it
        r = subprocess.run([sys.executable, "examples/identify_action_client.py", str(arm_bag),
                            "generations=300"], capture_output=True, text=True, env=ros_env,
                           timeout=120, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        lines = r.stdout.splitlines()
        assert lines[0].startswith("AIC -10744.78, 8 terms, free-run fit")
        assert "y(t-1)" in lines[1] and "= y[t-1]^1" in lines[1] and "(+- " in lines[1]
        assert "phase" not in r.stdout and "search: step" in r.stderr  # feedback logged

        # a bag named from the caller's folder, not the node's (it resolved it from its own)
        r = subprocess.run(call + ["--bag", arm_bag.name, "--set", "generations=5", "--quiet"],
                           capture_output=True, text=True, env=ros_env, timeout=120,
                           cwd=arm_bag.parent)
        assert r.returncode == 0, r.stderr
        assert r.stdout.startswith("success: ") and "terms" in r.stdout, r.stdout
        r = subprocess.run(call + ["--set", "criterion=xyz"], capture_output=True, text=True,
                           env=ros_env, timeout=60, cwd=ROOT)
        assert r.returncode == 1
        assert r.stderr.strip().endswith("refused (INVALID_SETTINGS): invalid settings: "
                                         "unknown criterion 'xyz'; choose one of ['aic', "
                                         "'aicc', 'bic', 'pmic2'] or pass a callable "
                                         "f(sse, n, k, coefficients)")

        proc = subprocess.Popen(call + ["--bag", str(arm_bag), "--set", "generations=100000"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=ros_env, cwd=ROOT)
        first = proc.stderr.readline()  # the first feedback line: the goal runs
        while first.startswith("still waiting for"):  # discovery slower than 3 s (loaded)
            first = proc.stderr.readline()
        assert first.startswith("checking data"), first
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 130, err
        assert "canceled: canceled by the client" in err and out == ""
        assert json.loads(harness.latched(String, "/spm_sysid/model").data)["terms"] == EQ1
    finally:
        stop(node)


@pytest.mark.slow
def test_the_regressors_parameter_and_a_goals_override_reach_the_job(ros_env, harness, arm_bag):
    """``-p regressors:=friction`` identifies with the friction bases; a goal may override
    it, and an expression outside the grammar is refused with the reason."""
    node = start_node(ros_env, "seed:=1", "regressors:=friction")
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        status, result = client.result(client.send(bag_path=arm_bag), 120)
        assert status == GoalStatus.STATUS_SUCCEEDED, result.message
        doc = json.loads(result.document)
        regs = doc["term_space"]["regressors"]
        assert regs[:2] == ["sign(y(t-1)-y(t-2))", "abs(y(t-1)-y(t-2))"]
        assert regs[2].startswith("tanh((y(t-1)-y(t-2))/") and len(regs) == 3
        assert result.model.candidate_terms == doc_terms(doc) == 77

        status, result = client.result(client.send(bag_path=arm_bag, regressors="abs(u(t-1))"),
                                       120)
        assert status == GoalStatus.STATUS_SUCCEEDED, result.message
        assert json.loads(result.document)["term_space"]["regressors"] == ["abs(u(t-1))"]

        status, result = client.result(client.send(bag_path=arm_bag, regressors="y(t+1)"), 60)
        assert status == GoalStatus.STATUS_ABORTED
        assert result.error_code == Code.INVALID_SETTINGS, result.message
        assert "y(t+...) reads the future" in result.message
    finally:
        stop(node)


def doc_terms(doc: dict) -> int:
    """Candidate terms of a document's space, counted by the term space."""
    from spm_sysid.core.model.terms import TermSpace

    return TermSpace.from_dict(doc["term_space"]).n_terms
