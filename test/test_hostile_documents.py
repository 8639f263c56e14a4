"""Model documents a job did not write: checked once at load, never a traceback nor a script.

And documents a job did write: always saved, whatever numbers it holds (no inf in JSON).
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.errors import ModelFormatError
from spm_sysid.core.model.narx import NarxModel

from .conftest import ROOT, eq1_model

XSS = "<img src=x onerror=\"document.title='PWNED'\">"


def cli(*args, cwd=ROOT, timeout=300):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=timeout)


def _document(robot_arm) -> dict:
    """Eq. (1) with the validation and monitor reference a job stores."""
    from spm_sysid.core.online.monitor import store_monitor_reference
    from spm_sysid.core.validate.validation import validate_model

    model = eq1_model(robot_arm)
    u, y = robot_arm
    report = validate_model(model, u, y)
    model.metadata["validation"] = report.to_dict()
    store_monitor_reference(model.metadata, report.residuals, u)
    return model.to_dict()


def _inflated_monitor(doc: dict) -> dict:
    monitor = json.loads(json.dumps(doc["metadata"]["monitor"]))
    for w in monitor["windows"]:
        w["rms_ratio_max"] = w["ljung_box_max"] = 1e300
    return monitor


HOSTILE = {
    "script in the orders": ({"orders": {"ny": XSS, "degree": 2}}, "metadata.orders.ny"),
    "warnings a number": ({"warnings": 5}, "metadata.warnings must be a list"),
    "orders text": ({"orders": "abc"}, "metadata.orders must be an object"),
    "orders without degree": ({"orders": {"ny": 2}}, "metadata.orders has no 'degree'"),
    "an operating point as text": ({"operating_point": {"reason": "r", "output": {"y": "1"}}},
                                   "metadata.operating_point.output.y must be a finite number"),
    "an operating point without its reason": ({"operating_point": {"output": {"y": 1.0}}},
                                              "metadata.operating_point has no 'reason'"),
    "certificate without its numbers": ({"certificate": {"status": "optimal"}},
                                        "metadata.certificate of status 'optimal' has no"),
    "selection text": ({"selection": "validated"}, "metadata.selection must be an object"),
    "data check of one field": ({"data_check": {"rows": 1}}, "metadata.data_check has no"),
    "skipped tests a number": ({"validation": {"correlation_tests_skipped": 5}},
                               "metadata.validation.correlation_tests_skipped must be text"),
    "a fraction as text": ({"validation": {"correlation_tests": [
        {"name": "ee", "passed": True, "fraction_inside": "0.5", "band": 0.06}]}},
        "correlation_tests[0].fraction_inside must be a number from 0 to 1"),
    "decimation of zero": ({"decimation": {"factor": 0}},
                           "metadata.decimation.factor must be an integer >= 1"),
    "decimation text": ({"decimation": "5"}, "metadata.decimation must be an object"),
    "a range upside down": ({"ranges": {"inputs": {"u": [2.0, -1.0]}}},
                            "metadata.ranges.inputs.u must be [low, high] with low <= high"),
    "a range as text": ({"ranges": {"outputs": {"y": ["a", 1.0]}}},
                        "metadata.ranges.outputs.y[0] must be a finite number"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_validate_refuses_a_crafted_document_with_one_line(robot_arm, robot_arm_path, tmp_path,
                                                           case):
    extra, message = HOSTILE[case]
    doc = _document(robot_arm)
    doc["metadata"].update(extra)
    (tmp_path / "x.json").write_text(json.dumps(doc))
    r = cli("validate", str(tmp_path / "x.json"), "--data", str(robot_arm_path),
            "--report", str(tmp_path / "r.html"))
    assert r.returncode == 2, r.stderr  # was 1 with a traceback, or a page that ran a script
    assert r.stderr.startswith("error: ") and len(r.stderr.strip().splitlines()) == 1
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "r.html").exists()


def test_a_monitor_reference_no_residuals_can_give_is_refused_at_load(robot_arm):
    doc = _document(robot_arm)
    NarxModel.from_dict(doc)  # the job's own reference loads
    doc["metadata"]["monitor"] = _inflated_monitor(doc)
    with pytest.raises(ModelFormatError, match=r"rms_ratio_max must be at most [0-9.]+ \(the "
                                               "largest RMS ratio 1020 residuals"):
        NarxModel.from_dict(doc)


def test_a_report_escapes_every_value_of_its_document(robot_arm, tmp_path, browser):
    """Even a model whose metadata was never checked (built in Python) cannot script the page."""
    from spm_sysid.core.validate.validation import validate_model
    from spm_sysid.tools.html_report import OutputSection, ReportContent, write_model_report

    u, y = robot_arm
    model = eq1_model(robot_arm)
    model.metadata.update(orders={"ny": XSS, "degree": XSS, "reason": XSS},
                          warnings=[XSS], focus="prediction",
                          operating_point={"reason": XSS, "output": {XSS: 1.0}, "inputs": {},
                                           "selected_terms": [XSS]})
    path = write_model_report(tmp_path / "r.html", ReportContent(title="t", command=XSS),
                              [OutputSection("y", model, validate_model(model, u, y))])
    html = path.read_text()
    assert XSS not in html and "&lt;img src=x onerror=" in html
    page = browser.new_page()
    page.goto(path.resolve().as_uri())
    page.wait_for_function("window.spmReport && spmReport.ready", timeout=20000)
    assert page.title() == "t" and page.evaluate("document.querySelectorAll('img').length") == 0


def _float_paths(node, path=()):
    """Every float leaf of a document (paths as tuples of keys and indices)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _float_paths(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _float_paths(v, path + (i,))
    elif isinstance(node, float):
        yield path


def _set(doc, path, value):
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


def test_every_number_a_job_writes_may_be_infinite_and_the_document_is_still_saved(
        robot_arm, tmp_path):
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.record import Record

    u, y = robot_arm
    result = run_job(Record.from_samples(u, y, source="robot arm"), JobSettings.from_values(
        {"focus": "simulation", "generations": 20, "population_size": 40, "seed": 1}))
    model = result.model
    paths = list(_float_paths(model.metadata))
    assert len(paths) > 50  # the search, the selection, the validation, the monitor ...
    for value in (math.inf, -math.inf, math.nan):
        for p in paths:
            _set(model.metadata, p, value)
        model.criterion_value = value
        model.mse = value
        saved = model.save(tmp_path / "m.json")  # was: "Out of range float values ..."
        doc = json.loads(saved.read_text())
        assert doc["criterion"]["value"] is None and doc["mse"] is None
        for p in paths:
            node = doc["metadata"]
            for key in p:
                node = node[key]
            assert node is None, p


def test_orders_auto_on_noise_free_data_writes_its_document(tmp_path):
    """The order scan of an exact record holds orders that cannot be fitted (was inf)."""
    n = 600
    u = np.sin(0.07 * np.arange(n)) + np.sin(0.31 * np.arange(n))
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = 0.9 * y[t - 1] + 0.1 * u[t - 1]
    np.savetxt(tmp_path / "exact.dat", np.column_stack([u, y]))
    r = cli("identify", "--data", "exact.dat", "--orders", "auto", "--json", "m.json",
            "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "m.json").read_text())
    scan = doc["metadata"]["orders"]["order_scan"]
    assert scan and all(v is None or math.isfinite(v) for _, v in scan)
    assert NarxModel.load(tmp_path / "m.json").terms == ["y(t-1)", "u(t-1)"]
