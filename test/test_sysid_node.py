"""sysid_node over real DDS: node, player, publisher and this test in separate processes."""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import json
import subprocess
import sys

import numpy as np
from std_msgs.msg import Float64MultiArray, String

from spm_sysid.core.io.bagio import write_io_bag
from spm_sysid.core.model.narx import NarxModel

from .conftest import EQ1, ROOT
from .ros_harness import finish_publisher, publisher, start_node, stop
from .ros_harness import play_bag as play


@pytest.mark.slow
def test_replay_identify_and_latched_results(ros_env, harness, arm_bag, robot_arm, tmp_path):
    u, y = robot_arm
    model_path = tmp_path / "saved" / "model.json"
    node = start_node(ros_env, "seed:=1", f"model_path:={model_path}", "certify:=true")
    try:
        harness.wait_ready()
        play(ros_env, arm_bag)
        kv = harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024)
        assert kv["samples"] == "1024" and kv["received_inputs"] == "1024"
        assert kv["unpaired_inputs"] == kv["unpaired_outputs"] == "0"

        res = harness.call("/spm_sysid/identify")
        assert res.success, res.message
        assert "y(t) = 3.158y(t-1) - 4.439y(t-2)" in res.message
        assert "AIC -10744.78" in res.message and "8 terms" in res.message
        assert "1024 samples" in res.message
        assert "certified optimal over all structures" in res.message  # certify:=true
        assert harness.spin_until(lambda: "certified optimal" in harness.statuses().get(
            "identification", (0, ""))[1], 10)

        # subscribers that start after the result still get it (latched)
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)
        coefs = harness.latched(Float64MultiArray, "/spm_sysid/coefficients")
        resid = harness.latched(Float64MultiArray, "/spm_sysid/residuals")
    finally:
        stop(node)
    assert doc["schema"] == "spm_sysid/narx-model" and doc["schema_version"] == 3
    assert doc["uncertainty"]["method"] == "least squares"
    assert len(doc["uncertainty"]["standard_errors"]) == len(EQ1)
    assert doc["terms"] == EQ1
    assert doc["criterion"]["name"] == "aic"
    assert doc["criterion"]["value"] == pytest.approx(-10744.78, abs=0.01)
    assert doc["term_space"] == {"ny": 4, "nu": 4, "degree": 2, "delay": 1, "constant": False,
                                 "inputs": ["u"], "output": "y"}
    meta = doc["metadata"]
    assert meta["samples_used"] == 1024
    assert meta["first_stamp_ns"] == 0 and meta["last_stamp_ns"] == 1023 * 10_000_000
    val = meta["validation"]
    assert val["one_step"]["max_abs"] == pytest.approx(0.01467, abs=5e-5)
    assert val["free_run"]["mse"] > val["one_step"]["mse"]
    assert {t["name"] for t in val["correlation_tests"]} == {"ee", "ue", "e_eu", "u2_e", "u2_e2"}
    # coefficients: same order as the JSON terms, layout labelled with them
    assert list(coefs.data) == doc["coefficients"]
    assert coefs.layout.dim[0].size == 8 and "y(t-1); y(t-2)" in coefs.layout.dim[0].label
    # residuals: equal to an independent computation from the model on the data
    model = NarxModel.from_dict(doc)
    expected = y[4:] - model.predict(u, y)
    assert len(resid.data) == 1020 == resid.layout.dim[0].size
    assert np.allclose(resid.data, expected, atol=1e-12)
    # the saved model loads and validates with the command line
    assert NarxModel.load(model_path).terms == EQ1
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "validate",
                        str(model_path), "--tail", "0.5"], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "validation on holdout data" in r.stdout


def test_diagnostics_report_buffer_and_correlation_tests(ros_env, harness, arm_bag):
    node = start_node(ros_env, "seed:=2", "diagnostics_period:=0.2")
    try:
        harness.wait_ready()
        play(ros_env, arm_bag, rate=20.0)
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024)
        assert harness.call("/spm_sysid/identify").success
        harness.diag.clear()
        harness.spin_until(lambda: "correlation ee" in harness.statuses(), 10)
        st = harness.statuses()
        # the documented example client, as another node in its own process
        example = subprocess.run([sys.executable, str(ROOT / "examples" /
                                                      "identify_from_node.py")],
                                 capture_output=True, text=True, env=ros_env, timeout=120)
    finally:
        stop(node)
    assert example.returncode == 0, example.stderr
    assert "identified: y(t) = 3.158y(t-1)" in example.stderr
    assert "model: y(t) = 3.158*y(t-1) + -4.439*y(t-2)" in example.stderr
    assert st["buffer"][0] == 0 and st["buffer"][2]["samples"] == "1024"
    assert st["identification"][0] == 0
    # eq. (1) leaves residual autocorrelation outside the band (paper Fig. 5): WARN
    assert st["correlation ee"][0] == 1 and "outside" in st["correlation ee"][1]
    assert st["correlation e_eu"][0] == 0 and "inside" in st["correlation e_eu"][1]


@pytest.mark.slow
def test_no_sample_lost_at_1khz_while_identify_runs(ros_env, harness):
    # a long search (6000 generations, several seconds) so recording and identification
    # overlap, and diagnostics (every 0.2 s) show it running
    node = start_node(ros_env, "generations:=6000", "min_samples:=500", "seed:=3",
                      "diagnostics_period:=0.2")
    try:
        harness.wait_ready()
        pub = publisher(ros_env, 1000, 6000)  # 1 kHz on both topics for 6 s
        assert json.loads(pub.stdout.readline())["started"]
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024)
        first = harness.call_async("/spm_sysid/identify")
        harness.spin_until(lambda: harness.statuses().get("identification", (0, ""))[1]
                           .startswith("running"), 10)
        second = harness.call("/spm_sysid/identify")  # while the first one runs
        harness.spin_until(first.done, 120)
        sent = finish_publisher(pub)
        kv = harness.wait_buffer(lambda kv: int(kv["received_outputs"]) >= sent["published"],
                                 timeout=20)
    finally:
        stop(node)
    assert not second.success and "already running" in second.message
    assert first.result().success, first.result().message
    assert int(kv["received_inputs"]) == int(kv["received_outputs"]) == sent["published"]
    assert kv["samples"] == "6000" and kv["unpaired_inputs"] == "0"


def test_bad_samples_are_counted_not_buffered(ros_env, harness):
    node = start_node(ros_env, "buffer_capacity:=100", "stamp_tolerance:=0.0001")
    try:
        harness.wait_ready()
        # every 10th output NaN: 30 rejected of 300, their inputs left unpaired
        pub = publisher(ros_env, 500, 300, "--nan-every", 10)
        sent = finish_publisher(pub)
        kv = harness.wait_buffer(lambda kv: int(kv["received_outputs"]) >= 300)
        assert sent["nans"] == 30
        assert kv["rejected_nonfinite"] == "30"
        assert int(kv["paired"]) == 270
        assert int(kv["unpaired_inputs"]) + int(kv["pending_inputs"]) == 30
        # the buffer is full: 270 pairs through a capacity of 100
        assert kv["samples"] == "100" and kv["dropped_oldest"] == "170"
        assert harness.statuses()["buffer"][0] == 1  # WARN: samples were rejected

        assert harness.call("/spm_sysid/clear").message == "cleared 100 samples"
        # outputs stamped 5 ms after their inputs: beyond the 0.1 ms tolerance
        pub = publisher(ros_env, 500, 100, "--output-offset-ns", 5_000_000,
                        "--start-ns", 10**9)
        finish_publisher(pub)
        kv = harness.wait_buffer(lambda kv: int(kv["received_outputs"]) >= 400)
        assert kv["samples"] == "0"
        assert int(kv["unpaired_inputs"]) + int(kv["unpaired_outputs"]) \
            + int(kv["pending_inputs"]) + int(kv["pending_outputs"]) >= 200 - 1 + 30
    finally:
        stop(node)


def test_refusals_and_parameter_validation_keep_the_node_working(ros_env, harness, arm_bag):
    node = start_node(ros_env, "seed:=4")
    try:
        harness.wait_ready()
        res = harness.call("/spm_sysid/identify")
        assert not res.success and "too few samples: 0 paired samples" in res.message

        results = harness.set_parameters("/spm_sysid", criterion="nope")
        assert not results[0].successful and "unknown criterion" in results[0].reason
        results = harness.set_parameters("/spm_sysid", spm_fraction=0.9)
        assert not results[0].successful
        results = harness.set_parameters("/spm_sysid", buffer_capacity=5)
        assert not results[0].successful  # read-only
        # SetParameters applies one at a time: ny=0 alone is fine, then nu=0 is not
        results = harness.set_parameters("/spm_sysid", ny=0, nu=0)
        assert results[0].successful
        assert not results[1].successful and "at least one" in results[1].reason
        assert harness.set_parameters("/spm_sysid", ny=4)[0].successful

        assert harness.set_parameters("/spm_sysid", criterion="bic")[0].successful
        play(ros_env, arm_bag, rate=20.0)
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024)
        res = harness.call("/spm_sysid/identify")
        assert res.success and "BIC -10707.48" in res.message and "7 terms" in res.message
    finally:
        stop(node)


def test_parameters_from_the_yaml_file_take_effect(ros_env, harness, arm_bag, tmp_path):
    import yaml

    defaults = yaml.safe_load((ROOT / "config" / "sysid_node.yaml").read_text())
    params = defaults["spm_sysid"]["ros__parameters"]
    params.update(buffer_capacity=2000, criterion="bic", min_samples=20, seed=5,
                  generations=120)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(defaults))
    node = start_node(ros_env, params_file=path)
    try:
        harness.wait_ready()
        assert harness.buffer()["capacity"] == "2000"
        play(ros_env, arm_bag, rate=20.0)
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024)
        res = harness.call("/spm_sysid/identify")
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)
    finally:
        stop(node)
    assert res.success and "BIC" in res.message
    assert doc["criterion"]["name"] == "bic" and doc["metadata"]["ga"]["generations"] == 120


def test_invalid_startup_parameters_exit_with_a_clear_error(ros_env):
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                        "-p", "input_type:=geometry_msgs/msg/Nope"],
                       capture_output=True, text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "not installed" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                        "-p", "criterion:=xyz"],
                       capture_output=True, text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "unknown criterion" in r.stderr
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                        "-p", "criterion:=1"],  # a number where text is expected
                       capture_output=True, text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert r.stderr.startswith("error: Trying to set parameter 'criterion' to '1' of type "
                               "'INTEGER', expecting type 'STRING'")


def test_two_joint_efforts_recorded_from_one_jointstate_topic(ros_env, harness, tmp_path):
    """The node with a list of inputs: effort[0] and effort[1] of sensor_msgs/JointState."""
    rng = np.random.default_rng(3)
    n = 600
    u = rng.uniform(-1, 1, (n, 2))
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.5 * y[t - 1] + 0.7 * u[t - 1, 0] - 0.4 * u[t - 1, 1] \
            + 0.3 * u[t - 2, 0] * u[t - 1, 1]
    y += 1e-3 * rng.standard_normal(n)
    bag = write_io_bag(tmp_path / "joints", u, y, input_topic="/arm/joint_states")
    node = start_node(ros_env, "seed:=1", "criterion:=bic", "ny:=2", "nu:=2",
                      "input_topic:=/arm/joint_states",
                      "input_type:=sensor_msgs/msg/JointState",
                      "input_field:=effort[0],effort[1]", "input_names:=shoulder,elbow")
    try:
        harness.wait_ready()
        play(ros_env, bag)
        kv = harness.wait_buffer(lambda kv: int(kv["samples"]) >= n)
        assert kv["samples"] == str(n) and kv["received_inputs"] == str(n)
        res = harness.call("/spm_sysid/identify")
        assert res.success, res.message
        assert ("y(t) = 0.500y(t-1) + 0.700shoulder(t-1) - 0.400elbow(t-1) "
                "+ 0.300shoulder(t-2)*elbow(t-1)") in res.message
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)
        assert doc["term_space"]["inputs"] == ["shoulder", "elbow"]
        topics = doc["metadata"]["topics"]  # what validate --bag reads by default
        assert (topics["input_topic"], topics["input_field"], topics["input_names"]) == (
            "/arm/joint_states", "effort[0],effort[1]", "shoulder,elbow")
        (tmp_path / "model.json").write_text(json.dumps(doc))
        r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "validate",
                            str(tmp_path / "model.json"), "--bag", str(bag)],
                           capture_output=True, text=True, env=ros_env, timeout=120, cwd=ROOT)
        assert r.returncode == 0, r.stderr
        assert "--input-topic /arm/joint_states, --input-field effort[0],effort[1]" in r.stdout
        assert "free-run: MSE" in r.stdout
    finally:
        stop(node)


def test_inconsistent_input_lists_stop_the_node_with_a_message(ros_env):
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                        "-p", "input_topic:=/a,/b,/c", "-p", "input_field:=x,y"],
                       capture_output=True, text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode != 0
    assert "input_field lists 2 entries for 3 inputs" in r.stderr + r.stdout
