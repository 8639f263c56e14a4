"""Over real DDS: the README's replay delivers every sample; the node stays healthy.

Every process here is real: sysid_node and bag_player started with the commands the
README shows, the test's rclpy node, publishers of the wrong type, kill -9.
"""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from std_msgs.msg import Float64MultiArray, String

from spm_sysid.core.io.bagio import is_rosbag2_dir

from .conftest import EQ1, ROOT
from .ros_harness import Harness, finish_publisher, publisher, start_node, stop

BIN = Path(sys.executable).parent
README_BAG = ROOT / "bags" / "robot_arm"


def _script(name: str) -> str:
    path = BIN / name
    return str(path) if path.exists() else shutil.which(name)


@pytest.fixture(scope="module")
def readme_bag():
    """bags/robot_arm as the README makes it (git-ignored), made once if missing."""
    if not is_rosbag2_dir(README_BAG):
        r = subprocess.run([_script("spm-sysid"), "make-bag", "--output", "bags/robot_arm",
                            "--rate", "100"], cwd=ROOT, capture_output=True, text=True,
                           timeout=120)
        # another test process may have made it at the same moment
        assert r.returncode == 0 or is_rosbag2_dir(README_BAG), r.stderr
    return README_BAG


def readme_node(env, *extra):
    """`sysid_node --ros-args --params-file config/sysid_node.yaml`, as the README says."""
    args = [_script("sysid_node"), "--ros-args", "--params-file", "config/sysid_node.yaml"]
    for p in extra:
        args += ["-p", p]
    return subprocess.Popen(args, env=env, cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def readme_player(env, rate="10.0"):
    """`bag_player --ros-args -p bag:=bags/robot_arm -p rate:=10.0`, as the README says."""
    return subprocess.run([_script("bag_player"), "--ros-args", "-p", "bag:=bags/robot_arm",
                           "-p", f"rate:={rate}"], env=env, cwd=ROOT, capture_output=True,
                          text=True, timeout=180)


def fast_player(env):
    """The same bag at 100x, where a test is not about the README's command."""
    return readme_player(env, "100.0")


def children(pid: int) -> list[int]:
    """Direct child processes of ``pid`` (from /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(entry.name))
    return out


def alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def wait_gone(pids, timeout=10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if not any(alive(p) for p in pids):
            return True
        time.sleep(0.1)
    return not any(alive(p) for p in pids)


@pytest.mark.slow
@pytest.mark.parametrize("rate, repeats", [("10.0", 3), ("1.0", 1)])
def test_readme_replay_delivers_every_pair_to_a_just_started_node(ros_env, harness, readme_bag,
                                                                 rate, repeats):
    for _ in range(repeats):
        node = readme_node(ros_env)
        try:
            # the player starts right after the node, as a user types the two commands
            player = readme_player(ros_env, rate)
            assert player.returncode == 0, player.stderr
            assert "delivery confirmed" in player.stderr and "NOT" not in player.stderr
            assert "/robot_arm/torque: 1024 published" in player.stderr
            kv = harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
            assert kv["samples"] == "1024" and kv["paired"] == "1024"
            assert kv["rejected_out_of_order"] == kv["unpaired_inputs"] == "0"
        finally:
            stop(node)


@pytest.mark.slow
def test_replaying_again_into_a_running_node_makes_a_new_segment(ros_env, harness,
                                                                 readme_bag):
    node = readme_node(ros_env, "seed:=1")
    try:
        assert readme_player(ros_env).returncode == 0
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
        time.sleep(2.0)  # the node has been running a while
        assert readme_player(ros_env).returncode == 0  # the same bag, same stamps, again
        kv = harness.wait_buffer(lambda kv: int(kv["samples"]) >= 2048, 30)
        res = harness.call("/spm_sysid/identify")
    finally:
        log = stop_and_log(node)
    assert kv["samples"] == "2048" and kv["time_jumps"] == "2"
    assert kv["rejected_out_of_order"] == "0" and kv["discarded_on_jump"] == "0"
    assert "stamps jumped back by 10.230 s" in log and "new segment" in log
    assert res.success, res.message
    assert "2048 samples in 2 contiguous segment(s); 0 gap(s)" in res.message
    assert "1 restart(s) of the stamps" in res.message


def stop_and_log(proc) -> str:
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


def test_player_without_subscribers_times_out_with_a_clear_error(ros_env, readme_bag):
    r = subprocess.run([_script("bag_player"), "--ros-args", "-p", "bag:=bags/robot_arm",
                        "-p", "wait_timeout:=1.0"], env=ros_env, cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert "no subscriber on /robot_arm/acceleration, /robot_arm/torque after 1 s" in r.stderr
    assert "nothing was published" in r.stderr and "Traceback" not in r.stderr


def test_interrupted_player_reports_counts_and_exits_nonzero(ros_env, harness, readme_bag):
    """SIGINT while it plays. The node is up first: on a loaded machine a node slower than
    the player's wait for subscribers (30 s) had the player end with 'no subscriber'."""
    node = readme_node(ros_env)
    try:
        harness.wait_ready()
        player = subprocess.Popen([_script("bag_player"), "--ros-args",
                                   "-p", "bag:=bags/robot_arm", "-p", "rate:=1.0"],
                                  env=ros_env, cwd=ROOT, stderr=subprocess.PIPE, text=True)
        kv = harness.wait_buffer(lambda kv: int(kv["samples"]) >= 100, 60)
        assert int(kv.get("samples", 0)) >= 100, kv
        player.send_signal(signal.SIGINT)
        _, err = player.communicate(timeout=20)
    finally:
        stop(node)
    assert player.returncode == 130, err
    assert "interrupted: /robot_arm/acceleration:" in err and " published" in err
    assert "Traceback" not in err


def test_nan_every_10th_sample_through_the_node_names_the_gaps(ros_env, harness):
    node = start_node(ros_env, "seed:=1", "min_samples:=100")
    try:
        harness.wait_ready()
        sent = finish_publisher(publisher(ros_env, 1000, 1024, "--nan-every", 10))
        kv = harness.wait_buffer(lambda kv: int(kv["received_outputs"]) >= 1024)
        res = harness.call("/spm_sysid/identify")
        doc = json.loads(harness.latched(String, "/spm_sysid/model").data)
        harness.diag.clear()
        harness.spin_until(lambda: "identification" in harness.statuses(), 10)
        ident = harness.statuses()["identification"]
    finally:
        stop(node)
    assert sent["nans"] == 103 and kv["rejected_nonfinite"] == "103"
    # every message acknowledged before the publisher ended (issue 30: a fixed 1 s sleep)
    assert sent["delivery_confirmed"] is True and kv["received_outputs"] == "1024"
    assert res.success, res.message
    assert ("918 samples in 102 contiguous segment(s); 102 gap(s) (102 samples missing), "
            "1 segment(s) too short to use (3 samples)") in res.message
    assert set(EQ1) <= set(doc["terms"]) and len(doc["terms"]) <= 9
    assert doc["metadata"]["data"]["gaps"] == 102
    assert ident[0] == 1 and "fitted around 102 gap(s)" in ident[1]
    assert ident[2]["data_gaps"] == "102"


def test_publisher_of_the_wrong_type_is_detected(ros_env, harness, tmp_path):
    logfile = (tmp_path / "node.log").open("w")
    node = start_node(ros_env, log=logfile)
    try:
        harness.wait_ready()
        wrong = harness.node.create_publisher(String, "/robot_arm/torque", 10)
        kv = harness.wait_buffer(lambda kv: kv.get("type_mismatch"), 20)
        level = harness.statuses()["buffer"][0]
        harness.node.destroy_publisher(wrong)
    finally:
        stop(node)
        logfile.close()
    log = (tmp_path / "node.log").read_text()
    assert "/test_harness publishes /robot_arm/torque as std_msgs/msg/String" \
        in kv["type_mismatch"]
    assert level == 2  # ERROR
    assert log.count("publishes /robot_arm/torque as std_msgs/msg/String") == 1  # logged once


def test_dead_worker_is_reported_and_restarted(ros_env, harness, readme_bag):
    node = start_node(ros_env, "seed:=1", "diagnostics_period:=0.2")
    try:
        harness.wait_ready()
        workers = children(node.pid)
        assert len(workers) == 1
        os.kill(workers[0], signal.SIGKILL)
        # the death is counted (a new worker may be ready again within one diagnostics
        # period: with the kernels' build it starts in about 0.2 s)
        kv = harness.wait_buffer(lambda kv: kv["worker_restarts"] == "1"
                                 and kv["worker_ready"] == "True", 60)
        assert kv["worker_restarts"] == "1" and kv["worker_ready"] == "True"
        assert children(node.pid) != workers  # a new process
        assert fast_player(ros_env).returncode == 0
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
        res = harness.call("/spm_sysid/identify")
        assert res.success and "AIC -10744.78" in res.message
    finally:
        stop(node)


def test_stuck_job_is_ended_by_the_job_timeout(ros_env, harness, readme_bag):
    node = start_node(ros_env, "generations:=100000", "job_timeout:=2.0")
    try:
        harness.wait_ready()
        assert fast_player(ros_env).returncode == 0
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
        res = harness.call("/spm_sysid/identify", timeout=60)  # 100 000 generations
        assert not res.success and "stopped after 2 s (job_timeout)" in res.message
        # the node works on: a short search after the timeout succeeds (with the time
        # limit lifted, so a loaded machine cannot make this one time out too)
        assert all(r.successful for r in harness.set_parameters(
            "/spm_sysid", generations=50, job_timeout=0.0))
        harness.wait_buffer(lambda kv: kv["worker_ready"] == "True", 60)
        assert harness.call("/spm_sysid/identify").success
    finally:
        stop(node)


def test_sigterm_during_a_search_stops_the_node_quickly(ros_env, harness, readme_bag):
    node = start_node(ros_env, "generations:=100000")
    harness.wait_ready()
    worker = children(node.pid)
    assert fast_player(ros_env).returncode == 0
    harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
    harness.call_async("/spm_sysid/identify")
    harness.spin_until(lambda: harness.statuses().get("identification", (0, ""))[1]
                       .startswith("running"), 20)
    node.send_signal(signal.SIGTERM)
    node.wait(timeout=60)  # it ends (a search of 100 000 generations would not)
    assert wait_gone(worker, 5.0)


def test_kill_9_leaves_no_process_behind(ros_env):
    node = start_node(ros_env, "generations:=100000")
    h = Harness(ros_env)
    try:
        h.wait_ready()
        kids = children(node.pid)
        grandkids = [g for k in kids for g in children(k)]
        assert kids
        node.send_signal(signal.SIGKILL)
        node.wait(timeout=10)
        assert wait_gone(kids + grandkids, 10.0), [p for p in kids + grandkids if alive(p)]
    finally:
        h.close()


def test_restarted_node_publishes_the_saved_model_again(ros_env, harness, readme_bag,
                                                       tmp_path):
    path = tmp_path / "models" / "arm.json"
    node = start_node(ros_env, "seed:=1", f"model_path:={path}")
    try:
        harness.wait_ready()
        assert fast_player(ros_env).returncode == 0
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
        assert harness.call("/spm_sysid/identify").success
    finally:
        stop(node)
    saved = json.loads(path.read_text())
    node = start_node(ros_env, f"model_path:={path}")
    try:
        harness.wait_ready()
        doc = json.loads(harness.latched(String, "/spm_sysid/model", 20).data)
        coefs = harness.latched(Float64MultiArray, "/spm_sysid/coefficients")
        harness.diag.clear()
        harness.spin_until(lambda: "identification" in harness.statuses(), 10)
        ident = harness.statuses()["identification"]
    finally:
        stop(node)
    assert doc == saved and doc["terms"] == EQ1
    assert list(coefs.data) == saved["coefficients"]
    assert "restored from" in ident[1]


@pytest.mark.slow
def test_model_path_is_checked_and_a_failed_save_publishes_nothing(ros_env, harness,
                                                                  readme_bag, tmp_path):
    (tmp_path / "afile").write_text("x")
    node = start_node(ros_env, "seed:=1", "generations:=40")
    try:
        harness.wait_ready()
        bad = harness.set_parameters("/spm_sysid", model_path=str(tmp_path / "afile" / "m.json"))
        assert not bad[0].successful and "not a directory" in bad[0].reason
        target = tmp_path / "d" / "m.json"
        assert harness.set_parameters("/spm_sysid", model_path=str(target))[0].successful
        (tmp_path / "d").write_text("now a file")  # the destination breaks after the check
        assert fast_player(ros_env).returncode == 0
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
        res = harness.call("/spm_sysid/identify")
        assert not res.success and "could not be saved" in res.message
        assert "nothing was published" in res.message
        assert harness.latched(String, "/spm_sysid/model", 3.0) is None
    finally:
        stop(node)


def test_unknown_fitness_parameter_is_refused(ros_env, harness):
    node = start_node(ros_env)
    try:
        harness.wait_ready()
        res = harness.set_parameters("/spm_sysid", fitness="nosuch")
        assert not res[0].successful and "fitness must be one of" in res[0].reason
    finally:
        stop(node)
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                        "-p", "fitness:=nosuch"], capture_output=True, text=True, env=ros_env,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "fitness must be one of" in r.stderr


def test_call_errors_go_to_stderr(ros_env):
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "call", "identify",
                        "--timeout", "1"], capture_output=True, text=True, env=ros_env,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.startswith("error: action /spm_sysid/identify is not available")
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "call", "identify",
                        "--trigger", "--timeout", "1"], capture_output=True, text=True,
                       env=ros_env, timeout=60, cwd=ROOT)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.startswith("error: service /spm_sysid/identify is not available")


@pytest.mark.slow
def test_the_readme_tutorial_as_written(ros_env, harness, readme_bag):
    """The README's five commands (the bag made by readme_bag): node, replay, identify, watch."""
    node = readme_node(ros_env, "dashboard_port:=8765")
    try:
        player = readme_player(ros_env)
        assert player.returncode == 0 and "delivery confirmed" in player.stderr
        import urllib.request

        with urllib.request.urlopen("http://127.0.0.1:8765/", timeout=10) as page:
            assert b"spm_sysid live" in page.read()  # the address the README gives
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= 1024, 30)
        r = subprocess.run([_script("spm-sysid"), "call", "identify", "--show-model"],
                           env=ros_env, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        out = r.stdout.splitlines()
        assert out[0].startswith("success: y(t) = 3.158y(t-1) - 4.439y(t-2)")
        assert "AIC -10744.78, 8 terms" in out[0]
        assert "fits: one-step fit 98.1 %, free-run fit 11.1 %" in out
        assert out[-1].startswith("criterion: AIC -10744.78, certified optimal over all")
        assert any(x.startswith("search: generation 0/300, best ") for x in
                   r.stderr.splitlines())
        watch = subprocess.Popen([_script("spm-sysid"), "call", "watch", "--timeout", "30"],
                                 env=ros_env, cwd=ROOT, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        assert watch.stdout.readline().startswith("VALID: ")  # the latched state at once
        assert readme_player(ros_env).returncode == 0  # step 3 again: the robot runs
        lines = []
        while not any("1020 samples monitored" in x for x in lines):
            line = watch.stdout.readline()
            assert line, watch.stderr.read()
            lines.append(line)
        watch.send_signal(signal.SIGINT)  # Ctrl-C
        rest, err = watch.communicate(timeout=30)
        assert watch.returncode == 0, err
        assert all(x.startswith("VALID: ") for x in lines + rest.splitlines()), lines
    finally:
        stop(node)
