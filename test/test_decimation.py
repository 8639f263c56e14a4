"""Decimation: a record identified at a slower rate, and everything that runs its model.

The friction issue's joint (1 kHz, encoder noise) is the case it is for: at the
record's rate the Coulomb force comes out 42 % high, at a fifth of it within 10 %.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.jobs import JobSettings, run_job
from spm_sysid.core.model.decimation import BlockDecimator, decimate_blocks
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.online.session import OnlineSession, held_out_mse
from spm_sysid.core.record import Record

from .helpers.joint import Joint, joint_record


def _blocks_by_hand(u, y, bounds, k):
    """Each segment's whole blocks, written as loops: the mean input, the first output."""
    us, ys, firsts = [], [], []
    for a, b in bounds:
        for s in range(a, b - k + 1, k):
            us.append(sum(u[s + j] for j in range(k)) / k)
            ys.append(y[s])
            firsts.append(s)
    return np.array(us), np.array(ys), firsts


def test_blocks_average_the_inputs_take_the_first_output_and_stay_inside_segments():
    rng = np.random.default_rng(0)
    n, k = 103, 4
    u, y = rng.standard_normal((n, 2)), rng.standard_normal(n)
    stamps = np.arange(n, dtype=np.int64) * 1_000_000
    stamps[50:] += 10_000_000  # a gap after sample 49: blocks restart at 50
    record = Record.from_samples(u, y, source="test", stamps_ns=stamps)
    d = record.decimated(k)
    want_u, want_y, firsts = _blocks_by_hand(u, y, [(0, 50), (50, n)], k)
    np.testing.assert_allclose(d.u, want_u, rtol=1e-12)
    np.testing.assert_array_equal(d.y, want_y)
    np.testing.assert_array_equal(d.stamps_ns, stamps[firsts])
    assert d.segments.bounds == [(0, 12), (12, 25)]  # 50 // 4 and 53 // 4 blocks
    assert d.segments.period_ns == 4_000_000 and d.segments.gaps == 1
    assert d.decimation == {"factor": 4, "samples": 103, "kept": 25, "unused": 3,
                            "inputs": "mean over the block",
                            "outputs": "first sample of the block"}
    assert "3 sample(s) at segment ends" in d.notes[-1]
    assert d.metadata()["decimation"]["factor"] == 4
    assert record.decimated(1) is record
    twice = record.decimated(2).decimated(2)  # the same blocks as decimating by 4
    np.testing.assert_allclose(twice.u, d.u, rtol=1e-12)
    np.testing.assert_array_equal(twice.y, d.y)
    assert twice.segments.bounds == d.segments.bounds
    assert twice.decimation == d.decimation


def test_the_stream_decimates_as_the_record_does_and_counts_partial_blocks():
    rng = np.random.default_rng(1)
    u, y = rng.standard_normal((40, 2)), rng.standard_normal(40)
    dec = BlockDecimator(5)
    out = [b for t in range(40) if (b := dec.push(t, u[t], y[t])) is not None]
    want_u, want_y, _, first = decimate_blocks(u, y, [(0, 40)], 5)
    assert [b[0] for b in out] == list(first)
    np.testing.assert_allclose([b[1] for b in out], want_u, rtol=1e-12)
    assert [b[2] for b in out] == list(want_y)
    dec.push(0, u[0], y[0])
    dec.push(1, u[1], y[1])
    dec.reset()  # a gap: the two samples of the partial block are given up, and counted
    assert dec.dropped == 2
    with pytest.raises(ValueError, match="factor must be >= 1"):
        BlockDecimator(0)


def _force(terms, coefficients):
    """The Coulomb force read from a joint model: the sign term over the input terms' sum."""
    th = dict(zip(terms, coefficients))
    return -th["sign(y(t-1)-y(t-2))"] / sum(v for k, v in th.items() if k.startswith("u("))


def test_the_joints_coulomb_force_within_ten_percent_at_a_fifth_of_its_rate(tmp_path):
    """The command as a user types it, then ``validate`` on the same 1 kHz file."""
    tau, q = joint_record(40.0, seed=0)
    data = tmp_path / "joint.csv"
    np.savetxt(data, np.c_[tau, q], delimiter=",", header="tau,q", comments="")
    cli = [sys.executable, "-m", "spm_sysid.apps.main"]
    common = ["--ny", "2", "--nu", "2", "--degree", "1", "--regressors", "friction",
              "--criterion", "bic", "--seed", "1", "--quiet"]
    out = subprocess.run([*cli, "identify", "--data", str(data), "--decimate", "5", *common,
                          "--json", str(tmp_path / "m.json")], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "note: decimated by 5: 40000 samples to 8000" in out.stdout
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["metadata"]["decimation"]["factor"] == 5
    model = NarxModel.load(tmp_path / "m.json")
    assert "sign(y(t-1)-y(t-2))" in model.terms
    assert _force(model.terms, model.coefficients) == pytest.approx(Joint().coulomb, rel=0.10)
    # at the record's own rate the same selection misreads the force (encoder noise)
    at_1khz = run_job(Record.from_samples(tau, q, source="joint"), JobSettings.from_values(
        {"ny": 2, "nu": 2, "degree": 1, "regressors": "friction", "criterion": "bic",
         "seed": 1})).model
    assert abs(_force(at_1khz.terms, at_1khz.coefficients) / Joint().coulomb - 1) > 0.25

    # certify reads the same options: the same decimated data, the preset expanded on it
    # (it ignored --regressors before), and proves the model's structure the best
    cert = subprocess.run([*cli, "certify", "--data", str(data), "--decimate", "5", *common,
                           "--json", str(tmp_path / "c.json")], capture_output=True, text=True,
                          timeout=300)
    assert cert.returncode == 0, cert.stderr
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["status"] == "optimal" and sorted(doc["terms"]) == sorted(model.terms)
    assert doc["value"] == pytest.approx(model.criterion_value, rel=1e-9)
    checked = subprocess.run([*cli, "validate", str(tmp_path / "m.json"), "--data", str(data)],
                             capture_output=True, text=True, timeout=300)
    assert checked.returncode == 0, checked.stderr
    assert "note: the model runs at 1/5 of the data's rate" in checked.stdout
    slow = Record.from_samples(tau, q, source="joint").decimated(5)
    e = model.residuals(slow.u, slow.y)  # the one-step error at the model's rate
    mse = float(checked.stdout.split("one-step: MSE ")[1].split(",")[0])
    assert mse == pytest.approx(float(np.mean(e * e)), rel=1e-3)


def test_the_monitor_predicts_a_decimated_model_once_a_block_as_offline():
    tau, q = joint_record(4.0, seed=2)
    settings = JobSettings.from_values({"ny": 2, "nu": 2, "degree": 1, "criterion": "bic",
                                        "seed": 0, "decimate": 4})
    model = run_job(Record.from_samples(tau, q, source="joint"), settings).model
    assert model.metadata["decimation"]["factor"] == 4
    session = OnlineSession(model)
    stamps = np.arange(len(q), dtype=np.int64) * 1_000_000
    got = [s for t in range(len(q)) if (s := session.feed(int(stamps[t]), tau[t], q[t]))]
    slow = Record.from_samples(tau, q, source="joint").decimated(4)
    want = slow.y[model.term_space.max_lag:] - model.residuals(slow.u, slow.y)
    np.testing.assert_allclose([s.predicted for s in got], want, rtol=1e-9, atol=1e-12)
    assert [s.stamp_ns for s in got] == list(stamps[::4][model.term_space.max_lag:])
    assert session.stats()["decimate"] == 4 and session.stats()["samples"] == len(q)
    e = model.residuals(slow.u, slow.y)
    assert held_out_mse(model, tau, q) == pytest.approx(float(np.mean(e * e)), rel=1e-12)
    assert not math.isclose(held_out_mse(model, tau, q, decimate=1), np.mean(e * e))


def test_a_decimation_that_leaves_too_few_samples_is_refused_in_words(tmp_path):
    data = tmp_path / "short.csv"
    rng = np.random.default_rng(0)
    np.savetxt(data, rng.standard_normal((60, 2)), delimiter=",")
    cli = [sys.executable, "-m", "spm_sysid.apps.main", "identify", "--data", str(data)]
    out = subprocess.run([*cli, "--decimate", "20"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode != 0 and "after decimating by 20" in out.stderr
    bad = subprocess.run([*cli, "--decimate", "0"], capture_output=True, text=True,
                         timeout=300)
    assert bad.returncode == 2 and "decimate" in bad.stderr and "Traceback" not in bad.stderr


def test_a_coupled_model_is_decimated_once_before_its_outputs_sessions():
    """The other outputs an output reads stay outputs (block starts), not block means."""
    from spm_sysid.core.model.mimo import augmented_inputs
    from spm_sysid.core.online.coupled import CoupledSession, coupled_held_out_mse

    from .helpers.two_joints import two_joint_record

    tau, q = two_joint_record(1200, seed=0)
    record = Record.from_samples(tau, q, source="two joints", output_names=("q1", "q2"))
    settings = JobSettings.from_values({"ny": 2, "nu": 1, "degree": 1, "seed": 0,
                                        "decimate": 3, "generations": 20})
    model = run_job(record, settings).model
    assert model.metadata["decimation"]["factor"] == 3
    session = CoupledSession(model)
    got = [s for t in range(len(q))
           for s in [session.feed(t * 1_000_000, tau[t], q[t])[0][1]] if s is not None]
    slow = record.decimated(3)
    m2 = model.models[1]
    e = m2.residuals(augmented_inputs(slow.u, slow.y, 1), slow.y[:, 1])
    np.testing.assert_allclose([s.residual for s in got], e, rtol=1e-9, atol=1e-12)
    assert session.stats()["samples"] == len(q) and session.stats()["decimate"] == 3
    assert np.isfinite(coupled_held_out_mse(model, tau, q))


def test_the_python_api_decimates_as_a_job_does(robot_arm):
    from spm_sysid.core.errors import SettingsError
    from spm_sysid.core.identify import identify

    u, y = robot_arm
    api = identify(u=u, y=y, decimate=2, seed=1).model
    job = run_job(Record.from_samples(u, y, source="arm"),
                  JobSettings.from_values({"decimate": 2, "seed": 1})).model
    assert api.terms == job.terms
    np.testing.assert_allclose(api.coefficients, job.coefficients, rtol=1e-12)
    assert api.metadata["decimation"] == job.metadata["decimation"]
    assert api.metadata["decimation"]["kept"] == len(y) // 2
    with pytest.raises(SettingsError, match="decimate must be between 1 and 10000, got 0"):
        identify(u=u, y=y, decimate=0)
    with pytest.raises(SettingsError, match="gap_factor is a setting of a record's timeline"):
        identify(u=u, y=y, gap_factor=2.0)


def test_the_data_check_says_when_a_record_is_sampled_far_faster_than_it_moves(robot_arm):
    """The 1 kHz joint is flagged with a decimation to try; the same joint decimated, the
    robot arm (acceleration, a broadband torque) and white noise are not."""
    from spm_sysid.core.validate.excitation import oversampling

    tau, q = joint_record(20.0, seed=0)
    assert oversampling(tau, q, [(0, len(q))]) == 20
    slow = Record.from_samples(tau, q, source="joint").decimated(5)
    assert oversampling(slow.u, slow.y, slow.segments.bounds) == 0
    u, y = robot_arm
    assert oversampling(u, y, None) == 0
    rng = np.random.default_rng(0)
    assert oversampling(rng.standard_normal(5000), rng.standard_normal(5000), None) == 0
    # by hand: a 2 Hz sine sampled at 1 kHz (250x) and at 50 Hz (12.5x), the power
    # of a sine sits at its frequency
    t = np.arange(20000) / 1000.0
    assert oversampling(np.sin(2 * np.pi * 2 * t), np.cos(2 * np.pi * 2 * t), None) == 100
    t = np.arange(2000) / 50.0
    assert oversampling(np.sin(2 * np.pi * 2 * t), np.cos(2 * np.pi * 2 * t), None) == 10
    model = run_job(Record.from_samples(tau, q, source="joint"), JobSettings.from_values(
        {"ny": 2, "nu": 2, "degree": 1, "seed": 0, "generations": 5})).model
    assert any("sampled about 20x faster" in w and "--decimate 5" in w
               for w in model.metadata["warnings"])


def test_a_study_config_that_asks_for_decimation_gets_it(tmp_path):
    """``decimate`` in a study's --config is a job setting like the others: not ignored."""
    config = tmp_path / "study.yaml"
    config.write_text("criteria: [bic]\npopulations: [50]\nspm_fractions: [0.15]\nruns: 2\n"
                      "generations: 10\ndecimate: 2\n")
    out = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "experiment",
                          "--config", str(config), "--out", str(tmp_path / "study"), "--quiet",
                          "--no-certify"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "note: decimated by 2: 1024 samples to 512" in out.stdout
    assert "2 runs on robot-arm data" in out.stdout and "512 samples" in out.stdout
