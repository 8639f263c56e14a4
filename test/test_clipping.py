"""An output held at its largest or smallest value: the data check says so.

The records here are clipped at levels the test chose, so the ends, shares and
runs found are checked against an independent count of what was put in; signals
that dwell at their extremes without a limit (a coarsely quantised sine, a
two-level output, a step response) are not named.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.io.data import load_io
from spm_sysid.core.io.datasets import find_robot_arm
from spm_sysid.core.validate.clipping import clipped_ends

from .helpers.joint import joint_record
from .helpers.signals import multisine

RUN = [sys.executable, "-m", "spm_sysid.apps.main"]


def clipped_record(n: int, top: float, bottom: float, seed: int = 1):
    """u and the measured output of a second-order plant, its sensor clipped to a range."""
    rng = np.random.default_rng(seed)
    u = multisine(n, rng, 0.03)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.3 * y[k - 1] - 0.45 * y[k - 2] + 0.5 * u[k - 1]
    return u, np.clip(y + 1e-3 * rng.standard_normal(n), bottom, top)


def _runs(held: np.ndarray) -> list[int]:
    lengths, count = [], 0
    for h in held:
        if h:
            count += 1
        elif count:
            lengths.append(count)
            count = 0
    return lengths + ([count] if count else [])


def test_the_ends_a_record_was_clipped_at_are_found_with_their_share_and_runs():
    u, y = clipped_record(20_000, top=2.0, bottom=-1.5)
    found = clipped_ends(y)
    assert [(c.side, c.value) for c in found] == [("largest", 2.0), ("smallest", -1.5)]
    for c, level in zip(found, (2.0, -1.5)):
        runs = _runs(y == level)
        assert c.samples == int(np.sum(y == level)) and c.share == c.samples / len(y)
        assert c.runs == len(runs) >= 3 and c.longest == max(runs)
    # one end only; and each segment's runs counted on its own
    _, y1 = clipped_record(20_000, top=2.0, bottom=-99.0)
    assert [c.side for c in clipped_ends(y1)] == ["largest"]
    whole = clipped_ends(y1)[0]
    halves = clipped_ends(y1, [(0, 10_000), (10_000, 20_000)])[0]
    assert halves.samples == whole.samples and halves.runs >= whole.runs


@pytest.mark.parametrize("kind", ["quantised sine", "two levels", "step response",
                                  "joint", "robot arm"])
def test_signals_that_dwell_at_their_extremes_without_a_limit_are_not_named(kind):
    t = np.arange(20_000)
    if kind == "quantised sine":  # ten levels: the top one held for long stretches
        y = np.round(5 * np.sin(2 * np.pi * t / 997)) / 5
    elif kind == "two levels":
        y = np.sign(np.sin(2 * np.pi * t / 500 + 0.1))
    elif kind == "step response":  # noiseless: it settles on each level exactly
        u = np.repeat(np.random.default_rng(0).uniform(-1, 1, 100), 200)
        y = np.zeros_like(u)
        for k in range(1, len(u)):
            y[k] = 0.9 * y[k - 1] + 0.1 * u[k - 1]
    elif kind == "joint":
        _, y = joint_record(20.0, seed=1)
    else:
        _, y = load_io(find_robot_arm())
    assert clipped_ends(y) == []


def test_check_data_and_identify_warn_of_a_clipped_output(tmp_path):
    u, y = clipped_record(4000, top=2.0, bottom=-2.0)
    path = tmp_path / "clipped.csv"
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    r = subprocess.run([*RUN, "check-data", "--data", str(path)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    top = clipped_ends(y)[0]
    assert (f"warning: the output y holds exactly its largest value 2 on {top.share:.0%} of "
            f"the samples ({top.runs} runs, the longest {top.longest} samples) and its "
            "smallest value -2") in r.stdout
    r = subprocess.run([*RUN, "identify", "--data", str(path), "--quiet", "--seed", "1",
                        "--json", str(tmp_path / "m.json")], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "holds exactly its largest value 2" in r.stderr + r.stdout
    warnings = json.loads((tmp_path / "m.json").read_text())["metadata"]["warnings"]
    assert any("holds exactly its largest value 2" in w for w in warnings)
