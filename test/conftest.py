"""Shared fixtures: the real robot-arm data and ROS environment isolation."""

from __future__ import annotations

import fcntl
import itertools
import os
import re
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from spm_sysid.core.io.data import load_io  # noqa: E402
from spm_sysid.core.io.datasets import find_robot_arm  # noqa: E402

# a worker's crash never hangs the suite; its test runs once more on a fresh worker
from .helpers.scheduling import (  # noqa: E402, F401
    pytest_handlecrashitem,
    pytest_report_teststatus,
    pytest_terminal_summary,
    pytest_xdist_make_scheduler,
)

# Ctrl-C reaches the processes the tests start, as in a terminal: a suite started in the
# background (`make test &` from a script) inherits SIGINT ignored, and so would every
# process it starts (an ignored signal survives exec), so the tests' Ctrl-C would be lost.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

#: Tests over about 2.5 s under three workers on two cores, measured (`make test-durations`):
#: marked ``slow`` here, so that ``make test-quick`` (``-m "not slow"``) stays near 2 minutes.
SLOW_LIST = Path(__file__).with_name("slow_tests.txt")


def slow_test_ids() -> set[str]:
    """The node ids test/slow_tests.txt lists (lines ``seconds<TAB>node id``; # comments)."""
    lines = SLOW_LIST.read_text().splitlines() if SLOW_LIST.exists() else []
    return {line.split("\t", 1)[1] for line in lines if line and not line.startswith("#")}


def pytest_collection_modifyitems(config, items):
    slow = slow_test_ids()
    for item in items:
        if item.nodeid in slow:
            item.add_marker(pytest.mark.slow)


# ROS traffic stays on this machine, whatever the caller's environment says.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", "62")

# Each ROS test gets a domain of its own, reserved with a lock file, so two suites on
# one host (two clones, CI and a developer) never share a domain. Domains 1..101 are
# valid with LOCALHOST discovery; SPM_SYSID_TEST_DOMAIN_BASE picks where to start.
_LOCK_DIR = Path(os.environ.get("SPM_SYSID_TEST_LOCK_DIR", "/tmp/spm_sysid_test_domains"))
_next = itertools.count(int(os.environ.get("SPM_SYSID_TEST_DOMAIN_BASE", "20")))


def _reserve_domain():
    """A free ROS domain id and the open lock file that holds it."""
    _LOCK_DIR.mkdir(parents=True, exist_ok=True)
    for _ in range(101):
        domain = next(_next) % 101 + 1
        if domain in (61, 62, 63):  # make run, make test and CI use these
            continue
        f = open(_LOCK_DIR / f"{domain}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        return domain, f
    raise RuntimeError("no free ROS domain id (101 in use)")


@pytest.fixture(scope="session")
def robot_arm() -> tuple[np.ndarray, np.ndarray]:
    """The real flexible robot-arm data (u = torque, y = acceleration)."""
    return load_io(find_robot_arm())


@pytest.fixture(scope="session")
def robot_arm_path() -> Path:
    return find_robot_arm()


@pytest.fixture
def ros_env():
    """Environment for a process that starts ROS: localhost only, its own domain."""
    domain, lock = _reserve_domain()
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONUNBUFFERED"] = "1"
    yield env
    lock.close()  # releases the domain


#: A sysid_node reading two joints from one JointState topic (effort in, velocity out).
JOINT_STATE_PARAMS = ("input_topic:=/joint_states", "input_type:=sensor_msgs/msg/JointState",
                      "input_field:=effort[0],effort[1]", "input_names:=u1,u2",
                      "output_topic:=/joint_states", "output_type:=sensor_msgs/msg/JointState",
                      "output_field:=velocity[0],velocity[1]", "output_names:=y1,y2",
                      "ny:=1", "nu:=1", "degree:=2", "criterion:=bic", "seed:=1")

EQ1 = ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)", "u(t-1)", "u(t-2)", "u(t-3)", "u(t-4)"]
EQ2 = ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)", "u(t-1)", "u(t-3)", "u(t-4)"]


def eq1_model(robot_arm):
    """The paper's eq. (1): y(t-1..4) and u(t-1..4) by least squares on the robot-arm data.

    A new model each call (tests change their metadata), criterion AIC as the paper's.
    """
    from spm_sysid.core.fit.problem import fit_structure
    from spm_sysid.core.model.terms import TermSpace

    u, y = robot_arm
    mask = np.zeros(44, dtype=bool)
    mask[:8] = True  # the first 8 candidates: the linear lags, in the documented order
    return fit_structure(u, y, mask, TermSpace(), criterion="aic", criterion_value=-10744.78)


@pytest.fixture
def harness(ros_env):
    """An rclpy node of the test's own on its domain (:class:`test.ros_harness.Harness`)."""
    from .ros_harness import Harness

    h = Harness(ros_env)
    yield h
    h.close()


@pytest.fixture(scope="module")
def arm_bag(robot_arm, tmp_path_factory):
    """The robot-arm data as an MCAP bag (in a temporary folder, never in git)."""
    from spm_sysid.core.io.bagio import write_io_bag

    u, y = robot_arm
    return write_io_bag(tmp_path_factory.mktemp("bags") / "robot_arm", u, y)


# -- a coupled system of two outputs and two inputs, known exactly (the several-output tests)

TRUE = {  # known cross terms: y2 enters y1's model and y1 enters y2's
    "y1": {"y1(t-1)": 0.5, "u1(t-1)": 0.8, "y2(t-1)": 0.2, "y1(t-1)*u1(t-1)": 0.1},
    "y2": {"y2(t-1)": 0.4, "u2(t-1)": 0.6, "y1(t-1)": -0.3, "y2(t-1)*y1(t-1)": 0.2},
}
FACTOR = re.compile(r"^(\w+)\(t-(\d+)\)(?:\^(\d+))?$")


def term_value(name: str, signals: dict, t: int) -> float:
    """A term's value at t from its printed name (independent of the package's code)."""
    value = 1.0
    for part in name.split("*"):
        m = FACTOR.match(part)
        value *= signals[m.group(1)][t - int(m.group(2))] ** int(m.group(3) or 1)
    return value


def reference_simulation(coefs: dict, u: np.ndarray, Y: np.ndarray, start: int) -> np.ndarray:
    """Plain-Python coupled free run: both outputs from their own predictions."""
    sig = {"u1": u[:, 0], "u2": u[:, 1], "y1": Y[:, 0].copy(), "y2": Y[:, 1].copy()}
    for t in range(start, len(Y)):
        new = {o: sum(c * term_value(n, sig, t) for n, c in coefs[o].items()) for o in coefs}
        sig["y1"][t], sig["y2"][t] = new["y1"], new["y2"]
    return np.column_stack([sig["y1"], sig["y2"]])[start:]


def two_output_system(n: int, seed: int, noise: float = 0.0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n, 2))
    Y = np.zeros((n, 2))
    Y[0] = 0.1
    Y[1:] = reference_simulation(TRUE, u, Y, 1)
    return u, Y + noise * rng.standard_normal(Y.shape)


def write_joint_state_bag(path, u, Y, rate_hz=100.0, topic="/joint_states",
                          shuffled: bool = False, gripper_every: int = 0):
    """One JointState topic: effort = the inputs, velocity = the outputs (rosbags Writer).

    ``shuffled``: every other message lists the joints j1, j2 the other way round (the
    publisher's order); ``gripper_every``: every so many samples another publisher's
    message on the same topic, naming only a joint ``finger``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    from spm_sysid.core.io.bagio import typestore

    store = typestore()
    T = store.types
    JointState, Header, Time = (T["sensor_msgs/msg/JointState"], T["std_msgs/msg/Header"],
                                T["builtin_interfaces/msg/Time"])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(topic, "sensor_msgs/msg/JointState", typestore=store)
        for k in range(len(Y)):
            t = int(round(k * 1e9 / rate_hz)) + 1_000_000_000
            stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
            order = [1, 0] if shuffled and k % 2 else [0, 1]
            msg = JointState(header=Header(stamp=stamp, frame_id="base"),
                             name=[["j1", "j2"][j] for j in order], position=np.zeros(2),
                             velocity=np.ascontiguousarray(Y[k, order]),
                             effort=np.ascontiguousarray(u[k, order]))
            w.write(c, t, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            if gripper_every and k % gripper_every == 0:
                grip = JointState(header=Header(stamp=stamp, frame_id="base"), name=["finger"],
                                  position=np.ones(1), velocity=np.zeros(1), effort=np.ones(1))
                w.write(c, t + 1, store.serialize_cdr(grip, "sensor_msgs/msg/JointState"))
    return path


def sine_record(n: int = 400):
    """A second-order system driven by one sine: it excites two input lags only."""
    u = np.sin(2 * np.pi * np.arange(n) / 37)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.5 * y[k - 1] - 0.7 * y[k - 2] + 0.5 * u[k - 1]
    return u, y + 1e-3 * np.random.default_rng(0).standard_normal(n)


def chromium_path() -> str | None:
    """Debian's headless-capable Chromium (make test installs it when it is missing)."""
    import shutil

    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture
def browser():
    """A real headless Chromium driven by Playwright (the system's browser, none downloaded).

    One per test: Playwright's synchronous API keeps an asyncio loop running while it
    is open, which would break the other tests of the same worker (asyncio.run).
    """
    sync_api = pytest.importorskip("playwright.sync_api",
                                   reason="playwright is not installed (make test installs it)")
    path = chromium_path()
    if path is None:
        pytest.skip("Chromium is not installed: apt-get install chromium (make test does it "
                    "as root)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=path, args=["--no-sandbox"])
        try:
            yield b
        finally:
            b.close()
