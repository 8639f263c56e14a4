"""Several outputs wherever a signal enters: CSV columns, bags, the buffer, the job, the CLI.

No ROS here (the node over DDS: test_mimo_node.py). Bags are written with
rosbags and read back by the package's reader; the coupled free run of each
output's report is checked against the plain-Python reference of test_mimo.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.errors import DataError
from spm_sysid.core.io.bagio import read_bag_signals, write_io_bag
from spm_sysid.core.jobs import JobSettings, run_job
from spm_sysid.core.jobs.several import MimoJobResult
from spm_sysid.core.model.mimo import MimoModel, read_model_document
from spm_sysid.core.record import DataSpec, Record, load_record
from spm_sysid.core.stream.buffer import SampleBuffer, pair_streams

from .conftest import TRUE, reference_simulation, two_output_system, write_joint_state_bag
from .helpers.two_orders import coupled_outputs

SETTINGS = {"ny": 1, "nu": 1, "degree": 2, "criterion": "bic", "seed": 0}


def test_the_buffer_aligns_two_output_streams_and_counts_them():
    buf = SampleBuffer(100, input_widths=(2,), output_widths=(1, 1))
    pairs = []
    buf.on_pair = lambda t, u, y: pairs.append((t, u.copy(), np.array(y)))
    for k in range(5):
        buf.add_output(k, 10.0 + k, 1)   # the second output arrives first
        buf.add_input(k, [k, -k])
        assert buf.add_output(k, 20.0 + k, 0)
    buf.add_output(5, float("nan"), 1)  # rejected, counted
    stamps, u, y = buf.snapshot()
    assert y.shape == (5, 2) and u.shape == (5, 2)
    np.testing.assert_array_equal(y[:, 0], 20.0 + np.arange(5))
    np.testing.assert_array_equal(y[:, 1], 10.0 + np.arange(5))
    st = buf.stats_dict()
    assert st["received_outputs"] == 11 and st["rejected_nonfinite"] == 1
    assert len(pairs) == 5 and pairs[2][2].tolist() == [22.0, 12.0]
    # offline, the same rule
    events = [(("y", 1), k, 10.0 + k) for k in range(3)] + [("u", k, [k, k]) for k in range(3)] \
        + [("y", k, 20.0 + k) for k in range(3)]
    _, _, y2, stats = pair_streams(events, 0, input_widths=(2,), output_widths=(1, 1))
    assert y2.tolist() == [[20.0, 10.0], [21.0, 11.0], [22.0, 12.0]]


def test_csv_with_two_output_columns_is_one_record_and_a_missing_value_drops_the_row(tmp_path):
    u, Y = two_output_system(50, seed=0)
    rows = np.column_stack([np.arange(50) * 0.01, u, Y])
    rows[10, 4] = np.nan  # y2 missing at one row: the row goes for both outputs
    path = tmp_path / "joints.csv"
    np.savetxt(path, rows, delimiter=",", header="t,u1,u2,y1,y2", comments="")
    rec = load_record(DataSpec(data=(str(path),), inputs=("u1", "u2"), output="y1,y2"))
    assert rec.n_outputs == 2 and rec.output_names == ("y1", "y2")
    assert rec.y.shape == (49, 2) and rec.rejected == 1
    np.testing.assert_array_equal(rec.y[:10], Y[:10])
    assert rec.segment_info().gaps == 1
    with pytest.raises(DataError, match="takes one output"):
        rec.require_one_output("spm-sysid certify")
    with pytest.raises(DataError, match="distinct input and output columns"):
        load_record(DataSpec(data=(str(path),), inputs=("u1", "u2"), output="y1,y1"))


def test_bags_with_two_output_topics_or_one_joint_state_topic(tmp_path):
    u, Y = two_output_system(300, seed=1)
    two = write_io_bag(tmp_path / "two", u, Y, input_topic="/tau", output_topic="/q1,/q2")
    sig = read_bag_signals(two, input_topic="/tau", input_field="effort[0],effort[1]",
                           output_topic="/q1,/q2", output_names="q1,q2")
    np.testing.assert_array_equal(sig.y, Y)
    np.testing.assert_array_equal(sig.u, u)
    assert sig.output_names == ("q1", "q2") and sig.unpaired == 0
    # outputs given in the other order come back in that order
    sig = read_bag_signals(two, input_topic="/tau", input_field="effort[0],effort[1]",
                           output_topic="/q2,/q1")
    np.testing.assert_array_equal(sig.y, Y[:, ::-1])
    # one JointState topic carrying both: effort in, velocity out
    joints = write_joint_state_bag(tmp_path / "joints", u, Y)
    rec = load_record(DataSpec(bag=str(joints), bag_options={
        "input_topic": "/joint_states", "input_field": "effort[0],effort[1]",
        "input_names": "tau1,tau2", "output_topic": "/joint_states",
        "output_field": "velocity[0],velocity[1]", "output_names": "q1,q2"}))
    assert rec.output_names == ("q1", "q2") and rec.input_names == ("tau1", "tau2")
    np.testing.assert_array_equal(rec.y, Y)
    assert rec.unpaired == 0
    with pytest.raises(DataError, match="name columns of --data files"):
        load_record(DataSpec(bag=str(two), output="q1,q2"))  # not silently one output
    with pytest.raises(Exception, match="same field"):
        read_bag_signals(joints, input_topic="/joint_states", output_topic="/joint_states")
    with pytest.raises(Exception, match="output topics for 2 outputs"):
        write_io_bag(tmp_path / "bad", u, Y, output_topic="/a,/b,/c")


def test_joints_named_in_field_paths_whatever_their_order(tmp_path):
    """``effort[elbow]``: the joint by its name in each message; others' messages skipped."""
    u, Y = two_output_system(300, seed=1)
    bag = write_joint_state_bag(tmp_path / "arm", u, Y, shuffled=True, gripper_every=7)
    options = {"input_topic": "/joint_states", "input_field": "effort[j1],effort[j2]",
               "input_names": "tau1,tau2", "output_topic": "/joint_states",
               "output_field": "velocity[j1],velocity[j2]", "output_names": "q1,q2"}
    rec = load_record(DataSpec(bag=str(bag), bag_options=options))
    np.testing.assert_array_equal(rec.u, u)
    np.testing.assert_array_equal(rec.y, Y)
    skipped = [n for n in rec.notes if "skipped" in n]
    # 43 gripper messages, each skipped once per stream (inputs and outputs)
    assert len(skipped) == 1 and skipped[0].startswith("86 message(s) on /joint_states")
    assert "does not name 'j1'" in skipped[0] and "finger" in skipped[0]
    # by index the same bag mixes the joints up (and fails on the gripper's message)
    with pytest.raises(DataError, match="effort\\[1\\]"):
        load_record(DataSpec(bag=str(bag), bag_options={
            **options, "input_field": "effort[0],effort[1]"}))
    # a name no message has: every message skipped, and the reading says so
    with pytest.raises(DataError, match="no input and output messages .* 386 message"
                                        "\\(s\\) on /joint_states skipped: .*'wrist'"):
        load_record(DataSpec(bag=str(bag), bag_options={
            **options, "input_field": "effort[wrist]", "input_names": "tau"}))


def test_a_job_on_two_outputs_validates_each_with_the_coupled_free_run():
    u, Y = two_output_system(600, seed=2, noise=0.002)
    rec = Record.from_samples(u, Y, source="test", input_names=("u1", "u2"),
                              output_names=("y1", "y2"))
    result = run_job(rec, JobSettings.from_values({**SETTINGS, "horizon": 3}))
    assert isinstance(result, MimoJobResult)
    assert result.output_names == ("y1", "y2")
    for name, r in zip(("y1", "y2"), result.outputs):
        assert set(TRUE[name]) <= set(r.model.terms)
        assert r.model.metadata["validation"]["free_run_coupled"] is True
    # each report's free run is the coupled one: both outputs from their own predictions
    lag = result.model.max_lag
    coupled, _ = result.model.simulate(u, Y)
    kstep, _ = result.model.k_step(u, Y, 3)
    for i, r in enumerate(result.outputs):
        np.testing.assert_allclose(r.report.free_run, coupled[:, i], rtol=1e-12)
        np.testing.assert_allclose(r.report.k_step, kstep[:, i], rtol=1e-12)  # coupled too
    # the fitted model's coupled run against the plain-Python reference
    coefs = {n: dict(zip(r.model.terms, r.model.coefficients))
             for n, r in zip(("y1", "y2"), result.outputs)}
    np.testing.assert_allclose(coupled, reference_simulation(coefs, u, Y, lag), rtol=1e-9,
                               atol=1e-12)
    assert [t.name for t in result.cross_tests] == ["cross_y1_y2"]
    assert result.cross_tests[0].checked[len(result.cross_tests[0].lags) // 2] == False  # noqa: E712
    assert result.residuals.shape == (len(Y) - lag, 2)
    assert "joint BIC" in result.summary("lines") and "y2:" in result.summary("line")


@pytest.mark.slow
def test_identify_with_two_output_columns_writes_a_coupled_model_and_figures(tmp_path):
    u, Y = two_output_system(400, seed=5, noise=0.001)
    path = tmp_path / "joints.csv"
    np.savetxt(path, np.column_stack([u, Y]), delimiter=",", header="u1,u2,y1,y2",
               comments="")
    out = tmp_path / "model.json"
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "identify", "--data",
                        str(path), "--inputs", "u1,u2", "--output", "y1,y2", "--ny", "1",
                        "--nu", "1", "--criterion", "bic", "--seed", "0", "--quiet",
                        "--json", str(out), "--plots", str(tmp_path / "figs")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "== output y1 ==" in r.stdout and "== output y2 ==" in r.stdout
    assert "cross_y1_y2" in r.stdout
    model, doc = read_model_document(out)
    assert isinstance(model, MimoModel) and doc["outputs"] == ["y1", "y2"]
    assert len(doc["metadata"]["cross_correlation_tests"]) == 1
    names = {p.name for p in (tmp_path / "figs").iterdir()}
    assert {"model_free_run.png", "model_one_step.png", "model_y1_correlation.png",
            "model_y2_correlation.png", "model_cross_correlation.png"} <= names
    # validate the written model on a second record: each output, coupled, cross tests
    u2, Y2 = two_output_system(400, seed=6, noise=0.001)
    other = tmp_path / "other.csv"
    np.savetxt(other, np.column_stack([u2, Y2]), delimiter=",", header="u1,u2,y1,y2",
               comments="")
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "validate", str(out),
                        "--data", str(other), "--inputs", "u1,u2", "--output", "y1,y2"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("coupled free-run:") == 2 and "cross_y1_y2" in r.stdout
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "validate", str(out),
                        "--data", str(other), "--inputs", "u1,u2", "--output", "y2,y1"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "the model has outputs y1, y2" in r.stderr
    # a command that takes one output says so
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "certify", "--data",
                        str(path), "--inputs", "u1,u2", "--output", "y1,y2"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "takes one output" in r.stderr
    assert json.loads(out.read_text())["schema"] == "spm_sysid/narx-mimo-model"


def test_simulation_focus_refines_the_outputs_jointly_in_the_job():
    u, Y = two_output_system(500, seed=9)
    Y = Y + 0.02 * np.random.default_rng(9).standard_normal(Y.shape)
    rec = Record.from_samples(u, Y, source="test", input_names=("u1", "u2"),
                              output_names=("y1", "y2"))
    result = run_job(rec, JobSettings.from_values({**SETTINGS, "focus": "simulation"}))
    sel = result.model.metadata["coupled_selection"]  # the joint refinement competed
    assert any(f["fitted"] == "jointly refined" for f in sel["finalists"])
    if sel["fitted"] == "jointly refined":
        info = result.model.metadata["coupled_refinement"]
        assert info["taken"] and info["after"] <= info["before"]
    coupled, _ = result.model.simulate(u, Y)
    for i, r in enumerate(result.outputs):
        assert r.model is result.model.models[i]
        np.testing.assert_allclose(r.report.free_run, coupled[:, i], rtol=1e-12)
        # the one-step report is the refined coefficients' too
        np.testing.assert_allclose(r.report.one_step, result.model.predict(u, Y)[:, i],
                                   rtol=1e-12)
    assert f"coupled judgement on {sel['folds']} held-out blocks" in result.summary("lines")


def test_batch_of_two_output_records_writes_coupled_models(tmp_path):
    paths = []
    for seed in (10, 11):
        u, Y = two_output_system(300, seed=seed, noise=0.001)
        paths.append(tmp_path / f"rec{seed}.csv")
        np.savetxt(paths[-1], np.column_stack([u, Y]), delimiter=",", header="u1,u2,y1,y2",
                   comments="")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "batch", *map(str, paths),
                        "--inputs", "u1,u2", "--output", "y1,y2", "--ny", "1", "--nu", "1",
                        "--criterion", "bic", "--seed", "0", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    import csv

    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert len(rows) == 2 and all("2 outputs y1, y2" in row["status"] for row in rows)
    for row in rows:
        model, doc = read_model_document(row["model"])
        assert isinstance(model, MimoModel)
        assert int(row["terms"]) == sum(len(m.terms) for m in model.models)
        assert float(row["value"]) == pytest.approx(doc["metadata"]["joint_criterion"]["value"])


def test_errors_from_scores_the_coupled_free_run_from_that_sample():
    """A coupled model validated with ``errors_from``: each output's RMSE from sample 50 on."""
    from spm_sysid.core.jobs.several import couple_reports
    from spm_sysid.core.model.mimo import augmented_inputs
    from spm_sysid.core.validate.validation import validate_model

    u, Y = two_output_system(600, seed=2, noise=0.002)
    rec = Record.from_samples(u, Y, source="test", input_names=("u1", "u2"),
                              output_names=("y1", "y2"))
    model = run_job(rec, JobSettings.from_values(SETTINGS)).model
    u2, Y2 = two_output_system(400, seed=3, noise=0.002)
    segments = [(0, 400)]
    reports = [validate_model(m, augmented_inputs(u2, Y2, i), Y2[:, i], segments=segments,
                              errors_from=50, bands=False) for i, m in enumerate(model.models)]
    couple_reports(model, u2, Y2, segments, reports)
    coupled, _ = model.simulate(u2, Y2)  # rows max_lag.. of the record
    lag = model.max_lag
    for i, rep in enumerate(reports):
        e = Y2[50:, i] - coupled[50 - lag:, i]
        assert rep.free_run_metrics["rmse"] == pytest.approx(np.sqrt(np.mean(e * e)),
                                                             rel=1e-12)
        np.testing.assert_allclose(rep.free_run, coupled[:, i], rtol=1e-12)


def test_the_coupled_judgement_reports_how_far_it_is():
    """Its phase says finalist i of n (n: the finalists and the final fit), in order."""
    u, Y = two_output_system(600, seed=2, noise=0.002)
    rec = Record.from_samples(u, Y, source="test", input_names=("u1", "u2"),
                              output_names=("y1", "y2"))
    seen = []
    result = run_job(rec, JobSettings.from_values(SETTINGS), progress=seen.append)
    finalists = len(result.model.metadata["coupled_selection"]["finalists"])
    coupled = [(p.step, p.total) for p in seen
               if p.phase == "refinement" and p.total == finalists + 1]
    assert [s for s, _ in coupled] == list(range(finalists + 1))
    assert all(p.elapsed >= 0 for p in seen)


def test_outputs_of_different_orders_validate_on_a_record_with_gaps(tmp_path):
    """``--orders auto`` gives each output its own space: a second-order y1 beside a
    first-order y2. ``validate`` (as typed, columns by the model's names) scores each
    output from the coupled run's first row of every segment, so their residuals line up
    for the cross tests (it stopped on arrays of 3 different lengths: one per segment);
    each output's RMSE from sample 50 equals the coupled free run's, computed here."""
    def record(n, seed):
        rng = np.random.default_rng(seed)
        u = rng.uniform(-1, 1, (n, 2))
        return u, coupled_outputs(u, rng)

    keep = np.ones(3000, bool)
    keep[1000:1040] = keep[2000:2005] = False  # two gaps: three segments
    for name, seed in (("a", 1), ("b", 2)):
        u, y = record(3000, seed)
        np.savetxt(tmp_path / f"{name}.csv", np.column_stack([np.arange(3000) * 0.01, u, y])[keep],
                   delimiter=",", header="time,u1,u2,y1,y2", comments="", fmt="%.12g")
    run = [sys.executable, "-m", "spm_sysid.apps.main"]
    r = subprocess.run([*run, "identify", "--data", str(tmp_path / "a.csv"), "--output", "y1,y2",
                        "--focus", "simulation", "--orders", "auto", "--seed", "1", "--json",
                        str(tmp_path / "m.json")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    model = MimoModel.load(tmp_path / "m.json")
    lags = [m.term_space.max_lag for m in model.models]
    assert lags[0] > lags[1], lags  # the case: outputs of different orders
    r = subprocess.run([*run, "validate", str(tmp_path / "m.json"), "--data",
                        str(tmp_path / "b.csv"), "--errors-from", "50"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "cross-correlation of the outputs' residuals" in r.stdout
    rec = load_record(DataSpec(data=(str(tmp_path / "b.csv"),), output="y1,y2"))
    lag, got = model.max_lag, r.stdout.split("coupled free-run: MSE")[1:]
    errors, bounds = [], rec.segment_info().bounds
    assert len(bounds) == 3
    for a, b in bounds:
        sim, _ = model.simulate(rec.u[a:b], rec.y[a:b])
        errors.append(rec.y[a + 50:b] - sim[50 - lag:])
    e = np.concatenate(errors)
    for i in range(2):
        rmse = float(got[i].split("RMSE")[1].split(",")[0])
        assert rmse == pytest.approx(np.sqrt(np.mean(e[:, i] ** 2)), rel=1e-3)
        assert rmse < 3e-3  # the noise is 1e-3


def test_validate_reads_another_bag_on_the_topics_the_model_was_identified_from(tmp_path):
    """``identify --bag`` on one JointState topic's efforts and velocities writes them in
    ``metadata.topics``; ``validate MODEL --bag OTHER`` (no options: the command as typed)
    reads the other recording the same way and says so; given options win; a document
    whose topics are not text is refused naming the field."""
    run = [sys.executable, "-m", "spm_sysid.apps.main"]
    u, Y = two_output_system(600, seed=1, noise=0.001)
    u2, Y2 = two_output_system(600, seed=2, noise=0.001)
    first = write_joint_state_bag(tmp_path / "first", u, Y)
    second = write_joint_state_bag(tmp_path / "second", u2, Y2, shuffled=True)
    options = {"--input-topic": "/joint_states", "--input-field": "effort[j1],effort[j2]",
               "--input-names": "tau1,tau2", "--output-topic": "/joint_states",
               "--output-field": "velocity[j1],velocity[j2]", "--output-names": "q1,q2"}
    r = subprocess.run([*run, "identify", "--bag", str(first), *sum(options.items(), ()),
                        "--ny", "1", "--nu", "1", "--degree", "2", "--criterion", "bic",
                        "--seed", "0", "--quiet", "--json", str(tmp_path / "m.json")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "m.json").read_text())
    topics = doc["metadata"]["topics"]
    assert {f"--{k.replace('_', '-')}": v for k, v in topics.items()
            if k != "stamp_tolerance"} == options
    r = subprocess.run([*run, "validate", str(tmp_path / "m.json"), "--bag", str(second)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert ("note: the bag is read on the model's topics and fields: --input-topic "
            "/joint_states, --input-field effort[j1],effort[j2]") in r.stdout
    model = MimoModel.load(tmp_path / "m.json")
    sim, _ = model.simulate(u2, Y2)
    for i, text in enumerate(r.stdout.split("coupled free-run: MSE")[1:]):
        rmse = float(text.split("RMSE")[1].split(",")[0])
        e = Y2[model.max_lag:, i] - sim[:, i]
        assert rmse == pytest.approx(np.sqrt(np.mean(e * e)), rel=1e-3)
    r = subprocess.run([*run, "validate", str(tmp_path / "m.json"), "--bag", str(second),
                        "--output-topic", "/nowhere"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "note: the bag" not in r.stdout  # the options as given
    assert "has no topic /robot_arm/torque" in r.stderr
    doc["metadata"]["topics"]["input_topic"] = 7
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    r = subprocess.run([*run, "validate", str(tmp_path / "bad.json"), "--bag", str(second)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "metadata.topics.input_topic must be text" in r.stderr
