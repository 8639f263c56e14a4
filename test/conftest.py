"""Shared fixtures: the real robot-arm data and ROS environment isolation."""

from __future__ import annotations

import itertools
import os
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from spm_sysid.core.data import find_robot_arm, load_io  # noqa: E402

# ROS traffic stays on this machine, whatever the caller's environment says.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", "62")

_domains = itertools.count(int(os.environ.get("SPM_SYSID_TEST_DOMAIN_BASE", "70")))


@pytest.fixture(scope="session")
def robot_arm() -> tuple[np.ndarray, np.ndarray]:
    """The real flexible robot-arm data (u = torque, y = acceleration)."""
    return load_io(find_robot_arm())


@pytest.fixture(scope="session")
def robot_arm_path() -> Path:
    return find_robot_arm()


@pytest.fixture
def ros_env() -> dict[str, str]:
    """Environment for a process that starts ROS: localhost only, its own domain."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(next(_domains) % 100 + 1)
    env["PYTHONUNBUFFERED"] = "1"
    return env


EQ1 = ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)", "u(t-1)", "u(t-2)", "u(t-3)", "u(t-4)"]
EQ2 = ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)", "u(t-1)", "u(t-3)", "u(t-4)"]
