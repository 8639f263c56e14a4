"""The ``spm-sysid`` command line.

Sub-commands: ``identify`` (the main offline job), ``validate``, ``experiment``,
``make-bag``, ``bench``, ``fetch-data`` and ``call`` (a service client for the
ROS node). Every failure a user can cause ends with one ``error: ...`` line and
exit status 2, never a traceback.
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

from ..core.errors import DataError  # noqa: E402
from ..core.files import check_writable_dir, check_writable_file  # noqa: E402
from ..core.io.data import load_data, load_io  # noqa: E402
from ..core.io.datasets import find_robot_arm  # noqa: E402
from ..core.narx.ga import GAConfig  # noqa: E402
from ..core.narx.terms import TermSpace  # noqa: E402

__all__ = ["main"]


class UserError(Exception):
    """A problem the user can fix; printed without a traceback."""


# -- shared options -------------------------------------------------------------------


def _add_data_options(p: argparse.ArgumentParser, bag: bool = True) -> None:
    g = p.add_argument_group("data (default: the robot-arm data)")
    g.add_argument("--data", metavar="PATH", help="two-column or CSV file of u, y")
    if bag:
        g.add_argument("--bag", metavar="PATH", help="rosbag2 bag (MCAP) to read u, y from")
        g.add_argument("--input-topic", default="/robot_arm/torque")
        g.add_argument("--input-field", default=None,
                       help="field path of u in the input message (default by type)")
        g.add_argument("--output-topic", default="/robot_arm/acceleration")
        g.add_argument("--output-field", default=None,
                       help="field path of y in the output message (default by type)")


def _add_model_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("term space (default: the paper's)")
    g.add_argument("--ny", type=int, default=4, help="output lags 1..ny (default 4)")
    g.add_argument("--nu", type=int, default=4, help="number of input lags (default 4)")
    g.add_argument("--degree", type=int, default=2, help="polynomial degree (default 2)")
    g.add_argument("--delay", type=int, default=1, help="input delay (default 1)")
    g.add_argument("--constant", action="store_true", help="add a constant candidate term")


def _add_ga_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("genetic algorithm (default: the paper's settings)")
    g.add_argument("--population", type=int, default=200)
    g.add_argument("--generations", type=int, default=300)
    g.add_argument("--crossover", type=float, default=0.6, help="crossover probability")
    g.add_argument("--mutation", type=float, default=0.01, help="per-bit mutation probability")
    g.add_argument("--spm", type=float, default=0.15, help="single parent mating fraction s")
    g.add_argument("--fitness", choices=("akaike", "rank", "window"), default="akaike",
                   help="roulette fitness transform (see docs/method.md)")


def _term_space(args) -> TermSpace:
    try:
        return TermSpace(ny=args.ny, nu=args.nu, degree=args.degree, delay=args.delay,
                         constant=args.constant)
    except (TypeError, ValueError) as exc:
        raise UserError(str(exc)) from None


def _ga_config(args) -> GAConfig:
    try:
        return GAConfig(population_size=args.population, generations=args.generations,
                        crossover_prob=args.crossover, mutation_prob=args.mutation,
                        spm_fraction=args.spm, fitness=args.fitness)
    except ValueError as exc:
        raise UserError(str(exc)) from None


@dataclass
class Loaded:
    """Data for a command: samples, where from, and the contiguous segments."""

    u: np.ndarray
    y: np.ndarray
    source: str
    stamps_ns: np.ndarray | None = None
    rejected: int = 0
    unpaired: int = 0

    def segments(self, max_lag: int) -> tuple[list[tuple[int, int]] | None, dict]:
        """Usable segments (None: the whole record) and the account of the data."""
        from ..core.narx.segments import SegmentInfo, find_segments, segment_report

        if self.stamps_ns is None:
            info = SegmentInfo([(0, len(self.y))])
        else:
            info = find_segments(self.stamps_ns)
        bounds, data = segment_report(info, max_lag, self.rejected, self.unpaired)
        if not bounds:
            raise UserError(f"{self.source}: no contiguous segment is longer than the largest "
                            f"lag ({max_lag}); {len(self.y)} samples in {len(info.bounds)} "
                            f"segment(s)")
        whole = len(bounds) == 1 and bounds[0] == (0, len(self.y))
        return (None if whole else bounds), data


def _load(args) -> Loaded:
    if getattr(args, "bag", None) and args.data:
        raise UserError("give either --data or --bag, not both")
    if getattr(args, "bag", None):
        from ..core.io.bagio import read_bag_signals

        sig = read_bag_signals(args.bag, input_topic=args.input_topic,
                               output_topic=args.output_topic,
                               input_field=args.input_field, output_field=args.output_field)
        return Loaded(sig.u, sig.y, f"bag {args.bag}", sig.stamps_ns,
                      sig.rejected_nonfinite, sig.unpaired)
    if args.data:
        d = load_data(args.data)
        stamps = None if d.t is None else np.round(d.t * 1e9).astype(np.int64)
        return Loaded(d.u, d.y, args.data, stamps, d.rejected)
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

    def __call__(self, stats) -> None:
        if self.bar is not None:
            if stats.generation:
                self.bar.update(1)
            self.bar.set_postfix(best=f"{stats.best:.2f}", fits=stats.evaluations)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# -- sub-commands -----------------------------------------------------------------------


def _check_outputs(args) -> None:
    """Check --json and --plots destinations before any work (a search must not be lost)."""
    if getattr(args, "json", None):
        check_writable_file(args.json, "--json")
    if getattr(args, "plots", None):
        check_writable_dir(args.plots, "--plots directory")


def _check_corr_lags(corr_lags: int, rows: int) -> None:
    if not 1 <= corr_lags < rows:
        raise UserError(f"--corr-lags must be between 1 and {rows - 1} for {rows} validation "
                        f"rows, got {corr_lags}")


def cmd_identify(args) -> int:
    from ..core.narx.identify import identify
    from ..core.narx.segments import describe_data
    from ..core.narx.validation import split_segments

    space = _term_space(args)
    config = _ga_config(args)
    if args.plots and args.validation == "none":
        raise UserError("--plots needs validation (--validation estimation or holdout)")
    if args.split is not None and args.validation != "holdout":
        raise UserError("--split applies to --validation holdout only (the estimation "
                        "fraction of the data)")
    if args.corr_lags < 1:
        raise UserError(f"--corr-lags must be >= 1, got {args.corr_lags}")
    _check_outputs(args)
    data = _load(args)
    u, y = data.u, data.y
    segments, account = data.segments(space.max_lag)
    est = val = segments
    if args.validation == "holdout":
        bounds = segments or [(0, len(y))]
        est, val = split_segments(bounds, len(y), 0.5 if args.split is None else args.split,
                                  space.max_lag)
    if args.validation != "none":
        rows = sum(b - a - space.max_lag for a, b in (val or [(0, len(y))]))
        _check_corr_lags(args.corr_lags, rows)
    progress = _Progress(config.generations, not args.quiet)
    try:
        result = identify(u=u, y=y, term_space=space, criterion=args.criterion, ga=config,
                          seed=args.seed, callback=progress, segments=est)
    finally:
        progress.close()
    model = result.model
    model.metadata["source"] = data.source
    model.metadata["data"] = account
    used = sum(b - a for a, b in (est or [(0, len(y))]))
    print(f"data: {data.source}, {used} samples used for estimation")
    if account["segments"] > 1 or account["gaps"] or account["rejected_samples"] \
            or account["unpaired_samples"]:
        print(f"note: the data has gaps; used {describe_data(account)}; no regression row "
              "crosses a gap")
    excluded = model.metadata.get("excluded_zero_terms")
    if excluded:
        print(f"note: {len(excluded)} candidate term(s) are zero on this data and were left "
              f"out of the search (e.g. {excluded[0]}); is the input zero?")
    print(result.summary())
    if args.validation != "none":
        _validate_and_report(model, u, y, args.validation, args.plots, args.corr_lags, val)
    if args.json:
        path = model.save(args.json)
        print(f"model written to {path}")
    return 0


def _validate_and_report(model, u, y, segment, plots, corr_lags, segments=None) -> None:
    """Validate, print the summary, store it in the model, write figures."""
    from ..core.narx.validation import validate_model

    report = validate_model(model, u, y, max_lag=corr_lags, segment=segment, segments=segments)
    model.metadata["validation"] = report.to_dict()
    print(report.summary())
    if plots:
        from .plots import write_model_figures

        paths = write_model_figures(report, plots)
        print(f"figures written to {plots}: {', '.join(p.name for p in paths)}")


def cmd_validate(args) -> int:
    from ..core.narx.model import NarxModel
    from ..core.narx.validation import split_segments

    if args.tail is not None and not 0 < args.tail < 1:
        raise UserError(f"--tail must be between 0 and 1, got {args.tail}")
    if args.corr_lags < 1:
        raise UserError(f"--corr-lags must be >= 1, got {args.corr_lags}")
    _check_outputs(args)
    model = NarxModel.load(args.model)
    data = _load(args)
    u, y = data.u, data.y
    lag0 = model.term_space.max_lag
    segments, _ = data.segments(lag0)
    if args.tail is not None:
        _, segments = split_segments(segments or [(0, len(y))], len(y), 1.0 - args.tail, lag0)
    rows = sum(b - a - lag0 for a, b in (segments or [(0, len(y))]))
    _check_corr_lags(args.corr_lags, rows)
    print(f"model: {args.model}")
    print(model.equation())
    print(f"data: {data.source}" + (f", last {args.tail:.0%}" if args.tail is not None else ""))
    _validate_and_report(model, u, y, "holdout" if args.tail is not None else "supplied",
                         args.plots, args.corr_lags, segments)
    return 0


def _list(text: str | None, kind):
    if text is None:
        return None
    try:
        return [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"cannot read {text!r} as a comma-separated list") from None


def cmd_experiment(args) -> int:
    import time

    from .experiment import (
        ExperimentConfig,
        run_experiment,
        summarise,
        summary_table,
        write_results,
    )

    overrides = dict(criteria=_list(args.criteria, str), populations=_list(args.populations, int),
                     spm_fractions=_list(args.spm, float), runs=args.runs,
                     generations=args.generations, seed=args.seed, fitness=args.fitness,
                     workers=args.workers)
    try:
        if args.config:
            config = ExperimentConfig.from_yaml(args.config, **overrides)
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
    try:
        records = run_experiment(u, y, config,
                                 progress=(lambda i, n: bar.update(1)) if bar else None)
    finally:
        if bar:
            bar.close()
    elapsed = time.perf_counter() - t0
    rows = summarise(records)
    write_results(records, rows, config, args.out)
    print(summary_table(rows))
    print(f"{n_runs} runs in {elapsed:.1f} s; per-run records and figure in {args.out}")
    if args.report:
        from .report import write_report

        path = write_report(records, rows, config, args.out, args.report, elapsed, source)
        print(f"report written to {path}")
    return 0


def cmd_call(args) -> int:
    # The one place the command line reaches into the ROS layer, and only when asked,
    # so every other sub-command runs on machines without ROS.
    try:
        from ..apps.call import main as call_main
    except ImportError as exc:
        raise UserError(f"`call` needs ROS 2 (rclpy): {exc}") from None
    return call_main(args.action, node_name=args.node, timeout=args.timeout,
                     show_model=args.show_model)


def cmd_bench(args) -> int:
    from .bench import run_benchmark

    u, y = load_io(args.data) if args.data else load_io(find_robot_arm())
    run_benchmark(u, y, criterion=args.criterion, repeats=args.repeats,
                  naive_repeats=args.naive_repeats,
                  config=GAConfig(population_size=args.population,
                                  generations=args.generations, spm_fraction=args.spm))
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
    u, y = load_io(args.data) if args.data else load_io(find_robot_arm())
    path = write_io_bag(args.output, u, y, rate_hz=args.rate, start_ns=int(args.start * 1e9),
                        input_topic=args.input_topic, output_topic=args.output_topic,
                        input_frame=args.input_frame, output_frame=args.output_frame,
                        overwrite=args.force)
    print(f"wrote {len(u)} samples per topic at {args.rate:g} Hz to {path} "
          f"({args.input_topic}, {args.output_topic})")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``spm-sysid identify: error: ...``), exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


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
    _add_model_options(p)
    _add_ga_options(p)
    p.add_argument("--criterion", default="aic", help="aic, bic or pmic2 (default aic)")
    p.add_argument("--seed", type=_seed, default=None,
                   help="random seed >= 0 (reproducible runs)")
    p.add_argument("--json", metavar="PATH", help="write the model document here")
    p.add_argument("--plots", metavar="DIR", help="write validation figures here")
    p.add_argument("--validation", choices=("none", "estimation", "holdout"),
                   default="estimation",
                   help="validate on the estimation data or a held-out tail")
    p.add_argument("--split", type=float, default=None,
                   help="estimation fraction for --validation holdout (default 0.5)")
    p.add_argument("--corr-lags", type=int, default=20,
                   help="largest lag of the correlation tests (default 20)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_identify)

    p = sub.add_parser("validate", help="validate a saved model on data")
    p.add_argument("model", metavar="MODEL.json")
    _add_data_options(p)
    p.add_argument("--tail", type=float, default=None,
                   help="validate on this final fraction of the data only (e.g. 0.5)")
    p.add_argument("--plots", metavar="DIR", help="write validation figures here")
    p.add_argument("--corr-lags", type=int, default=20)
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("experiment", help="the paper's study: SPM vs plain GA, repeated runs")
    _add_data_options(p, bag=False)
    p.add_argument("--config", metavar="YAML", help="settings file (options below override)")
    p.add_argument("--criteria", help="comma-separated (default aic,bic,pmic2)")
    p.add_argument("--populations", help="comma-separated (default 200,100)")
    p.add_argument("--spm", help="comma-separated SPM fractions (default 0,0.15)")
    p.add_argument("--runs", type=int, help="runs per setting (default 15)")
    p.add_argument("--generations", type=int, help="default 300")
    p.add_argument("--seed", type=_seed, help="first seed (default 0)")
    p.add_argument("--fitness", choices=("akaike", "rank", "window"),
                   help="roulette fitness transform (default akaike)")
    p.add_argument("--workers", type=int, help="processes (default: one per core)")
    p.add_argument("--out", metavar="DIR", default="out/experiment")
    p.add_argument("--report", metavar="DIR", help="write a Markdown report here")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("call", help="call the sysid node's identify or clear service")
    p.add_argument("action", choices=("identify", "clear"))
    p.add_argument("--node", default="/spm_sysid", help="node name (default /spm_sysid)")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds to wait")
    p.add_argument("--show-model", action="store_true",
                   help="print the published model document after identify")
    p.set_defaults(func=cmd_call)

    p = sub.add_parser("bench", help="time the engine against a naive evaluator")
    p.add_argument("--data", metavar="PATH")
    p.add_argument("--criterion", default="aic")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--naive-repeats", type=int, default=3)
    p.add_argument("--population", type=int, default=200)
    p.add_argument("--generations", type=int, default=300)
    p.add_argument("--spm", type=float, default=0.15)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("make-bag", help="write u, y data as a rosbag2 MCAP bag")
    p.add_argument("--data", metavar="PATH", help="two-column or CSV file (default: robot arm)")
    p.add_argument("--output", metavar="PATH", default="bags/robot_arm",
                   help="bag directory to create (default bags/robot_arm)")
    p.add_argument("--rate", type=float, default=100.0,
                   help="nominal sample rate in Hz (default 100: the data gives none)")
    p.add_argument("--start", type=float, default=0.0, help="first stamp, seconds")
    p.add_argument("--input-topic", default="/robot_arm/torque")
    p.add_argument("--output-topic", default="/robot_arm/acceleration")
    p.add_argument("--input-frame", default="robot_arm_base")
    p.add_argument("--output-frame", default="robot_arm_tip")
    p.add_argument("--force", action="store_true", help="replace an existing bag")
    p.set_defaults(func=cmd_make_bag)

    p = sub.add_parser("fetch-data", help="download the robot-arm data into the user cache")
    p.add_argument("--url", help="alternative download address")
    p.add_argument("--output", metavar="PATH", help="where to save (default: user cache)")
    p.set_defaults(func=cmd_fetch_data)

    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``spm-sysid`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
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
