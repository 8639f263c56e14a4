"""A small study end to end through the CLI; same seeds give the same records."""

import csv
import json
import subprocess
import sys

import pytest

from spm_sysid.tools.experiment import ExperimentConfig, RunRecord, mark_reached, summarise

from .conftest import ROOT


def _study(out, report=None, extra=()):
    args = [sys.executable, "-m", "spm_sysid.apps.main", "experiment", "--criteria", "aic,bic",
            "--populations", "30", "--spm", "0,0.15", "--runs", "3", "--generations", "15",
            "--seed", "5", "--out", str(out), *extra]
    if report:
        args += ["--report", str(report)]
    return subprocess.run(args, capture_output=True, text=True, cwd=ROOT, timeout=300)


@pytest.mark.slow
def test_small_study_end_to_end_and_reproducible(tmp_path):
    r1 = _study(tmp_path / "a", tmp_path / "report")
    assert r1.returncode == 0, r1.stderr
    assert "| AIC | 30 | 0.15 |" in r1.stdout
    rows = list(csv.DictReader(open(tmp_path / "a" / "runs.csv")))
    assert len(rows) == 12
    assert {r["seed"] for r in rows} == {"5", "6", "7"}
    for name in ("runs.json", "summary.csv", "summary.md", "convergence.png", "convergence.svg"):
        assert (tmp_path / "a" / name).stat().st_size > 100
    report = (tmp_path / "report" / "report.md").read_text()
    assert "Beside the paper" in report and "![convergence](convergence.png)" in report
    assert (tmp_path / "report" / "convergence.png").exists()

    r2 = _study(tmp_path / "b", extra=("--workers", "1"))
    assert r2.returncode == 0, r2.stderr
    runs_a = json.loads((tmp_path / "a" / "runs.json").read_text())["runs"]
    runs_b = json.loads((tmp_path / "b" / "runs.json").read_text())["runs"]
    strip = ("seconds",)
    assert [{k: v for k, v in r.items() if k not in strip} for r in runs_a] == \
        [{k: v for k, v in r.items() if k not in strip} for r in runs_b]
    assert (tmp_path / "a" / "summary.md").read_text().splitlines()[2].split("|")[4] == \
        (tmp_path / "b" / "summary.md").read_text().splitlines()[2].split("|")[4]


def test_yaml_config_and_bad_settings(tmp_path):
    cfg = tmp_path / "study.yaml"
    cfg.write_text("criteria: [bic]\npopulations: [20]\nspm_fractions: [0.0]\nruns: 2\n"
                   "generations: 5\n")
    c = ExperimentConfig.from_yaml(cfg, runs=3)
    assert c.criteria == ["bic"] and c.runs == 3 and c.generations == 5
    cfg.write_text("populations: [20]\nbogus: 1\n")
    with pytest.raises(ValueError, match="unknown setting"):
        ExperimentConfig.from_yaml(cfg)
    with pytest.raises(ValueError, match="unknown criterion"):
        ExperimentConfig(criteria=["nope"])
    with pytest.raises(ValueError, match="spm_fraction"):
        ExperimentConfig(spm_fractions=[0.7])
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "experiment", "--spm",
                        "0,x"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "comma-separated" in r.stderr


def _rec(crit, s, value, terms, run=0):
    return RunRecord(crit, 100, s, run, run, value, terms, len(terms), 10, 0.1, 100)


def test_reach_counts_and_fisher_test_against_hand_values():
    from scipy.stats import fisher_exact

    best, other = ["a", "b"], ["a"]
    recs = [_rec("aic", 0.15, -10.0, best, i) for i in range(5)]
    recs += [_rec("aic", 0.0, -10.0, best, i) for i in range(1)]
    recs += [_rec("aic", 0.0, -9.0, other, i) for i in range(1, 5)]
    mark_reached(recs)
    rows = {r.spm_fraction: r for r in summarise(recs)}
    assert rows[0.15].reached == 5 and rows[0.0].reached == 1
    assert rows[0.15].fisher_p == pytest.approx(fisher_exact([[5, 0], [1, 4]])[1])
    assert rows[0.0].fisher_p is None


def test_reached_counts_against_a_certified_optimum():
    # the runs' best (-10) is not the certified optimum (-11): no run reached it
    recs = [_rec("aic", 0.15, -10.0, ["a", "b"], i) for i in range(3)]
    recs += [_rec("bic", 0.15, -5.0, ["a"], i) for i in range(3)]
    optima = {"aic": {"status": "optimal", "value": -11.0, "terms": ["c"]},
              "bic": {"status": "limit", "value": -5.0, "terms": ["a"]}}
    best = mark_reached(recs, optima)
    assert best["aic"] == (-11.0, ["c"], "certified optimum")
    assert best["bic"] == (-5.0, ["a"], "best found across runs")  # not proved: runs' best
    rows = {r.criterion: r for r in summarise(recs)}
    assert rows["aic"].reached == 0 and rows["aic"].reference == "certified optimum"
    assert rows["bic"].reached == 3 and rows["bic"].reference == "best found across runs"


def test_small_study_reports_the_certified_optimum(tmp_path, robot_arm):
    from spm_sysid.tools.experiment import run_experiment, summary_table

    u, y = robot_arm
    cfg = ExperimentConfig(criteria=["aic", "pmic2"], populations=[50], spm_fractions=[0.15],
                           runs=2, generations=40, workers=1)
    recs = run_experiment(u, y, cfg)
    aic = [r for r in recs if r.criterion == "aic"]
    assert all(r.reference == "certified optimum" for r in aic)
    eq1 = ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)", "u(t-1)", "u(t-2)", "u(t-3)", "u(t-4)"]
    assert all(r.reached_best == (sorted(r.terms) == sorted(eq1)) for r in aic)
    assert all(r.reference == "best found across runs" for r in recs if r.criterion == "pmic2")
    table = summary_table(summarise(recs))
    assert "| AIC | 50 | 0.15 |" in table and "certified optimum" in table
