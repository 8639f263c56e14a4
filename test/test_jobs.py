"""Jobs (core/jobs): one path from a record to a model; the same input, the same model document."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.identify import identify
from spm_sysid.core.jobs import JobSettings, run_job
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.record import DataSpec, Record, load_record
from spm_sysid.core.search.ga import GAConfig

from .conftest import ROOT

#: Fields of a model document that record when and how fast, not what.
VOLATILE = ("created", "identify_seconds", "search_seconds")


def _strip(doc: dict) -> dict:
    doc = json.loads(json.dumps(doc))
    for key in VOLATILE:
        doc.pop(key, None)
        doc["metadata"].pop(key, None)
    doc["metadata"].get("certificate", {}).pop("seconds", None)
    return doc


def spm(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def test_a_study_run_is_the_computation_identify_does(robot_arm):
    from spm_sysid.tools.experiment import ExperimentConfig, run_experiment

    u, y = robot_arm
    cfg = ExperimentConfig(criteria=["bic", "pmic2"], populations=[40], spm_fractions=[0.15],
                           runs=2, seed=7, generations=30, workers=1, certify_reference=False,
                           ny=3, nu=3)
    assert cfg.polish is False and cfg.auto_certify_time_limit == 0  # the GA alone
    records = run_experiment(u, y, cfg)
    assert len(records) == 4
    for r in records:
        res = identify(u=u, y=y, term_space=TermSpace(ny=3, nu=3), criterion=r.criterion,
                       ga=GAConfig(population_size=40, generations=30, spm_fraction=0.15),
                       seed=r.seed, polish=False, auto_certify_time_limit=0)
        assert r.terms == res.model.terms
        assert r.final_value == res.model.criterion_value
        assert r.best_curve == res.ga.history_array("best").tolist()


def _two_input_csv(path, n=600, seed=3):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n, 2))
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.5 * y[t - 1] + 0.7 * u[t - 1, 0] - 0.4 * u[t - 1, 1]
    y += 1e-3 * rng.standard_normal(n)
    path.write_text("time,torque,cmd,acc\n" + "".join(
        f"{k * 0.01:.2f},{float(u[k, 0])!r},{float(u[k, 1])!r},{float(y[k])!r}\n"
        for k in range(n)))


@pytest.mark.parametrize("kind", ["bag", "csv"])
def test_identify_and_batch_write_the_same_model_document(tmp_path, robot_arm, kind):
    """A single-input bag named torque: identify named it torque, batch u."""
    common = ["--criterion", "bic", "--seed", "3", "--generations", "40",
              "--population-size", "60"]
    if kind == "bag":
        from spm_sysid.core.io.bagio import write_io_bag

        u, y = robot_arm
        src = write_io_bag(tmp_path / "arm", u, y)
        data = ["--input-names", "torque"]
        ident = spm("identify", "--bag", str(src), *data, *common, "--quiet",
                    "--json", str(tmp_path / "identify.json"))
    else:
        src = tmp_path / "take.csv"
        _two_input_csv(src)
        data = ["--inputs", "torque,cmd", "--output", "acc"]
        ident = spm("identify", "--data", str(src), *data, *common, "--quiet",
                    "--json", str(tmp_path / "identify.json"))
    assert ident.returncode == 0, ident.stderr
    batch = spm("batch", str(src), "--out", str(tmp_path / "batch"), *data, *common,
                "--quiet", "--workers", "1")
    assert batch.returncode == 0, batch.stderr
    a = json.loads((tmp_path / "identify.json").read_text())
    b = json.loads((tmp_path / "batch" / f"{src.stem}.json").read_text())
    assert _strip(a) == _strip(b)
    names = ["torque"] if kind == "bag" else ["torque", "cmd"]
    assert a["term_space"]["inputs"] == names


@pytest.mark.slow
def test_the_candidate_matrix_is_built_once_per_identification(robot_arm, monkeypatch):
    calls = []
    original = TermSpace.regression_matrix

    def counting(self, u, y, terms=None, scales=None, out=None):
        if terms is None:
            calls.append(len(y))
        return original(self, u, y, terms, scales, out=out)

    monkeypatch.setattr(TermSpace, "regression_matrix", counting)
    u, y = robot_arm
    record = Record.from_samples(u, y, source="arm")
    for focus, extra in (("prediction", {"certify": True}), ("simulation", {})):
        calls.clear()
        settings = JobSettings.from_values({"seed": 1, "generations": 20, "focus": focus,
                                            "shortlist": 3, "horizon": 5, **extra})
        result = run_job(record, settings)
        assert result.report is not None and len(calls) == 1, (focus, calls)


def test_every_loader_gives_one_record_type(robot_arm, robot_arm_path, tmp_path):
    from spm_sysid.core.io.bagio import write_io_bag

    u, y = robot_arm
    default = load_record()
    from_file = load_record(DataSpec(data=(str(robot_arm_path),)))
    from_bag = load_record(DataSpec(bag=str(write_io_bag(tmp_path / "b", u, y))))
    for r in (default, from_file, from_bag):
        assert isinstance(r, Record) and r.input_names == ("u",) and r.output_name == "y"
        np.testing.assert_array_equal(r.u, u)
        np.testing.assert_array_equal(r.y, y)
    assert from_bag.stamps_ns is not None and from_file.stamps_ns is None
    assert default.source.startswith("robot-arm data")
    both = load_record(DataSpec(data=(str(robot_arm_path), str(robot_arm_path))))
    assert len(both) == 2048 and len(both.segment_info().bounds) == 2
    assert [p["samples"] for p in both.parts] == [1024, 1024]


def test_a_drawn_seed_is_written_and_repeats_the_run(robot_arm):
    """No seed given: a new one each run, in the document and the answer, that repeats it."""
    u, y = robot_arm
    record = Record.from_samples(u, y, source="robot arm")
    small = {"population_size": 40, "generations": 30, "validation": "none"}
    first = run_job(record, JobSettings.from_values(small))
    meta = first.model.metadata
    assert meta["seed_drawn"] is True and isinstance(meta["seed"], int) and meta["seed"] >= 0
    assert f"--seed {meta['seed']} repeats this run" in first.summary()
    assert f"seed {meta['seed']}, drawn: the setting seed={meta['seed']} repeats this run" \
        in first.summary("line")  # the node's answer and log
    again = run_job(record, JobSettings.from_values({**small, "seed": meta["seed"]}))
    assert "seed_drawn" not in again.model.metadata
    assert again.model.term_indices == first.model.term_indices
    np.testing.assert_array_equal(again.model.coefficients, first.model.coefficients)
    other = run_job(record, JobSettings.from_values(small)).model.metadata["seed"]
    assert other != meta["seed"]  # 1 in 2^31 of failing by chance
