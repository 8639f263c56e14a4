"""One self-contained HTML page per identification or validation (``--report FILE.html``).

The page shows what the terminal prints and the figures, in one place a user can
open, keep and send: the equation; the coefficients with standard errors and
intervals; criterion, certification, selection and orders; the data check and
the warnings; and interactive plots (pan, box zoom, wheel zoom, reset) of the
measured output against the one-step, k-step and free-run predictions with
their bands, the residuals, the correlation tests with their confidence bands,
and the GA's convergence. A model with several outputs gets a section per
output and the residuals' cross-correlation.

The plots are Bokeh's (a NumFOCUS project): BokehJS's core and plotting API
(about 1.4 MB, read from the installed bokeh package) are inlined, so the page
makes no network request and works offline; Plotly's bundle is 4.8 MB alone,
too much for a page that should stay under 5 MB with its data. The data go in
as JSON and the page's few lines draw the figures with BokehJS's own API, so
writing a report does not import bokeh's Python side (0.5 s) nor serialise its
models (another 0.5 s). A long record's plots draw each stretch's extremes
(:func:`thinned_rows`, at most about 20 000 rows a plot, the title says how
many): a page of 10^5 samples was 26 MB drawn whole. Every plot's data source has a name
(``<output>/<plot>``) in ``window.spmReport.sources`` so that a reader -- or a
test in a browser -- can find the numbers behind it; every coefficient cell
carries the full-precision value (``data-value``).
"""

from __future__ import annotations

import html
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .pages import read_page_file, render_page

__all__ = ["OutputSection", "ReportContent", "build_report", "thinned_rows", "verdict",
           "write_model_report"]

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


def _x(n: int, times) -> tuple[np.ndarray, str]:
    if times is not None and len(times) == n:
        return np.asarray(times, dtype=float), "time (s)"
    return np.arange(n, dtype=float), "sample"


class _Plots:
    """The page's plots as data: each a figure spec the page's script draws with BokehJS."""

    def __init__(self) -> None:
        self.specs: list[dict] = []

    def figure(self, title: str, x_label: str, y_label: str, height: int = HEIGHT,
               link_x: str | None = None) -> dict:
        spec = {"id": f"plot{len(self.specs)}", "title": title, "x_label": x_label,
                "y_label": y_label, "height": height, "link_x": link_x, "sources": {},
                "glyphs": [], "spans": []}
        self.specs.append(spec)
        return spec


#: A data source of more rows than this is drawn from its extremes (:func:`thinned_rows`):
#: the page stays a few MB whatever the record's length (10^5 samples drawn whole made
#: a 26 MB page).
PLOT_ROWS = 20_000
#: Stretches a long source is cut into; each keeps its first row and the rows of every
#: column's smallest and largest value.
PLOT_STRETCHES = 2_000


def thinned_rows(columns: dict, stretches: int = PLOT_STRETCHES) -> np.ndarray:
    """The rows of a long source that draw the same picture: each stretch's extremes.

    The rows are cut into ``stretches`` stretches of equal length; each keeps its
    first row and, for every column, the rows of its smallest and largest finite
    value (a gap, NaN, is kept where it starts). Lines through these rows have
    every column's envelope of the whole: a peak, a spike or a divergence stays
    visible at any zoom out.
    """
    data = [np.asarray(col, dtype=float) for col in columns.values()]
    n = len(data[0])
    size = -(-n // stretches)
    starts = np.arange(0, n, size)
    keep = [starts]
    padded = np.full(len(starts) * size, np.nan)
    for col in data:
        padded[:n] = col
        block = padded.reshape(len(starts), size)
        finite = np.isfinite(block)
        low = np.where(finite, block, np.inf).argmin(axis=1)
        high = np.where(finite, block, -np.inf).argmax(axis=1)
        keep += [starts + low, starts + high]
        gaps = np.flatnonzero(~np.isfinite(col))
        if gaps.size:  # the first sample of each gap
            keep.append(gaps[np.r_[True, np.diff(gaps) > 1]])
    rows = np.unique(np.concatenate(keep))
    return rows[rows < n]


def _source(spec: dict, name: str, columns: dict) -> str:
    """Attach a named data source to a figure spec (NaN and inf as null: a gap).

    A source of more than :data:`PLOT_ROWS` rows keeps its :func:`thinned_rows`,
    and the figure's title says how many of how many samples are drawn.
    """
    n = len(next(iter(columns.values()))) if columns else 0
    if n > PLOT_ROWS:
        rows = thinned_rows(columns)
        columns = {k: np.asarray(col, dtype=float)[rows] for k, col in columns.items()}
        spec["title"] += (f" -- {len(rows)} of {n} samples drawn: every stretch's "
                          "extremes")
        spec["thinned"] = {"drawn": int(len(rows)), "samples": int(n)}
    spec["sources"][name] = {k: [float(v) if np.isfinite(v) else None
                                 for v in np.asarray(col, dtype=float)]
                             for k, col in columns.items()}
    return name


def _prediction_plots(plots: _Plots, section: OutputSection, kind: str) -> str:
    """Measured against one kind of prediction (with its band), the error beneath."""
    rep = section.report
    pred = {"one_step": rep.one_step, "k_step": rep.k_step, "free_run": rep.free_run}[kind]
    m = {"one_step": rep.one_step_metrics, "k_step": rep.k_step_metrics,
         "free_run": rep.free_run_metrics}[kind] or {}
    label = {"one_step": "one-step prediction", "k_step": f"{rep.horizon}-step prediction",
             "free_run": "free-run simulation"}[kind]
    x, x_label = _x(len(rep.measured), section.times)
    data = {"x": x, "measured": rep.measured, "predicted": pred,
            "error": np.asarray(rep.measured) - np.asarray(pred)}
    band = {"one_step": rep.one_step_band, "free_run": rep.free_run_band}.get(kind)
    if band is not None:
        data["lower"], data["upper"] = band.lower, band.upper
    if m.get("diverged_at") is not None:
        summary = f"DIVERGED at sample {m['diverged_at']}"
    else:
        summary = (f"fit {m.get('fit_percent', float('nan')):.2f} %, max |e| "
                   f"{m.get('max_abs', float('nan')):.4g}, mean |e| "
                   f"{m.get('mean_abs', float('nan')):.4g}")
    top = plots.figure(f"{section.name}: measured and {label} ({summary})", x_label,
                       section.name)
    top["y_range"] = _signal_range(rep.measured, pred)
    src = _source(top, f"{section.name}/{kind}", data)
    if band is not None:
        top["glyphs"].append({"type": "varea", "source": src, "x": "x", "y1": "lower",
                              "y2": "upper", "color": "#d62728", "alpha": 0.2,
                              "legend": f"{band.level:.0%} band (coefficient uncertainty)"})
    top["glyphs"] += [
        {"type": "line", "source": src, "x": "x", "y": "measured", "color": "black",
         "width": 1, "legend": "measured"},
        {"type": "line", "source": src, "x": "x", "y": "predicted", "color": "#d62728",
         "width": 1, "dash": "dashed", "legend": label}]
    err = plots.figure("error (measured - predicted)", x_label, "error", SMALL,
                       link_x=top["id"])
    err["glyphs"].append({"type": "line", "source": src, "x": "x", "y": "error",
                          "color": "#1f77b4", "width": 1})
    return summary


def _signal_range(*signals) -> list[float] | None:
    """The y range of the signals (finite values, 5 % margin).

    A band's spread (the coefficient uncertainty of a free run can be ten times
    the signal) is clipped to it.
    """
    values = np.concatenate([np.asarray(s, dtype=float).ravel() for s in signals])
    values = values[np.isfinite(values)]
    if not values.size:
        return None
    lo, hi = float(values.min()), float(values.max())
    pad = 0.05 * (hi - lo) or 0.5 * abs(hi) or 1.0
    return [lo - pad, hi + pad]


def _residual_plot(plots: _Plots, section: OutputSection) -> None:
    e = np.asarray(section.report.residuals, dtype=float)
    x, x_label = _x(len(e), section.times)
    p = plots.figure(f"{section.name}: one-step residuals", x_label, "residual", SMALL)
    src = _source(p, f"{section.name}/residuals", {"x": x, "residual": e})
    p["glyphs"].append({"type": "scatter", "source": src, "x": "x", "y": "residual",
                        "color": "#1f77b4", "size": 2})


def _correlation_plots(plots: _Plots, name: str, tests, prefix: str = "correlation"
                       ) -> list[str]:
    ids = []
    for t in tests:
        state = "passed" if t.passed else "OUTSIDE"
        # short enough for half the page's width: the symbol, the verdict, the share
        symbol = t.label.split("  ")[-1]
        p = plots.figure(f"{symbol}: {state}, {t.fraction_inside:.0%} of lags in the band",
                         "lag", "correlation", SMALL)
        src = _source(p, f"{name}/{prefix}/{t.name}", {"lag": t.lags, "value": t.values})
        p["glyphs"] += [{"type": "segment", "source": src, "x": "lag", "y": "value",
                         "color": "#1f77b4", "width": 2},
                        {"type": "scatter", "source": src, "x": "lag", "y": "value",
                         "color": "#1f77b4", "size": 4}]
        p["spans"] = [float(t.band), -float(t.band)]
        ids.append(p["id"])
    return ids


def _convergence_plot(plots: _Plots, name: str, history) -> str:
    p = plots.figure(f"{name}: the GA's convergence, best and mean criterion per generation",
                     "generation", "criterion", SMALL + 60)
    src = _source(p, f"{name}/convergence",
                  {"generation": [h.generation for h in history],
                   "best": [h.best for h in history], "mean": [h.mean for h in history]})
    p["glyphs"] += [{"type": "line", "source": src, "x": "generation", "y": "best",
                     "color": "#d62728", "width": 2, "legend": "best"},
                    {"type": "line", "source": src, "x": "generation", "y": "mean",
                     "color": "#7f7f7f", "width": 1, "legend": "population mean"}]
    return p["id"]


def verdict(section: OutputSection) -> tuple[str, str]:
    """(kind, sentence): what the fits say, in one line, and what to try next.

    ``kind`` is ``good``, ``caution`` or ``bad`` (the box's colour).
    """
    rep, meta = section.report, section.model.metadata or {}
    one = rep.one_step_metrics.get("fit_percent")
    free = rep.free_run_metrics.get("fit_percent")
    failed = [t.name for t in rep.tests if not t.passed]
    focus = meta.get("focus", "prediction")
    if rep.diverged_at is not None:
        return "bad", (f"The free-run simulation diverges (at sample {rep.diverged_at}): the "
                       "model predicts one step ahead but cannot be simulated. Next: "
                       "--focus simulation, which chooses and fits the model on its "
                       "simulation error.")
    if one is None or free is None or not (np.isfinite(one) and np.isfinite(free)):
        return "caution", "The fits could not be computed on these data (see below)."
    fits = f"One-step fit {one:.1f} %, free-run fit {free:.1f} %"
    if one - free > 20 and focus == "prediction":
        return "caution", (f"{fits}: each one-step prediction starts from measured outputs, "
                           "so its errors never add up; simulated from its own outputs the "
                           "model drifts. It was chosen for one-step prediction (the paper's "
                           "criterion). For simulation or control design, try --focus "
                           "simulation (or more lags: spm-sysid propose-lags).")
    if failed:
        return "caution", (f"{fits}; the residuals are correlated ({', '.join(failed)} "
                           "outside the band): the model misses some dynamics. Next: more "
                           "lags (spm-sysid propose-lags) or a higher degree.")
    return "good", f"{fits}; the residuals pass the correlation tests: the model describes " \
        "these data."


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
    from ..core.model.narx import together_words

    for group in m.lags_together() if hasattr(m, "lags_together") else []:
        note += f'<p class="small">{_esc(" ".join(together_words(group).split()))}</p>'
    return (f'<table class="coefficients" id="coefficients-{_esc(section.name)}">'
            f"{head}{''.join(rows)}</table>{note}")


def _facts(section: OutputSection) -> str:
    """Criterion, certification, selection, orders, data check and warnings."""
    from ..core.jobs.single import describe_selection
    from ..core.model.operating_point import operating_point_words
    from ..core.search.certify import describe_certificate
    from ..core.validate.excitation import describe_check

    m, meta = section.model, section.model.metadata or {}
    items = []
    if m.criterion:
        crit = m.criterion.upper() + (" (simulation)" if meta.get("focus") == "simulation"
                                      else "")
        value = "" if m.criterion_value is None else f" = {m.criterion_value:.2f}"
        items.append(f"<li><b>criterion</b> {_esc(crit)}{_esc(value)}, {_esc(len(m.terms))} "
                     "terms" + (f", {_esc(m.n_samples)} samples" if m.n_samples else "")
                     + "</li>")
    cert = describe_certificate(meta.get("certificate"))
    if cert:
        items.append(f"<li><b>certification</b> {_esc(cert)}</li>")
    point = operating_point_words(meta.get("operating_point"))
    if point:
        items.append(f"<li><b>operating point</b> {_esc(point)}</li>")
    sel = describe_selection(meta.get("selection"))
    if sel:
        items.append(f"<li><b>selection</b> {_esc(sel)}</li>")
    orders = meta.get("orders")
    if orders:
        items.append(f"<li><b>orders</b> ny = nu = {_esc(orders['ny'])}, degree "
                     f"{_esc(orders['degree'])}: {_esc(orders.get('reason') or '')}</li>")
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


def _bokeh_scripts() -> str:
    """BokehJS (its core and its plotting API), read from the installed bokeh package.

    The Python package is not imported: only its two script files are read, so
    a report costs the time to write it, not the time to import bokeh.
    """
    import importlib.util

    spec = importlib.util.find_spec("bokeh")
    if spec is None or spec.origin is None:
        raise RuntimeError("the report needs bokeh (pip install bokeh): its scripts draw "
                           "the plots")
    base = Path(spec.origin).parent / "server" / "static" / "js"
    return "\n".join("<script>" + (base / f).read_text(encoding="utf-8").replace(
        "</script", "<\\/script") + "</script>" for f in ("bokeh.min.js", "bokeh-api.min.js"))


def build_report(content: ReportContent, sections: list[OutputSection]) -> str:
    """The page's HTML (one string, scripts and data inlined)."""
    import json

    plots = _Plots()
    body = ["\n".join(_output_section(plots, sec, several=len(sections) > 1))
            for sec in sections]
    if content.cross_tests:
        body.append("<section><h2>Cross-correlation of the outputs' residuals</h2>")
        body += [_div(i, "half") for i in _correlation_plots(plots, "outputs",
                                                             content.cross_tests, "cross")]
        body.append("</section>")
    text = "\n".join(body)
    data = json.dumps(plots.specs, allow_nan=False).replace("</", "<\\/")
    notes = "".join(f"<li>{_esc(n)}</li>" for n in content.notes)
    summary = (f'<details><summary>What the command printed</summary><pre>'
               f"{_esc(content.summary)}</pre></details>" if content.summary else "")
    return render_page(
        "report.html", title=_esc(content.title), bokeh=_bokeh_scripts(),
        command=_esc(content.command), data=_esc(content.data),
        written=_esc(time.strftime("%Y-%m-%d %H:%M:%S")),
        notes=f'<ul class="notes">{notes}</ul>' if notes else "", body=text,
        summary=summary, plots=data, draw=read_page_file("report.js"))


def _div(plot_id: str, cls: str = "") -> str:
    """The empty element a plot is drawn into."""
    return f'<div id="{plot_id}"{f" class={chr(34)}{cls}{chr(34)}" if cls else ""}></div>'


def _output_section(plots: _Plots, sec: OutputSection, several: bool) -> list[str]:
    """One output's section: equation, verdict, coefficients, facts, validation, search."""
    part = [f'<section class="output" id="output-{_esc(sec.name)}">'
            + (f"<h2>Output {_esc(sec.name)}</h2>" if several else "")
            + f'<p class="equation" id="equation-{_esc(sec.name)}">'
            f"{_esc(sec.model.equation())}</p>",
            _coefficient_table(sec), _facts(sec)]
    rep = sec.report
    if rep is None:
        part.append("<p>No validation was run (validation: none).</p>")
    else:
        kind, sentence = verdict(sec)
        part.insert(1, f'<p class="verdict {kind}" id="verdict-{_esc(sec.name)}">'
                    f"{_esc(sentence)}</p>")
        part += _validation_part(plots, sec)
    if sec.history:
        part.append("<h3>Search</h3>" + _div(_convergence_plot(plots, sec.name, sec.history)))
    part.append("</section>")
    return part


def _validation_part(plots: _Plots, sec: OutputSection) -> list[str]:
    """Divergence, prediction plots, residuals and correlation tests of one output."""
    rep = sec.report
    part = []
    if rep.diverged_at is not None:
        part.append(f'<p class="diverged" id="diverged-{_esc(sec.name)}">The free-run '
                    f"simulation DIVERGED at sample {_esc(rep.diverged_at)}: the model "
                    "does not describe the system there.</p>")
    part.append(f"<h3>Validation ({_esc(rep.segment)} data, {_esc(rep.n_samples)} "
                "samples)</h3>")
    kinds = ["one_step"] + (["k_step"] if rep.k_step is not None else []) + ["free_run"]
    for kind in kinds:
        first = len(plots.specs)
        _prediction_plots(plots, sec, kind)
        part += [_div(s["id"]) for s in plots.specs[first:]]
    _residual_plot(plots, sec)
    part.append(_div(plots.specs[-1]["id"]))
    part.append("<h3>Correlation tests</h3>")
    if rep.tests_skipped:
        part.append(f"<p>{_esc(rep.tests_skipped)}</p>")
    part += [_div(i, "half") for i in _correlation_plots(plots, sec.name, rep.tests)]
    return part


def write_model_report(path: str | Path, content: ReportContent,
                       sections: list[OutputSection]) -> Path:
    """Write the page (:func:`build_report`) all at once; the path written.

    The caller checks the destination first (the command line's one check of its
    outputs, :func:`spm_sysid.core.files.check_destinations`); the page goes to a
    temporary file that then replaces the path, so a reader never sees half a page.
    """
    from ..core.files import atomic_write_text

    return atomic_write_text(path, build_report(content, sections))
