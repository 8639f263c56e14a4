"""Identifying many recordings at once: ``spm-sysid batch INPUT... --out DIR``.

Each input (a data file, or a rosbag2 bag directory or ``.mcap`` file) is one
job (:func:`spm_sysid.core.job.run_job`) with the same settings, or with its own
from a YAML file; jobs run on this machine or on a Dask cluster
(:mod:`spm_sysid.tools.runner`). Every input gets a row in the summary
(``summary.csv``, ``summary.md``): samples, terms, criterion value, one-step and
free-run fit, status and seconds, and a model document ``DIR/NAME.json``. A bad
input is a row with status ``error: ...``; it never stops the others.

Per-input settings (YAML): a mapping of input name patterns (``fnmatch`` on the
path as given and on its file name) to settings; ``default`` applies to all::

    default: {criterion: bic}
    "joint2_*.csv": {ny: 6, nu: 6, inputs: "tau,cmd", output: acc}
"""

from __future__ import annotations

import csv
import fnmatch
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from .runner import run_tasks

__all__ = ["BATCH_COLUMNS", "model_names", "run_batch", "settings_for"]

#: The summary table's columns.
BATCH_COLUMNS = ("input", "samples", "terms", "criterion", "value", "one_step_fit",
                 "free_run_fit", "status", "seconds", "model")

#: Data options an input's settings may carry besides the schema's settings.
DATA_KEYS = ("inputs", "output", "input_topic", "input_field", "input_names", "output_topic",
             "output_field")


def settings_for(path: str, base: dict, per_input: dict | None) -> dict:
    """``base`` updated by the YAML's ``default`` and every pattern matching ``path``."""
    values = dict(base)
    per_input = per_input or {}
    values.update(per_input.get("default") or {})
    for pattern, extra in per_input.items():
        if pattern != "default" and (fnmatch.fnmatch(path, pattern)
                                     or fnmatch.fnmatch(Path(path).name, pattern)):
            values.update(extra or {})
    return values


def model_names(inputs: Sequence[str]) -> list[str]:
    """A distinct file stem per input (``take.csv`` -> ``take``; repeats get ``-2``...)."""
    seen: dict[str, int] = {}
    out = []
    for p in inputs:
        stem = Path(p.rstrip("/")).stem or "input"
        seen[stem] = seen.get(stem, 0) + 1
        out.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return out


def _load(path: str, values: dict):
    """u, y, stamps, rejected, unpaired, input names, output name of one input."""
    from ..core.io.bagio import is_rosbag2_dir, read_bag_signals
    from ..core.io.data import load_data

    p = Path(path)
    if p.suffix == ".mcap" or (p.is_dir() and is_rosbag2_dir(p)):
        kw = {k: values[k] for k in ("input_topic", "input_field", "input_names",
                                     "output_topic", "output_field") if values.get(k)}
        sig = read_bag_signals(p, **kw)
        names = sig.input_names if getattr(sig.u, "ndim", 1) == 2 else ()
        return sig.u, sig.y, sig.stamps_ns, sig.rejected_nonfinite, sig.unpaired, names, "y"
    inputs = values.get("inputs")
    if isinstance(inputs, str):
        inputs = [c for c in inputs.split(",") if c]
    d = load_data(p, inputs, values.get("output"))
    return d.u, d.y, None, d.rejected, 0, tuple(d.input_names or ()), d.output_name or "y"


def _identify_one(task: tuple, shared) -> dict:
    """One input: identify, validate, write the model; the summary row."""
    from ..core.files import atomic_write_text
    from ..core.job import JobSettings, run_job

    path, name, values, out_dir = task
    t0 = time.perf_counter()
    u, y, stamps, rejected, unpaired, inputs, output = _load(path, values)
    names = {"inputs": tuple(inputs), "output": output} if inputs else {}
    settings = JobSettings.from_values(values, **names)
    result = run_job(u, y, settings, stamps_ns=stamps, rejected=rejected, unpaired=unpaired,
                     metadata={"source": str(path)})
    model = result.model
    target = Path(out_dir) / f"{name}.json"
    atomic_write_text(target, json.dumps(model.to_dict(), indent=2, allow_nan=False) + "\n")
    report = result.report
    one = free = None
    status = "ok"
    if report is not None:
        one = report.one_step_metrics["fit_percent"]
        f = report.free_run_metrics
        free = f["fit_percent"] if f.get("diverged_at") is None else None
        if f.get("diverged_at") is not None:
            status = f"ok (free-run diverged at sample {f['diverged_at']})"
    return {"input": path, "samples": int(result.data.get("used_samples", len(y))),
            "terms": len(model.terms), "criterion": model.criterion,
            "value": float(model.criterion_value), "one_step_fit": one, "free_run_fit": free,
            "status": status, "seconds": round(time.perf_counter() - t0, 3),
            "model": str(target)}


def run_batch(inputs: Sequence[str], out: str | Path, values: dict, *,
              per_input: dict | None = None, scheduler: str | None = None, workers: int = 0,
              progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Identify every input; write the models and the summary; return the rows in input order.

    ``values`` are settings by schema name (and data options, see
    :data:`DATA_KEYS`); ``per_input`` the YAML mapping (see the module doc).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = model_names(inputs)
    tasks = {str(i): (str(p), n, settings_for(str(p), values, per_input), str(out))
             for i, (p, n) in enumerate(zip(inputs, names))}
    count = [0]

    def on_done(outcome) -> None:
        count[0] += 1
        if progress:
            progress(count[0], len(tasks))

    outcomes = run_tasks(_identify_one, tasks, scheduler=scheduler, workers=workers,
                         retries=0, on_done=on_done)
    rows = []
    for key, (path, _, _, _) in tasks.items():
        o = outcomes[key]
        if o.ok:
            rows.append(o.result)
        else:
            rows.append({"input": path, "samples": None, "terms": None, "criterion": None,
                         "value": None, "one_step_fit": None, "free_run_fit": None,
                         "status": f"error: {o.error}", "seconds": None, "model": None})
    write_summary(rows, out)
    return rows


def write_summary(rows: Sequence[dict], out: Path) -> list[Path]:
    """``summary.csv`` and ``summary.md`` in ``out``."""
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=BATCH_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow(r)
    (out / "summary.md").write_text(summary_table(rows))
    return [out / "summary.csv", out / "summary.md"]


def summary_table(rows: Sequence[dict]) -> str:
    """The rows as a Markdown table."""
    def fmt(v, spec=""):
        return "—" if v is None else format(v, spec)

    lines = ["| input | samples | terms | criterion | value | one-step fit % | "
             "free-run fit % | status | s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['input']} | {fmt(r['samples'])} | {fmt(r['terms'])} | "
                     f"{(r['criterion'] or '—').upper()} | {fmt(r['value'], '.2f')} | "
                     f"{fmt(r['one_step_fit'], '.1f')} | {fmt(r['free_run_fit'], '.1f')} | "
                     f"{r['status']} | {fmt(r['seconds'], '.2f')} |")
    return "\n".join(lines) + "\n"
