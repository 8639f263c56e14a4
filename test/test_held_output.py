"""An output that repeats each value for a fixed number of samples: a slower sensor, held.

A second-order plant's output read every 10th sample and held (a slow sensor
merged into a faster log) got a model of the hold and no word of it. The data
check now reads the runs of equal output values and warns when they are many
and regular, with the sensor's rate and the --decimate that reads it.
"""

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spm_sysid.core.validate.held_output import describe_held_output, held_output

sys.path.insert(0, str(Path(__file__).parent))
from helpers.signals import multisine, second_order, squared  # noqa: E402

EXE = str(Path(sys.executable).with_name("spm-sysid"))


def _plant(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = multisine(n, rng, 0.02)
    return u, second_order(u, squared(0.2)) + 0.002 * rng.standard_normal(n)


def _held(y: np.ndarray, every: float) -> np.ndarray:
    """The output read at every ``every``-th sample (not always a whole number) and held."""
    read = np.floor(np.floor(np.arange(len(y)) / every) * every).astype(int)
    return y[read]


def _csv(path: Path, u, y) -> Path:
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    return path


def test_check_data_and_identify_as_typed_say_the_output_is_held(tmp_path):
    u, y = _plant(5000)
    data = _csv(tmp_path / "held.csv", u, _held(y, 10))
    r = subprocess.run([EXE, "check-data", "--data", str(data)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    said = [line for line in r.stdout.splitlines() if "repeats each value" in line]
    assert len(said) == 1 and said[0].startswith("warning: output y repeats each value for "
                                                 "about 10.0 samples (90% of its steps")
    assert said[0].endswith("--decimate 10 (docs/cli.md)")
    r = subprocess.run([EXE, "identify", "--data", str(data), "--focus", "simulation",
                        "--orders", "auto", "--json", str(tmp_path / "m.json")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "m.json").read_text())
    assert sum("repeats each value" in w for w in doc["metadata"]["warnings"]) == 1


def test_the_runs_equal_a_direct_count():
    """Zero steps and run lengths from itertools.groupby, each segment alone."""
    rng = np.random.default_rng(3)
    y = np.repeat(rng.standard_normal(120), rng.choice([3, 4], size=120))
    segments = [(0, 200), (230, len(y))]
    found = held_output(y, segments)
    runs, steps, zero = [], 0, 0
    for a, b in segments:
        part = y[a:b]
        steps += len(part) - 1
        zero += int(np.sum(part[1:] == part[:-1]))
        lengths = [len(list(g)) for _, g in itertools.groupby(part)]
        runs += lengths[1:-1]  # the runs cut by the segment's ends are left out
    assert found.runs == len(runs) and found.zero_steps == pytest.approx(zero / steps)
    assert found.mean == pytest.approx(np.mean(runs))
    assert found.median == int(np.median(runs)) and found.regular == 1.0 and found.held


def test_a_sensor_at_30_hz_in_a_100_hz_log_gets_its_rate_and_a_near_factor():
    _, y = _plant(6000)
    found = held_output(_held(y, 10 / 3))
    said = describe_held_output(found)
    assert found.held and "about 3.3 samples" in said and "runs 3 or 4 samples long" in said
    assert "about 1/3.3 of the record's), or try --decimate 3" in said


@pytest.mark.parametrize("kind", ["noisy", "quantized", "clipped", "held input", "too short"])
def test_outputs_that_are_not_held_get_no_warning(kind):
    u, y = _plant(6000)
    if kind == "quantized":  # an encoder: runs of equal counts, of irregular lengths
        step = 0.05 * np.std(y)
        y = np.round(_plant(6000)[1] / step) * step
        y = np.round(np.convolve(y, np.ones(50) / 50, mode="same") / step) * step
    elif kind == "clipped":
        y = np.clip(y, -0.5, 0.5)
    elif kind == "held input":  # a command held between updates: what the plant gets
        u = _held(u, 10)
    elif kind == "too short":
        y = _held(y, 10)[:150]
    found = held_output(y)
    assert describe_held_output(found) == ""
    if kind == "quantized":
        assert found.zero_steps > 0.5 and found.regular < 0.9  # repeats, but irregular
