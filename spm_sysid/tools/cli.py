"""The ``spm-sysid`` command line.

Sub-commands: ``identify`` (the main offline job), ``validate``, ``experiment``,
``make-bag``, ``bench`` and ``fetch-data``; :mod:`spm_sysid.apps.main` adds
``call`` (a service client for the ROS node). Options of the job's settings come
from the settings schema (:mod:`spm_sysid.core.settings`). Every failure a user
can cause ends with one ``error: ...`` line and exit status 2, never a traceback.
"""

from __future__ import annotations

import os

# Our matrices are small: one BLAS thread per process is fastest, and the experiment
# runner uses one process per core. Set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from ..core.errors import DataError, SettingsError  # noqa: E402
from ..core.files import check_writable_dir, check_writable_file  # noqa: E402
from ..core.io.data import load_data, load_io  # noqa: E402
from ..core.io.datasets import find_robot_arm  # noqa: E402
from ..core.narx.terms import TermSpace  # noqa: E402
from ..core.settings import SETTINGS, check  # noqa: E402

__all__ = ["main"]


class UserError(Exception):
    """A problem the user can fix; printed without a traceback."""


# -- shared options -------------------------------------------------------------------


def _add_data_options(p: argparse.ArgumentParser, bag: bool = True) -> None:
    g = p.add_argument_group("data (default: the robot-arm data)")
    g.add_argument("--data", metavar="PATH", action="append",
                   help="two-column or CSV file of u, y; give it several times for several "
                        "records (no regression row crosses from one to the next)")
    if bag:
        g.add_argument("--bag", metavar="PATH", help="rosbag2 bag (MCAP) to read u, y from")
        g.add_argument("--inputs", metavar="NAMES", type=lambda t: [c for c in t.split(",") if c],
                       help="input columns of --data files, by header name or 0-based index "
                            "(comma-separated; several inputs make a MISO model)")
        g.add_argument("--output", dest="output_column", metavar="NAME",
                       help="output column of --data files (default: 'y', else the last)")
        for name in ("input_topic", "input_field", "input_names", "output_topic",
                     "output_field"):
            s = SETTINGS[name]
            g.add_argument(s.option, dest=name, default=s.default or None,
                           help=f"{s.help} (default {s.default!r})")


PER_INPUT = ("nu", "delay")  # one value for all inputs, or a comma list: one per input


def _schema_type(name: str):
    """An argparse type that checks a value against the settings schema."""
    setting = SETTINGS[name]

    def convert(text: str):
        if name in PER_INPUT and "," in text:
            return tuple(convert(part) for part in text.split(","))
        try:
            value = setting.kind(text) if setting.kind is not bool else text
        except ValueError:
            kind = {int: "an integer", float: "a number"}.get(setting.kind, "text")
            raise argparse.ArgumentTypeError(f"must be {kind}, got {text!r}") from None
        try:
            return check(name, value)
        except SettingsError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = setting.kind.__name__
    return convert


def add_schema_options(p: argparse.ArgumentParser, groups: tuple[str, ...],
                       titles: dict[str, str]) -> None:
    """Options for every command-line setting of ``groups``, from the schema.

    The option is ``--`` + the setting's name with dashes; older spellings are
    aliases; the default and the allowed values come from the schema.
    """
    for group in groups:
        g = p.add_argument_group(titles.get(group, group))
        for s in SETTINGS.values():
            if s.group != group or not s.cli:
                continue
            names = [s.option, *s.aliases]
            rng = s.describe_range()
            text = f"{s.help} (default {s.default!r}{'; ' + rng if rng else ''})"
            # default None: "not given" (the schema's default applies in JobSettings)
            if s.kind is bool:
                g.add_argument(*names, dest=s.name, action="store_true", default=None,
                               help=f"{s.help}")
            elif s.choices:
                g.add_argument(*names, dest=s.name, choices=s.choices, help=text)
            else:
                g.add_argument(*names, dest=s.name, type=_schema_type(s.name),
                               metavar=s.kind.__name__.upper(), help=text)


JOB_TITLES = {
    "term_space": "term space (default: the paper's)",
    "ga": "genetic algorithm (default: the paper's settings)",
    "criterion": "criterion and seed",
    "validation": "validation",
}


def _job_settings(args, data=None):
    """Checked job settings; with ``data``, the signals are named (and counted) from it."""
    from ..core.job import JobSettings

    names = {} if data is None or not data.input_names else {
        "inputs": data.input_names, "output": data.output_name}
    try:
        return JobSettings.from_values(vars(args), **names)
    except (TypeError, ValueError) as exc:
        raise UserError(str(exc)) from None


@dataclass
class Loaded:
    """Data for a command: samples, where from, and how they split into segments.

    Several records (``--data`` given several times) are concatenated; each keeps
    its own segments, and no regression row crosses from one record to the next.
    """

    u: np.ndarray
    y: np.ndarray
    source: str
    stamps_ns: np.ndarray | None = None
    rejected: int = 0
    unpaired: int = 0
    info: object = None  # a SegmentInfo when the records were combined
    records: list = None  # [{"source", "samples"}] for data files
    input_names: tuple = ()
    output_name: str = "y"

    def segment_info(self):
        """The contiguous segments (:class:`~spm_sysid.core.narx.segments.SegmentInfo`)."""
        from ..core.narx.segments import SegmentInfo, find_segments

        if self.info is not None:
            return self.info
        if self.stamps_ns is None:
            return SegmentInfo([(0, len(self.y))])
        return find_segments(self.stamps_ns)

    def segments(self, max_lag: int) -> tuple[list[tuple[int, int]] | None, dict]:
        """Usable segments (None: one whole record) and the account of the data."""
        from ..core.narx.segments import segment_report

        info = self.segment_info()
        bounds, data = segment_report(info, max_lag, self.rejected, self.unpaired)
        if not bounds:
            raise UserError(f"{self.source}: no contiguous segment is longer than the largest "
                            f"lag ({max_lag}); {len(self.y)} samples in {len(info.bounds)} "
                            f"segment(s)")
        whole = len(bounds) == 1 and bounds[0] == (0, len(self.y))
        return (None if whole else bounds), data


def _load_file(path: str, inputs=None, output=None) -> Loaded:
    d = load_data(path, inputs, output)
    stamps = None if d.t is None else np.round(d.t * 1e9).astype(np.int64)
    return Loaded(d.u, d.y, path, stamps, d.rejected,
                  records=[{"source": path, "samples": int(len(d.y))}],
                  input_names=d.input_names, output_name=d.output_name)


def _combine(records: list[Loaded]) -> Loaded:
    """Several records as one: arrays concatenated, segments kept apart (offsets)."""
    from ..core.narx.segments import SegmentInfo

    bounds, gaps, missing, restarts, start = [], 0, 0, 0, 0
    periods = set()
    for r in records:
        info = r.segment_info()
        bounds += [(a + start, b + start) for a, b in info.bounds]
        gaps, missing, restarts = gaps + info.gaps, missing + info.missing_samples, \
            restarts + info.restarts
        periods.add((info.period_ns, info.period_source))
        start += len(r.y)
    period, source = periods.pop() if len(periods) == 1 else (None, "per record")
    info = SegmentInfo(bounds, period, source, gaps, missing, restarts)
    if len({(r.input_names, r.output_name, np.ndim(r.u)) for r in records}) > 1:
        raise UserError("the records differ in their signals (columns); give files of the "
                        "same layout")
    return Loaded(np.concatenate([r.u for r in records]), np.concatenate([r.y for r in records]),
                  f"{len(records)} records ({', '.join(r.source for r in records)})",
                  rejected=sum(r.rejected for r in records), info=info,
                  records=[x for r in records for x in r.records],
                  input_names=records[0].input_names, output_name=records[0].output_name)


def _load(args) -> Loaded:
    if getattr(args, "bag", None) and args.data:
        raise UserError("give either --data or --bag, not both")
    if getattr(args, "bag", None):
        from ..core.io.bagio import read_bag_signals

        sig = read_bag_signals(args.bag, input_topic=args.input_topic,
                               output_topic=args.output_topic,
                               input_field=args.input_field, output_field=args.output_field,
                               input_names=args.input_names)
        if sig.unset_stamps:
            print(f"note: {sig.unset_stamps} message(s) in {args.bag} repeat header.stamp 0 (the "
                  "recording driver did not fill it in?); their log times were used")
        return Loaded(sig.u, sig.y, f"bag {args.bag}", sig.stamps_ns,
                      sig.rejected_nonfinite, sig.unpaired,
                      input_names=sig.input_names if np.ndim(sig.u) == 2 or args.input_names
                      else ())
    if args.data:
        files = args.data if isinstance(args.data, list) else [args.data]
        inputs, output = getattr(args, "inputs", None), getattr(args, "output_column", None)
        loaded = [_load_file(f, inputs, output) for f in files]
        return loaded[0] if len(loaded) == 1 else _combine(loaded)
    path = find_robot_arm()
    u, y = load_io(path)
    return Loaded(u, y, f"robot-arm data ({path})")


class _Progress:
    """A tqdm bar over generations showing the best criterion so far."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="GA", unit="gen", file=sys.stderr, leave=False,
                            disable=None)  # None: silent when stderr is not a terminal

    def __call__(self, generation: int, best: float, evaluations: int) -> None:
        if self.bar is not None:
            if generation:
                self.bar.update(1)
            self.bar.set_postfix(best=f"{best:.2f}", fits=evaluations)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# -- sub-commands -----------------------------------------------------------------------


def read_yaml(path: str, option: str):
    """A YAML file's content, or one ``error:`` line naming the option, line and problem."""
    import yaml

    from ..core.files import read_bytes

    raw = read_bytes(path, f"{option} file", error=UserError)
    try:
        return yaml.safe_load(raw.decode("utf-8-sig"))
    except UnicodeDecodeError:
        raise UserError(f"{option} {path} is not a text file") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        raise UserError(f"{option} {path} is not valid YAML{where}: {problem}") from None


def _check_outputs(args) -> None:
    """Check --json and --plots destinations before any work (a search must not be lost).

    A destination that is one of the inputs (``--json`` naming the ``--data`` file)
    is refused: the recording would be overwritten by the model.
    """
    from ..core.files import same_file

    data = getattr(args, "data", None) or []
    inputs = [p for p in ([data] if isinstance(data, str) else data)
              + [getattr(args, "model", None)] if p]
    if getattr(args, "json", None):
        check_writable_file(args.json, "--json")
        for p in inputs:
            if same_file(args.json, p):
                raise UserError(f"--json {args.json} is the input {p}: it would be "
                                "overwritten; give another path")
    if getattr(args, "plots", None):
        check_writable_dir(args.plots, "--plots directory")


def _check_corr_lags(corr_lags: int, rows: int) -> None:
    """The validation rule, named as the option (before any work)."""
    from ..core.narx.validation import check_correlation_lags

    try:
        check_correlation_lags(corr_lags, rows)
    except SettingsError as exc:
        raise UserError(str(exc).replace("correlation_lags", "--correlation-lags")) from None


def cmd_identify(args) -> int:
    from ..core.job import run_job
    from ..core.narx.segments import describe_data

    settings = _job_settings(args)
    if args.plots and settings.validation == "none":
        raise UserError("--plots needs validation (--validation estimation or holdout)")
    if args.validation_split is not None and settings.validation != "holdout":
        raise UserError("--validation-split (--split) applies to --validation holdout only "
                        "(the estimation fraction of the data)")
    _check_outputs(args)
    data = _load(args)
    settings = _job_settings(args, data)  # the signals' names and number from the data
    segments = data.segment_info()
    progress = _Progress(settings.ga.generations, not args.quiet)
    try:
        result = run_job(data.u, data.y, settings, segments=segments, rejected=data.rejected,
                         unpaired=data.unpaired, progress=lambda g, b, e: progress(g, b, e),
                         progress_every=1,
                         metadata={"source": data.source,
                                   **({"records": data.records} if data.records else {})})
    except SettingsError as exc:  # a setting that depends on the data (correlation_lags)
        raise UserError(str(exc).replace("correlation_lags", "--correlation-lags")) from None
    finally:
        progress.close()
    model = result.model
    print(f"data: {data.source}, {result.estimation_samples} samples used for estimation")
    account = result.data
    if account["gaps"] or account["rejected_samples"] or account["unpaired_samples"]:
        print(f"note: the data has gaps; used {describe_data(account)}; no regression row "
              "crosses a gap")
    elif account["segments"] > 1:  # several records, or stamps that went back
        print(f"note: the data comes in {account['segments']} parts (records or restarts); "
              f"used {describe_data(account)}; no regression row crosses from one to the next")
    excluded = model.metadata.get("excluded_zero_terms")
    if excluded:
        print(f"note: {len(excluded)} candidate term(s) are zero on this data and were left "
              f"out of the search (e.g. {excluded[0]}); is the input zero?")
    repeats = model.metadata.get("excluded_duplicate_terms")
    if repeats:
        term, first = next(iter(repeats.items()))
        print(f"note: {len(repeats)} candidate term(s) repeat an earlier term on this data "
              f"and were left out of the search (e.g. {term} is proportional to {first}); "
              "is an input constant, or equal to another signal?")
    print(result.summary("lines"))
    if args.plots:
        from .plots import write_model_figures

        paths = write_model_figures(result.report, args.plots, model=result.model)
        print(f"figures written to {args.plots}: {', '.join(p.name for p in paths)}")
    if args.json:
        path = model.save(args.json)
        print(f"model written to {path}")
    return 0


def cmd_certify(args) -> int:
    import json
    import time

    from ..core.files import atomic_write_text
    from ..core.narx.certify import (
        CERTIFIABLE,
        certify_data,
        check_certify_memory,
        ensure_compiled,
        search_is_compiled,
    )
    from ..core.narx.identify import identify

    if args.criterion not in CERTIFIABLE:
        raise UserError(f"--criterion {args.criterion} cannot be certified (its value depends "
                        f"on the coefficients); certifiable: {', '.join(CERTIFIABLE)}")
    if not args.time_limit > 0:
        raise UserError(f"--time-limit must be > 0 seconds, got {args.time_limit}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be at least 1, got {args.threads}")
    if args.node_limit is not None and args.node_limit < 1:
        raise UserError(f"--node-limit must be at least 1, got {args.node_limit}")
    _check_outputs(args)
    data = _load(args)
    settings = _job_settings(args, data)
    segments, _ = data.segments(settings.term_space.max_lag)
    lag = settings.term_space.max_lag
    check_certify_memory(sum(b - a - lag for a, b in (segments or [(0, len(data.y))])),
                         settings.term_space.n_terms)  # before the GA: nothing wasted
    print(f"data: {data.source}, {len(data.y)} samples; "
          f"{settings.term_space.n_terms} candidate terms, {args.criterion.upper()}")
    if not search_is_compiled():
        print("compiling the branch and bound (the first use on this machine, about 20 s; "
              "cached after; not counted in --time-limit) ...", flush=True)
        ensure_compiled()
    started = time.perf_counter()  # --time-limit covers the warm start and the proof
    warm = None
    if not args.no_ga:
        progress = _Progress(settings.ga.generations, not args.quiet)

        def on_generation(st):
            progress(st.generation, st.best, st.evaluations)
            # the warm start may take half the time limit; the proof gets the rest
            return time.perf_counter() - started < 0.5 * args.time_limit

        try:
            res = identify(u=data.u, y=data.y, term_space=settings.term_space,
                           criterion=args.criterion, ga=settings.ga, seed=settings.seed,
                           segments=segments, callback=on_generation)
        finally:
            progress.close()
        warm = res.model.mask
        stopped = (f", stopped at generation {len(res.ga.history) - 1} by half the time "
                   "limit" if res.ga.stopped_early else "")
        print(f"warm start: the GA's best, {args.criterion.upper()} {res.ga.best_score:.2f} "
              f"({int(warm.sum())} terms, {res.ga.elapsed:.2f} s{stopped})")
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(desc="branch and bound", unit=" nodes", file=sys.stderr, leave=False,
                   disable=None)

    def progress_bb(nodes, best, lower):
        if bar is not None:
            bar.n = nodes
            bar.set_postfix(best=f"{best:.2f}", bound=f"{lower:.2f}", refresh=True)

    try:
        cert = certify_data(data.u, data.y, term_space=settings.term_space,
                            criterion=args.criterion, segments=segments, warm_start=warm,
                            time_limit=args.time_limit, node_limit=args.node_limit,
                            progress=progress_bb, threads=args.threads, started=started)
    finally:
        if bar is not None:
            bar.close()
    print(f"status: {cert.status}" + (f" ({cert.reason})" if cert.reason else ""))
    print(f"value: {cert.value:.4f}   lower bound: {cert.lower_bound:.4f}   gap: {cert.gap:.4f}")
    print(f"terms ({len(cert.terms)}): {' + '.join(cert.terms)}")
    print(f"proof: {cert.nodes} nodes, {cert.seconds:.2f} s (warm start included), bounds: "
          f"{cert.bound}"
          + (f"; improved on the warm start ({cert.warm_start:.4f})" if cert.improved else ""))
    if args.json:
        doc = {**cert.to_dict(), "criterion": args.criterion, "source": data.source,
               "term_space": settings.term_space.to_dict()}
        path = atomic_write_text(args.json, json.dumps(doc, indent=2, allow_nan=False) + "\n")
        print(f"certificate written to {path}")
    return 0


def cmd_batch(args) -> int:
    from pathlib import Path

    from .batch import run_batch, summary_table

    per_input = None
    if args.settings:
        from .batch import check_per_input

        per_input = check_per_input(read_yaml(args.settings, "--settings"),
                                    f"--settings {args.settings}")
    values = {k: v for k, v in vars(args).items() if v is not None and k in SETTINGS}
    for k in ("input_topic", "input_field", "input_names", "output_topic", "output_field"):
        if getattr(args, k, None):
            values[k] = getattr(args, k)
    if args.inputs:
        values["inputs"] = ",".join(args.inputs)
    if args.output_column:
        values["output"] = args.output_column
    _job_settings(argparse.Namespace(**values))  # settings errors before any work
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(args.input), desc="inputs", unit="input", file=sys.stderr,
                   disable=None)
    where = f"the Dask cluster at {args.scheduler}" if args.scheduler else "this machine"
    print(f"batch: {len(args.input)} input(s) on {where}; models and summary in {args.out}")
    try:
        rows = run_batch(args.input, args.out, values, per_input=per_input,
                         scheduler=args.scheduler, workers=args.workers or 0,
                         progress=(lambda i, n: bar.update(1)) if bar else None,
                         force=args.force)
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


def _validate_and_report(model, u, y, segment, plots, corr_lags, segments=None,
                         horizon: int = 0) -> None:
    """Validate, print the summary, store it in the model, write figures."""
    from ..core.narx.validation import validate_model

    report = validate_model(model, u, y, max_lag=corr_lags, segment=segment, segments=segments,
                            horizon=horizon or None)
    model.metadata["validation"] = report.to_dict()
    print(report.summary())
    if plots:
        from .plots import write_model_figures

        paths = write_model_figures(report, plots, model=model)
        print(f"figures written to {plots}: {', '.join(p.name for p in paths)}")


def cmd_validate(args) -> int:
    from ..core.narx.model import NarxModel
    from ..core.narx.validation import split_segments

    if args.tail is not None and not 0 < args.tail < 1:
        raise UserError(f"--tail must be between 0 and 1, got {args.tail}")
    _check_outputs(args)
    model = NarxModel.load(args.model)
    data = _load(args)
    u, y = data.u, data.y
    lag0 = model.term_space.max_lag
    segments, _ = data.segments(lag0)
    if args.tail is not None:
        _, segments = split_segments(segments or [(0, len(y))], len(y), 1.0 - args.tail, lag0)
    rows = sum(b - a - lag0 for a, b in (segments or [(0, len(y))]))
    _check_corr_lags(args.correlation_lags, rows)
    print(f"model: {args.model}")
    print(model.equation())
    print(f"data: {data.source}" + (f", last {args.tail:.0%}" if args.tail is not None else ""))
    _validate_and_report(model, u, y, "holdout" if args.tail is not None else "supplied",
                         args.plots, args.correlation_lags, segments, args.horizon)
    return 0


def _list(text: str | None, kind):
    if text is None:
        return None
    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"cannot read {text!r} as a comma-separated list") from None


def cmd_experiment(args) -> int:
    import json
    import time
    from pathlib import Path

    from .experiment import (
        ExperimentConfig,
        run_experiment,
        summarise,
        summary_table,
        write_results,
    )

    overrides = dict(criteria=_list(args.criteria, str), populations=_list(args.populations, int),
                     spm_fractions=_list(args.spm_fractions, float), runs=args.runs,
                     generations=args.generations, seed=args.seed, fitness=args.fitness,
                     workers=args.workers, focus=args.focus,
                     certify=False if args.no_certify else None,
                     certify_time_limit=args.certify_time_limit)
    try:
        if args.config:
            config = ExperimentConfig.from_mapping(read_yaml(args.config, "--config"),
                                                   f"--config {args.config}", **overrides)
        else:
            config = ExperimentConfig(**{k: v for k, v in overrides.items() if v is not None})
    except TypeError as exc:
        raise UserError(f"bad experiment settings: {exc}") from None
    data = _load(args)
    u, y, source = data.u, data.y, data.source
    space = TermSpace.from_dict(config.term_space)
    if data.segments(space.max_lag)[0] is not None:
        raise UserError(f"{source} has gaps; the study needs one contiguous record")
    n_runs = (len(config.criteria) * len(config.populations) * len(config.spm_fractions)
              * config.runs)
    print(f"study: {n_runs} runs on {source}, {len(y)} samples")
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=n_runs, desc="runs", unit="run", file=sys.stderr, disable=None)
    t0 = time.perf_counter()

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
        records = run_experiment(u, y, config, progress=tick, scheduler=args.scheduler,
                                 out=args.out, resume=args.resume)
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
    elapsed = time.perf_counter() - t0
    if records.resumed:
        print(f"resumed: {records.resumed} run(s) were already done and were not run again")
    rows = summarise(records)
    if records:
        write_results(records, rows, config, args.out)
        print(summary_table(rows))
    done_here = f" ({records.resumed} from the earlier session)" if records.resumed else ""
    print(f"{len(records)} of {n_runs} runs{done_here} in {elapsed:.1f} s; per-run records "
          "and figure "
          f"in {args.out}")
    if records.failures:
        for f in records.failures:
            print(f"run {f.key} FAILED after {f.attempts} attempt(s): {f.error}",
                  file=sys.stderr)
        (Path(args.out) / "failures.json").write_text(json.dumps(
            [{"run": f.key, "error": f.error, "attempts": f.attempts}
             for f in records.failures], indent=1))
        print(f"error: {len(records.failures)} run(s) failed (listed above and in "
              f"{Path(args.out) / 'failures.json'}); the summary covers the others; "
              "--resume runs only what is missing", file=sys.stderr)
        return 1
    if args.report:
        from .report import write_report

        path = write_report(records, rows, config, args.out, args.report, elapsed, source,
                            records.resumed)
        print(f"report written to {path}")
    return 0


def cmd_bench(args) -> int:
    from .bench import run_benchmark, run_simulation_benchmark

    settings = _job_settings(args)
    u, y = load_io(args.data) if args.data else load_io(find_robot_arm())
    run_benchmark(u, y, criterion=settings.criterion, repeats=args.repeats,
                  naive_repeats=args.naive_repeats, config=settings.ga)
    run_simulation_benchmark(u, y, repeats=args.repeats, config=settings.ga)
    return 0


def cmd_bench_sizes(args) -> int:
    from .bench_sizes import run

    return run(args)


def cmd_propose_lags(args) -> int:
    from ..core.narx.orders import propose_orders

    data = _load(args)
    if data.segment_info().gaps or len(data.segment_info().bounds) > 1:
        raise UserError(f"{data.source} has gaps or several records; propose lags on one "
                        "contiguous record")
    proposal = propose_orders(data.u, data.y, max_order=args.max_order,
                              max_degree=args.max_degree, delay=args.delay,
                              criterion=args.criterion, inputs=data.input_names)
    print(f"data: {data.source}, {len(data.y)} samples")
    print(proposal.summary())
    n, d = proposal.order, proposal.degree
    print(f"proposal: --ny {n} --nu {n} --degree {d} --delay {args.delay}")
    return 0


def cmd_settings(args) -> int:
    from ..core.settings import node_yaml, settings_table

    print(node_yaml() if args.yaml else settings_table(), end="")
    return 0


def cmd_fetch_data(args) -> int:
    from ..core.io.datasets import DAISY_ROBOT_ARM_URL, download_robot_arm

    path = download_robot_arm(url=args.url or DAISY_ROBOT_ARM_URL, dest=args.output)
    print(f"robot-arm data verified and saved to {path}")
    return 0


def cmd_make_bag(args) -> int:
    import math

    from ..core.io.bagio import write_io_bag

    # everything is checked before anything is read or touched
    if not (args.rate > 0 and math.isfinite(args.rate)):
        raise UserError(f"--rate must be a positive number of Hz, got {args.rate}")
    if not (args.start >= 0 and math.isfinite(args.start) and args.start < 4e9):
        raise UserError(f"--start must be a time in seconds, 0 <= start < 4e9, got {args.start}")
    names = None
    if args.data and (args.inputs or args.output_column):
        from ..core.io.data import load_data

        d = load_data(args.data, args.inputs, args.output_column)
        if d.rejected:
            raise UserError(f"{args.data}: {d.rejected} row(s) with NaN/inf; a bag replays "
                            "every sample, so clean the file first")
        u, y, names = d.u, d.y, d.input_names
    else:
        u, y = load_io(args.data) if args.data else load_io(find_robot_arm())
    path = write_io_bag(args.output, u, y, rate_hz=args.rate, start_ns=int(args.start * 1e9),
                        input_topic=args.input_topic, output_topic=args.output_topic,
                        input_frame=args.input_frame, output_frame=args.output_frame,
                        input_names=names, overwrite=args.force)
    kind = (f"{u.shape[1]} inputs as sensor_msgs/msg/JointState effort[0..{u.shape[1] - 1}]"
            f" ({', '.join(names or [])})" if np.ndim(u) == 2 else "")
    print(f"wrote {len(u)} samples per topic at {args.rate:g} Hz to {path} "
          f"({args.input_topic}, {args.output_topic}){'; ' + kind if kind else ''}")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``spm-sysid identify: error: ...``), exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for documentation and tests)."""
    from .. import __version__

    parser = _Parser(
        prog="spm-sysid",
        description="Polynomial NARX identification with a single-parent-mating GA.",
    )
    parser.add_argument("--version", action="version", version=f"spm-sysid {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("identify", help="select and fit a NARX model on data")
    _add_data_options(p)
    add_schema_options(p, ("term_space", "ga", "criterion", "validation"), JOB_TITLES)
    g = p.add_argument_group("output")
    g.add_argument("--json", metavar="PATH", help="write the model document here")
    g.add_argument("--plots", metavar="DIR", help="write validation figures here")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_identify)

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
    g.add_argument("--inputs", metavar="NAMES", type=lambda t: [c for c in t.split(",") if c],
                   help="input columns of data files (comma-separated)")
    g.add_argument("--output", dest="output_column", metavar="NAME",
                   help="output column of data files")
    for name in ("input_topic", "input_field", "input_names", "output_topic", "output_field"):
        g.add_argument(SETTINGS[name].option, dest=name, default=None,
                       help=f"bags: {SETTINGS[name].help}")
    add_schema_options(p, ("term_space", "ga", "criterion", "validation"), JOB_TITLES)
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("certify", help="prove the best structure of the whole term space "
                       "(branch and bound; AIC, BIC), or bound the gap")
    _add_data_options(p)
    add_schema_options(p, ("term_space", "ga"), JOB_TITLES)
    g = p.add_argument_group("certification")
    g.add_argument("--criterion", default="bic", choices=("aic", "bic"),
                   help="criterion to certify (default bic)")
    g.add_argument("--seed", type=_seed, default=1, help="seed of the warm-start GA run")
    g.add_argument("--no-ga", action="store_true",
                   help="warm-start from forward selection instead of a GA run")
    g.add_argument("--time-limit", type=float, default=60.0,
                   help="seconds before stopping with the best, a lower bound and the gap")
    g.add_argument("--node-limit", type=int, default=None, help="nodes before stopping")
    g.add_argument("--threads", type=int, default=None,
                   help="workers searching at once (default: the usable cores, at most 8)")
    g.add_argument("--json", metavar="PATH", help="write the certificate here")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_certify)

    p = sub.add_parser("validate", help="validate a saved model on data")
    p.add_argument("model", metavar="MODEL.json")
    _add_data_options(p)
    p.add_argument("--tail", type=float, default=None,
                   help="validate on this final fraction of the data only (e.g. 0.5)")
    p.add_argument("--plots", metavar="DIR", help="write validation figures here")
    p.add_argument("--correlation-lags", "--corr-lags", dest="correlation_lags",
                   type=_schema_type("correlation_lags"),
                   default=SETTINGS["correlation_lags"].default,
                   help=SETTINGS["correlation_lags"].help)
    p.add_argument("--horizon", type=_schema_type("horizon"), default=0, metavar="K",
                   help="also report K-step-ahead prediction (0: only one-step and free-run)")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("experiment", help="the paper's study: SPM vs plain GA, repeated runs")
    _add_data_options(p, bag=False)
    p.add_argument("--config", metavar="YAML", help="settings file (options below override)")
    p.add_argument("--criteria", help="comma-separated (default aic,bic,pmic2)")
    p.add_argument("--populations", help="comma-separated (default 200,100)")
    p.add_argument("--spm-fractions", "--spm", dest="spm_fractions",
                   help="comma-separated SPM fractions (default 0,0.15)")
    p.add_argument("--runs", type=int, help="runs per setting (default 15)")
    p.add_argument("--generations", type=_schema_type("generations"), help="default 300")
    p.add_argument("--seed", type=_seed, help="first seed (default 0)")
    p.add_argument("--fitness", choices=SETTINGS["fitness"].choices,
                   help="roulette fitness transform (default akaike)")
    p.add_argument("--workers", type=int, help="processes (default: one per core)")
    p.add_argument("--focus", choices=SETTINGS["focus"].choices,
                   help="prediction (default) or simulation: see spm-sysid settings")
    p.add_argument("--no-certify", action="store_true",
                   help="count runs reaching the best found, without proving it optimal")
    p.add_argument("--certify-time-limit", type=_schema_type("certify_time_limit"),
                   help="seconds per criterion to prove its optimum (default 60)")
    p.add_argument("--out", metavar="DIR", default="out/experiment")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on this Dask cluster (tcp://HOST:PORT; needs the dask extra); "
                        "default: this machine")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted study in --out: only missing runs are run")
    p.add_argument("--force", action="store_true",
                   help="start over in an --out that holds an earlier study's runs")
    p.add_argument("--report", metavar="DIR", help="write a Markdown report here")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("bench", help="time the engine against a naive evaluator")
    p.add_argument("--data", metavar="PATH")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--naive-repeats", type=int, default=3)
    add_schema_options(p, ("ga", "criterion"), JOB_TITLES)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("make-bag", help="write u, y data as a rosbag2 MCAP bag")
    p.add_argument("--data", metavar="PATH", help="two-column or CSV file (default: robot arm)")
    p.add_argument("--output", metavar="PATH", default="bags/robot_arm",
                   help="bag directory to create (default bags/robot_arm)")
    p.add_argument("--rate", type=float, default=100.0,
                   help="nominal sample rate in Hz (default 100: the data gives none)")
    p.add_argument("--start", type=float, default=0.0, help="first stamp, seconds")
    p.add_argument("--inputs", metavar="NAMES", type=lambda t: [c for c in t.split(",") if c],
                   help="input columns of --data (several: written as JointState efforts)")
    p.add_argument("--output-column", dest="output_column", metavar="NAME",
                   help="output column of --data (with --inputs; default 'y', else the last)")
    p.add_argument("--input-topic", default="/robot_arm/torque")
    p.add_argument("--output-topic", default="/robot_arm/acceleration")
    p.add_argument("--input-frame", default="robot_arm_base")
    p.add_argument("--output-frame", default="robot_arm_tip")
    p.add_argument("--force", action="store_true", help="replace an existing bag")
    p.set_defaults(func=cmd_make_bag)

    from .bench_sizes import add_options as bench_sizes_options

    p = sub.add_parser("bench-sizes",
                       help="GA time and memory against term-space size and samples")
    bench_sizes_options(p)
    p.set_defaults(func=cmd_bench_sizes)

    p = sub.add_parser("propose-lags", help="propose lags and degree from the data")
    _add_data_options(p, bag=True)
    p.add_argument("--max-order", type=_positive_int, default=10,
                   help="largest lag order (default 10)")
    p.add_argument("--max-degree", type=_positive_int, default=3, help="largest degree (default 3)")
    p.add_argument("--delay", type=_schema_type("delay"), default=1,
                   help="input delay of the candidates (default 1)")
    p.add_argument("--criterion", choices=("aic", "bic"), default="bic",
                   help="criterion of both scans (default bic)")
    p.set_defaults(func=cmd_propose_lags)

    p = sub.add_parser("settings", help="every setting: default, allowed values, where")
    p.add_argument("--yaml", action="store_true",
                   help="print the node's parameter file (config/sysid_node.yaml)")
    p.set_defaults(func=cmd_settings)

    p = sub.add_parser("fetch-data", help="download the robot-arm data into the user cache")
    p.add_argument("--url", help="alternative download address")
    p.add_argument("--output", metavar="PATH", help="where to save (default: user cache)")
    p.set_defaults(func=cmd_fetch_data)

    return parser


def main(argv: list[str] | None = None) -> int:
    """The offline command line (every sub-command but ``call``, which needs ROS).

    The ``spm-sysid`` console script is :func:`spm_sysid.apps.main.main`: this
    parser plus ``call``.
    """
    return run(build_parser(), argv)


def threading_is_main() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _terminate_as_interrupt(signum, frame):
    raise KeyboardInterrupt


def run(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse and run a sub-command; user errors become one ``error:`` line, status 2.

    SIGTERM (``timeout``, systemd, a job scheduler) is handled as Ctrl-C: work in
    progress stops, partial results stay, worker processes end; exit status 130.
    """
    import signal

    args = parser.parse_args(argv)
    if threading_is_main():
        signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        # the reader went away (e.g. `| head`): stop quietly, as command-line tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except (UserError, DataError, ValueError, OSError) as exc:  # ModelFormatError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
