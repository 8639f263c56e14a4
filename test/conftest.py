"""Shared fixtures: the real robot-arm data and ROS environment isolation."""

from __future__ import annotations

import fcntl
import itertools
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from spm_sysid.core.io.data import load_io  # noqa: E402
from spm_sysid.core.io.datasets import find_robot_arm  # noqa: E402

# Ctrl-C reaches the processes the tests start, as in a terminal: a suite started in the
# background (`make test &` from a script) inherits SIGINT ignored, and so would every
# process it starts (an ignored signal survives exec), so the tests' Ctrl-C would be lost.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

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
