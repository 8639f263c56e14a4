"""Several outputs through the node, over real DDS: a JointState topic in, one coupled model out.

A robot driver publishes one ``sensor_msgs/msg/JointState`` topic with the
joint efforts (inputs) and velocities (outputs). Here that topic is an MCAP
bag written with rosbags and replayed by ``bag_player``; the node reads
``effort[0],effort[1]`` as inputs and ``velocity[0],velocity[1]`` as outputs
of the same topic.
"""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import json
import subprocess
import sys

import numpy as np
from spm_sysid_interfaces.msg import NarxModelSet, Prediction, Validity

from spm_sysid.core.io.bagio import read_bag_signals

from .conftest import JOINT_STATE_PARAMS, ROOT, TRUE, two_output_system, write_joint_state_bag
from .helpers.two_joints import two_joint_record
from .ros_harness import IdentifyClient, play_bag, start_node, stop

# the joints by name (their order in the messages is the publisher's); by index: test_dashboard
PARAMS = tuple(p.replace("[0]", "[j1]").replace("[1]", "[j2]") for p in JOINT_STATE_PARAMS)


@pytest.mark.slow
def test_the_node_identifies_two_joints_from_a_joint_state_topic(ros_env, harness, tmp_path):
    u, Y = two_output_system(1200, seed=3)
    # the joints in either order, and a gripper's messages on the same topic
    bag = write_joint_state_bag(tmp_path / "joints", u, Y, shuffled=True, gripper_every=10)
    node = start_node(ros_env, *PARAMS)
    try:
        harness.wait_ready()
        play_bag(ros_env, bag)
        kv = harness.wait_buffer(lambda kv: int(kv["samples"]) >= len(Y))
        # 120 gripper messages, each skipped by the input and the output subscription
        assert kv["unnamed"] == "240" and kv["field_errors"] == "0"
        level, message, _ = harness.statuses()["buffer"]
        assert "240 message(s) skipped that do not name the joint(s)" in message
        client = IdentifyClient(harness)
        status, result = client.result(client.send())
        assert result.error_code == result.NONE, result.message
        models = result.models
        assert list(models.output_names) == ["y1", "y2"]
        assert list(models.input_names) == ["u1", "u2"]
        for name, m in zip(("y1", "y2"), models.models):
            # noise-free: exactly the true structure, cross terms included
            got = dict(zip([t.name for t in m.terms], m.coefficients))
            assert set(got) == set(TRUE[name]), (name, sorted(got))
            for term, c in TRUE[name].items():
                assert abs(got[term] - c) < 1e-6
            assert m.output_name == name
            assert list(m.input_names) == ["u1", "u2", "y2" if name == "y1" else "y1"]
        assert len(models.reports) == 2
        assert all(r.free_run.fit_percent > 99.0 for r in models.reports)
        assert [t.name for t in models.cross_correlation_tests] == ["cross_y1_y2"]
        assert models.joint_criterion_value == sum(m.criterion_value for m in models.models)
        doc = json.loads(result.document)
        assert doc["schema"] == "spm_sysid/narx-mimo-model" and doc["outputs"] == ["y1", "y2"]
        latched = harness.latched(NarxModelSet, "/spm_sysid/narx_models")
        assert [len(m.terms) for m in latched.models] == [len(m.terms) for m in models.models]
        got_model = client.get_model()
        assert got_model.available and len(got_model.models.models) == 2

        # online: the same motion again, each output predicted and monitored
        predictions = []
        sub = harness.node.create_subscription(Prediction, "/spm_sysid/prediction",
                                               predictions.append, 5000)
        play_bag(ros_env, bag)
        harness.spin_until(lambda: len(predictions) >= 2 * (len(Y) - 20), 30)
        harness.node.destroy_subscription(sub)
        by_output = {n: [p for p in predictions if p.output_name == n] for n in ("y1", "y2")}
        assert all(len(v) >= len(Y) - 20 for v in by_output.values())
        for name in ("y1", "y2"):
            res = np.array([p.residual for p in by_output[name]])
            assert np.max(np.abs(res)) < 1e-6, name  # the exact model predicts exactly
        v = harness.latched(Validity, "/spm_sysid/validity")
        assert list(v.output_names) == ["y1", "y2"]
        assert len(v.output_states) == 2 and v.state != Validity.NO_MODEL
    finally:
        stop(node)


def test_a_goal_reads_two_outputs_from_a_bag_with_the_node_topics(ros_env, harness, tmp_path):
    u, Y = two_output_system(800, seed=4)
    bag = write_joint_state_bag(tmp_path / "joints", u, Y)
    sig = read_bag_signals(bag, input_topic="/joint_states", input_field="effort[0],effort[1]",
                           output_topic="/joint_states",
                           output_field="velocity[0],velocity[1]")
    np.testing.assert_array_equal(sig.y, Y)
    node = start_node(ros_env, *PARAMS)
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        status, result = client.result(client.send(bag_path=str(bag)))
        assert result.error_code == result.NONE, result.message
        assert [m.output_name for m in result.models.models] == ["y1", "y2"]
        assert "y1:" in result.message and "y2:" in result.message
        # the single-output fields stay empty for a coupled model
        assert len(result.model.terms) == 0
        # the example client reads every output
        r = subprocess.run([sys.executable, "examples/identify_action_client.py", str(bag)],
                           capture_output=True, text=True, env=ros_env, timeout=120, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        heads = [line for line in r.stdout.splitlines() if line.startswith("output ")]
        assert [h.split(":")[0] for h in heads] == ["output y1", "output y2"]
        assert all("(coupled)" in h for h in heads)
        assert "joint BIC" in r.stdout
    finally:
        stop(node)


@pytest.mark.slow
def test_a_goal_with_the_friction_preset_gives_each_joint_its_sign_term(ros_env, harness,
                                                                       tmp_path):
    """Two joints with Coulomb friction: the goal's override ``regressors: friction``."""
    u, Y = two_joint_record(1500, seed=5)
    bag = write_joint_state_bag(tmp_path / "joints", u, Y)
    node = start_node(ros_env, *PARAMS)
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        status, result = client.result(client.send(bag_path=str(bag), regressors="friction",
                                                   ny=2, nu=1, degree=1, criterion="bic"))
        assert result.error_code == result.NONE, result.message
        for name, m in zip(("y1", "y2"), result.models.models):
            names = [t.name for t in m.terms]
            own = f"sign({name}(t-1)-{name}(t-2))"
            assert own in names, (name, names)
            assert m.coefficients[names.index(own)] < 0  # against the motion
        doc = json.loads(result.document)
        assert all(len(d["term_space"]["regressors"]) == 6 for d in doc["models"])
    finally:
        stop(node)


@pytest.mark.parametrize("extra, message", [
    (("output_names:=u1,y2",), "an input and an output share the name u1"),
    (("output_field:=effort[0],velocity[1]",), "output y1 reads the same field of "
                                               "/joint_states as an input"),
    (("output_field:=velocity[0]",), "two outputs read the same field of the same topic"),
])
def test_outputs_that_clash_with_the_inputs_are_one_error_line(ros_env, extra, message):
    params = [p for p in JOINT_STATE_PARAMS if not p.startswith(
        tuple(e.split(":=")[0] + ":=" for e in extra))] + list(extra)
    args = [sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args"]
    for p in params:
        args += ["-p", p]
    r = subprocess.run(args, capture_output=True, text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 1
    assert message in r.stderr, r.stderr
