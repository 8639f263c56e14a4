"""Over real DDS: a node that starts whatever is in its files, clear errors,
stamps that were never filled in, namesakes, back-pressure."""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import json
import subprocess
import sys

import numpy as np
from std_msgs.msg import String

from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace

from .conftest import ROOT, sine_record
from .ros_harness import start_node, stop


def _model_doc() -> dict:
    return NarxModel(TermSpace(ny=1, nu=1, degree=1), [0, 1], np.array([0.5, 0.1])).to_dict()


_BLINDING = {  # fields the node reads, crafted: /diagnostics raised, the monitor was blind
    "skipped": {"validation": {"correlation_tests_skipped": 5}},
    "monitor": {"monitor": {"version": 1, "samples": 1000, "sigma": 0.1, "innovation_sd": 0.1,
                            "whitening_ar": [], "cusum_mean_max": 1e300,
                            "cusum_variance_max": 1e300,
                            "windows": [{"window": 50, "ljung_box_max": 1e300,
                                         "rms_ratio_max": 1e300}]}},
}


@pytest.mark.parametrize("kind", ["nested", "huge", "nan", *_BLINDING])
def test_a_bad_model_path_file_does_not_stop_the_node(ros_env, harness, tmp_path, kind):
    """Deeply nested JSON (RecursionError), 10**400 (OverflowError), NaN: exit 1 before.

    Fields the node reads, of the wrong type or beyond what residuals can give: every
    diagnostics tick raised (nothing on /diagnostics), or the monitor stayed VALID at
    343 times the identification's residual RMS.
    """
    path = tmp_path / "model.json"
    if kind == "nested":
        path.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "huge":
        path.write_text(json.dumps(_model_doc()).replace("0.5", "1" + "0" * 400, 1))
    elif kind == "nan":
        path.write_text(json.dumps({**_model_doc(), "metadata": {"x": float("nan")}}))
    else:
        path.write_text(json.dumps({**_model_doc(), "metadata": _BLINDING[kind]}))
    before = path.read_bytes()
    log = open(tmp_path / "node.log", "w")
    node = start_node(ros_env, f"model_path:={path}", log=log)
    try:
        harness.wait_ready()
        assert node.poll() is None
        assert harness.latched(String, "/spm_sysid/model", 2.0) is None  # nothing re-published
    finally:
        stop(node)
    text = (tmp_path / "node.log").read_text()
    assert "holds no readable model" in text and "nothing re-published" in text
    assert "Traceback" not in text and path.read_bytes() == before
    if kind in _BLINDING:
        assert f"metadata.{next(iter(_BLINDING[kind]))}" in text, text


def test_a_topic_name_ros_refuses_is_one_error_line(ros_env):
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args", "-p",
                        "input_topic:=/" + "a" * 250], capture_output=True, text=True,
                       env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert "input_topic '/aaaa" in r.stderr and "is not a valid topic name" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_call_with_a_node_name_ros_refuses(ros_env):
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "call", "identify",
                        "--node", "bad name!!", "--timeout", "1"], capture_output=True,
                       text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.startswith("error: --node 'bad name!!' is not a valid ROS node name")


def test_zero_header_stamps_are_stamped_on_receipt_and_counted(ros_env, harness):
    """All-zero stamps kept one sample, and nothing named the stamps as the cause."""
    node = start_node(ros_env, "diagnostics_period:=0.2", "stamp_tolerance:=0.004")
    pub = subprocess.Popen([sys.executable, "-m", "spm_sysid.ros.signal_publisher", "100",
                            "300", "--stamps", "zero"], env=ros_env, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        harness.wait_ready()
        out, err = pub.communicate(timeout=120)
        assert pub.returncode == 0, err
        kv = harness.wait_buffer(lambda kv: int(kv["unset_stamps"]) >= 598, 30)
        level, message, _ = harness.statuses()["buffer"]
    finally:
        stop(node)
    assert kv["unset_stamps"] == "598"  # each topic's first 0 may be a real time
    # paired by receive time, not collapsed to one: most of the 300 pairs (a busy machine
    # delays some messages beyond the 4 ms tolerance: 241 of 300 once, under load)
    assert int(kv["samples"]) > 150
    assert level == 1 and "header.stamp never set (receive time used)" in message


def test_a_misspelled_parameter_is_named_in_the_log_and_diagnostics(ros_env, harness,
                                                                    tmp_path):
    """ROS keeps a value the node does not declare and says nothing: input_topc was lost."""
    params = tmp_path / "params.yaml"
    params.write_text("spm_sysid:\n  ros__parameters:\n    input_topc: /arm/torque\n"
                      "    seed: 3\n")
    log = open(tmp_path / "node.log", "w")
    node = start_node(ros_env, "genrations:=50", "qos_overrides./x.subscription.depth:=5",
                      params_file=params, log=log)
    try:
        harness.wait_ready()
        assert harness.spin_until(lambda: "ignored_parameters" in harness.buffer(), 30)
        level, message, values = harness.statuses()["buffer"]
    finally:
        stop(node)
        log.close()
    assert values["ignored_parameters"] == "genrations, input_topc"  # not qos_overrides
    assert level == 1 and "parameter(s) not of this node, ignored: genrations, input_topc" \
        in message
    text = (tmp_path / "node.log").read_text()
    assert "parameter 'genrations' is not one of this node's (did you mean 'generations'?): " \
           "ignored" in text
    assert "parameter 'input_topc' is not one of this node's (did you mean 'input_topic'?)" \
        in text


def test_a_second_node_with_the_same_name_is_reported(ros_env, harness):
    first = start_node(ros_env, "diagnostics_period:=0.2")
    second = start_node(ros_env, "diagnostics_period:=0.2")
    try:
        harness.wait_ready()
        assert harness.spin_until(
            lambda: harness.buffer().get("namesakes", "0") != "0", 30)
        assert "other node(s) with this node's name" in harness.statuses()["buffer"][1]
    finally:
        stop(second)
        stop(first)


def test_the_publisher_waits_out_back_pressure_and_never_crashes(ros_env, tmp_path):
    """A subscriber that never takes its messages: an error line and exit 1, no traceback."""
    sink = subprocess.Popen([sys.executable, "-c", (
        "import rclpy, time\n"
        "from rclpy.qos import QoSProfile, HistoryPolicy, ReliabilityPolicy\n"
        "from geometry_msgs.msg import WrenchStamped, AccelStamped\n"
        "rclpy.init(); n = rclpy.create_node('sink')\n"
        "q = QoSProfile(history=HistoryPolicy.KEEP_ALL, "
        "reliability=ReliabilityPolicy.RELIABLE)\n"
        "n.create_subscription(WrenchStamped, '/robot_arm/torque', lambda m: None, q)\n"
        "n.create_subscription(AccelStamped, '/robot_arm/acceleration', lambda m: None, q)\n"
        "rclpy.spin_once(n, timeout_sec=2.0)\n"
        "time.sleep(600)\n")], env=ros_env, cwd=ROOT)
    try:
        r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.signal_publisher", "50000",
                            "200000", "--backpressure-timeout", "2"], capture_output=True,
                           text=True, env=ros_env, timeout=240, cwd=ROOT)
    finally:
        sink.kill()
        sink.wait()
    assert "Traceback" not in r.stderr, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert r.returncode == 1 and summary["blocked"] > 0 and "error" in summary
    assert r.stderr.startswith("error: the subscriber did not take messages for 2 s")


def test_the_answer_and_diagnostics_carry_the_data_checks_warnings(ros_env, harness, tmp_path):
    """A sine input excites two lags of the four in the space: the node says so."""
    u, y = sine_record()
    data = tmp_path / "sine.dat"
    np.savetxt(data, np.column_stack([u, y]))
    node = start_node(ros_env, "generations:=20")
    try:
        harness.wait_ready()
        pub = subprocess.run([sys.executable, "-m", "spm_sysid.ros.signal_publisher", "400",
                              "400", "--data", str(data)], capture_output=True, text=True,
                             env=ros_env, timeout=120, cwd=ROOT)
        assert pub.returncode == 0, pub.stderr
        harness.wait_buffer(lambda kv: int(kv.get("samples", 0)) >= 400, 30)
        res = harness.call("/spm_sysid/identify")
        assert res.success, res.message
        assert ("WARNING: input u is persistently exciting of order 2 only: of its 4 lags "
                "only 2 can be told apart") in res.message
        assert harness.spin_until(lambda: "warnings" in harness.statuses(), 10)
        level, message, values = harness.statuses()["warnings"]
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)
    finally:
        stop(node)
    assert level == 1 and message.startswith(f"{len(doc['metadata']['warnings'])} warning(s)")
    assert any("persistently exciting of order 2" in v for v in values.values())
    assert doc["metadata"]["data_check"]["excitation_order"] == {"u": 2}


RESILIENT = """
import sys
import rclpy
from rclpy.node import Node
from spm_sysid.ros.common import CallbackErrors, run_node

class Faulty(Node):
    def __init__(self):
        super().__init__("faulty")
        self.callback_errors = CallbackErrors(self.get_logger())  # run_node counts into it
        self.ticks = 0
        self.create_timer(0.05, self.tick)

    def tick(self):
        self.ticks += 1
        if self.ticks in (2, 4):
            raise ValueError("a bad sample")
        if self.ticks >= 8:
            rclpy.try_shutdown()  # as SIGINT would

def finish(node, interrupted):
    print(f"ticks {node.ticks} callback_errors {node.callback_errors.count}")
    return 0

sys.exit(run_node(Faulty, errors=(ValueError,), finish=finish))
"""


def test_a_callback_that_raises_is_logged_and_counted_and_the_node_goes_on(ros_env):
    """Before, a ValueError in any callback while spinning was taken for a start-up error
    and stopped the node (exit 1)."""
    r = subprocess.run([sys.executable, "-c", RESILIENT], capture_output=True, text=True,
                       env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ticks 8 callback_errors 2"
    assert r.stderr.count("a callback raised ValueError: a bad sample") == 2
    assert "the node goes on" in r.stderr


SHUT_DOWN_MID_WAIT = """
import sys
import rclpy
from rclpy.node import Node
from spm_sysid.ros.common import run_node

class Player(Node):
    def __init__(self):
        super().__init__("player")
        self.create_timer(0.01, lambda: None)

def until(node):  # the context shut down after the loop's rclpy.ok(), before the wait
    rclpy.try_shutdown()  # as SIGINT does when it lands there
    return False

def finish(node, interrupted):
    print(f"interrupted {interrupted}")
    return 130 if interrupted else 0

sys.exit(run_node(Player, until=until, finish=finish))
"""


def test_a_context_shut_down_between_the_check_and_the_wait_is_an_interruption(ros_env):
    """SIGINT may shut the context down after the spin loop's rclpy.ok() and before the
    executor's wait, which then raises RCLError ('the given context is not valid'): a
    loaded CI run's bag_player printed that traceback and 'not every subscriber
    acknowledged', exit 1. Real rclpy, the race made certain by ``until``."""
    r = subprocess.run([sys.executable, "-c", SHUT_DOWN_MID_WAIT], capture_output=True,
                       text=True, env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 130, r.stderr
    assert r.stdout.strip() == "interrupted True"
    assert "Traceback" not in r.stderr and "RCLError" not in r.stderr
