"""A system that changed during the record: the returned structure fitted on each half.

A plant whose input gain went from 0.5 to 0.6 halfway got a model and no word of
the change. ``identify`` now fits the returned structure on each half of the
estimation rows and warns when each half's one-step error with the other's
coefficients is several times its own and the Chow test rejects equal
coefficients (``metadata.constancy``).
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from spm_sysid.core.identify import identify
from spm_sysid.core.model import narx as narx_module
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.validate.constancy import CHANGED, constancy

sys.path.insert(0, str(Path(__file__).parent))
from helpers.changing_gain import changing_gain  # noqa: E402

EXE = str(Path(sys.executable).with_name("spm-sysid"))


def _direct(model, u, y, first, second):
    """The ratios and the Chow p-value from whole regression matrices (numpy lstsq)."""
    p = len(model.term_indices)
    P1, t1 = model.term_space.regression(u, y, first, terms=model.term_indices)
    P2, t2 = model.term_space.regression(u, y, second, terms=model.term_indices)
    th1, th2 = (np.linalg.lstsq(P, t, rcond=None)[0] for P, t in ((P1, t1), (P2, t2)))
    own1, own2 = np.sum((t1 - P1 @ th1) ** 2), np.sum((t2 - P2 @ th2) ** 2)
    ratios = [np.sum((t1 - P1 @ th2) ** 2) / len(t1) / (own1 / (len(t1) - p)),
              np.sum((t2 - P2 @ th1) ** 2) / len(t2) / (own2 / (len(t2) - p))]
    P, t = np.vstack([P1, P2]), np.concatenate([t1, t2])
    joint = np.sum((t - P @ np.linalg.lstsq(P, t, rcond=None)[0]) ** 2)
    dof = len(t) - 2 * p
    f = (joint - own1 - own2) / p / ((own1 + own2) / dof)
    return ratios, stats.f.sf(f, p, dof), len(t1), len(t2)


@pytest.mark.parametrize("slices", [None, 97])
def test_the_halves_ratios_and_chow_test_equal_a_direct_computation(monkeypatch, slices):
    """Three segments (the rows split inside the second), whole or read 97 rows at a time."""
    if slices:
        monkeypatch.setattr(narx_module, "slice_rows", lambda k: slices)
    u, y = changing_gain(3000, seed=3, at=0.45)
    space = TermSpace(ny=2, nu=1, degree=2)
    terms = [space.term_names().index(name) for name in ("y(t-1)", "y(t-2)", "u(t-1)", "u(t-1)^2")]
    model = NarxModel(space, terms, np.zeros(4))
    segments = [(0, 900), (950, 2400), (2500, 3000)]
    found = constancy(model, u, y, segments)
    # rows: 898 + 1448 + 498 = 2844; the first half ends 524 rows into the second segment
    first, second = [(0, 900), (950, 1476)], [(1474, 2400), (2500, 3000)]
    ratios, p_value, m1, m2 = _direct(model, u, y, first, second)
    assert (m1, m2) == (1422, 1422)
    assert found["at"] == 1476
    assert found["ratios"] == pytest.approx(ratios, rel=1e-6)
    assert found["p_value"] == pytest.approx(p_value, rel=1e-6, abs=1e-300)
    assert min(ratios) > CHANGED and found["changed"]


def test_one_system_throughout_is_not_called_changed():
    u, y = changing_gain(3000, seed=4, after=0.5)
    space = TermSpace(ny=2, nu=1, degree=2)
    terms = [space.term_names().index(name) for name in ("y(t-1)", "y(t-2)", "u(t-1)", "u(t-1)^2")]
    found = constancy(NarxModel(space, terms, np.zeros(4)), u, y)
    assert max(found["ratios"]) < 1.1 and not found["changed"]
    # too few rows for the structure on each half: no statement
    assert constancy(NarxModel(space, terms, np.zeros(4)), u[:12], y[:12]) is None


def test_a_noise_free_record_is_judged_on_its_changes_not_on_rounding():
    """Exact fits (1e-30) compare at the rounding floor: unchanged about 1, changed warned."""
    space = TermSpace(ny=2, nu=1, degree=2)
    terms = [space.term_names().index(name) for name in ("y(t-1)", "y(t-2)", "u(t-1)", "u(t-1)^2")]
    model = NarxModel(space, terms, np.zeros(4))
    same = constancy(model, *changing_gain(2000, seed=5, after=0.5, noise=0.0))
    assert same["ratios"] == pytest.approx([1.0, 1.0], abs=0.01) and not same["changed"]
    changed = constancy(model, *changing_gain(2000, seed=5, noise=0.0))
    # the first half's rows end at t = 1000, the first sample at the new gain: not exact
    assert changed["ratios"][0] > 100 and changed["ratios"][1] > 1e12
    assert changed["p_value"] < 1e-12 and changed["changed"]


def test_identify_as_typed_warns_of_a_gain_that_changed_halfway(tmp_path):
    """The command as typed on a record whose gain changes halfway: the warning on the
    terminal and in the document; the same plant unchanged: no warning."""
    for name, after in (("changed", 0.6), ("same", 0.5)):
        u, y = changing_gain(4000, seed=1, after=after)
        np.savetxt(tmp_path / f"{name}.csv", np.column_stack([u, y]), delimiter=",",
                   header="u,y", comments="")
        done = subprocess.run(
            [EXE, "identify", "--data", f"{name}.csv", "--focus", "simulation", "--orders",
             "auto", "--json", f"{name}.json"], capture_output=True, text=True, cwd=tmp_path,
            timeout=300)
        assert done.returncode == 0, done.stderr
        doc = json.loads((tmp_path / f"{name}.json").read_text())
        found = doc["metadata"]["constancy"]
        said = "first and second halves fit different coefficients" in done.stdout + done.stderr
        warned = any("halves fit different" in w for w in doc["metadata"].get("warnings", []))
        if name == "changed":
            assert found["changed"] and min(found["ratios"]) >= CHANGED
            assert found["p_value"] < 1e-3 and said and warned
        else:
            assert not found["changed"] and max(found["ratios"]) < CHANGED
            assert not said and not warned


def test_the_python_api_carries_the_same_account():
    u, y = changing_gain(3000, seed=2)
    model = identify(u=u, y=y, focus="simulation", orders="auto", seed=1).model
    assert model.metadata["constancy"]["changed"]
    assert any("halves fit different" in w for w in model.metadata["warnings"])
