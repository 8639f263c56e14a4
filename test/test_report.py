"""The HTML report, opened in a real headless Chromium with no network."""

import json
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace

from .conftest import ROOT, two_output_system


def _cli(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def _open_offline(browser, path):
    """The page in a context with no network; every request it made."""
    context = browser.new_context(offline=True, viewport={"width": 1200, "height": 900})
    page = context.new_page()
    requests = []
    page.on("request", lambda r: requests.append(r.url))
    page.goto(path.resolve().as_uri())
    page.wait_for_function("window.spmReport && spmReport.ready", timeout=20000)
    assert page.evaluate("spmReport.errors") == []
    return context, page, requests


def _source(page, name):
    """A plot's data (columns as lists), read from the page's BokehJS data sources."""
    return page.evaluate("""(name) => {
        const m = spmReport.sources[name];
        if (!m) { return null; }
        const out = {};
        const d = m.data;
        const entries = (d instanceof Map) ? Array.from(d.entries()) : Object.entries(d);
        for (const [k, v] of entries) {
            out[k] = Array.from(v, x => Number.isNaN(x) ? null : x);
        }
        return out;
    }""", name)


@pytest.mark.slow
def test_identify_report_shows_the_model_and_its_data_offline(browser, tmp_path, robot_arm):
    report, doc_path = tmp_path / "report.html", tmp_path / "m.json"
    r = _cli("identify", "--report", "report.html", cwd=tmp_path)  # as the README writes it
    assert r.returncode == 0, r.stderr
    assert "report written to report.html" in r.stdout
    r = _cli("identify", "--quiet", "--json", str(doc_path))  # the model document
    assert r.returncode == 0, r.stderr
    assert report.stat().st_size < 5_000_000
    doc = json.loads(doc_path.read_text())
    model = NarxModel.from_dict(doc)
    context, page, requests = _open_offline(browser, report)
    try:
        assert all(u.startswith(("file:", "data:", "blob:")) for u in requests), requests
        assert page.inner_text("#equation-y") == model.equation()
        values = page.eval_on_selector_all("#coefficients-y td[data-value]",
                                           "cells => cells.map(c => c.dataset.value)")
        # coefficient, standard error per row: every coefficient equals the document's
        coefs = [float(v) for v in values[0::2]]
        assert coefs == [float(c) for c in doc["coefficients"]]
        se = np.array([float(v) for v in values[1::2]])
        assert np.allclose(se, model.uncertainty.standard_errors, rtol=1e-12)
        assert "certified optimal" in page.inner_text("body")
        u, y = robot_arm
        one = _source(page, "y/one_step")
        lag = model.term_space.max_lag
        assert len(one["measured"]) == len(y) - lag
        expected = model.predict(u, y)  # independent of the page: the model's own prediction
        for i in (0, 500, len(y) - lag - 1):
            assert one["measured"][i] == y[lag + i]
            assert one["predicted"][i] == pytest.approx(expected[i], rel=1e-12)
            assert one["lower"][i] <= one["predicted"][i] <= one["upper"][i]
        free = _source(page, "y/free_run")
        sim, _ = model.run(u, y)
        assert free["predicted"][700] == pytest.approx(sim[700], rel=1e-9)
        resid = _source(page, "y/residuals")
        assert resid["residual"][10] == pytest.approx(y[lag + 10] - expected[10], abs=1e-12)
        ee = _source(page, "y/correlation/ee")
        assert len(ee["lag"]) == 41 and ee["lag"][0] == -20  # lags -20..20
        conv = _source(page, "y/convergence")
        assert len(conv["generation"]) == doc["metadata"]["generations_run"] + 1
        assert min(conv["best"]) == pytest.approx(doc["criterion"]["value"], abs=1e-6)
        png = page.screenshot(full_page=True)
    finally:
        context.close()
    from io import BytesIO

    import matplotlib.image as mpimg

    pixels = mpimg.imread(BytesIO(png), format="png")[..., :3]
    assert pixels.std() > 0.05  # not blank
    assert (pixels.mean(axis=2) < 0.5).mean() > 0.005  # lines and text drawn


def test_a_report_of_a_diverged_model_opens_and_says_so(browser, tmp_path, robot_arm,
                                                        robot_arm_path):
    u, y = robot_arm
    from .conftest import eq1_model

    model = eq1_model(robot_arm)
    model.coefficients = model.coefficients * 1.05  # unstable: its free run diverges
    model.save(tmp_path / "wild.json")
    report = tmp_path / "wild.html"
    r = _cli("validate", str(tmp_path / "wild.json"), "--data", str(robot_arm_path),
             "--report", str(report))
    assert r.returncode == 0, r.stderr
    context, page, _ = _open_offline(browser, report)
    try:
        text = page.inner_text("#diverged-y")
        assert "DIVERGED at sample" in text
        assert "try --focus simulation" in page.inner_text("#verdict-y").replace(
            "Next: --focus", "try --focus")
        free = _source(page, "y/free_run")
        assert free["predicted"][-1] is None  # NaN after the divergence: a gap, not a crash
    finally:
        context.close()


def test_the_page_says_what_the_fits_mean_and_shows_the_signals_not_the_band(
        browser, tmp_path, robot_arm):
    """Eq. (1): 98 % one step, 11 % free run, a free-run band ten times the signal."""
    from spm_sysid.core.validate.validation import validate_model
    from spm_sysid.tools.html_report import OutputSection, ReportContent, write_model_report

    from .conftest import eq1_model

    u, y = robot_arm
    model = eq1_model(robot_arm)
    report = validate_model(model, u, y)
    band = report.free_run_band
    assert band.upper.max() - band.lower.min() > 5 * np.ptp(y)  # the case of the review
    path = write_model_report(tmp_path / "r.html", ReportContent(title="eq. 1"),
                              [OutputSection("y", model, report)])
    context, page, _ = _open_offline(browser, path)
    try:
        verdict = page.inner_text("#verdict-y")
        assert verdict.startswith("One-step fit 98.1 %, free-run fit 11.1 %")
        assert "--focus simulation" in verdict
        ranges = page.evaluate("""Object.values(spmReport.figures).filter(
            f => f.title.text.indexOf("free-run simulation") >= 0).map(
            f => [f.y_range.start, f.y_range.end])""")
        assert len(ranges) == 1
        low, high = ranges[0]
        assert low <= y.min() and high >= y.max() and high - low < 1.2 * np.ptp(y)
        titles = page.evaluate("Object.values(spmReport.figures).map(f => f.title.text)")
        tests = [t for t in titles if "of lags in the band" in t]
        assert len(tests) == 5 and max(len(t) for t in tests) <= 50, tests
    finally:
        context.close()


def test_a_model_of_300_terms_renders_every_row(browser, tmp_path, robot_arm):
    """A large model's page is drawn whole and without errors (how fast is a figure for
    a benchmark, not an assertion: a busy machine must not fail this test)."""
    from spm_sysid.core.validate.validation import validate_model
    from spm_sysid.tools.html_report import OutputSection, ReportContent, write_model_report

    u, y = robot_arm
    space = TermSpace(ny=12, nu=12, degree=2)  # 24 linear + 300 quadratic terms
    idx = list(range(24, 324))
    model = NarxModel(space, idx, np.full(300, 1e-6), criterion="bic", criterion_value=0.0)
    report = validate_model(model, u, y)
    path = write_model_report(tmp_path / "big.html", ReportContent(title="300 terms"),
                        [OutputSection("y", model, report)])
    context = browser.new_context(offline=True)
    page = context.new_page()
    try:
        page.goto(path.as_uri())
        page.wait_for_function("window.spmReport && spmReport.ready", timeout=60000)
        rows = page.eval_on_selector_all("#coefficients-y tr", "r => r.length")
        errors = page.evaluate("spmReport.errors")
    finally:
        context.close()
    assert rows == 301
    assert errors == []


def test_a_report_of_two_outputs_has_a_section_each_and_the_cross_correlation(
        browser, tmp_path):
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.record import Record
    from spm_sysid.tools.html_report import OutputSection, ReportContent, write_model_report

    u, Y = two_output_system(600, seed=4, noise=0.01)
    rec = Record.from_samples(u, Y, source="test", input_names=("u1", "u2"),
                              output_names=("y1", "y2"))
    result = run_job(rec, JobSettings.from_values({"ny": 1, "nu": 1, "seed": 0}))
    path = write_model_report(tmp_path / "two.html", ReportContent(
        title="two", cross_tests=result.cross_tests),
        [OutputSection(n, r.model, r.report) for n, r in zip(("y1", "y2"), result.outputs)])
    context, page, _ = _open_offline(browser, path)
    try:
        for i, name in enumerate(("y1", "y2")):
            assert page.inner_text(f"#equation-{name}") == result.outputs[i].model.equation()
            free = _source(page, f"{name}/free_run")
            assert free["predicted"][5] == pytest.approx(
                result.outputs[i].report.free_run[5], rel=1e-12)  # the coupled run
        cross = _source(page, "outputs/cross/cross_y1_y2")
        assert cross is not None and len(cross["lag"]) == 41
    finally:
        context.close()


def test_report_refuses_a_path_that_is_not_html(tmp_path):
    r = _cli("identify", "--quiet", "--report", str(tmp_path / "r.txt"))
    assert r.returncode == 2 and "give a file name ending in .html" in r.stderr


def test_thinned_rows_keep_every_columns_envelope_and_every_gap():
    from spm_sysid.tools.html_report import thinned_rows

    rng = np.random.default_rng(0)
    n = 100_003
    a, b = rng.standard_normal(n), np.cumsum(rng.standard_normal(n))
    a[77_777] = 50.0  # a spike
    b[90_000:] = np.nan  # a divergence: a gap from there on
    rows = thinned_rows({"a": a, "b": b}, stretches=1000)
    assert rows[0] == 0 and np.all(np.diff(rows) > 0) and rows[-1] < n
    assert len(rows) <= 1000 * 5
    size = -(-n // 1000)
    for start in range(0, n, size):  # each stretch: the same extremes as the whole
        inside = rows[(rows >= start) & (rows < start + size)]
        for col in (a, b):
            stretch = col[start:start + size]
            if np.isfinite(stretch).any():
                assert np.nanmax(col[inside]) == np.nanmax(stretch)
                assert np.nanmin(col[inside]) == np.nanmin(stretch)
    assert 77_777 in rows and 90_000 in rows


@pytest.mark.slow
def test_a_report_of_a_long_record_stays_small_and_draws_its_extremes(browser, tmp_path,
                                                                      robot_arm):
    from .conftest import eq1_model

    model = eq1_model(robot_arm)
    model.save(tmp_path / "m.json")
    rng = np.random.default_rng(1)
    u = np.tile(robot_arm[0], 98)  # 100 352 samples of the arm's own excitation
    y = np.zeros_like(u)
    y[:10] = robot_arm[1][:10]
    sim, _ = model.run(u, y)
    y[model.term_space.max_lag:] = sim + 1e-3 * rng.standard_normal(len(sim))
    y[61_234] += 5.0  # one spike in the measured output
    np.savetxt(tmp_path / "long.csv", np.column_stack([u, y]), delimiter=",",
               header="u,y", comments="")
    report = tmp_path / "long.html"
    r = _cli("validate", "m.json", "--data", "long.csv", "--inputs", "u", "--output", "y",
             "--report", "long.html", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert report.stat().st_size < 5_000_000  # 26 MB when every sample was drawn
    context, page, _ = _open_offline(browser, report)
    try:
        free = _source(page, "y/free_run")
        assert len(free["x"]) < 20_000
        assert max(v for v in free["measured"] if v is not None) == pytest.approx(y.max())
        peak = int(np.nanargmax(np.array(free["measured"], dtype=float)))
        # the spike is drawn where it is (the report's rows start after the largest lag)
        assert free["x"][peak] == 61_234 - model.term_space.max_lag
        assert "samples drawn: every stretch's extremes" in page.content()
    finally:
        context.close()
