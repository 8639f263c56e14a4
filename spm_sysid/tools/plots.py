"""Figures (matplotlib, written as PNG and SVG), in the style of the paper's.

* :func:`plot_correlation_tests` -- the correlation tests with their 95 % band
  (paper Fig. 5);
* :func:`plot_prediction` -- predicted and measured output superimposed, the
  error beneath (Figs. 6-7), for one-step or free-run;
* :func:`plot_convergence` -- mean best criterion per generation over runs, one
  line per SPM fraction (Figs. 3-4).

Every function writes ``<stem>.png`` and ``<stem>.svg`` and returns both paths.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.narx.validation import ValidationReport  # noqa: E402

__all__ = ["plot_convergence", "plot_correlation_tests", "plot_prediction", "write_model_figures"]


def _save(fig, stem: Path) -> list[Path]:
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    for p in paths:
        fig.savefig(p, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return paths


def plot_correlation_tests(report: ValidationReport, stem: Path, title: str = "") -> list[Path]:
    """Stem plots of the five correlation tests with the ±1.96/√N band."""
    tests = report.tests
    fig, axes = plt.subplots(len(tests), 1, figsize=(7, 2.0 * len(tests)), sharex=False)
    for ax, t in zip(np.atleast_1d(axes), tests):
        ax.vlines(t.lags, 0, t.values, color="tab:blue", lw=1.2)
        ax.plot(t.lags, t.values, "o", ms=3, color="tab:blue")
        ax.axhline(t.band, ls=":", color="k", lw=1)
        ax.axhline(-t.band, ls=":", color="k", lw=1)
        ax.axhline(0, color="0.6", lw=0.5)
        ax.set_ylim(-1.05, 1.05)
        state = "OK" if t.passed else "outside band"
        ax.set_title(f"{t.label} — {t.fraction_inside:.0%} inside ({state})", fontsize=9)
        ax.set_ylabel("correlation", fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel("lag τ (samples)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, stem)


def plot_prediction(report: ValidationReport, stem: Path, kind: str = "one_step",
                    title: str = "") -> list[Path]:
    """Measured and predicted output superimposed, with the error beneath.

    ``kind``: ``one_step``, ``k_step`` (the report's horizon) or ``free_run``. A
    run that diverged is drawn up to the divergence, marked by a vertical line.
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
    t = np.arange(len(report.measured))
    err = report.measured - pred
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True,
                                   gridspec_kw={"height_ratios": [2, 1]})
    ax1.plot(t, report.measured, color="k", lw=1.0, label="measured")
    ax1.plot(t, pred, color="tab:red", lw=0.9, ls="--", label=label)
    ax1.set_ylabel("output y")
    if m.get("diverged_at") is not None:
        bad = np.flatnonzero(~np.isfinite(pred))
        row = int(bad[0]) if bad.size else len(pred) - 1
        for ax in (ax1, ax2):
            ax.axvline(row, color="tab:red", lw=1.5)
        ax1.annotate(f"diverged at sample {m['diverged_at']}", (row, ax1.get_ylim()[1]),
                     xytext=(-5, -12), textcoords="offset points", ha="right",
                     color="tab:red", fontsize=9)
        summary = f"{label[0].upper() + label[1:]}: DIVERGED at sample {m['diverged_at']}"
    else:
        summary = (f"{label[0].upper() + label[1:]}: max |e| {m['max_abs']:.4g}, "
                   f"mean |e| {m['mean_abs']:.4g}, fit {m['fit_percent']:.1f} %")
    ax1.legend(loc="upper right", fontsize=8)
    ax1.set_title(title or summary, fontsize=9)
    ax2.plot(t, err, color="tab:blue", lw=0.8)
    ax2.set_ylabel("error")
    ax2.set_xlabel("sample")
    fig.tight_layout()
    return _save(fig, stem)


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
    for ax, title in zip(axes.ravel(), panels):
        for s, runs in sorted(curves[title].items()):
            arr = np.asarray(runs, dtype=float)
            mean = np.nanmean(np.where(np.isfinite(arr), arr, np.nan), axis=0)
            ax.plot(np.arange(len(mean)), mean, lw=1.3, label=f"{s:g}")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("generation")
        ax.set_ylabel("mean best criterion")
        ax.legend(title="SPM s", fontsize=8)
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    fig.tight_layout()
    return _save(fig, stem)


def write_model_figures(
    report: ValidationReport, directory: Path, name: str = "model"
) -> list[Path]:
    """The correlation, one-step, k-step (with a horizon) and free-run figures."""
    directory = Path(directory)
    paths = []
    if report.tests:  # not computed after a divergence (report.tests_skipped says why)
        paths += plot_correlation_tests(report, directory / f"{name}_correlation",
                                        title=f"Correlation tests ({report.segment} data)")
    paths += plot_prediction(report, directory / f"{name}_one_step", "one_step")
    if report.k_step is not None:
        paths += plot_prediction(report, directory / f"{name}_k_step", "k_step")
    paths += plot_prediction(report, directory / f"{name}_free_run", "free_run")
    return paths
