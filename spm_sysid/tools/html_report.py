"""One self-contained HTML page per identification or validation (``--report FILE.html``).

The page shows what the terminal prints and the figures, in one place a user can
open, keep and send: the equation; the coefficients with standard errors and
intervals; criterion, certification, selection and orders; the data check and
the warnings; and interactive plots (pan, box zoom, wheel zoom, reset) of the
measured output against the one-step, k-step and free-run predictions with
their bands, the residuals, the correlation tests with their confidence bands,
and the GA's convergence. A model with several outputs gets a section per
output and the residuals' cross-correlation.

The plots are Bokeh's (a NumFOCUS project): its core JavaScript is inlined
(about 1.3 MB; no widgets, tables or MathJax bundles), so the page makes no network
request and works offline; Plotly's bundle is 4.8 MB alone, too much for a
page that should stay under 5 MB with its data. Every plot's data source has a
name (``<output>/<plot>``) so that a reader -- or a test in a browser -- can
find the numbers behind it (``Bokeh.documents[0].get_model_by_name``); every
coefficient cell carries the full-precision value (``data-value``).
"""

from __future__ import annotations

import html
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["OutputSection", "build_report", "write_report"]

#: Plot width and heights (CSS pixels); the page is responsive in width.
HEIGHT, SMALL = 300, 180


@dataclass
class OutputSection:
    """One output's part of the page.

    Attributes
    ----------
    name : str
        The output's name (the section's title and the plots' name prefix).
    model : NarxModel
    report : ValidationReport or None
        None: no validation (the page says so).
    times : ndarray or None
        Seconds of the report's rows (a time axis), else the sample index.
    history : list of GenerationStats
        The GA's generations (identify), for the convergence plot; empty: none.
    """

    name: str
    model: object
    report: object | None
    times: np.ndarray | None = None
    history: list = field(default_factory=list)


@dataclass
class ReportContent:
    """Everything :func:`build_report` lays out (besides the sections)."""

    title: str
    command: str = ""
    data: str = ""
    summary: str = ""
    cross_tests: list = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _esc(text) -> str:
    return html.escape(str(text), quote=True)


def _finite(a) -> np.ndarray:
    """Float array with non-finite values as NaN (Bokeh draws NaN as a gap)."""
    a = np.asarray(a, dtype=float)
    return np.where(np.isfinite(a), a, np.nan)


def _x(n: int, times) -> tuple[np.ndarray, str]:
    if times is not None and len(times) == n:
        return np.asarray(times, dtype=float), "time (s)"
    return np.arange(n, dtype=float), "sample"


def _figure(title: str, x_label: str, y_label: str, height: int = HEIGHT, x_range=None):
    from bokeh.plotting import figure

    kw = {"x_range": x_range} if x_range is not None else {}
    p = figure(title=title, height=height, sizing_mode="stretch_width",
               tools="pan,box_zoom,wheel_zoom,reset,save,hover",
               active_scroll="wheel_zoom", x_axis_label=x_label, y_axis_label=y_label, **kw)
    p.toolbar.logo = None
    return p


def _prediction_plots(section: OutputSection, kind: str) -> tuple[list, str]:
    """Measured against one kind of prediction (with its band), the error beneath."""
    from bokeh.models import ColumnDataSource

    rep = section.report
    pred = {"one_step": rep.one_step, "k_step": rep.k_step, "free_run": rep.free_run}[kind]
    m = {"one_step": rep.one_step_metrics, "k_step": rep.k_step_metrics,
         "free_run": rep.free_run_metrics}[kind] or {}
    label = {"one_step": "one-step prediction", "k_step": f"{rep.horizon}-step prediction",
             "free_run": "free-run simulation"}[kind]
    x, x_label = _x(len(rep.measured), section.times)
    data = {"x": x, "measured": _finite(rep.measured), "predicted": _finite(pred),
            "error": _finite(rep.measured - pred)}
    band = {"one_step": rep.one_step_band, "free_run": rep.free_run_band}.get(kind)
    if band is not None:
        data["lower"], data["upper"] = _finite(band.lower), _finite(band.upper)
    source = ColumnDataSource(data, name=f"{section.name}/{kind}")
    if m.get("diverged_at") is not None:
        summary = f"DIVERGED at sample {m['diverged_at']}"
    else:
        summary = (f"fit {m.get('fit_percent', float('nan')):.2f} %, max |e| "
                   f"{m.get('max_abs', float('nan')):.4g}, mean |e| "
                   f"{m.get('mean_abs', float('nan')):.4g}")
    top = _figure(f"{section.name}: measured and {label} ({summary})", x_label, section.name)
    if band is not None:
        top.varea("x", "lower", "upper", source=source, fill_color="#d62728", fill_alpha=0.2,
                  legend_label=f"{band.level:.0%} band (coefficient uncertainty)")
    top.line("x", "measured", source=source, color="black", line_width=1,
             legend_label="measured")
    top.line("x", "predicted", source=source, color="#d62728", line_dash="dashed",
             line_width=1, legend_label=label)
    top.legend.click_policy = "hide"
    top.legend.location = "top_right"
    err = _figure("error (measured - predicted)", x_label, "error", SMALL, x_range=top.x_range)
    err.line("x", "error", source=source, color="#1f77b4", line_width=1)
    return [top, err], summary


def _residual_plot(section: OutputSection):
    from bokeh.models import ColumnDataSource

    rep = section.report
    e = _finite(rep.residuals)
    x, x_label = _x(len(e), section.times)
    source = ColumnDataSource({"x": x, "residual": e}, name=f"{section.name}/residuals")
    p = _figure(f"{section.name}: one-step residuals", x_label, "residual", SMALL)
    p.scatter("x", "residual", source=source, size=2, color="#1f77b4")
    return p


def _correlation_plots(name: str, tests, prefix: str = "correlation") -> list:
    from bokeh.models import ColumnDataSource, Span

    plots = []
    for t in tests:
        lags = np.asarray(t.lags, dtype=float)
        source = ColumnDataSource({"lag": lags, "value": _finite(t.values)},
                                  name=f"{name}/{prefix}/{t.name}")
        state = "inside" if t.passed else "OUTSIDE"
        p = _figure(f"{state}: {t.fraction_inside:.0%} of lags inside the 95 % band, "
                    f"{t.label}", "lag", "correlation", SMALL)
        p.segment("lag", 0, "lag", "value", source=source, color="#1f77b4", line_width=2)
        p.scatter("lag", "value", source=source, size=4, color="#1f77b4")
        for level in (t.band, -t.band):
            p.add_layout(Span(location=float(level), dimension="width", line_color="#d62728",
                              line_dash="dashed"))
        plots.append(p)
    return plots


def _convergence_plot(name: str, history):
    from bokeh.models import ColumnDataSource

    gen = np.array([h.generation for h in history], dtype=float)
    best = _finite([h.best for h in history])
    mean = _finite([h.mean for h in history])
    source = ColumnDataSource({"generation": gen, "best": best, "mean": mean},
                              name=f"{name}/convergence")
    p = _figure(f"{name}: the GA's convergence, best and mean criterion per generation",
                "generation", "criterion", SMALL + 60)
    p.line("generation", "best", source=source, color="#d62728", line_width=2,
           legend_label="best")
    p.line("generation", "mean", source=source, color="#7f7f7f", line_width=1,
           legend_label="population mean")
    p.legend.click_policy = "hide"
    return p


def _coefficient_table(section: OutputSection) -> str:
    m = section.model
    rows = []
    unc = getattr(m, "uncertainty", None)
    se = unc.standard_errors if unc is not None else None
    iv = unc.intervals(m.coefficients) if unc is not None else None
    for j, (term, c) in enumerate(zip(m.terms, m.coefficients)):
        cells = [f'<td class="term">{_esc(term)}</td>',
                 f'<td class="num" data-value="{float(c)!r}">{float(c):.6g}</td>']
        if se is not None:
            spans = iv[j][0] <= 0 <= iv[j][1]
            cells += [f'<td class="num" data-value="{float(se[j])!r}">{float(se[j]):.3g}</td>',
                      f'<td class="num{" zero" if spans else ""}">[{iv[j][0]:.4g}, '
                      f'{iv[j][1]:.4g}]</td>']
        rows.append("<tr>" + "".join(cells) + "</tr>")
    head = "<tr><th>term</th><th>coefficient</th>" + (
        "<th>std. error</th><th>95 % interval</th>" if se is not None else "") + "</tr>"
    note = (f'<p class="small">{_esc(unc.method)} uncertainty, {unc.dof} degrees of freedom; '
            "intervals in red span zero.</p>" if unc is not None else
            '<p class="small">no coefficient uncertainty for this model.</p>')
    return (f'<table class="coefficients" id="coefficients-{_esc(section.name)}">'
            f"{head}{''.join(rows)}</table>{note}")


def _facts(section: OutputSection) -> str:
    """Criterion, certification, selection, orders, data check and warnings."""
    from ..core.jobs.single import describe_selection
    from ..core.search.certify import describe_certificate
    from ..core.validate.excitation import describe_check

    m, meta = section.model, section.model.metadata or {}
    items = []
    if m.criterion:
        crit = m.criterion.upper() + (" (simulation)" if meta.get("focus") == "simulation"
                                      else "")
        value = "" if m.criterion_value is None else f" = {m.criterion_value:.2f}"
        items.append(f"<li><b>criterion</b> {_esc(crit)}{_esc(value)}, {len(m.terms)} terms"
                     + (f", {m.n_samples} samples" if m.n_samples else "") + "</li>")
    cert = describe_certificate(meta.get("certificate"))
    if cert:
        items.append(f"<li><b>certification</b> {_esc(cert)}</li>")
    sel = describe_selection(meta.get("selection"))
    if sel:
        items.append(f"<li><b>selection</b> {_esc(sel)}</li>")
    orders = meta.get("orders")
    if orders:
        items.append(f"<li><b>orders</b> ny = nu = {orders['ny']}, degree {orders['degree']}: "
                     f"{_esc(orders.get('reason', ''))}</li>")
    check = describe_check(meta.get("data_check"))  # starts "data check: ..."
    if check:
        head, _, rest = check.partition(":")
        items.append(f"<li><b>{_esc(head)}</b> {_esc(rest.strip())}</li>")
    out = f"<ul class=\"facts\">{''.join(items)}</ul>"
    warnings = meta.get("warnings") or []
    if warnings:
        out += ('<div class="warnings"><b>Warnings</b><ul>'
                + "".join(f"<li>{_esc(w)}</li>" for w in warnings) + "</ul></div>")
    return out


def build_report(content: ReportContent, sections: list[OutputSection]) -> str:
    """The page's HTML (one string, scripts and data inlined)."""
    from bokeh.embed import components
    from bokeh.resources import Resources

    inline = Resources(mode="inline", components=["bokeh"])  # plots only: 1.3 MB
    plots, body = {}, []
    for i, sec in enumerate(sections):
        part = [f'<section class="output" id="output-{_esc(sec.name)}">'
                + (f"<h2>Output {_esc(sec.name)}</h2>" if len(sections) > 1 else "")
                + f'<p class="equation" id="equation-{_esc(sec.name)}">'
                f"{_esc(sec.model.equation())}</p>",
                _coefficient_table(sec), _facts(sec)]
        rep = sec.report
        if rep is None:
            part.append("<p>No validation was run (validation: none).</p>")
        else:
            if rep.diverged_at is not None:
                part.append(f'<p class="diverged" id="diverged-{_esc(sec.name)}">The free-run '
                            f"simulation DIVERGED at sample {rep.diverged_at}: the model does "
                            "not describe the system there.</p>")
            part.append(f"<h3>Validation ({_esc(rep.segment)} data, {rep.n_samples} "
                        "samples)</h3>")
            kinds = ["one_step"] + (["k_step"] if rep.k_step is not None else []) \
                + ["free_run"]
            for kind in kinds:
                figs, _ = _prediction_plots(sec, kind)
                for j, f in enumerate(figs):
                    key = f"p{i}_{kind}_{j}"
                    plots[key] = f
                    part.append(f"{{{{{key}}}}}")
            plots[f"p{i}_residuals"] = _residual_plot(sec)
            part.append(f"{{{{p{i}_residuals}}}}")
            part.append("<h3>Correlation tests</h3>")
            if rep.tests_skipped:
                part.append(f"<p>{_esc(rep.tests_skipped)}</p>")
            for j, f in enumerate(_correlation_plots(sec.name, rep.tests)):
                plots[f"p{i}_corr{j}"] = f
                part.append(f'<div class="half">{{{{p{i}_corr{j}}}}}</div>')
        if sec.history:
            plots[f"p{i}_convergence"] = _convergence_plot(sec.name, sec.history)
            part.append(f"<h3>Search</h3>{{{{p{i}_convergence}}}}")
        part.append("</section>")
        body.append("\n".join(part))
    if content.cross_tests:
        body.append("<section><h2>Cross-correlation of the outputs' residuals</h2>")
        for j, f in enumerate(_correlation_plots("outputs", content.cross_tests, "cross")):
            plots[f"cross{j}"] = f
            body.append(f'<div class="half">{{{{cross{j}}}}}</div>')
        body.append("</section>")
    script, divs = components(plots) if plots else ("", {})
    text = "\n".join(body)
    for key, div in divs.items():
        text = text.replace(f"{{{{{key}}}}}", div)
    notes = "".join(f"<li>{_esc(n)}</li>" for n in content.notes)
    summary = (f'<details><summary>What the command printed</summary><pre>'
               f"{_esc(content.summary)}</pre></details>" if content.summary else "")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{_esc(content.title)}</title>
{inline.render_js()}
{inline.render_css()}
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1100px;
       padding: 0 1em; color: #222; }}
.equation {{ font-family: ui-monospace, monospace; background: #f4f4f4; padding: .6em;
            overflow-x: auto; }}
table.coefficients {{ border-collapse: collapse; font-size: 90%; }}
table.coefficients td, table.coefficients th {{ border-bottom: 1px solid #ddd;
  padding: .2em .8em; text-align: right; }}
td.term {{ text-align: left; font-family: ui-monospace, monospace; }}
td.zero {{ color: #b00; }}
.small {{ font-size: 85%; color: #555; }}
.warnings {{ background: #fff4e5; border-left: 4px solid #f0a020; padding: .3em 1em; }}
.diverged {{ background: #fde8e8; border-left: 4px solid #c00; padding: .5em 1em;
            font-weight: bold; }}
.half {{ display: inline-block; width: 49%; vertical-align: top; }}
@media (max-width: 800px) {{ .half {{ width: 100%; }} }}
</style></head>
<body>
<h1>{_esc(content.title)}</h1>
<p class="small">{_esc(content.command)}<br>{_esc(content.data)}<br>
written {_esc(time.strftime("%Y-%m-%d %H:%M:%S"))} by spm_sysid; pan and zoom with the mouse,
reset with the toolbar's arrows.</p>
{f'<ul class="notes">{notes}</ul>' if notes else ""}
{text}
{summary}
{script}
</body></html>
"""


def write_report(path: str | Path, content: ReportContent,
                 sections: list[OutputSection]) -> Path:
    """Write the page (:func:`build_report`); the path written."""
    path = Path(path)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(build_report(content, sections), encoding="utf-8")
    return path
