"""Commands of many runs: ``experiment`` (the paper's study) and ``batch`` (many inputs)."""

from __future__ import annotations

import sys
from pathlib import Path

from ...core.settings import SETTINGS
from .common import (
    UserError,
    add_column_options,
    add_data_options,
    add_schema_options,
    job_settings,
    load,
    read_yaml,
    seed_type,
)
from .progress import count_bar

__all__ = ["add_parsers"]


def _list(text: str | None, kind):
    if text is None:
        return None
    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"cannot read {text!r} as a comma-separated list") from None


# -- experiment -------------------------------------------------------------------------------

#: Job settings the study takes from the command line (the grid has its own options).
STUDY_SETTINGS = ("term_space", "ga")
GRID_SETTINGS = ("population_size", "spm_fraction")


def cmd_experiment(args) -> int:
    """``spm-sysid experiment``: the study grid on one record, summarised (and its report)."""
    import time

    from ..experiment import summarise, summary_table, write_results

    config = _study_config(args)
    record = load(args)
    info = record.segment_info()
    if info.gaps or len(info.bounds) > 1:
        raise UserError(f"{record.source} has gaps; the study needs one contiguous record")
    if config.decimate > 1:  # a study's config may ask for it as a job's settings do
        record = record.decimated(config.decimate)
        print(f"note: {record.notes[-1]}")
    n_runs = (len(config.criteria) * len(config.populations) * len(config.spm_fractions)
              * config.runs)
    print(f"study: {n_runs} runs on {record.source}, {len(record.y)} samples")
    t0 = time.perf_counter()
    records = _run_study(args, record, config, n_runs)
    elapsed = time.perf_counter() - t0
    if records.resumed:
        print(f"resumed: {records.resumed} run(s) were already done and were not run again")
    rows = summarise(records)
    if records:
        write_results(records, rows, config, args.out)
        print(summary_table(rows))
    done_here = f" ({records.resumed} from the earlier session)" if records.resumed else ""
    print(f"{len(records)} of {n_runs} runs{done_here} in {elapsed:.1f} s; per-run records "
          f"and figure in {args.out}")
    if records.failures:
        _report_failures(records.failures, Path(args.out))
        return 1
    if args.report:
        from ..report import write_study_report

        path = write_study_report(records, rows, config, args.out, args.report, elapsed,
                                  record.source, records.resumed)
        print(f"report written to {path}")
    return 0


def _study_config(args):
    """The study's settings: the options given, over ``--config`` when one is given."""
    from ...core.errors import SettingsError
    from ..experiment import ExperimentConfig

    overrides = {k: getattr(args, k) for k, s in SETTINGS.items()
                 if s.group in STUDY_SETTINGS and s.cli and k not in GRID_SETTINGS}
    overrides.update(criteria=_list(args.criteria, str), populations=_list(args.populations, int),
                     spm_fractions=_list(args.spm_fractions, float), runs=args.runs,
                     seed=args.seed, workers=args.workers, focus=args.focus,
                     shortlist=args.shortlist,
                     certify_reference=False if args.no_certify else None,
                     certify_time_limit=args.certify_time_limit)
    try:
        if args.config:
            return ExperimentConfig.from_mapping(read_yaml(args.config, "--config"),
                                                 f"--config {args.config}", **overrides)
        return ExperimentConfig(**{k: v for k, v in overrides.items() if v is not None})
    except TypeError as exc:
        raise UserError(f"bad experiment settings: {exc}") from None
    except SettingsError as exc:
        raise UserError(str(exc)) from None


def _run_study(args, record, config, n_runs: int):
    """The runs (here or on the Dask cluster), with a bar; an interruption keeps what finished."""
    from ..experiment import run_experiment

    bar = count_bar(n_runs, "runs", "run", not args.quiet)

    def tick(i, n):
        if bar:
            bar.n = i
            bar.refresh()

    partial = Path(args.out) / "runs.partial.jsonl"
    if args.force and not args.resume and partial.exists():
        old = sum(1 for _ in open(partial))
        partial.unlink()
        print(f"note: --force: the {old} run(s) of the earlier study in {args.out} are "
              "discarded")
    where = f"the Dask cluster at {args.scheduler}" if args.scheduler else "this machine"
    print(f"running on {where}" + ("; resuming" if args.resume else ""))
    try:
        return run_experiment(record.u, record.y, config, progress=tick,
                              scheduler=args.scheduler, out=args.out, resume=args.resume)
    except (FileExistsError, OSError, ValueError, RuntimeError) as exc:
        raise UserError(str(exc)) from None
    except KeyboardInterrupt:
        kept = sum(1 for _ in open(partial)) if partial.exists() else 0
        print(f"interrupted: {kept} finished run(s) kept in {partial}; continue with "
              "--resume", file=sys.stderr)
        raise
    finally:
        if bar:
            bar.close()


def _report_failures(failures, out: Path) -> None:
    """Each failed run on stderr and in OUT/failures.json, then one error line."""
    import json

    for f in failures:
        print(f"run {f.key} FAILED after {f.attempts} attempt(s): {f.error}", file=sys.stderr)
    (out / "failures.json").write_text(json.dumps(
        [{"run": f.key, "error": f.error, "attempts": f.attempts} for f in failures], indent=1))
    print(f"error: {len(failures)} run(s) failed (listed above and in "
          f"{out / 'failures.json'}); the summary covers the others; "
          "--resume runs only what is missing", file=sys.stderr)


# -- batch -------------------------------------------------------------------------------------


def cmd_batch(args) -> int:
    from ...core.record import BAG_OPTIONS
    from ..batch import check_per_input, run_batch, summary_table

    per_input = None
    if args.settings:
        per_input = check_per_input(read_yaml(args.settings, "--settings"),
                                    f"--settings {args.settings}")
    values = {k: v for k, v in vars(args).items() if v is not None and k in SETTINGS}
    for k in BAG_OPTIONS:
        if getattr(args, k, None):
            values[k] = getattr(args, k)
    if args.inputs:
        values["inputs"] = ",".join(args.inputs)
    if args.output_column:
        values["output"] = args.output_column
    job_settings(_Namespace(values))  # settings errors before any work
    bar = count_bar(len(args.input), "inputs", "input", not args.quiet)
    where = f"the Dask cluster at {args.scheduler}" if args.scheduler else "this machine"
    print(f"batch: {len(args.input)} input(s) on {where}; models and summary in {args.out}")
    try:
        rows = run_batch(args.input, args.out, values, per_input=per_input,
                         scheduler=args.scheduler, workers=args.workers or 0,
                         progress=(lambda i, n: bar.update(1)) if bar else None,
                         force=args.force, note=lambda text: print(f"note: {text}"))
    except (OSError, RuntimeError) as exc:
        raise UserError(str(exc)) from None
    finally:
        if bar:
            bar.close()
    print(summary_table(rows), end="")
    failed = [r for r in rows if r["status"].startswith("error")]
    print(f"{len(rows) - len(failed)} of {len(rows)} input(s) identified; summary in "
          f"{Path(args.out) / 'summary.csv'}")
    if failed:
        print(f"error: {len(failed)} input(s) failed (status in the summary): "
              + ", ".join(r["input"] for r in failed), file=sys.stderr)
        return 1
    return 0


class _Namespace:
    """Settings values as attributes, for :func:`job_settings`."""

    def __init__(self, values: dict) -> None:
        self.__dict__.update(values)


# -- the parsers -----------------------------------------------------------------------------


def add_parsers(sub) -> None:
    """Register ``experiment`` and ``batch``."""
    _add_batch_parser(sub)
    _add_experiment_parser(sub)


def _add_batch_parser(sub) -> None:
    """``batch``: many inputs, one model each."""
    from ...core.record import BAG_OPTIONS

    p = sub.add_parser("batch", help="identify many data files and bags (here or on a Dask "
                       "cluster): one model each and a summary table")
    p.add_argument("input", nargs="+", metavar="INPUT",
                   help="data files, rosbag2 bag directories or .mcap files")
    p.add_argument("--out", metavar="DIR", required=True, help="models and summary go here")
    p.add_argument("--settings", metavar="YAML",
                   help="per-input settings: input patterns -> settings (see docs)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on this Dask cluster (tcp://HOST:PORT); default: this machine")
    p.add_argument("--workers", type=int, help="local processes (default: one per core)")
    p.add_argument("--force", action="store_true",
                   help="replace the files of an earlier batch in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    g = p.add_argument_group("data options (each input)")
    add_column_options(g)
    for name in BAG_OPTIONS:
        g.add_argument(SETTINGS[name].option, dest=name, default=None,
                       help=f"bags: {SETTINGS[name].help}")
    add_schema_options(p, ("term_space", "ga", "criterion", "validation", "data"))
    p.set_defaults(func=cmd_batch)


def _add_experiment_parser(sub) -> None:
    """``experiment``: the paper's study grid."""
    p = sub.add_parser("experiment", help="the paper's study: SPM vs plain GA, repeated runs")
    add_data_options(p, bag=False)
    p.add_argument("--config", metavar="YAML", help="settings file (options below override)")
    g = p.add_argument_group("the grid")
    g.add_argument("--criteria", help="comma-separated (default aic,bic,pmic2)")
    g.add_argument("--populations", help="comma-separated (default 200,100)")
    g.add_argument("--spm-fractions", "--spm", dest="spm_fractions",
                   help="comma-separated SPM fractions (default 0,0.15)")
    g.add_argument("--runs", type=int, help="runs per setting (default 15)")
    g.add_argument("--seed", type=seed_type, help="first seed (default 0)")
    add_schema_options(p, STUDY_SETTINGS, exclude=GRID_SETTINGS)
    g = p.add_argument_group("selection and the reference")
    for name in ("focus", "shortlist", "certify_time_limit"):
        s = SETTINGS[name]
        if s.choices:
            g.add_argument(s.option, dest=name, choices=s.choices, help=s.help)
        else:
            from .common import schema_type

            g.add_argument(s.option, dest=name, type=schema_type(name), help=s.help)
    g.add_argument("--no-certify", action="store_true",
                   help="count runs reaching the best found, without proving it optimal "
                        "(certify_reference false)")
    g = p.add_argument_group("running")
    g.add_argument("--workers", type=int, help="processes (default: one per core)")
    g.add_argument("--out", metavar="DIR", default="out/experiment")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on this Dask cluster (tcp://HOST:PORT; needs the dask extra); "
                        "default: this machine")
    g.add_argument("--resume", action="store_true",
                   help="continue the interrupted study in --out: only missing runs are run")
    g.add_argument("--force", action="store_true",
                   help="start over in an --out that holds an earlier study's runs")
    g.add_argument("--report", metavar="DIR", help="write a Markdown report here")
    g.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_experiment)
