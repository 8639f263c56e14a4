"""The study's results: a run's record, the per-setting summary and the files written.

Per setting the summary counts the runs that *reached the best*: whose final
structure equals the reference structure of that criterion (the certified
optimum where there is one, else the best found across all runs), as the paper
does. Fisher's exact test (scipy, two-sided) compares each fraction's reach
count with that of s = 0 at the same criterion and population.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["RunRecord", "SettingSummary", "StudyRecords", "mark_reached", "summarise",
           "summary_table", "write_results"]


@dataclass
class RunRecord:
    """One GA run of the study."""

    criterion: str
    population_size: int
    spm_fraction: float
    run: int
    seed: int
    final_value: float
    terms: list[str]
    n_terms: int
    first_best_generation: int
    seconds: float
    evaluations: int
    best_curve: list[float] = field(repr=False, default_factory=list)
    reached_best: bool = False
    focus: str = "prediction"
    free_run_fit: float | None = None  # percent on the data; None when it diverged
    reference: str = "best found across runs"  # or "certified optimum"


class StudyRecords(list):
    """The study's records (a list, in task order) and the runs that failed."""

    failures: list
    resumed: int = 0


def mark_reached(records: Sequence[RunRecord], optima: dict[str, dict] | None = None
                 ) -> dict[str, tuple[float, list[str], str]]:
    """Flag runs whose final structure is their criterion's reference structure.

    The reference is the certified optimum where ``optima`` has one (status
    ``optimal``), else the best structure found across the runs. Returns
    criterion -> (value, terms, what the reference is).
    """
    best: dict[str, tuple[float, list[str], str]] = {}
    for r in records:
        if r.criterion not in best or r.final_value < best[r.criterion][0]:
            best[r.criterion] = (r.final_value, r.terms, "best found across runs")
    for crit, doc in (optima or {}).items():
        if doc.get("status") == "optimal":
            best[crit] = (doc["value"], doc["terms"], "certified optimum")
    for r in records:
        value, terms, label = best[r.criterion]
        r.reached_best = sorted(r.terms) == sorted(terms)
        r.reference = label
    return best


# -- summary ---------------------------------------------------------------------------


@dataclass
class SettingSummary:
    """One row of the study's table."""

    criterion: str
    population_size: int
    spm_fraction: float
    runs: int
    reached: int
    mean_final: float
    best_final: float
    mean_generation_to_best: float
    mean_seconds: float
    fisher_p: float | None  # against s = 0 at the same criterion and population
    mean_free_run_fit: float | None = None  # percent, over runs that did not diverge
    diverged: int = 0
    reference: str = "best found across runs"


def summarise(records: Sequence[RunRecord]) -> list[SettingSummary]:
    """The per-setting table, with Fisher's exact test against s = 0."""
    from scipy.stats import fisher_exact

    groups: dict[tuple, list[RunRecord]] = defaultdict(list)
    for r in records:
        groups[(r.criterion, r.population_size, r.spm_fraction)].append(r)
    rows = []
    for (crit, pop, s), runs in groups.items():
        reached = sum(r.reached_best for r in runs)
        base = groups.get((crit, pop, 0.0))
        p = None
        if base is not None and s != 0.0:
            b = sum(r.reached_best for r in base)
            p = float(fisher_exact([[reached, len(runs) - reached], [b, len(base) - b]])[1])
        rows.append(SettingSummary(
            criterion=crit, population_size=pop, spm_fraction=s, runs=len(runs), reached=reached,
            mean_final=float(np.mean([r.final_value for r in runs])),
            best_final=float(np.min([r.final_value for r in runs])),
            mean_generation_to_best=float(np.mean([r.first_best_generation for r in runs])),
            mean_seconds=float(np.mean([r.seconds for r in runs])),
            fisher_p=p,
            mean_free_run_fit=_mean([r.free_run_fit for r in runs if r.free_run_fit is not None]),
            diverged=sum(r.free_run_fit is None for r in runs),
            reference=runs[0].reference,
        ))
    return rows


def _mean(values: list) -> float | None:
    return float(np.mean(values)) if values else None


def summary_table(rows: Sequence[SettingSummary]) -> str:
    """The summary as a Markdown table (free-run fit: mean over runs that did not diverge)."""
    head = ("| criterion | population | SPM s | reached | reference | mean final | best final | "
            "mean free-run fit | mean gen. to best | mean s/run | Fisher p vs s=0 |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r.criterion.upper()} | {r.population_size} | {r.spm_fraction:g} | "
        f"{r.reached}/{r.runs} | {r.reference} | "
        f"{r.mean_final:.2f} | {r.best_final:.2f} | {_fit(r)} | "
        f"{r.mean_generation_to_best:.1f} | "
        f"{r.mean_seconds:.2f} | {'—' if r.fisher_p is None else f'{r.fisher_p:.3g}'} |\n"
        for r in rows
    )
    return head + body


def _fit(r: SettingSummary) -> str:
    text = "—" if r.mean_free_run_fit is None else f"{r.mean_free_run_fit:.1f} %"
    return text + (f" ({r.diverged} diverged)" if r.diverged else "")


def write_results(records: Sequence[RunRecord], rows: Sequence[SettingSummary],
                  config, out: Path) -> list[Path]:
    """runs.csv, runs.json (with convergence curves), summary.csv, summary.md, figure.

    ``config`` is the study's :class:`~spm_sysid.tools.experiment.ExperimentConfig`.
    """
    from .plots import plot_convergence

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fields = [f for f in RunRecord.__dataclass_fields__ if f != "best_curve"]
    with open(out / "runs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in records:
            row = {k: v for k, v in asdict(r).items() if k in fields}
            row["terms"] = " + ".join(r.terms)
            w.writerow(row)
    (out / "runs.json").write_text(json.dumps(
        {"config": config.to_dict(), "runs": [asdict(r) for r in records]}, indent=1))
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(SettingSummary.__dataclass_fields__))
        w.writeheader()
        for row in rows:
            w.writerow(asdict(row))
    (out / "summary.md").write_text(summary_table(rows))
    curves: dict[str, dict[float, list]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        key = f"{r.criterion.upper()}, population {r.population_size}"
        curves[key][r.spm_fraction].append(r.best_curve)
    figs = plot_convergence(curves, out / "convergence")
    return [out / "runs.csv", out / "runs.json", out / "summary.csv", out / "summary.md", *figs]
