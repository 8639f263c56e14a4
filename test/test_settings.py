"""One settings schema: the YAML file, --help, the node's parameters and every entry point."""

import subprocess
import sys

import pytest
import yaml

from spm_sysid.core.errors import SettingsError
from spm_sysid.core.jobs import JobSettings
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.search.ga import GAConfig
from spm_sysid.core.settings import SETTINGS, check, node_settings
from spm_sysid.core.stream.diagnostics import ERROR, OK, WARN, diagnostic_statuses
from spm_sysid.tools.experiment import ExperimentConfig

from .conftest import ROOT


def cli(*args):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_yaml_file_lists_every_node_parameter_with_its_default():
    text = (ROOT / "config" / "sysid_node.yaml").read_text()
    assert text == cli("settings", "--yaml").stdout  # generated from the schema
    params = yaml.safe_load(text)["spm_sysid"]["ros__parameters"]
    assert list(params) == [s.name for s in node_settings()]
    for s in node_settings():
        assert params[s.name] == s.default and type(params[s.name]) is s.kind, s.name


def test_help_offers_every_command_line_setting_with_its_aliases():
    text = cli("identify", "--help").stdout
    for s in SETTINGS.values():
        if s.cli:
            assert s.option in text, s.name
            for alias in s.aliases:
                assert alias in text, alias
        else:
            assert s.option not in text, s.name


@pytest.mark.ros
def test_node_declares_the_schema_parameters(ros_env):
    pytest.importorskip("rclpy", reason="ROS 2 is not installed here")
    from rcl_interfaces.srv import DescribeParameters, GetParameters

    from .ros_harness import Harness, start_node, stop

    node = start_node(ros_env, schema_defaults=True)
    h = Harness(ros_env)
    try:
        h.wait_ready()
        names = [s.name for s in node_settings()]
        got = _call(h, GetParameters, "/spm_sysid/get_parameters", names=names)
        desc = _call(h, DescribeParameters, "/spm_sysid/describe_parameters", names=names)
    finally:
        stop(node)
        h.close()
    for s, value, d in zip(node_settings(), got.values, desc.descriptors):
        actual = {1: value.bool_value, 2: value.integer_value, 3: value.double_value,
                  4: value.string_value}[value.type]
        assert actual == s.default, s.name
        assert d.read_only == s.read_only and d.description == s.help, s.name
        if s.kind is int and s.low is not None:
            r = d.integer_range[0]
            assert (r.from_value, r.to_value) == (s.low, s.high), s.name
        if s.kind is float and s.low is not None:
            r = d.floating_point_range[0]
            assert (r.from_value, r.to_value) == (s.low, s.high), s.name


def _call(h, srv, name, **fields):
    client = h.node.create_client(srv, name)
    try:
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(srv.Request(**fields))
        h.spin_until(future.done, 30)
        return future.result()
    finally:
        h.node.destroy_client(client)


@pytest.mark.parametrize("name, value, message", [
    ("population_size", 1, "population_size must be between 2 and 100000, got 1"),
    ("spm_fraction", 0.9, "spm_fraction must be between 0 and 0.5, got 0.9"),
    ("fitness", "nosuch", "fitness must be one of akaike, rank, window, got 'nosuch'"),
    ("ny", 2.5, "ny must be an integer, got 2.5"),
    ("constant", 1, "constant must be true or false, got 1"),
    ("mutation_prob", float("nan"), "mutation_prob must be a finite number"),
])
def test_python_api_rejects_with_the_schemas_reason(name, value, message):
    with pytest.raises(SettingsError, match=message.replace("(", r"\(").replace(")", r"\)")):
        check(name, value)
    cls = TermSpace if SETTINGS[name].group == "term_space" else GAConfig
    with pytest.raises(SettingsError, match=message.split(",")[0]):
        cls(**{name: value})
    with pytest.raises(SettingsError, match=message.split(",")[0]):
        JobSettings.from_values({name: value})


@pytest.mark.parametrize("args, message", [
    (["--population-size", "1"], "population_size must be between 2 and 100000, got 1"),
    (["--population", "1"], "population_size must be between 2 and 100000, got 1"),
    (["--spm", "0.9"], "spm_fraction must be between 0 and 0.5, got 0.9"),
    (["--fitness", "nosuch"], "invalid choice: 'nosuch'"),
    (["--ny", "2.5"], "must be an integer, got '2.5'"),
    (["--criterion", "nope"], "unknown criterion"),
])
def test_command_line_rejects_once_with_a_reason(args, message):
    r = cli("identify", "--generations", "100000", *args)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "criterion" not in r.stdout


@pytest.mark.parametrize("text, message", [
    ("populations: [1]", "population_size must be between 2 and 100000"),
    ("fitness: nosuch", "fitness must be one of akaike, rank, window"),
    ("spm_fractions: [0.9]", "spm_fraction must be between 0 and 0.5"),
    ("term_space: {ny: -1}", "ny must be between 0 and 100"),
    ("term_space: {lags: 3}", "term_space: unknown setting(s) ['lags']"),
    ("criteria: [nope]", "unknown criterion"),
    ("seed: -3", "seed must be between -1 and"),
])
def test_experiment_yaml_rejects_with_a_reason(tmp_path, text, message):
    p = tmp_path / "study.yaml"
    p.write_text(text + "\nruns: 1\n")
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")
                       .replace("(", r"\(").replace(")", r"\)")):
        ExperimentConfig.from_yaml(p)
    r = cli("experiment", "--config", str(p), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and message in r.stderr, r.stderr


@pytest.mark.ros
def test_node_parameter_rejected_with_the_schemas_reason(ros_env):
    pytest.importorskip("rclpy", reason="ROS 2 is not installed here")
    from .ros_harness import Harness, start_node, stop

    node = start_node(ros_env)
    h = Harness(ros_env)
    try:
        h.wait_ready()
        res = h.set_parameters("/spm_sysid", fitness="nosuch", validation="sideways",
                               criterion="nope", model_path="/proc/version/x.json")
        reasons = [r.reason for r in res]
        assert not any(r.successful for r in res)
        assert "fitness must be one of akaike, rank, window" in reasons[0]
        assert "validation must be one of estimation, holdout, none" in reasons[1]
        assert "unknown criterion" in reasons[2]
        assert "model_path" in reasons[3]
        res = h.set_parameters("/spm_sysid", population_size=1, spm_fraction=0.9)
        assert not res[0].successful and not res[1].successful  # the descriptors' ranges
        assert h.set_parameters("/spm_sysid", fitness="rank")[0].successful
    finally:
        stop(node)
        h.close()


# -- diagnostics, as plain data -------------------------------------------------------------

STATS = {"samples": 1024, "capacity": 100000, "received_inputs": 1024,
         "received_outputs": 1024, "paired": 1024, "dropped_oldest": 0,
         "rejected_nonfinite": 0, "rejected_out_of_order": 0, "time_jumps": 0,
         "discarded_on_jump": 0, "held_out_of_order": 0, "unpaired_inputs": 0,
         "unpaired_outputs": 0, "pending_inputs": 0, "pending_outputs": 0, "cleared": 0}

DOC = {"terms": ["y(t-1)", "u(t-1)"], "criterion": {"name": "aic", "value": -10.0},
       "mse": 0.1,
       "metadata": {"data": {"gaps": 2, "skipped_segments": 0, "samples": 100},
                    "validation": {"correlation_tests": [
                        {"name": "ee", "passed": False, "fraction_inside": 0.5},
                        {"name": "ue", "passed": True, "fraction_inside": 1.0}]}}}


def test_diagnostics_healthy_buffer_and_a_model_fitted_around_gaps():
    st = {s.name: s for s in diagnostic_statuses("/n", STATS, model=DOC)}
    assert st["/n: buffer"].level == OK and st["/n: buffer"].message == "1024 paired samples"
    assert st["/n: buffer"].values["worker_ready"] == "True"
    ident = st["/n: identification"]
    assert ident.level == WARN and ident.message == "model with 2 terms, fitted around 2 " \
        "gap(s) in the data"
    assert ident.values["data_gaps"] == "2" and ident.values["criterion"] == "aic"
    assert st["/n: correlation ee"].level == WARN and "50% of lags" in \
        st["/n: correlation ee"].message
    assert st["/n: correlation ue"].level == OK


def test_diagnostics_problems_and_their_levels():
    bad = dict(STATS, rejected_nonfinite=3, rejected_out_of_order=2, time_jumps=1)
    st = diagnostic_statuses("/n", bad, worker_ready=False)
    assert st[0].level == WARN
    assert st[0].message == ("1024 paired samples, 5 rejected, 1 jump(s) back in time, "
                             "worker not ready")
    st = diagnostic_statuses("/n", STATS, type_mismatches=["/x publishes /t as String"])
    assert st[0].level == ERROR and st[0].values["type_mismatch"] == "/x publishes /t as String"
    from spm_sysid.core.progress import Progress

    st = diagnostic_statuses("/n", STATS, running=(Progress("search", 25, 300, -1.5, 300), 2.0))
    assert st[1].message == "running: generation 25" and st[1].values["seconds"] == "2.00"
    st = diagnostic_statuses("/n", STATS, last_error="boom", model=DOC)
    assert st[1].level == ERROR and st[1].message == "boom" and len(st) == 2
    st = diagnostic_statuses("/n", STATS, model=dict(DOC, metadata={}), restored_from="/m")
    assert st[1].level == OK and st[1].message == "model with 2 terms, restored from /m"
    st = diagnostic_statuses("/n", STATS, callback_errors=3)
    assert st[0].level == WARN and st[0].message == ("1024 paired samples, 3 callback error(s) "
                                                     "(see the log)")
    assert st[0].values["callback_errors"] == "3"
    st = diagnostic_statuses("/n", STATS, ignored_parameters=["genrations"])
    assert st[0].level == WARN and st[0].message == ("1024 paired samples, parameter(s) not of "
                                                     "this node, ignored: genrations")
    st = diagnostic_statuses("/n", STATS, unnamed=7)  # another publisher's: counted, no fault
    assert st[0].level == OK and st[0].message == ("1024 paired samples, 7 message(s) skipped "
                                                   "that do not name the joint(s) asked for")


def test_diagnostics_of_a_coupled_model_of_two_outputs():
    mimo = {"schema": "spm_sysid/narx-mimo-model", "outputs": ["q1", "q2"],
            "models": [DOC, dict(DOC, metadata={})],
            "metadata": {"cross_correlation_tests": [{"name": "cross_q1_q2", "passed": False,
                                                       "fraction_inside": 0.7, "band": 0.04,
                                                       "max_abs": 0.2, "worst_lag": -1}]}}
    st = {s.name: s for s in diagnostic_statuses("/n", STATS, model=mimo)}
    assert st["/n: identification (q1)"].message == ("model with 2 terms, fitted around 2 "
                                                     "gap(s) in the data")
    assert st["/n: identification (q2)"].message == "model with 2 terms"
    assert st["/n: residual cross_q1_q2"].level == WARN
    assert "/n (q1): correlation ee" in st


def test_a_setting_added_to_the_schema_reaches_the_command_line_the_node_and_its_yaml(
        monkeypatch, capsys):
    """One schema entry: the command line offers it, the node declares it, the YAML has it."""
    from spm_sysid.core import settings as schema
    from spm_sysid.tools.cli import build_parser

    knob = schema.Setting("test_knob", int, 3, "a knob this test adds", "criterion",
                          low=0, high=9)
    monkeypatch.setattr(schema, "_LIST", [*schema._LIST, knob])
    monkeypatch.setitem(schema.SETTINGS, "test_knob", knob)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["identify", "--help"])
    assert "--test-knob" in capsys.readouterr().out  # the command line offers it
    assert knob in schema.node_settings()  # the node declares it as a parameter
    assert "    test_knob: 3  # a knob this test adds" in schema.node_yaml()


def test_the_typed_settings_hold_every_job_setting_of_the_schema_and_no_other():
    """A setting added to the schema must be a typed field (else this fails): none is
    passed on by a keyword that happens to have its name."""
    from dataclasses import fields

    from spm_sysid.core.jobs.settings import JOB_FIELDS
    from spm_sysid.core.options import SearchOptions
    from spm_sysid.core.settings import JOB_GROUPS, SETTINGS

    held = [n for names in JOB_FIELDS.values() for n in names]
    assert len(held) == len(set(held))
    assert set(held) == {n for n, st in SETTINGS.items() if st.group in JOB_GROUPS}
    for f in fields(SearchOptions):
        if f.name in SETTINGS and f.name != "seed":
            assert f.default == SETTINGS[f.name].default, f.name
    with pytest.raises(AttributeError):
        JobSettings().no_such_setting  # noqa: B018 - no name matching any more


def _non_default(name: str):
    from spm_sysid.core.settings import SETTINGS

    st = SETTINGS[name]
    if st.choices:
        return next(c for c in st.choices if c != st.default)
    if st.kind is bool:
        return not st.default
    if name == "seed":
        return 7
    return st.kind(st.low if st.low is not None and st.low != st.default else st.default + 1)


def test_every_search_setting_reaches_a_studys_runs(robot_arm):
    """Each search setting of the schema (a new one included) set in a study reaches the
    options its runs search with; and one run shows it end to end."""
    from spm_sysid.core.options import SEARCH_SETTINGS
    from spm_sysid.tools.experiment import ExperimentConfig, run_experiment

    # a study refuses certify; grids the criterion; seeds each run from its own first seed
    skip = {"certify", "auto_certify_time_limit", "criterion", "seed"}
    for name in SEARCH_SETTINGS:
        if name in skip:
            continue
        value = _non_default(name)
        config = ExperimentConfig(criteria=["bic"], populations=[20], spm_fractions=[0.0],
                                  runs=1, **{name: value})
        search = config.job("bic", 20, 0.0).search
        assert getattr(search, name) == value, name
    u, y = robot_arm
    config = ExperimentConfig(criteria=["bic"], populations=[20], spm_fractions=[0.0],
                              runs=2, generations=5, init_terms=4.0, max_terms=5,
                              certify_reference=False, workers=1)
    records = run_experiment(u, y, config)
    assert len(records) == 2 and all(r.n_terms <= 5 for r in records), records.failures
