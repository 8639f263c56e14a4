"""bag_player over real DDS: player and subscriber in separate processes."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.io.bagio import write_io_bag

from .conftest import ROOT

HELPER = str(ROOT / "test" / "helpers" / "record_topics.py")


def player_cmd(*params):
    args = [sys.executable, "-m", "spm_sysid.ros.bag_player", "--ros-args"]
    for p in params:
        args += ["-p", p]
    return args


def _record(env, expected, timeout, *topics):
    rec = subprocess.Popen([sys.executable, HELPER, str(expected), str(timeout), *topics],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert rec.stdout.readline().strip() == "ready"
    return rec


def test_subscriber_receives_every_message_in_order_at_10x(arm_bag, robot_arm, ros_env):
    u, y = robot_arm
    rec = _record(ros_env, 1024, 60)
    player = subprocess.run(player_cmd(f"bag:={arm_bag}", "rate:=10.0",
                                       "wait_for_subscribers:=1"),
                            capture_output=True, text=True, env=ros_env, timeout=90)
    out, err = rec.communicate(timeout=90)
    assert player.returncode == 0, player.stderr
    assert "published 2048 messages" in player.stderr + player.stdout
    assert "/robot_arm/torque: 1024 published, 1 subscriber(s), delivery confirmed" \
        in player.stderr
    got = json.loads(out.strip().splitlines()[-1])
    assert np.array_equal(got["u"], u) and np.array_equal(got["y"], y)  # all, in order
    assert got["tu"] == got["ty"] == [k * 10_000_000 for k in range(1024)]


def test_topic_selection_and_remapping(tmp_path, ros_env):
    bag = write_io_bag(tmp_path / "small", np.arange(20.0), -np.arange(20.0))
    rec = _record(ros_env, 20, 60, "/robot_arm/torque", "/renamed/acc")
    player = subprocess.run(
        player_cmd(f"bag:={bag}", "rate:=20.0", "wait_for_subscribers:=1",
                   "remap:=['/robot_arm/acceleration:=/renamed/acc']", "rat:=5.0"),
        capture_output=True, text=True, env=ros_env, timeout=60)
    got = json.loads(rec.communicate(timeout=60)[0].strip().splitlines()[-1])
    assert player.returncode == 0, player.stderr
    # a parameter it does not have is said, not kept silently
    assert "parameter 'rat' is not one of this node's (did you mean 'rate'?): ignored" \
        in player.stderr, player.stderr
    assert got["y"] == (-np.arange(20.0)).tolist() and got["u"] == np.arange(20.0).tolist()

    rec = _record(ros_env, "20,0", 60)  # nothing may arrive on the other topic
    player = subprocess.run(
        player_cmd(f"bag:={bag}", "rate:=20.0", "topics:=['/robot_arm/torque']",
                   "wait_for_subscribers:=1"),
        capture_output=True, text=True, env=ros_env, timeout=60)
    got = json.loads(rec.communicate(timeout=60)[0].strip().splitlines()[-1])
    assert player.returncode == 0, player.stderr
    assert len(got["u"]) == 20 and got["y"] == []


@pytest.mark.parametrize("params, message", [
    ([], "parameter 'bag' is required"),
    (["bag:=/no/such/bag"], "bag not found"),
    (["bag:=/tmp", "rate:=2.0"], "no metadata.yaml"),
    (["rate:=0.0", "bag:=x"], "'rate' must be > 0"),
])
def test_player_errors_exit_nonzero_with_one_line(params, message, ros_env):
    r = subprocess.run(player_cmd(*params), capture_output=True, text=True, env=ros_env,
                       timeout=30)
    assert r.returncode == 1
    assert message in r.stderr and "Traceback" not in r.stderr


def test_player_reports_missing_topic(arm_bag, ros_env):
    r = subprocess.run(player_cmd(f"bag:={arm_bag}", "topics:=['/nope']"),
                       capture_output=True, text=True, env=ros_env, timeout=30)
    assert r.returncode == 1 and "has no topic /nope" in r.stderr


def test_loop_replays_until_stopped(tmp_path, ros_env):
    import signal

    bag = write_io_bag(tmp_path / "tiny", np.arange(10.0), np.arange(10.0))
    rec = _record(ros_env, 30, 30)
    player = subprocess.Popen(player_cmd(f"bag:={bag}", "rate:=20.0", "loop:=true",
                                         "wait_for_subscribers:=1"),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=ros_env)
    got = json.loads(rec.communicate(timeout=60)[0].strip().splitlines()[-1])
    assert player.poll() is None  # still looping
    player.send_signal(signal.SIGINT)
    player.communicate(timeout=20)
    assert len(got["u"]) >= 30
    assert got["u"][:30] == (np.arange(30) % 10).astype(float).tolist()
