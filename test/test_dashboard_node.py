"""The live dashboard served by a real sysid_node, read by a real headless Chromium."""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")
pytestmark = pytest.mark.ros

import json
import socket
import struct
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

from spm_sysid_interfaces.msg import Prediction, Validity

from spm_sysid.core.io.bagio import write_io_bag

from .conftest import EQ1
from .ros_harness import ROOT, play_bag, start_node, stop


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url: str, method: str = "GET"):
    """(status, body) of a request to the dashboard."""
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method=method),
                                    timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def wait_http(url: str, timeout: float = 30.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            return get(url)
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"nothing answers at {url}")


@pytest.mark.slow
def test_the_live_page_shows_validity_the_model_and_the_predictions(
        ros_env, harness, browser, robot_arm, tmp_path):
    u, y = robot_arm
    arm = write_io_bag(tmp_path / "arm", u, y)
    scaled = write_io_bag(tmp_path / "scaled", 1.5 * u, 1.5 * y)
    port = free_port()
    node = start_node(ros_env, "seed:=1", f"dashboard_port:={port}")
    page = browser.new_page()
    try:
        harness.wait_ready()
        base = f"http://127.0.0.1:{port}/"
        assert wait_http(base)[0] == 200
        page.goto(base)
        page.wait_for_function("window.spmDashboard && spmDashboard.updates > 0")
        assert page.inner_text("#state") == "NO MODEL"
        play_bag(ros_env, arm)
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= len(y))
        res = harness.call("/spm_sysid/identify")
        assert res.success and "8 terms" in res.message
        page.wait_for_function("spmDashboard.state && spmDashboard.state.model && "
                               "spmDashboard.state.monitor.state === 'VALID'", timeout=10000)
        # a model that has predicted nothing yet is not called valid: nothing was checked
        assert page.inner_text("#state") == "WAITING FOR SAMPLES"
        terms = page.eval_on_selector_all("#model td.term", "c => c.map(x => x.textContent)")
        assert terms == EQ1
        origin = page.evaluate("performance.timeOrigin")

        # the bag again: what the page plots equals ~/prediction at the same stamps
        predictions = []
        sub = harness.node.create_subscription(Prediction, "/spm_sysid/prediction",
                                               predictions.append, 2000)
        play_bag(ros_env, arm)
        harness.spin_until(lambda: len(predictions) >= len(y) - 4, 30)
        harness.node.destroy_subscription(sub)
        sent = {p.header.stamp.sec * 10**9 + p.header.stamp.nanosec: p for p in predictions}
        # the page keeps every stride-th sample (about 1000 a window): wait for one of the
        # last 50 sent to be its newest
        recent = sorted(sent)[-50]
        page.wait_for_function(
            "(recent) => { const s = spmDashboard.state.outputs.y; if (!s) return false;"
            " const n = s.stamp_sec.length - 1;"
            " return BigInt(s.stamp_sec[n]) * 1000000000n + BigInt(s.stamp_nanosec[n])"
            " >= BigInt(recent); }", arg=str(recent), timeout=10000)
        shown = page.evaluate("spmDashboard.state.outputs.y")
        matched = 0
        for sec, nsec, m, p in zip(shown["stamp_sec"], shown["stamp_nanosec"],
                                   shown["measured"], shown["predicted"]):
            msg = sent.get(sec * 10**9 + nsec)
            if msg is not None:
                matched += 1
                assert (m, p) == (msg.measured, msg.predicted)
        assert matched >= 50, (matched, shown["stride"])
        assert page.inner_text("#state") == "VALID"

        # scaled by 1.5: the page turns INVALID within 2 s of the node, without a reload
        seen = {}
        vsub = harness.node.create_subscription(
            Validity, "/spm_sysid/validity",
            lambda m: seen.setdefault("node", time.monotonic())
            if m.state == Validity.INVALID else None, 100)
        player = subprocess.Popen([sys.executable, "-m", "spm_sysid.ros.bag_player",
                                   "--ros-args", "-p", f"bag:={scaled}", "-p", "rate:=10.0"],
                                  env=ros_env, cwd=ROOT, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        try:
            end = time.monotonic() + 60
            while time.monotonic() < end and "page" not in seen:
                harness._spin_once(0.05)
                if page.evaluate("spmDashboard.state.monitor.state") == "INVALID":
                    seen["page"] = time.monotonic()
            assert player.wait(timeout=120) == 0
        finally:
            player.kill()
        harness.spin_until(lambda: "node" in seen, 10)
        harness.node.destroy_subscription(vsub)
        assert "page" in seen and "node" in seen, seen
        assert seen["page"] - seen["node"] <= 2.0, seen
        assert page.evaluate("performance.timeOrigin") == origin  # never reloaded
        assert "change detected" in page.inner_text("#reason")

        # the last identification's report is linked and opens
        href = page.get_attribute("#report-link", "href")
        status, body = get(base + href)
        assert status == 200 and b"the last identification" in body
        assert b"y(t-1)" in body
        # read-only: nothing but GET
        assert get(base + "state.json", method="POST")[0] == 405
        state = json.loads(get(base + "state.json")[1])
        assert state["monitor"]["state"] == "INVALID"
    finally:
        page.close()
        stop(node)


def test_the_dashboard_refuses_an_open_bind_without_a_token_and_a_taken_port(
        ros_env, harness, tmp_path):
    port = free_port()
    log = tmp_path / "open.log"
    with open(log, "w") as f:
        node = start_node(ros_env, f"dashboard_port:={port}", "dashboard_host:=0.0.0.0",
                          log=f)
        try:
            harness.wait_ready()  # the node runs on
            assert "needs dashboard_token" in log.read_text()
            with pytest.raises(OSError):
                socket.create_connection(("127.0.0.1", port), timeout=2).close()
        finally:
            stop(node)

    # a token: asked of every request
    first_log = tmp_path / "first.log"
    with open(first_log, "w") as f:
        first = start_node(ros_env, f"dashboard_port:={port}", "dashboard_token:=s3cret",
                           log=f)
    second_log = tmp_path / "second.log"
    try:
        harness.wait_ready()
        base = f"http://127.0.0.1:{port}/"
        status, body = wait_http(base)
        assert status == 403 and b"needs its token" in body
        assert get(base + "state.json?token=wrong")[0] == 403
        assert get(base + "state.json?token=s3cret")[0] == 200
        # a second node on the same port: one clear error line, and it keeps running
        with open(second_log, "w") as f:
            second = subprocess.Popen(
                [sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args",
                 "-r", "__node:=second", "-p", f"dashboard_port:={port}"],
                env=ros_env, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)
        try:
            end = time.monotonic() + 60
            while time.monotonic() < end and "cannot listen" not in second_log.read_text():
                time.sleep(0.2)
            text = second_log.read_text()
            assert f"cannot listen on 127.0.0.1:{port}" in text, text
            assert "Choose another dashboard_port" in text
            time.sleep(1.0)
            assert second.poll() is None  # still running: no crash
            assert get(base + "state.json?token=s3cret")[0] == 200  # the first still serves
        finally:
            stop(second)
    finally:
        stop(first)


@pytest.mark.slow
def test_the_live_page_shows_every_output_of_a_coupled_model(ros_env, harness, browser,
                                                             tmp_path):
    from .conftest import JOINT_STATE_PARAMS as PARAMS
    from .conftest import two_output_system, write_joint_state_bag

    u, Y = two_output_system(1200, seed=3, noise=0.001)
    bag = write_joint_state_bag(tmp_path / "joints", u, Y)
    port = free_port()
    node = start_node(ros_env, *PARAMS, f"dashboard_port:={port}")
    page = browser.new_page()
    try:
        harness.wait_ready()
        play_bag(ros_env, bag)
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= len(Y))
        assert harness.call("/spm_sysid/identify").success
        play_bag(ros_env, bag)  # the robot runs: both outputs predicted
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function(
            "spmDashboard.state && spmDashboard.state.model && "
            "Object.keys(spmDashboard.state.outputs).length === 2", timeout=20000)
        outputs = page.eval_on_selector_all("canvas.signals",
                                            "c => c.map(x => x.dataset.output)")
        assert sorted(outputs) == ["y1", "y2"]
        residuals = page.eval_on_selector_all("canvas.residual",
                                              "c => c.map(x => x.dataset.output)")
        assert sorted(residuals) == ["y1", "y2"]
        tables = page.eval_on_selector_all("#model table", "t => t.map(x => x.dataset.output)")
        assert tables == ["y1", "y2"]
        rows = page.eval_on_selector_all("#residuals tr", "r => r.length")
        assert rows == 3  # a header and a row per output
        assert page.inner_text("#state") in ("VALID", "DEGRADED")
    finally:
        page.close()
        stop(node)


def _closed_by_server(s: socket.socket) -> bool:
    """The server closed the connection (an empty read or a reset), before our long timeout."""
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def _idle(host: str, port: int, count: int) -> list:
    """``count`` connections that send nothing (closed by the caller)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    out = []
    for _ in range(count):
        s = socket.socket(family, socket.SOCK_STREAM)
        s.settimeout(10)
        s.connect((host, port))
        out.append(s)
    return out


@pytest.mark.slow
def test_hundreds_of_idle_clients_never_take_the_nodes_descriptors(
        ros_env, harness, robot_arm, tmp_path):
    """Under ulimit -n 256: 600 connections that send nothing, then the node still answers."""
    from spm_sysid_interfaces.action import Identify

    from .ros_harness import IdentifyClient

    u, y = robot_arm
    bag = write_io_bag(tmp_path / "arm", u, y)
    port = free_port()
    log = tmp_path / "node.log"
    with open(log, "w") as f:
        node = start_node(ros_env, "seed:=1", f"dashboard_port:={port}", log=f,
                          open_files=256)
    idle = []
    try:
        harness.wait_ready()
        play_bag(ros_env, bag)
        harness.wait_buffer(lambda kv: int(kv["samples"]) >= len(y))
        assert wait_http(f"http://127.0.0.1:{port}/state.json")[0] == 200
        idle = _idle("127.0.0.1", port, 600)  # each held a thread and a descriptor before
        client = IdentifyClient(harness)
        answer = client.get_model()
        assert answer.available is False and "no model yet" in answer.message
        status, result = client.result(client.send(criterion="bic"))
        assert result.error_code == Identify.Result.NONE, result.message
        assert len(client.get_model().models.models) == 1
        # the idle ones are closed by the node (refused, or at its request timeout)
        for s in idle[:50]:
            s.settimeout(60)
        assert all(_closed_by_server(s) for s in idle[:50])
        for s in idle:
            s.close()
        idle = []
        # a client that resets its connection: counted, no traceback in the log
        rst = socket.create_connection(("127.0.0.1", port))
        rst.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        rst.send(b"GET /state.json HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        rst.close()
        # a page of another site (DNS rebinding) is refused: no token, so the Host counts
        req = urllib.request.Request(f"http://127.0.0.1:{port}/state.json",
                                     headers={"Host": "attacker.example"})
        with pytest.raises(urllib.error.HTTPError) as exc:
            urllib.request.urlopen(req, timeout=10)
        assert exc.value.code == 421
        assert get(f"http://localhost:{port}/state.json")[0] == 200

        def board():
            return harness.statuses().get("dashboard", (None, "", {}))

        assert harness.spin_until(lambda: board()[2].get("bad_host") == "1", 10)
        level, message, values = board()
        assert int(values["refused"]) > 0 and "refused" in message and level == 1
    finally:
        for s in idle:
            s.close()
        stop(node)
    text = log.read_text()
    assert "Traceback" not in text and "Too many open files" not in text, text[-3000:]


def test_a_token_is_never_logged_and_an_ipv6_dashboard_closes_silent_clients(
        ros_env, harness, tmp_path):
    token = "Sup3r Secret/+?"  # the token: URL-encoded in the page's address
    port = free_port()
    log = tmp_path / "node.log"
    with open(log, "w") as f:
        node = start_node(ros_env, f"dashboard_port:={port}", "dashboard_host:='::'",
                          f"dashboard_token:={token}", log=f)
    try:
        harness.wait_ready()
        quoted = urllib.parse.quote(token)
        base = f"http://[::1]:{port}/"
        assert wait_http(base)[0] == 403
        assert get(f"{base}state.json?token={quoted}")[0] == 200
        silent = _idle("::1", port, 100)
        for s in silent:
            s.settimeout(60)  # held 80 s and more before (no request timeout)
        closed = [_closed_by_server(s) for s in silent]
        for s in silent:
            s.close()
        assert all(closed)
        assert get(f"{base}state.json?token={quoted}")[0] == 200
    finally:
        stop(node)
    text = log.read_text()
    assert f"live dashboard at http://[::]:{port}/" in text, text
    assert "dashboard_token parameter" in text
    assert token not in text and quoted not in text and "Secret" not in text
