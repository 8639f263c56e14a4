"""Output spikes: the data check finds them, ``--spikes gaps`` leaves them out, counted.

A spike (a bad read, a dropped packet) is fitted by least squares like any sample;
the records here carry spikes at samples the test chose, so what is found is
checked against what was put in.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.errors import ModelFormatError
from spm_sysid.core.io.data import load_io
from spm_sysid.core.model.metadata import check_metadata
from spm_sysid.core.record import Record
from spm_sysid.core.validate.spikes import output_spikes, without_spikes

from .helpers.duffing import duffing
from .helpers.joint import joint_record
from .helpers.signals import multisine
from .helpers.velocity_loop import velocity_record

RUN = [sys.executable, "-m", "spm_sysid.apps.main"]


def system(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u, the clean output and the measured one (noise 0.01) of a second-order NARX system."""
    rng = np.random.default_rng(seed)
    u = multisine(n, rng, 0.05)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = (1.2 * y[k - 1] - 0.5 * y[k - 2] + 0.5 * u[k - 1] + 0.2 * u[k - 1] ** 2
                - 0.05 * y[k - 1] ** 3)
    return u, y, y + 0.01 * rng.standard_normal(n)


def spiked(y: np.ndarray, count: int, size: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``y`` with ``count`` one-sample spikes of ``size`` standard deviations, 10+ apart."""
    rng = np.random.default_rng(seed)
    at = np.sort(rng.choice(np.arange(50, len(y) - 50, 10), count, replace=False))
    out = y.copy()
    out[at] += size * np.std(y) * rng.choice([-1.0, 1.0], count)
    return out, at


@pytest.mark.parametrize("size", [3.0, 20.0])
def test_every_spike_put_in_is_found_and_nothing_else(size):
    u, _, y = system(8000, 1)
    assert output_spikes(y, u) is None
    y2, at = spiked(y, 40, size, 2)
    found = output_spikes(y2, u)
    assert found is not None and list(found.starts) == list(at), (found, at)
    assert found.widths == (1,) * 40 and found.samples == 40


def test_records_without_spikes_get_no_warning(robot_arm_path):
    """The robot arm, a cubic spring, a joint and a velocity loop with friction (their
    jumps are the physics'), and a step response without noise: none."""
    records = [load_io(robot_arm_path), duffing(20000), joint_record(20.0, seed=1),
               velocity_record(20.0, seed=1)]
    steps = np.repeat(np.random.default_rng(0).uniform(-1, 1, 50), 200)
    out = np.zeros(len(steps))
    for k in range(1, len(steps)):
        out[k] = 0.9 * out[k - 1] + 0.1 * steps[k - 1]
    records.append((steps, out))
    for u, y in records:
        assert output_spikes(np.ravel(y), u) is None


def test_segments_split_around_spikes_and_rows_never_cross():
    u, _, y = system(3000, 3)
    y2, at = spiked(y, 5, 10.0, 4)
    found = output_spikes(y2, u, [(0, 1500), (1500, 3000)])
    bounds = without_spikes([(0, 1500), (1500, 3000)], found)
    kept = np.concatenate([np.arange(a, b) for a, b in bounds])
    assert not set(at) & set(kept)
    assert len(kept) == 3000 - 5 and all(a < b for a, b in bounds)
    assert (0, 1500) not in bounds or not any(a_ < 1500 for a_ in at)


def test_a_record_of_two_outputs_loses_the_spikes_of_each():
    u, _, y = system(4000, 5)
    _, _, other = system(4000, 6)
    y1, at1 = spiked(y, 3, 10.0, 7)
    y2, at2 = spiked(other, 4, 10.0, 8)
    record = Record.from_samples(u, np.column_stack([y1, y2]), source="two",
                                 output_names=("a", "b")).spikes_as_gaps()
    assert record.spikes["spikes"] == 7 and record.spikes["samples"] == 7
    assert sorted(record.spikes["at"]) == sorted([*at1, *at2])
    assert "7 output spike(s) left out" in record.notes[-1]
    clean = Record.from_samples(u, y, source="clean")
    assert clean.spikes_as_gaps() is clean


def test_check_data_warns_and_identify_leaves_them_out_with_the_count(tmp_path):
    """The commands as a user types them: ``check-data`` names the spikes and the option;
    ``identify --spikes gaps`` counts them in its answer and its document, and finds
    the system's terms and coefficients, which the spikes hide without the option."""
    u, clean, y = system(6000, 9)
    y2, at = spiked(y, 60, 20.0, 10)
    np.savetxt(tmp_path / "take.csv", np.column_stack([u, y2]), delimiter=",", header="u,y",
               comments="", fmt="%.10g")
    out = subprocess.run([*RUN, "check-data", "--data", "take.csv"], capture_output=True,
                         text=True, cwd=tmp_path, timeout=120)
    assert out.returncode == 0, out.stderr
    [line] = [ln for ln in out.stdout.splitlines() if "spike" in ln]
    assert "60 spike(s)" in line and "--spikes gaps" in line and str(at[0]) in line, line
    space = ["--ny", "2", "--nu", "2", "--degree", "3", "--criterion", "bic"]
    fits = {}
    for how in ("warn", "gaps"):
        out = subprocess.run([*RUN, "identify", "--data", "take.csv", *space, "--spikes", how,
                              "--json", f"{how}.json"],
                             capture_output=True, text=True, cwd=tmp_path, timeout=300)
        assert out.returncode == 0, out.stderr
        fits[how] = json.loads((tmp_path / f"{how}.json").read_text())
        if how == "gaps":
            assert "60 output spike(s) left out (60 sample(s)" in out.stdout
            assert "(60 left out as spikes)" in out.stdout
    meta = fits["gaps"]["metadata"]
    assert meta["spikes"]["spikes"] == 60 and meta["spikes"]["at"] == [int(t) for t in at]
    assert meta["data"]["spike_samples"] == 60 and "spikes" not in fits["warn"]["metadata"]
    u2, clean2, _ = system(6000, 11)  # a new record without noise nor spikes
    np.savetxt(tmp_path / "clean.csv", np.column_stack([u2, clean2]), delimiter=",",
               header="u,y", comments="", fmt="%.10g")
    rmse = {}
    for how in fits:
        out = subprocess.run([*RUN, "validate", f"{how}.json", "--data", "clean.csv"],
                             capture_output=True, text=True, cwd=tmp_path, timeout=120)
        assert out.returncode == 0, out.stderr
        line = next(ln for ln in out.stdout.splitlines() if ln.strip().startswith("free-run:"))
        rmse[how] = float(line.split("RMSE ")[1].split(",")[0])
    assert rmse["gaps"] < 0.01 * np.std(clean2) and rmse["warn"] > 10 * rmse["gaps"], rmse
    assert "spike" not in out.stdout


def _validate(tmp_path, *args) -> tuple[list[str], float]:
    out = subprocess.run([*RUN, "validate", *args], capture_output=True, text=True,
                         cwd=tmp_path, timeout=120)
    assert out.returncode == 0, out.stderr
    line = next(ln for ln in out.stdout.splitlines() if ln.strip().startswith("free-run:"))
    spikes = [ln for ln in out.stdout.splitlines() if "spike" in ln]
    return spikes, float(line.split("RMSE ")[1].split(",")[0])


def test_validate_says_when_its_data_have_spikes_and_can_leave_them_out(tmp_path):
    u, _, y = system(4000, 12)
    np.savetxt(tmp_path / "fit.csv", np.column_stack([u, y]), delimiter=",",  # no spikes
               header="u,y", comments="", fmt="%.10g")
    out = subprocess.run([*RUN, "identify", "--data", "fit.csv", "--ny", "2", "--nu", "2",
                          "--degree", "3", "--criterion", "bic", "--json", "m.json"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    u2, _, y2 = system(4000, 14)
    y3, at = spiked(y2, 20, 20.0, 15)
    np.savetxt(tmp_path / "new.csv", np.column_stack([u2, y3]), delimiter=",",
               header="u,y", comments="", fmt="%.10g")
    [warning], with_spikes = _validate(tmp_path, "m.json", "--data", "new.csv")
    assert warning.startswith("warning:") and "20 spike(s)" in warning, warning
    assert f"at sample {at[0]}," in warning and "--spikes gaps" in warning
    [note], without = _validate(tmp_path, "m.json", "--data", "new.csv", "--spikes", "gaps")
    assert note.startswith("note: 20 output spike(s) left out (20 sample(s)"), note
    assert without < with_spikes / 10, (without, with_spikes)


def test_the_document_field_is_checked_when_read():
    check_metadata({"spikes": {"spikes": 2, "samples": 3, "at": [10, 40]}})
    with pytest.raises(ModelFormatError, match="metadata.spikes.at"):
        check_metadata({"spikes": {"spikes": 2, "samples": 3, "at": ["ten"]}})
