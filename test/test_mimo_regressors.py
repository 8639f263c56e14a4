"""Several outputs with regressors: the coupled run, the identification, the refusals.

The record (test/helpers/two_joints.py) is made by a plain-Python loop, so the
coupled simulation is checked against the system itself, and the
identification against its terms.
"""

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from spm_sysid.core.errors import SettingsError
from spm_sysid.core.jobs import JobSettings, run_job
from spm_sysid.core.model.mimo import MimoModel, output_space
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.record import Record

from .conftest import ROOT
from .helpers.two_joints import SIGN, TRUE
from .helpers.two_joints import two_joint_record as _system

NAMES, INPUTS = ("q1", "q2"), ("t1", "t2")


def _space(i: int, regressors=SIGN, **kw) -> TermSpace:
    base = TermSpace(ny=2, nu=1, degree=kw.pop("degree", 1), inputs=INPUTS, output=NAMES[0],
                     **kw)
    return replace(output_space(base, NAMES, i), regressors=tuple(regressors))


def _model(terms: dict, spaces) -> MimoModel:
    models = []
    for name, space in zip(NAMES, spaces):
        names = space.term_names()
        idx = sorted(names.index(t) for t in terms[name])
        models.append(NarxModel(space, idx, np.array([terms[name][names[j]] for j in idx])))
    return MimoModel(NAMES, INPUTS, models)


def test_the_coupled_run_with_regressors_reproduces_the_system_that_made_the_record():
    u, Y = _system(1500, seed=3, noise=0.0)
    model = _model(TRUE, [_space(0), _space(1)])
    sim, div = model.simulate(u, Y)
    assert div == [None, None]
    np.testing.assert_allclose(sim, Y[2:], rtol=0, atol=1e-12)
    ahead, div = model.k_step(u, Y, horizon=5)
    assert div == [None, None]
    np.testing.assert_allclose(ahead, Y[2:], rtol=0, atol=1e-12)
    # a sign left out of the coupled run changes it: the regressor is really computed
    lost = _model({k: {t: c for t, c in v.items() if "sign" not in t} for k, v in TRUE.items()},
                  [_space(0), _space(1)])
    assert np.max(np.abs(lost.simulate(u, Y)[0] - Y[2:])) > 0.05


def test_any_coupled_structure_with_regressors_steps_as_its_own_columns_say():
    """Products of regressors, a constant, unused regressors, one output without any."""
    rng = np.random.default_rng(0)
    regs = ("sign(q1(t-1)-q1(t-2))", "tanh((q2(t-1)-q2(t-2))/0.1)", "abs(t1(t))*2.5",
            "sat(t2(t-3),0.5)")
    for trial in range(4):
        spaces = [_space(0, regs, degree=2, constant=True),
                  _space(1, regs if trial % 2 else (), degree=2, constant=True)]
        models = []
        for space in spaces:
            idx = sorted({0, *(int(j) for j in rng.choice(space.n_terms, 7, replace=False))})
            models.append(NarxModel(space, idx, 0.1 * rng.standard_normal(len(idx))))
        model = MimoModel(NAMES, INPUTS, models)
        u, Y = rng.standard_normal((200, 2)), 0.3 * rng.standard_normal((200, 2))
        sim, div = model.simulate(u, Y)
        assert div == [None, None]
        # the reference: each step's row of the term spaces' own columns (numpy)
        np.testing.assert_allclose(sim, _stepped_together(models, u, Y), rtol=0, atol=1e-12)


def test_joint_refinement_of_structures_with_regressors_lowers_the_coupled_error():
    """Their coupled run has no sensitivities: finite differences refine them."""
    from spm_sysid.core.fit.refine_coupled import refine_coupled

    u, Y = _system(600, seed=4)
    off = {k: {t: c * (0.9 if "sign" not in t else 1.3) for t, c in v.items()}
           for k, v in TRUE.items()}  # every coefficient a little off
    start = _model(off, [_space(0), _space(1)])
    refined, info = refine_coupled(start, u, Y, max_evaluations=20)
    assert info["taken"] and info["after"] < 0.5 * info["before"]
    sim, div = refined.simulate(u, Y)
    r = (Y[2:] - sim) / Y.std(axis=0)
    assert div == [None, None] and float(np.sum(r * r)) == pytest.approx(info["after"], rel=1e-9)


def test_a_joint_refinement_beyond_its_finite_difference_budget_keeps_the_outputs_own(
        monkeypatch):
    """Six coupled joints with the friction preset (240 coefficients, 4·10^4 samples) spent
    over ten minutes on one finalist's folds: one coupled run per coefficient per step.
    Beyond JOINT_DIFFERENCE_SAMPLES the outputs' own coefficients are kept, and the
    account says why; within it the same start is refined (the test above)."""
    import spm_sysid.core.fit.refine_coupled as joint
    from spm_sysid.core.defaults import JOINT_DIFFERENCE_SAMPLES

    u, Y = _system(600, seed=4)
    off = {k: {t: c * 0.9 for t, c in v.items()} for k, v in TRUE.items()}
    start = _model(off, [_space(0), _space(1)])
    coefficients = sum(len(m.term_indices) for m in start.models)
    work = (coefficients + 1) * 2 * (600 - start.max_lag)
    assert work < JOINT_DIFFERENCE_SAMPLES  # the default refines it
    monkeypatch.setattr(joint, "JOINT_DIFFERENCE_SAMPLES", work - 1)
    kept, info = joint.refine_coupled(start, u, Y, max_evaluations=20)
    assert kept is start and not info["taken"] and info["evaluations"] == 1
    assert info["message"] == (
        f"not refined jointly: with regressors each of the {coefficients} coefficients costs "
        f"a coupled run of {2 * (600 - start.max_lag)} samples per step ({work:.2g} in all, "
        f"more than {work - 1:.2g}); each output's own refinement kept")


def _stepped_together(models, u, Y) -> np.ndarray:
    """Every output at t from the simulated past of both (numpy columns, plain loop)."""
    S, lag = Y.copy(), max(m.term_space.max_lag for m in models)
    for t in range(lag, len(Y)):
        new = []
        for i, m in enumerate(models):
            inputs = np.column_stack([u, S[:, 1 - i]])[:t + 1]
            P, _ = m.term_space.regression(inputs, S[:t + 1, i], [(0, t + 1)],
                                           terms=m.term_indices)
            new.append(P[-1] @ m.coefficients)
        S[t] = new
    return S[lag:]


@pytest.mark.slow
def test_friction_on_two_outputs_finds_each_joints_sign_and_simulates_a_new_record_better(
        tmp_path):
    u, Y = _system(2000, seed=1)
    record = Record.from_samples(u, Y, output_names=NAMES, input_names=INPUTS, source="joints")
    values = {"ny": 2, "nu": 1, "degree": 1, "criterion": "bic"}
    with_friction = run_job(record, JobSettings.from_values({**values,
                                                            "regressors": "friction"})).model
    without = run_job(record, JobSettings.from_values(values)).model
    for i, m in enumerate(with_friction.models):
        # every output's space holds both joints' friction bases
        assert sum(r.startswith("sign(") for r in m.term_space.regressors) == 2
        names = [m.term_space.term_names()[j] for j in m.term_indices]
        assert SIGN[i] in names, names
        assert m.coefficients[names.index(SIGN[i])] < 0  # against the motion
    u2, Y2 = _system(2000, seed=2)

    def rmse(model):
        sim, div = model.simulate(u2, Y2)
        assert div == [None, None]
        return np.sqrt(np.mean((Y2[model.max_lag:] - sim) ** 2, axis=0))

    assert np.all(rmse(with_friction) * 2 < rmse(without))
    path = with_friction.save(tmp_path / "m.json")
    again = MimoModel.load(path)
    np.testing.assert_array_equal(again.simulate(u2, Y2)[0], with_friction.simulate(u2, Y2)[0])


def test_the_saturation_preset_clips_the_shared_inputs_at_each_outputs_level():
    """Two outputs driven through one amplifier that clips at 1.0 (benchmarks/actuator.py)."""
    from benchmarks.actuator import LIMIT, record
    from spm_sysid.core.jobs.several import _with_regressors

    u, v = record(2000, seed=0)
    Y = np.column_stack([v, 0.5 * v + 0.01 * np.random.default_rng(0).standard_normal(2000)])
    U = np.column_stack([u, np.random.default_rng(1).uniform(-1, 1, 2000)])
    rec = Record.from_samples(U, Y, output_names=NAMES, input_names=INPUTS, source="loop")
    base = JobSettings.from_values({"ny": 2, "nu": 2, "degree": 1, "regressors": "saturation",
                                    "validation_fraction": 0.0})
    texts = _with_regressors(rec, base.for_signals(INPUTS, NAMES[0])).regressors.split("; ")
    clipped = {t.split(",")[0] for t in texts}
    assert clipped == {"sat(t1(t-1)", "sat(t1(t-2)", "sat(t2(t-1)", "sat(t2(t-2)"}
    levels = {float(t.split(",")[1].rstrip(")")) for t in texts if t.startswith("sat(t1")}
    assert all(abs(level - LIMIT) < 0.02 for level in levels)  # both outputs see the limit


def test_a_regressor_reading_another_output_at_t_is_refused_with_one_line():
    u, Y = _system(400, seed=0)
    record = Record.from_samples(u, Y, output_names=NAMES, input_names=INPUTS, source="joints")
    with pytest.raises(SettingsError, match=r"reads q2\(t\), an output .* q2\(t-1\)"):
        run_job(record, JobSettings.from_values({"regressors": "sign(q2(t))", "ny": 2}))
    with pytest.raises(SettingsError, match="unknown name 'q3'"):
        run_job(record, JobSettings.from_values({"regressors": "abs(q3(t-1))", "ny": 2}))


@pytest.mark.slow
def test_identify_two_outputs_with_the_preset_on_the_command_line(tmp_path):
    u, Y = _system(1500, seed=4)
    csv = tmp_path / "joints.csv"
    np.savetxt(csv, np.column_stack([u, Y]), delimiter=",", header="t1,t2,q1,q2", comments="")
    run = [sys.executable, "-m", "spm_sysid.apps.main"]
    out = subprocess.run([*run, "identify", "--data", str(csv), "--inputs", "t1,t2", "--output",
                          "q1,q2", "--ny", "2", "--nu", "1", "--regressors", "friction",
                          "--json", str(tmp_path / "m.json")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    equations = [line for line in lines if line.startswith(("q1(t) =", "q2(t) ="))]
    assert len(equations) == 2 and all("sign(" in e for e in equations), equations
    out = subprocess.run([*run, "validate", str(tmp_path / "m.json"), "--data", str(csv)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "coupled" in out.stdout
