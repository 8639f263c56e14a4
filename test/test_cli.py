"""The spm-sysid command line, run as a real subprocess."""

import json
import subprocess
import sys

import pytest

from .conftest import EQ1, ROOT


def spm(*args, cwd=ROOT, **kw):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=300, **kw)


def test_identify_on_robot_arm_writes_model(tmp_path):
    out = tmp_path / "model.json"
    r = spm("identify", "--criterion", "aic", "--seed", "1", "--json", str(out),
            "--validation", "none")
    assert r.returncode == 0, r.stderr
    assert "y(t) = 3.158y(t-1) - 4.439y(t-2)" in r.stdout
    assert "AIC = -10744.78" in r.stdout and "8 terms" in r.stdout
    assert "MSE 2.6199e-05" in r.stdout
    doc = json.loads(out.read_text())
    assert doc["terms"] == EQ1 and doc["metadata"]["seed"] == 1


def test_identify_small_settings_on_a_data_file(tmp_path, robot_arm_path):
    csv = tmp_path / "d.csv"
    lines = robot_arm_path.read_text().splitlines()
    csv.write_text("u,y\n" + "\n".join(ln.replace(" ", ",") for ln in lines) + "\n")
    r = spm("identify", "--data", str(csv), "--criterion", "bic", "--ny", "2", "--nu", "2",
            "--degree", "1", "--population", "20", "--generations", "10", "--spm", "0",
            "--seed", "3", "--validation", "none")
    assert r.returncode == 0, r.stderr
    assert "criterion BIC" in r.stdout


@pytest.mark.parametrize("args, message", [
    (["identify", "--data", "/no/such/file.dat"], "data file not found"),
    (["identify", "--criterion", "xyz", "--generations", "1"], "unknown criterion"),
    (["identify", "--spm", "0.9"], "spm_fraction"),
    (["identify", "--degree", "0"], "degree"),
    (["identify", "--data", "x", "--bag", "y"], "either --data or --bag"),
])
def test_identify_errors_are_one_line_without_traceback(args, message):
    r = spm(*args)
    assert r.returncode == 2
    assert message in r.stderr and "Traceback" not in r.stderr


def test_bad_file_content_error(tmp_path):
    p = tmp_path / "bad.dat"
    p.write_text("1 2\n3 x\n")
    r = spm("identify", "--data", str(p))
    assert r.returncode == 2 and "line 2: 'x' is not a number" in r.stderr


@pytest.mark.slow
def test_bench_prints_figures():
    """`make bench`'s command (the benchmarks live beside the package, not in spm-sysid)."""
    r = subprocess.run([sys.executable, "-m", "benchmarks.commands", "bench", "--repeats", "1",
                        "--naive-repeats", "1", "--generations", "15"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "naive/engine time ratio" in r.stdout and "cache hits" in r.stdout
    assert "simulation kernel: free-run of 1024 samples, 30 terms: compiled" in r.stdout
    assert "focus simulation (BIC, population 200, 15 generations)" in r.stdout


@pytest.mark.slow
def test_identify_plots_and_validate_saved_model_on_other_data(tmp_path, robot_arm_path):
    model = tmp_path / "m.json"
    figs = tmp_path / "figs"
    r = spm("identify", "--criterion", "bic", "--seed", "2", "--json", str(model),
            "--plots", str(figs), "--validation", "holdout", "--split", "0.5")
    assert r.returncode == 0, r.stderr
    assert "validation on holdout data (516 samples)" in r.stdout
    assert "512 samples used for estimation" in r.stdout
    names = sorted(p.name for p in figs.iterdir())
    assert names == sorted(f"model_{k}.{e}" for k in ("correlation", "one_step", "free_run")
                           for e in ("png", "svg"))
    doc = json.loads(model.read_text())
    assert doc["metadata"]["validation"]["segment"] == "holdout"
    # validate on a different data file: the second half, written as CSV
    lines = robot_arm_path.read_text().splitlines()[512:]
    other = tmp_path / "other.csv"
    other.write_text("u,y\n" + "\n".join(ln.replace(" ", ",") for ln in lines) + "\n")
    r = spm("validate", str(model), "--data", str(other), "--plots", str(tmp_path / "v"))
    assert r.returncode == 0, r.stderr
    assert "validation on supplied data (512 samples)" in r.stdout
    assert "one-step 95% band from the coefficients' uncertainty" in r.stdout  # schema 3
    assert "std. error" in r.stdout and "95% interval" in r.stdout
    assert (tmp_path / "v" / "model_free_run.png").stat().st_size > 1000
    # a version 2 document (no uncertainty) is still validated, without bands
    doc["schema_version"] = 2
    del doc["uncertainty"]
    old = tmp_path / "v2.json"
    old.write_text(json.dumps(doc))
    r = spm("validate", str(old), "--data", str(other))
    assert r.returncode == 0, r.stderr
    assert "validation on supplied data (512 samples)" in r.stdout
    assert "uncertainty" not in r.stdout.split("validation on")[1]  # no bands
    assert "(no coefficient uncertainty for this model)" in r.stdout
    r = spm("validate", str(tmp_path / "missing.json"))
    assert r.returncode == 2 and "model file not found" in r.stderr


def test_readme_python_example_runs_as_written(tmp_path):
    import re

    text = (ROOT / "README.md").read_text()
    code = re.search(r"## Python\n\n```python\n(.*?)```", text, re.S).group(1)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "y(t) = 3.128y(t-1)" in r.stdout and "-10707.48" in r.stdout  # eq. (2), BIC
    assert (tmp_path / "model.json").exists()


def test_validate_errors_from_prints_the_benchmarks_rmse(tmp_path, robot_arm):
    """``validate MODEL --data FILE --errors-from 50``: RMSE of the free run from sample 50."""
    import numpy as np

    from .conftest import eq1_model

    u, y = robot_arm
    model = eq1_model(robot_arm)
    path = model.save(tmp_path / "eq1.json")
    test = tmp_path / "test.csv"  # the second half as a test record of its own
    np.savetxt(test, np.column_stack([u[512:], y[512:]]), delimiter=",", header="u,y",
               comments="")
    r = spm("validate", str(path), "--data", str(test), "--errors-from", "50")
    assert r.returncode == 0, r.stderr
    sim, _ = model.run(u[512:], y[512:])  # from the test record's own first samples
    e = y[512 + 50:] - sim[50 - model.term_space.max_lag:]
    line = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("free-run:"))
    assert f"RMSE {np.sqrt(np.mean(e * e)):.4g}," in line
    assert "(512 samples; errors from sample 50 of each segment)" in r.stdout
    for bad, message in (("-1", "--errors-from must be 0 or more, got -1"),
                         ("600", "errors from sample 600 leave no sample to score")):
        r = spm("validate", str(path), "--data", str(test), "--errors-from", bad)
        assert r.returncode == 2 and message in r.stderr, r.stderr


def test_readme_offline_commands_fit_then_score_from_sample_50(tmp_path, robot_arm):
    """The README's offline pair as written: identify on take.csv, validate it from sample 50."""
    import numpy as np

    from spm_sysid.core.model.narx import NarxModel

    u, y = robot_arm
    np.savetxt(tmp_path / "take.csv", np.column_stack([u, y]), delimiter=",",
               header="torque,acc", comments="", fmt="%.10g")
    text = (ROOT / "README.md").read_text().replace("\n", " ")
    for command in ("spm-sysid identify --data take.csv --inputs torque --output acc --json "
                    "model.json --plots figs/",
                    "spm-sysid validate model.json --data take.csv --errors-from 50"):
        assert command in text
    r = spm("identify", "--data", "take.csv", "--inputs", "torque", "--output", "acc",
            "--json", "model.json", "--plots", "figs/", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = spm("validate", "model.json", "--data", "take.csv", "--errors-from", "50",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    model = NarxModel.load(tmp_path / "model.json")
    data = np.loadtxt(tmp_path / "take.csv", delimiter=",", skiprows=1)
    sim, _ = model.run(data[:, 0], data[:, 1])
    e = data[50:, 1] - sim[50 - model.term_space.max_lag:]
    line = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("free-run:"))
    assert f"RMSE {np.sqrt(np.mean(e * e)):.4g}," in line


def test_readme_long_record_command_on_the_robot_arm_is_judged_on_its_free_run(
        tmp_path, robot_arm):
    """`spm-sysid identify --data take.csv --focus simulation --orders auto` as the README
    writes it, on the robot arm: its order-6 ARX reads a pole at 1.0071 that no higher
    order has, and the command was judged on the 10-step prediction (a 59.9x overfit)."""
    import numpy as np

    u, y = robot_arm
    np.savetxt(tmp_path / "take.csv", np.column_stack([u, y]), delimiter=",",
               header="torque,acc", comments="", fmt="%.10g")
    command = "spm-sysid identify --data take.csv --focus simulation --orders auto"
    assert command in (ROOT / "README.md").read_text().replace("\n", " ")
    r = spm(*command.split()[1:], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert "selected by its free-run error on" in out, out
    assert "unstable in open loop" not in out and "10-step" not in out, out
    overfit = [ln for ln in out.splitlines() if "(overfit?)" in ln]
    # a warning of overfitting says what the same blocks said against the best linear model,
    # when the model returned is the one judged there, unchanged (the drawn seed decides:
    # a draw whose challenger the guard shrank or removed gets no such clause)
    judged = "by more than the noise, returned;" in out
    assert all(("x the best linear model's error" in ln) == judged for ln in overfit), (
        judged, overfit)
