"""Over real DDS: a goal never freezes the node; every request gets an answer.

A real sysid_node process; this test's rclpy node is the client.
"""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import os

from action_msgs.msg import GoalStatus
from spm_sysid_interfaces.action import Identify

from spm_sysid.ros.common import REQUESTS

from .ros_harness import IdentifyClient, start_node, stop

Code = Identify.Result


def test_a_pipe_as_the_goals_bag_ends_at_once_and_the_node_stays_responsive(
        ros_env, harness, arm_bag, tmp_path):
    fifo = tmp_path / "f.mcap"
    os.mkfifo(fifo)
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text((arm_bag / "metadata.yaml").read_text())
    os.mkfifo(bag / "robot_arm.mcap")  # the name the metadata lists, as a pipe
    node = start_node(ros_env, "seed:=1")
    try:
        harness.wait_ready()
        client = IdentifyClient(harness)
        for path, words in ((fifo, "is a pipe, not a bag"),
                            (bag, "robot_arm.mcap is a pipe, not a bag file")):
            status, result = client.result(client.send(bag_path=path), timeout=60)
            assert status == GoalStatus.STATUS_ABORTED
            assert result.error_code == Code.BAD_DATA and words in result.message, \
                result.message
        # the node answers on: its model service, and a goal on a real bag
        assert not client.get_model().available
        status, result = client.result(client.send(bag_path=arm_bag), timeout=120)
        assert status == GoalStatus.STATUS_SUCCEEDED and "AIC -10744.78" in result.message
    finally:
        stop(node)


def test_thirty_goals_and_thirty_cancels_at_once_each_get_an_answer(ros_env, harness, arm_bag):
    """30 goals at once, then 30 cancels at once: each gets an answer.

    Before, the server kept the last 10 requests: the others were never answered. The
    clients keep 1000 answers, as ``spm-sysid call`` does: with rclpy's default (the
    last 10) a client that sends a burst before it spins loses answers on its own side,
    which no server can prevent (the clients of one node share the answers' topic).
    """
    from action_msgs.srv import CancelGoal
    node = start_node(ros_env, "seed:=1")
    try:
        harness.wait_ready()
        client = harness.action_client(Identify, "/spm_sysid/identify",
                                       goal_service_qos_profile=REQUESTS,
                                       result_service_qos_profile=REQUESTS)
        assert client.wait_for_server(timeout_sec=30.0)
        goal = Identify.Goal(setting_names=["generations"], setting_values=["100000"],
                             bag_path=str(arm_bag))
        sent = [client.send_goal_async(goal) for _ in range(30)]  # before any spin
        assert harness.spin_until(lambda: all(f.done() for f in sent), 60), \
            f"{sum(f.done() for f in sent)} of 30 goals answered"
        handles = [f.result() for f in sent]
        assert all(h.accepted for h in handles)
        results = [h.get_result_async() for h in handles]
        # 29 end at once, BUSY; one runs (a long search)
        assert harness.spin_until(lambda: sum(r.done() for r in results) >= 29, 60)
        busy = [r.result().result for r in results if r.done()]
        assert len(busy) == 29 and all(b.error_code == Code.BUSY for b in busy)
        (running,) = [h for h, r in zip(handles, results) if not r.done()]
        canceller = harness.node.create_client(
            CancelGoal, "/spm_sysid/identify/_action/cancel_goal", qos_profile=REQUESTS)
        assert canceller.wait_for_service(timeout_sec=30.0)
        request = CancelGoal.Request()
        request.goal_info.goal_id = running.goal_id
        cancels = [canceller.call_async(request) for _ in range(30)]
        assert harness.spin_until(lambda: all(c.done() for c in cancels), 60), \
            f"{sum(c.done() for c in cancels)} of 30 cancels answered"
        assert harness.spin_until(lambda: all(r.done() for r in results), 60)
        last = results[handles.index(running)].result()
        assert last.status == GoalStatus.STATUS_CANCELED and \
            last.result.error_code == Code.CANCELED, (last.status, last.result.message)
    finally:
        stop(node)


def test_call_with_no_node_says_at_once_that_it_waits(ros_env):
    import subprocess
    import sys

    from .conftest import ROOT

    proc = subprocess.Popen([sys.executable, "-m", "spm_sysid.apps.main", "call", "clear",
                             "--timeout", "8"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ros_env, cwd=ROOT)
    first = proc.stderr.readline()  # before the timeout: it says what it waits for
    assert first.startswith("still waiting for /spm_sysid/clear after 3 s")
    assert "sysid_node running" in first
    assert proc.poll() is None
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "is not available" in err


def test_sysid_node_without_its_messages_built_is_one_error_line(ros_env):
    import subprocess
    import sys

    from .conftest import ROOT

    code = ("import sys; sys.modules['spm_sysid_interfaces'] = None\n"  # as if never built
            "from spm_sysid.ros.entry import sysid_node; sys.exit(sysid_node([]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=ros_env, cwd=ROOT, timeout=120)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [r.stderr.strip()]  # one line, no traceback
    assert "spm_sysid_interfaces" in r.stderr and "make setup" in r.stderr
