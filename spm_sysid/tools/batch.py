"""Identifying many recordings at once: ``spm-sysid batch INPUT... --out DIR``.

Each input (a data file, or a rosbag2 bag directory or ``.mcap`` file) is one
job (:func:`spm_sysid.core.jobs.run_job`) with the same settings, or with its own
from a YAML file; jobs run on this machine or on a Dask cluster
(:mod:`spm_sysid.tools.runner`). Every input gets a row in the summary
(``summary.csv``, ``summary.md``): samples, terms, criterion value, one-step and
free-run fit, status and seconds, and a model document ``DIR/NAME.json``. A bad
input is a row with status ``error: ...``; it never stops the others.

Per-input settings (YAML): a mapping of input name patterns (``fnmatch`` on the
path as given and on its file name) to settings; ``default`` applies to all::

    default: {criterion: bic}
    "joint2_*.csv": {ny: 6, nu: 6, inputs: "tau,cmd", output: acc}

Every key is checked before any work (a misspelled setting is an error naming
it, never silently ignored), and so is every input's resulting settings.

Models are written by this process (the client), whatever runs the jobs: a Dask
worker on another machine sends the model document back with its summary row,
so the files land in ``DIR`` here. Each input gets a distinct file name (``x``,
``x-2``, ... never one taken, compared case-insensitively). A batch writes over
nothing but an earlier batch's own files (listed in its manifest,
:data:`MANIFEST`), and those only with ``force``; never over an input, never
over a file it did not write (:func:`check_destinations`).
"""

from __future__ import annotations

import csv
import fnmatch
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from .runner import run_tasks

__all__ = ["BATCH_COLUMNS", "MANIFEST", "check_destinations", "check_per_input", "model_names",
           "run_batch", "settings_for"]

#: The summary table's columns.
BATCH_COLUMNS = ("input", "samples", "terms", "criterion", "value", "one_step_fit",
                 "free_run_fit", "status", "seconds", "model")

#: The list of the files a batch wrote in its folder (what a later batch may replace).
MANIFEST = ".spm_sysid_batch.json"
SUMMARY_FILES = ("summary.csv", "summary.md")

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


def check_per_input(per_input, source: str = "--settings") -> dict:
    """Check a per-input settings mapping (see the module doc); returns it.

    Raises
    ------
    SettingsError
        Not a mapping of text patterns to mappings, or an unknown setting (named,
        with the closest known name).
    """
    import difflib

    from ..core.errors import SettingsError
    from ..core.settings import JOB_GROUPS, SETTINGS

    known = sorted([n for n, st in SETTINGS.items() if st.group in JOB_GROUPS]
                   + list(DATA_KEYS))
    if per_input is None:
        return {}
    if not isinstance(per_input, dict):
        raise SettingsError(f"{source}: expected a mapping of input patterns to settings, "
                            f"got {type(per_input).__name__}")
    for pattern, values in per_input.items():
        if not isinstance(pattern, str):
            raise SettingsError(f"{source}: the pattern {pattern!r} must be text (quote it)")
        if values is None:
            continue
        if not isinstance(values, dict):
            raise SettingsError(f"{source}: {pattern!r} must map to settings (name: value), "
                                f"got {values!r}")
        for name in values:
            if name not in known:
                close = difflib.get_close_matches(str(name), known, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise SettingsError(f"{source}: {pattern!r}: unknown setting {name!r}{hint}")
    return per_input


def model_names(inputs: Sequence[str]) -> list[str]:
    """A distinct file stem per input: ``take.csv`` -> ``take``; a taken name gets -2, -3...

    Names are compared case-insensitively (two files may not differ by case
    alone on every file system), and a suffixed name never takes one that
    another input has by its own stem (``a/x.csv``, ``c/x.csv``, ``x-2.csv``).
    """
    stems = [Path(p.rstrip("/")).stem or "input" for p in inputs]
    taken = {s.lower() for s in stems}
    used: set[str] = set()
    out = []
    for stem in stems:
        name, k = stem, 1
        while name.lower() in used or (name != stem and name.lower() in taken):
            k += 1
            name = f"{stem}-{k}"
        used.add(name.lower())
        out.append(name)
    return out


def _identify_one(task: tuple, shared) -> tuple[dict, dict]:
    """One input: identify and validate; its summary row and model document."""
    from ..core.jobs import JobSettings, run_job
    from ..core.record import DataSpec, load_record

    path, name, values, model_path = task
    t0 = time.perf_counter()
    record = load_record(DataSpec.for_path(path, values))
    result = run_job(record, JobSettings.from_values(values))
    if record.n_outputs > 1:
        return _several_row(path, record, result, t0, model_path)
    model = result.model
    report = result.report
    one = free = None
    status = "ok"
    if report is not None:
        one = report.one_step_metrics["fit_percent"]
        f = report.free_run_metrics
        free = f["fit_percent"] if f.get("diverged_at") is None else None
        if f.get("diverged_at") is not None:
            status = f"ok (free-run diverged at sample {f['diverged_at']})"
    row = {"input": path, "samples": int(result.data.get("used_samples", len(record))),
           "terms": len(model.terms), "criterion": model.criterion,
           "value": float(model.criterion_value), "one_step_fit": one, "free_run_fit": free,
           "status": status, "seconds": round(time.perf_counter() - t0, 3),
           "model": model_path}
    return row, model.to_dict()


def _several_row(path: str, record, result, t0: float, model_path) -> tuple[dict, dict]:
    """The summary row of a coupled model of several outputs: totals, worst fits."""
    reports = [r.report for r in result.outputs]
    one = free = None
    if all(r is not None for r in reports):
        one = min(r.one_step_metrics["fit_percent"] for r in reports)
        frees = [r.free_run_metrics["fit_percent"] for r in reports]
        free = None if result.diverged else min(frees)
    status = (f"ok ({record.n_outputs} outputs {', '.join(record.output_names)}; fits are "
              "the worst output's, free run coupled)")
    if result.diverged:
        status += f"; coupled free run diverged for {', '.join(result.diverged)}"
    row = {"input": path, "samples": int(result.data.get("used_samples", len(record))),
           "terms": sum(len(r.model.terms) for r in result.outputs),
           "criterion": result.outputs[0].model.criterion,
           "value": result.criterion_value, "one_step_fit": one, "free_run_fit": free,
           "status": status, "seconds": round(time.perf_counter() - t0, 3),
           "model": model_path}
    return row, result.model.to_dict()


def run_batch(inputs: Sequence[str], out: str | Path, values: dict, *,
              per_input: dict | None = None, scheduler: str | None = None, workers: int = 0,
              progress: Callable[[int, int], None] | None = None,
              force: bool = False, note: Callable[[str], None] | None = None) -> list[dict]:
    """Identify every input; write the models and the summary; return the rows in input order.

    ``values`` are settings by schema name (and data options, see
    :data:`DATA_KEYS`); ``per_input`` the YAML mapping (see the module doc).
    ``note`` is told what the user should know beside the rows (an earlier
    batch's model files removed because this one did not write them again).
    A model that cannot be written makes its input's row an error; the others go on.

    Raises
    ------
    FileExistsError
        A file would be written over an input or a file no batch wrote, or over
        an earlier batch's files without ``force`` (:func:`check_destinations`).
    SettingsError
        A per-input setting that is unknown or invalid (before any work).
    """
    from ..core.files import atomic_write_text, document_json

    out = Path(out)
    names = model_names(inputs)
    tasks = _tasks(inputs, names, out, values, check_per_input(per_input))
    own = check_destinations(out, inputs, [out / f"{n}.json" for n in names], force)
    out.mkdir(parents=True, exist_ok=True)
    count = [0]
    failed_writes: dict[str, str] = {}

    def on_done(outcome) -> None:
        if outcome.ok:  # the model lands here, wherever the job ran
            row, doc = outcome.result
            try:  # a link in OUT is replaced by the file, never written through
                atomic_write_text(row["model"], document_json(doc) + "\n", follow_links=False)
            except (OSError, ValueError) as exc:
                failed_writes[row["model"]] = f"the model could not be written ({exc})"
        count[0] += 1
        if progress:
            progress(count[0], len(tasks))

    outcomes = run_tasks(_identify_one, tasks, scheduler=scheduler, workers=workers,
                         retries=0, on_done=on_done)
    rows = [_row(path, outcomes[key], failed_writes) for key, (path, _, _, _) in tasks.items()]
    written = {Path(r["model"]).name for r in rows if r.get("model")} | set(SUMMARY_FILES)
    stale = remove_stale(out, own - written - {MANIFEST})
    write_summary(rows, out)
    atomic_write_text(out / MANIFEST, json.dumps(
        {"written_by": "spm-sysid batch", "files": sorted(written)}, indent=2) + "\n",
        follow_links=False)
    if stale and note:
        note(f"removed {len(stale)} model file(s) of the earlier batch in {out} that this "
             f"one did not write again: {', '.join(stale)}")
    return rows


def _tasks(inputs: Sequence[str], names: list[str], out: Path, values: dict,
           per_input: dict) -> dict[str, tuple]:
    """One task per input: (path, name, settings, model file); every input's settings checked."""
    from ..core.jobs import JobSettings

    tasks = {}
    for i, (p, n) in enumerate(zip(inputs, names)):
        v = settings_for(str(p), values, per_input)
        JobSettings.from_values(v)  # every input's settings checked before any work
        tasks[str(i)] = (str(p), n, v, str(out / f"{n}.json"))
    return tasks


def _row(path: str, outcome, failed_writes: dict[str, str]) -> dict:
    """The summary row of one input: its job's, or an error row saying why."""
    if outcome.ok and outcome.result[0]["model"] not in failed_writes:
        return outcome.result[0]
    error = outcome.error if not outcome.ok else failed_writes[outcome.result[0]["model"]]
    return {"input": path, "samples": None, "terms": None, "criterion": None,
            "value": None, "one_step_fit": None, "free_run_fit": None,
            "status": f"error: {error}", "seconds": None, "model": None}


def remove_stale(out: Path, names: set[str]) -> list[str]:
    """Remove an earlier batch's model files that this batch did not write again.

    A summary must not stand beside models it does not list. Only names the
    earlier batch's manifest lists are removed (never anything else), and a link
    is removed, not what it names. Returns the names removed.
    """
    removed = []
    for name in sorted(names):
        p = out / name
        if p.is_symlink() or p.is_file():
            p.unlink()
            removed.append(name)
    return removed


def _earlier_files(out: Path) -> set[str]:
    """Names of the files in ``out`` that an earlier batch wrote (from its manifest).

    A folder from a version before the manifest is recognised by its
    ``summary.csv`` (the batch's columns): that summary, ``summary.md`` and the
    models its rows name.
    """
    manifest = out / MANIFEST
    if manifest.is_file():
        try:
            doc = json.loads(manifest.read_text())
            if doc.get("written_by") == "spm-sysid batch":
                return {Path(str(f)).name for f in doc["files"]} | {MANIFEST}
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            pass
        return set()
    try:
        with open(out / "summary.csv", newline="") as f:
            reader = csv.DictReader(f)
            if tuple(reader.fieldnames or ()) != BATCH_COLUMNS:
                return set()
            models = {Path(r["model"]).name for r in reader if r.get("model")}
    except (OSError, UnicodeDecodeError, csv.Error):
        return set()
    return set(SUMMARY_FILES) | models


def check_destinations(out: Path, inputs: Sequence[str], models: Sequence[Path],
                       force: bool) -> set[str]:
    """Refuse to write over an input or a file no batch wrote; the earlier batch's files.

    A batch writes its models, ``summary.csv``, ``summary.md`` and a manifest
    (:data:`MANIFEST`, the files it wrote). It never writes over one of its
    inputs (with or without ``force``), never over a file that an earlier batch
    did not write, and over an earlier batch's files only with ``force``.

    Raises
    ------
    FileExistsError
        Naming the file and why (nothing is changed).
    """
    from ..core.files import same_file

    own = _earlier_files(out) if out.is_dir() else set()
    planned = [*models, out / "summary.csv", out / "summary.md", out / MANIFEST]
    for dest in planned:
        for source in inputs:
            if same_file(dest, source) or (Path(source).is_dir()
                                           and same_file(dest.parent, source)):
                raise FileExistsError(
                    f"{dest} would be written, and it is one of the inputs ({source}); choose "
                    "another --out (nothing was changed)")
    clash = [d for d in planned if d.exists() or d.is_symlink()]
    foreign = [d for d in clash if d.name not in own]
    if foreign:
        raise FileExistsError(
            f"{foreign[0]} exists and no earlier batch wrote it; a batch writes over its own "
            "files only: move it, or choose another --out (nothing was changed)")
    if clash and not force:
        raise FileExistsError(
            f"{out} holds an earlier batch ({', '.join(d.name for d in clash[:3])}"
            f"{' ...' if len(clash) > 3 else ''}); choose another --out, or --force to "
            "replace its files (nothing was changed)")
    return own


def write_summary(rows: Sequence[dict], out: Path) -> list[Path]:
    """``summary.csv`` and ``summary.md`` in ``out`` (regular files: a link there is replaced)."""
    import io

    from ..core.files import atomic_write_text

    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=BATCH_COLUMNS)
    w.writeheader()
    for r in rows:
        w.writerow(r)
    atomic_write_text(out / "summary.csv", text.getvalue(), follow_links=False)
    atomic_write_text(out / "summary.md", summary_table(rows), follow_links=False)
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
