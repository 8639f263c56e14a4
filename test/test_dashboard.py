"""The dashboard's content and server on their own: no node, no DDS (ros/node/dashboard*.py)."""

import json
import socket
import urllib.error
import urllib.request

import numpy as np
import pytest

from spm_sysid.core.online.session import OnlineSample

pytest.importorskip("rclpy", reason="the dashboard ships with the ROS layer")

from spm_sysid.ros.node.dashboard import MAX_POINTS, Dashboard, NodeStatus  # noqa: E402
from spm_sysid.ros.node.dashboard_server import DashboardServer, host_name  # noqa: E402


def _get(url, host=None):
    req = urllib.request.Request(url, headers={"Host": host} if host else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _samples(n: int, period_ns: int = 1_000_000):
    """A 1 kHz stream of predictions: measured sin, predicted 0.9 of it."""
    t = np.arange(n)
    for k in t:
        m = float(np.sin(0.01 * k))
        yield OnlineSample(int(1e9 + k * period_ns), m, 0.9 * m, 0.1 * m, 0.0, None, False)


def test_the_content_thins_a_window_to_about_max_points_and_states_the_snapshot():
    board = Dashboard(seconds=2.0)
    board.update(NodeStatus(node="/n", quality={"y": (1.02, 0.3)}))
    for s in _samples(5000):  # 5 s at 1 kHz
        board.feed(("y",), (s,))
    first = board.state()  # the stride is learned from the first window's stamps
    for s in _samples(5000):
        board.feed(("y",), (s,))
    state = board.state()
    y = state["outputs"]["y"]
    assert state["node"] == "/n" and len(first["outputs"]["y"]["t"]) == 2000  # all kept
    assert y["stride"] == 2 and len(y["t"]) <= MAX_POINTS + 1  # 2 s at 1 kHz, every 2nd
    assert y["t"][-1] == 0.0 and y["t"][0] >= -2.0
    assert y["stats"]["rms_ratio"] == 1.02 and y["stats"]["whiteness_p"] == 0.3
    resid = np.array(y["measured"]) - np.array(y["predicted"])
    assert y["stats"]["rms"] == pytest.approx(np.sqrt(np.mean(resid ** 2)), rel=1e-9)
    json.dumps(state, allow_nan=False)  # what the server sends


def test_the_server_answers_get_only_and_the_loopback_only_without_a_token():
    board = Dashboard()
    board.update(NodeStatus(node="/alone"))
    server = DashboardServer(board, 0)
    try:
        base = f"http://127.0.0.1:{server.port}/"
        status, body = _get(base + "state.json")
        assert status == 200 and json.loads(body)["node"] == "/alone"
        assert _get(base + "state.json", host="evil.example:80")[0] == 421
        assert _get(base + "report.html")[0] == 404  # no identification yet
        assert server.counts["bad_host"] == 1 and server.requests == 3
        assert [host_name(h) for h in ("[::1]:8765", "localhost:1")] == ["::1", "localhost"]
    finally:
        server.close()


def _closed_by_server(s: socket.socket) -> bool:
    """The server closed the connection (an empty read or a reset), before our long timeout."""
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def test_past_its_cap_the_server_refuses_and_idle_clients_are_closed():
    server = DashboardServer(Dashboard(), 0)
    idle = []
    try:
        for _ in range(60):
            idle.append(socket.create_connection(("127.0.0.1", server.port), timeout=60))
        assert all(_closed_by_server(s) for s in idle)  # refused, or timed out: none held
        assert server.counts["refused"] >= 20 and server.counts["connection_errors"] >= 1
    finally:
        for s in idle:
            s.close()
        server.close()
