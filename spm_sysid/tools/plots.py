"""Figures (matplotlib, written as PNG and SVG), in the style of the paper's.

* :func:`plot_correlation_tests` -- the correlation tests with their 95 % band
  (paper Fig. 5);
* :func:`plot_prediction` -- predicted and measured output superimposed, the
  error beneath (Figs. 6-7), for one-step or free-run;
* :func:`plot_convergence` -- mean best criterion per generation over runs, one
  line per SPM fraction (Figs. 3-4);
* :func:`plot_outputs` and :func:`write_mimo_figures` -- several outputs: one
  panel per output (coupled free run, one-step), the residuals'
  cross-correlation between outputs.

Every function writes ``<stem>.png`` and ``<stem>.svg`` and returns both paths.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from ..core.validate.validation import ValidationReport  # noqa: E402

__all__ = ["model_label", "plot_convergence", "plot_correlation_tests", "plot_outputs",
           "plot_prediction", "write_mimo_figures", "write_model_figures"]

#: The correlation tests' symbols, as matplotlib mathtext (the core's labels are plain text).
MATH_LABELS = {
    "ee": r"residual autocorrelation  $\phi_{\varepsilon\varepsilon}(\tau)$",
    "ue": r"input–residual  $\phi_{u\varepsilon}(\tau)$",
    "e_eu": r"residual–(residual·input)  $\phi_{\varepsilon(\varepsilon u)}(\tau)$",
    "u2_e": r"squared input–residual  $\phi_{(u^2)'\varepsilon}(\tau)$",
    "u2_e2": r"squared input–squared residual  $\phi_{(u^2)'(\varepsilon^2)}(\tau)$",
}

#: Samples in the zoomed window of a prediction figure.
ZOOM = 150


def model_label(model) -> str:
    """Which model a figure shows: criterion, focus and size (``AIC, prediction, 8 terms``)."""
    if model is None:
        return ""
    crit = (model.criterion or "model").upper()
    focus = model.metadata.get("focus", "prediction")
    return f"{crit}, focus {focus}, {len(model.term_indices)} terms"


def _save(fig, stem: Path) -> list[Path]:
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    for p in paths:
        fig.savefig(p, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return paths


def plot_correlation_tests(report: ValidationReport, stem: Path, title: str = "") -> list[Path]:
    """Stem plots of the five correlation tests with the ±1.96/√N band.

    ``report`` may also be a list of tests (the cross-correlation of several
    outputs' residuals).
    """
    tests = report if isinstance(report, list) else report.tests
    fig, axes = plt.subplots(len(tests), 1, figsize=(7, 2.0 * len(tests)), sharex=False)
    for ax, t in zip(np.atleast_1d(axes), tests):
        ax.vlines(t.lags, 0, t.values, color="tab:blue", lw=1.2)
        ax.plot(t.lags, t.values, "o", ms=3, color="tab:blue")
        ax.axhline(t.band, ls=":", color="k", lw=1)
        ax.axhline(-t.band, ls=":", color="k", lw=1)
        ax.axhline(0, color="0.6", lw=0.5)
        ax.set_ylim(-1.05, 1.05)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        state = "OK" if t.passed else "outside band"
        ax.set_title(f"{MATH_LABELS.get(t.name, t.label)} — {t.fraction_inside:.0%} inside "
                     f"({state})", fontsize=9)
        ax.set_ylabel("correlation", fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel(r"lag $\tau$ (samples)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, stem)


def _axis(n: int, times: np.ndarray | None) -> tuple[np.ndarray, str]:
    """The x values of n rows and their label: seconds where the stamps are known."""
    if times is not None and len(times) == n:
        return np.asarray(times, dtype=float), "time (s)"
    return np.arange(n), "sample"


def plot_prediction(report: ValidationReport, stem: Path, kind: str = "one_step",
                    title: str = "", times: np.ndarray | None = None) -> list[Path]:
    """Measured and predicted output superimposed, with the error beneath.

    ``kind``: ``one_step``, ``k_step`` (the report's horizon) or ``free_run``. A
    run that diverged is drawn up to the divergence, marked by a vertical line.
    ``times``: seconds of the report's rows (the x axis; else the sample index).
    """
    if kind not in ("one_step", "k_step", "free_run"):
        raise ValueError(f"kind must be 'one_step', 'k_step' or 'free_run', got {kind!r}")
    if kind == "k_step" and report.k_step is None:
        raise ValueError("this report has no k-step prediction (validate with a horizon)")
    pred = {"one_step": report.one_step, "k_step": report.k_step,
            "free_run": report.free_run}[kind]
    m = {"one_step": report.one_step_metrics, "k_step": report.k_step_metrics,
         "free_run": report.free_run_metrics}[kind]
    label = {"one_step": "one-step prediction", "k_step": f"{report.horizon}-step prediction",
             "free_run": "free-run simulation"}[kind]
    t, xlabel = _axis(len(report.measured), times)
    err = report.measured - pred
    fig, (ax1, axz, ax2) = plt.subplots(3, 1, figsize=(8, 7),
                                        gridspec_kw={"height_ratios": [2, 1.5, 1]})
    band = {"one_step": report.one_step_band, "free_run": report.free_run_band}.get(kind)
    ax1.plot(t, report.measured, color="k", lw=0.8, label="measured")
    ax1.plot(t, pred, color="tab:red", lw=0.7, ls="--", label=label)
    ax1.set_ylabel("output y")
    z = _zoom(err, len(t))
    if band is not None:
        text = f"{band.level:.0%} band (coefficient uncertainty)"
        ax1.fill_between(t, band.lower, band.upper, color="tab:red", alpha=0.2, lw=0,
                         label=text)
        axz.fill_between(t[z], band.lower[z], band.upper[z], color="tab:red", alpha=0.2, lw=0,
                         label=text)
    axz.plot(t[z], report.measured[z], color="k", lw=1.0, marker=".", ms=2.5, label="measured")
    axz.plot(t[z], pred[z], color="tab:red", lw=1.0, ls="--", label=label)
    axz.set_ylabel("output y")
    span = (f"samples {t[z][0]}–{t[z][-1]}" if xlabel == "sample"
            else f"{t[z][0]:.3f}–{t[z][-1]:.3f} s")
    axz.set_title(f"{span} (around the largest error)", fontsize=8)
    ax1.axvspan(t[z][0], t[z][-1], color="tab:orange", alpha=0.15, lw=0)
    if m.get("diverged_at") is not None:
        _mark_divergence(ax1, ax2, t, pred, m["diverged_at"])
        summary = f"{label[0].upper() + label[1:]}: DIVERGED at sample {m['diverged_at']}"
    else:
        summary = (f"{label[0].upper() + label[1:]}: max |e| {m['max_abs']:.4g}, "
                   f"mean |e| {m['mean_abs']:.4g}, fit {m['fit_percent']:.1f} %")
    ax1.legend(loc="upper right", fontsize=8)
    ax1.set_title(f"{title} — {summary}" if title else summary, fontsize=9)
    ax2.plot(t, err, color="tab:blue", lw=0.7)
    ax2.set_ylabel("error")
    ax2.set_xlabel(xlabel)
    ax2.sharex(ax1)
    fig.tight_layout()
    return _save(fig, stem)


def _zoom(err: np.ndarray, n: int) -> slice:
    """A window of ZOOM rows around the largest error, so the two curves can be told apart."""
    finite = np.isfinite(err)
    peak = int(np.nanargmax(np.abs(np.where(finite, err, np.nan)))) if finite.any() else 0
    a = int(np.clip(peak - ZOOM // 2, 0, max(n - ZOOM, 0)))
    return slice(a, a + ZOOM)


def _mark_divergence(ax1, ax2, t: np.ndarray, pred: np.ndarray, at: int) -> None:
    """A vertical line where the run stops being finite, and its sample named."""
    bad = np.flatnonzero(~np.isfinite(pred))
    row = int(bad[0]) if bad.size else len(pred) - 1
    for ax in (ax1, ax2):
        ax.axvline(t[row], color="tab:red", lw=1.5)
    ax1.annotate(f"diverged at sample {at}", (t[row], ax1.get_ylim()[1]),
                 xytext=(-5, -12), textcoords="offset points", ha="right",
                 color="tab:red", fontsize=9)


def plot_convergence(
    curves: Mapping[str, Mapping[float, Sequence[Sequence[float]]]], stem: Path,
) -> list[Path]:
    """Mean best criterion per generation, one panel per setting, one line per s.

    ``curves[panel_title][spm_fraction]`` is a list of per-run best-so-far curves.
    """
    panels = list(curves)
    cols = min(3, len(panels)) or 1
    rows = -(-len(panels) // cols) or 1
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    n_runs = 0
    for ax, title in zip(axes.ravel(), panels):
        tops = []
        for s, runs in sorted(curves[title].items()):
            arr = np.asarray(runs, dtype=float)
            n_runs = max(n_runs, len(arr))
            mean = np.nanmean(np.where(np.isfinite(arr), arr, np.nan), axis=0)
            # generation + 1 on a log axis: the first tens of generations, where the
            # search moves, get the room; the plateau takes the rest
            ax.plot(np.arange(1, len(mean) + 1), mean, lw=1.3, label=f"{s:g}")
            tops.append(mean[min(len(mean) - 1, 4)])  # the mean at generation 5
            low = np.nanmin(mean)
        ax.set_xscale("log")
        finite = [v for v in tops if np.isfinite(v)]
        if finite and np.isfinite(low) and max(finite) > low:
            pad = 0.05 * (max(finite) - low)
            ax.set_ylim(low - pad, max(finite) + pad)  # generation 0's outliers cropped
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("generation + 1 (log scale)")
        ax.set_ylabel("mean best criterion")
        ax.legend(title="SPM s", fontsize=8)
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    fig.suptitle(f"Mean best criterion so far, over {n_runs} runs per line (lower is better; "
                 "y axis from generation 5)", fontsize=10)
    fig.tight_layout()
    return _save(fig, stem)


def write_model_figures(
    report: ValidationReport, directory: Path, name: str = "model", model=None,
    times: np.ndarray | None = None,
) -> list[Path]:
    """The correlation, one-step, k-step (with a horizon) and free-run figures.

    With ``model``, every title says which model it shows (criterion, focus, size).
    ``times``: seconds of the report's rows (time stamps known: a time axis).
    """
    directory = Path(directory)
    which = model_label(model)
    prefix = f"{which} — " if which else ""
    paths = []
    if report.tests:  # not computed after a divergence (report.tests_skipped says why)
        paths += plot_correlation_tests(report, directory / f"{name}_correlation",
                                        title=f"{prefix}correlation tests ({report.segment} "
                                              "data)")
    paths += plot_prediction(report, directory / f"{name}_one_step", "one_step", which, times)
    if report.k_step is not None:
        paths += plot_prediction(report, directory / f"{name}_k_step", "k_step", which, times)
    paths += plot_prediction(report, directory / f"{name}_free_run", "free_run", which, times)
    return paths


def plot_outputs(reports: Sequence[ValidationReport], names: Sequence[str], stem: Path,
                 kind: str = "free_run", title: str = "",
                 times: np.ndarray | None = None) -> list[Path]:
    """Several outputs: measured and predicted, one panel per output (error beneath each).

    ``kind``: ``free_run`` (for a coupled model: the coupled simulation) or
    ``one_step``.
    """
    if kind not in ("one_step", "free_run"):
        raise ValueError(f"kind must be 'one_step' or 'free_run', got {kind!r}")
    label = "one-step prediction" if kind == "one_step" else "coupled free-run simulation"
    fig, axes = plt.subplots(2 * len(reports), 1, figsize=(8, 3.2 * len(reports)),
                             gridspec_kw={"height_ratios": [2, 1] * len(reports)})
    for k, (rep, name) in enumerate(zip(reports, names)):
        ax, axe = axes[2 * k], axes[2 * k + 1]
        pred = rep.one_step if kind == "one_step" else rep.free_run
        m = rep.one_step_metrics if kind == "one_step" else rep.free_run_metrics
        t, xlabel = _axis(len(rep.measured), times)
        ax.plot(t, rep.measured, color="k", lw=0.8, label="measured")
        ax.plot(t, pred, color="tab:red", lw=0.7, ls="--", label=label)
        ax.set_ylabel(name)
        state = (f"DIVERGED at sample {m['diverged_at']}" if m.get("diverged_at") is not None
                 else f"fit {m['fit_percent']:.1f} %, max |e| {m['max_abs']:.4g}")
        ax.set_title(f"output {name}: {label}, {state}", fontsize=9)
        ax.legend(loc="upper right", fontsize=7)
        axe.plot(t, rep.measured - pred, color="tab:blue", lw=0.7)
        axe.set_ylabel("error")
        axe.sharex(ax)
    axes[-1].set_xlabel(xlabel)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, stem)


def write_mimo_figures(reports: Sequence[ValidationReport], models: Sequence, names: Sequence[str],
                       cross_tests: list, directory: Path, name: str = "model",
                       times: np.ndarray | None = None) -> list[Path]:
    """The figures of a coupled model of several outputs, one report and model per output.

    ``<name>_free_run`` and ``<name>_one_step`` (a panel per output), each
    output's correlation tests (``<name>_<output>_correlation``) and the
    residuals' cross-correlation between outputs (``<name>_cross_correlation``).
    """
    directory = Path(directory)
    paths = plot_outputs(reports, names, directory / f"{name}_free_run", "free_run",
                         "coupled model — every output's simulation fed back into all", times)
    paths += plot_outputs(reports, names, directory / f"{name}_one_step", "one_step",
                          times=times)
    for out, rep, model in zip(names, reports, models):
        if rep.tests:
            paths += plot_correlation_tests(
                rep, directory / f"{name}_{out}_correlation",
                title=f"output {out} ({model_label(model)}) — correlation tests "
                      f"({rep.segment} data)")
    if cross_tests:
        paths += plot_correlation_tests(list(cross_tests),
                                        directory / f"{name}_cross_correlation",
                                        title="cross-correlation of the outputs' one-step "
                                              "residuals (lag 0 not checked)")
    return paths
