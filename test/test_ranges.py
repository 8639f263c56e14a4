"""The range each signal was fitted on, and new data beyond it (``metadata.ranges``).

A short record's model of ``y(t-1)^2*u(t-1)`` diverged on a second record whose
input went lower than the first's had ever been; ``validate`` said DIVERGED and
nothing of why. The document keeps each signal's range on the estimation samples,
and ``validate`` names every signal of new data beyond it.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from spm_sysid.core.validate.envelope import BEYOND, data_ranges, range_notes

sys.path.insert(0, str(Path(__file__).parent))
from helpers.speed_sensor import speed_sensor  # noqa: E402

EXE = str(Path(sys.executable).with_name("spm-sysid"))


def cli(*args, cwd):
    return subprocess.run([EXE, *args], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_ranges_cover_the_segments_samples_and_leave_nan_out():
    u = np.array([5.0, 1.0, np.nan, -2.0, 9.0])
    y = np.array([[0.0, 7.0], [1.0, 2.0], [2.0, np.nan], [3.0, 4.0], [9.0, 9.0]])
    got = data_ranges(u, y, [(1, 4)], ("u",), ("a", "b"))
    assert got == {"inputs": {"u": [-2.0, 1.0]}, "outputs": {"a": [1.0, 3.0], "b": [2.0, 4.0]}}
    assert data_ranges(np.full(3, np.nan), np.zeros(3), [(0, 3)], ("u",), ("y",))["inputs"] == {}


def test_only_a_signal_beyond_its_range_by_more_than_the_margin_is_named():
    ranges = {"inputs": {"u": [0.0, 10.0]}, "outputs": {"y": [-1.0, 1.0]}}
    y = np.zeros(100)
    inside = np.linspace(-0.9 * BEYOND * 10, 10 + 0.9 * BEYOND * 10, 100)  # within the margin
    assert range_notes(ranges, inside, y, None, ("u",), ("y",)) == []
    assert range_notes(None, inside, y, None, ("u",), ("y",)) == []  # an older document
    u = np.linspace(0.0, 10.0, 100)
    u[:10] = -3.0  # 10 % of the samples at -3, 30 % of the width below
    y[50:] = 4.0
    notes = range_notes(ranges, u, y, [(0, 100)], ("u",), ("y",))
    assert len(notes) == 2
    assert notes[0].startswith("the input u goes down to -3 on these data, beyond the 0 to 10 "
                               "the model was fitted on (10% of the samples outside)")
    assert notes[1].startswith("the output y goes up to 4 on these data, beyond the -1 to 1")
    assert "(50% of the samples outside)" in notes[1]
    assert range_notes(ranges, u, y, [(20, 40)], ("u",), ("y",)) == []  # only those samples


def test_validate_names_the_input_that_leaves_the_range_the_model_was_fitted_on(tmp_path):
    """The command as typed on a short record, then validate on a second record whose input
    reaches levels the first never had (and on the first itself: nothing said)."""
    u1, y1 = speed_sensor(300, seed=7, low=-1.0, high=3.0)
    u2, y2 = speed_sensor(400, seed=8)
    for name, u, y in (("a", u1, y1), ("b", u2, y2)):
        np.savetxt(tmp_path / f"{name}.csv", np.column_stack([u, y]), delimiter=",",
                   header="u,y", comments="")
    r = cli("identify", "--data", "a.csv", "--output", "y", "--focus", "simulation", "--orders",
            "auto", "--json", "m.json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    ranges = json.loads((tmp_path / "m.json").read_text())["metadata"]["ranges"]
    assert ranges == {"inputs": {"u": [u1.min(), u1.max()]},
                      "outputs": {"y": [y1.min(), y1.max()]}}
    r = cli("validate", "m.json", "--data", "a.csv", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "fitted on" not in r.stdout
    r = cli("validate", "m.json", "--data", "b.csv", "--errors-from", "50", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    share = np.mean(u2 < u1.min())
    assert (f"note: the input u goes down to {u2.min():.4g} on these data, beyond the "
            f"{u1.min():.4g} to {u1.max():.4g} the model was fitted on ({share:.0%} of the "
            "samples outside)") in r.stdout
    assert r.stdout.index("note: the input u") < r.stdout.index("validation on supplied data")


def test_the_live_watch_counts_samples_beyond_and_says_the_first_once():
    from spm_sysid.core.validate.envelope import RangeWatch

    ranges = {"inputs": {"tau": [-1.0, 1.0]}, "outputs": {"q1": [0.0, 10.0], "q2": [0.0, 1.0]}}
    watch = RangeWatch(ranges, ("tau",), ("q1", "q2"))
    assert watch.update(1.04, [10.4, 0.5]) is None  # within 5 % of the widths
    first = watch.update(0.0, [11.0, 0.5])
    assert first.startswith("q1 = 11, beyond the 0 to 10 the model was fitted on")
    assert watch.update(-2.0, [5.0, 1.5]) is None  # counted, not said again
    assert watch.update(0.0, [5.0, 0.5]) is None
    assert watch.values() == {"beyond_fitted_range": 2, "beyond_fitted_range_signals":
                              "tau down to -2; q1 up to 11; q2 up to 1.5"}
    old = RangeWatch(None, ("tau",), ("q1", "q2"))  # a document without ranges
    assert old.update(1e9, [1e9, -1e9]) is None and old.values()["beyond_fitted_range"] == 0
