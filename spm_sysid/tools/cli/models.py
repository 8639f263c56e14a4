"""Commands on one model: ``identify``, ``certify``, ``validate``, ``propose-lags``."""

from __future__ import annotations

import argparse

from ...core.errors import SettingsError
from .common import (
    UserError,
    add_data_options,
    add_schema_options,
    announce_compile,
    as_option,
    check_correlation_lags_option,
    check_outputs,
    job_settings,
    load,
    positive_int,
    schema_type,
    seed_type,
)
from .progress import PhaseBars

__all__ = ["add_parsers"]


def usable_segments(record, max_lag: int) -> list[tuple[int, int]]:
    """The record's segments longer than ``max_lag`` (one error line when there are none)."""
    from ...core.model.segments import usable_segments as usable

    info = record.segment_info()
    bounds, _, _ = usable(info.bounds, max_lag)
    if not bounds:
        raise UserError(f"{record.source}: no contiguous segment is longer than the largest "
                        f"lag ({max_lag}); {len(record)} samples in {len(info.bounds)} "
                        "segment(s)")
    return bounds


# -- identify -------------------------------------------------------------------------


def cmd_identify(args) -> int:
    from ...core.jobs import run_job

    settings = job_settings(args)
    if args.plots and settings.validation == "none":
        raise UserError("--plots needs validation (--validation estimation or holdout)")
    if args.validation_split is not None and settings.validation != "holdout":
        raise UserError("--validation-split (--split) applies to --validation holdout only "
                        "(the estimation fraction of the data)")
    check_outputs(args)
    record = load(args, several=True)
    announce_compile()
    bars = PhaseBars(not args.quiet)
    try:
        result = run_job(record, settings, progress=bars, progress_every=1)
    except SettingsError as exc:  # a setting that depends on the data (correlation_lags)
        raise UserError(as_option(exc)) from None
    finally:
        bars.close()
    if record.n_outputs > 1:
        return report_several(args, record, result)
    from ...core.validate.excitation import describe_check

    model = result.model
    print(f"data: {record.source}, {result.estimation_samples} samples used for estimation")
    check = describe_check(model.metadata.get("data_check"))
    if check:
        print(check)
    for note in data_notes(result.data, model.metadata):
        print(f"note: {note}")
    print(result.summary("lines"))
    if args.plots:
        from ..plots import write_model_figures

        paths = write_model_figures(result.report, args.plots, model=model,
                                    times=validation_times(record, args))
        print(f"figures written to {args.plots}: {', '.join(p.name for p in paths)}")
    if args.json:
        path = model.save(args.json)
        print(f"model written to {path}")
    if args.report:
        from ..html_report import OutputSection, ReportContent, write_model_report

        path = write_model_report(args.report, ReportContent(
            title=f"{model.term_space.output}: identified NARX model", command=command_line(),
            data=f"data: {record.source}, {result.estimation_samples} samples used for "
                 "estimation", summary=result.summary("lines"),
            notes=data_notes(result.data, model.metadata)),
            [OutputSection(model.term_space.output, model, result.report,
                           validation_times(record, args), result.search.history)])
        print(f"report written to {path}")
    return 0


def command_line() -> str:
    """The command as typed (for a report's header)."""
    import shlex
    import sys

    return "spm-sysid " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def validation_times(record, args):
    """Seconds of the validation rows of ``identify`` (None without time stamps)."""
    from ...core.jobs import validation_segments

    settings = job_settings(args)
    _, val, _ = validation_segments(record, settings)
    return record.row_seconds(val, settings.term_space.max_lag)


def report_several(args, record, result) -> int:
    """``identify`` of several outputs (``--output a,b``, ``--output-topic a,b``).

    One coupled model: each output's block, the joint summary, figures per output.
    """
    from ...core.validate.excitation import describe_check

    print(f"data: {record.source}, {len(record)} samples, outputs "
          f"{', '.join(record.output_names)} (one coupled model: each output's terms may "
          "use the other outputs' past)")
    check = describe_check(result.outputs[0].model.metadata.get("data_check"))
    if check:
        print(check)
    for note in data_notes(result.data, result.outputs[0].model.metadata):
        print(f"note: {note}")
    print(result.summary("lines"))
    if args.plots:
        from ..plots import write_mimo_figures

        paths = write_mimo_figures([r.report for r in result.outputs],
                                   [r.model for r in result.outputs], result.output_names,
                                   result.cross_tests, args.plots,
                                   times=validation_times(record, args))
        print(f"figures written to {args.plots}: {', '.join(p.name for p in paths)}")
    if args.json:
        path = result.model.save(args.json)
        print(f"model written to {path}")
    if args.report:
        from ..html_report import OutputSection, ReportContent, write_model_report

        times = validation_times(record, args)
        path = write_model_report(args.report, ReportContent(
            title=f"{', '.join(result.output_names)}: identified coupled NARX model",
            command=command_line(), data=f"data: {record.source}, {len(record)} samples",
            summary=result.summary("lines"), cross_tests=result.cross_tests,
            notes=data_notes(result.data, result.outputs[0].model.metadata)),
            [OutputSection(name, r.model, r.report, times, r.search.history)
             for name, r in zip(result.output_names, result.outputs)])
        print(f"report written to {path}")
    return 0


def data_notes(account: dict, metadata: dict) -> list[str]:
    """What a user should know about the data an identification used."""
    from ...core.model.segments import describe_data

    notes = []
    if account["gaps"] or account["rejected_samples"] or account["unpaired_samples"]:
        notes.append(f"the data has gaps; used {describe_data(account)}; no regression row "
                     "crosses a gap")
    elif account["segments"] > 1:  # several records, or stamps that went back
        notes.append(f"the data comes in {account['segments']} parts (records or restarts); "
                     f"used {describe_data(account)}; no regression row crosses from one to "
                     "the next")
    excluded = metadata.get("excluded_zero_terms")
    if excluded:
        notes.append(f"{len(excluded)} candidate term(s) are zero on this data and were left "
                     f"out of the search (e.g. {excluded[0]}); is the input zero?")
    repeats = metadata.get("excluded_duplicate_terms")
    if repeats:
        term, first = next(iter(repeats.items()))
        notes.append(f"{len(repeats)} candidate term(s) repeat an earlier term on this data "
                     f"and were left out of the search (e.g. {term} is proportional to "
                     f"{first}); is an input constant, or equal to another signal?")
    return notes


# -- certify -------------------------------------------------------------------------------


def cmd_certify(args) -> int:
    import time

    from ...core.files import atomic_write_text, document_json
    from ...core.identify import identify
    from ...core.search.certify import (
        CERTIFIABLE,
        certify_data,
        check_certify_memory,
        describe_certificate,
        ensure_compiled,
        search_is_compiled,
    )

    if args.criterion not in CERTIFIABLE:
        raise UserError(f"--criterion {args.criterion} cannot be certified (its value depends "
                        f"on the coefficients); certifiable: {', '.join(CERTIFIABLE)}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be at least 1, got {args.threads}")
    if args.node_limit is not None and args.node_limit < 1:
        raise UserError(f"--node-limit must be at least 1, got {args.node_limit}")
    settings = job_settings(args)
    time_limit = settings.certify_time_limit
    if not time_limit > 0:
        raise UserError(f"--certify-time-limit (--time-limit) must be > 0 seconds, got "
                        f"{time_limit:g}")
    check_outputs(args)
    record = load(args)
    settings = settings.for_signals(record.input_names, record.output_name)
    space = settings.term_space
    segments = usable_segments(record, space.max_lag)
    check_certify_memory(sum(b - a - space.max_lag for a, b in segments),
                         space.n_terms)  # before the GA: nothing wasted
    print(f"data: {record.source}, {len(record)} samples; "
          f"{space.n_terms} candidate terms, {args.criterion.upper()}")
    if not search_is_compiled():
        print("compiling the branch and bound (the first use on this machine, about 20 s; "
              "cached after; not counted in the time limit; `spm-sysid compile` does it "
              "ahead) ...", flush=True)
        ensure_compiled()
    started = time.perf_counter()  # the time limit covers the warm start and the proof
    warm = None
    bars = PhaseBars(not args.quiet).for_generations(settings.ga.generations)
    try:
        if not args.no_ga:
            def on_generation(stats):
                bars.generation(stats)
                # the warm start may take half the time limit; the proof gets the rest
                return time.perf_counter() - started < 0.5 * time_limit

            # the criterion's best is the warm start (not a validated selection's
            # choice), and the proof below is the only certification
            res = identify(u=record.u, y=record.y, term_space=space, criterion=args.criterion,
                           ga=settings.ga, seed=settings.seed, segments=segments,
                           callback=on_generation, selection="criterion",
                           auto_certify_time_limit=0)
            warm = res.model.mask
            stopped = (f", stopped at generation {len(res.ga.history) - 1} by half the time "
                       "limit" if res.ga.stopped_early else "")
            bars.close()
            print(f"warm start: the GA's best, {args.criterion.upper()} "
                  f"{res.ga.best_score:.2f} ({int(warm.sum())} terms, {res.ga.elapsed:.2f} s"
                  f"{stopped})")
        cert = certify_data(record.u, record.y, term_space=space, criterion=args.criterion,
                            segments=segments, warm_start=warm, time_limit=time_limit,
                            node_limit=args.node_limit, progress=bars.nodes,
                            threads=args.threads, started=started)
    finally:
        bars.close()
    doc = cert.to_dict()
    print(f"status: {cert.status}" + (f" ({cert.reason})" if cert.reason else ""))
    print(f"value: {cert.value:.4f}   lower bound: {cert.lower_bound:.4f}   gap: {cert.gap:.4f}")
    print(f"terms ({len(cert.terms)}): {' + '.join(cert.terms)}")
    print(f"{describe_certificate(doc)}; bounds: {cert.bound}; time limit {time_limit:g} s "
          "(warm start included)")
    if args.json:
        doc = {**doc, "criterion": args.criterion, "source": record.source,
               "term_space": space.to_dict()}
        path = atomic_write_text(args.json, document_json(doc) + "\n")
        print(f"certificate written to {path}")
    return 0


# -- validate -------------------------------------------------------------------------------


def cmd_validate(args) -> int:
    from ...core.validate.validation import validate_model

    if args.tail is not None and not 0 < args.tail < 1:
        raise UserError(f"--tail must be between 0 and 1, got {args.tail}")
    check_outputs(args)
    from ...core.errors import ModelFormatError
    from ...core.model.mimo import MimoModel, read_model_document

    try:
        model, _ = read_model_document(args.model)
    except ModelFormatError as exc:
        raise UserError(str(exc)) from None
    if isinstance(model, MimoModel):
        return validate_several(args, model)
    record = load_by_names(args, model.term_space.inputs, (model.term_space.output,))
    u, y = record.u, record.y
    segments = validated_segments(args, record, model.term_space.max_lag)
    print(f"model: {args.model}")
    print(model.equation())
    print(model.coefficient_table())
    for w in model.metadata.get("warnings") or []:
        print(f"warning (from identification): {w}")
    print(f"data: {record.source}" + (f", last {args.tail:.0%}" if args.tail is not None
                                      else ""))
    report = validate_model(model, u, y, correlation_lags=args.correlation_lags,
                            segment="holdout" if args.tail is not None else "supplied",
                            segments=segments, horizon=args.horizon or None)
    model.metadata["validation"] = report.to_dict()
    print(report.summary())
    if args.plots:
        from ..plots import write_model_figures

        paths = write_model_figures(report, args.plots, model=model,
                                    times=record.row_seconds(segments,
                                                             model.term_space.max_lag))
        print(f"figures written to {args.plots}: {', '.join(p.name for p in paths)}")
    if args.report:
        from ..html_report import OutputSection, ReportContent, write_model_report

        path = write_model_report(args.report, ReportContent(
            title=f"{model.term_space.output}: model {args.model} validated",
            command=command_line(), data=f"data: {record.source}", summary=report.summary()),
            [OutputSection(model.term_space.output, model, report,
                           record.row_seconds(segments, model.term_space.max_lag))])
        print(f"report written to {path}")
    return 0


def load_by_names(args, inputs, outputs, several: bool = False):
    """The data, its columns chosen by the model's signal names when the options do not.

    A model identified on columns ``tau``, ``acc`` validates on a file's columns of
    those names; a file without them (no header, other names) is read in its
    default layout, and a note says so.
    """
    from ...core.errors import DataError

    default = {"u", "y"} | {f"u{i}" for i in range(1, 10)} | {f"y{i}" for i in range(1, 10)}
    given = getattr(args, "inputs", None) or getattr(args, "output_column", None)
    if given or getattr(args, "data", None) is None or set(inputs) | set(outputs) <= default:
        return load(args, several)
    named = argparse.Namespace(**{**vars(args), "inputs": list(inputs),
                                  "output_column": ",".join(outputs)})
    try:
        record = load(named, several)
    except DataError as exc:
        if "no column" not in str(exc):
            raise
        print(f"note: the data has no columns named as the model's signals "
              f"({', '.join(inputs)} -> {', '.join(outputs)}); its columns are read in the "
              "default layout (choose them with --inputs and --output)")
        return load(args, several)
    print(f"note: columns chosen by the model's signal names: inputs {', '.join(inputs)}, "
          f"output {', '.join(outputs)}")
    return record


def validated_segments(args, record, lag0: int) -> list[tuple[int, int]]:
    """The segments ``validate`` runs on: the usable ones, their last ``--tail``."""
    from ...core.validate.validation import split_segments

    segments = usable_segments(record, lag0)
    if args.tail is not None:
        _, segments = split_segments(segments, len(record), 1.0 - args.tail, lag0)
    check_correlation_lags_option(args.correlation_lags,
                                  sum(b - a - lag0 for a, b in segments))
    return segments


def validate_several(args, model) -> int:
    """``validate`` of a coupled model of several outputs.

    Each output's report with the coupled free run, the residuals'
    cross-correlation, figures with a panel per output.
    """
    from ...core.jobs.several import couple_reports, cross_summary
    from ...core.model.mimo import augmented_inputs
    from ...core.validate.validation import validate_model

    record = load_by_names(args, model.inputs, model.outputs, several=True)
    if record.output_names != model.outputs or record.n_inputs != len(model.inputs):
        raise UserError(f"the model has outputs {', '.join(model.outputs)} and "
                        f"{len(model.inputs)} input(s); the data has outputs "
                        f"{', '.join(record.output_names)} and {record.n_inputs} input(s) "
                        "(give --output " + ",".join(model.outputs) + " and the inputs in "
                        "the model's order)")
    u, Y = record.u, record.y
    segments = validated_segments(args, record, model.max_lag)
    print(f"model: {args.model} (outputs {', '.join(model.outputs)}, coupled)")
    print(f"data: {record.source}" + (f", last {args.tail:.0%}" if args.tail is not None
                                      else ""))
    reports = [validate_model(m, augmented_inputs(u, Y, i), Y[:, i],
                              correlation_lags=args.correlation_lags,
                              segment="holdout" if args.tail is not None else "supplied",
                              segments=segments, horizon=args.horizon or None)
               for i, m in enumerate(model.models)]
    cross = couple_reports(model, u, Y, segments, reports, args.correlation_lags)
    for name, m, rep in zip(model.outputs, model.models, reports):
        print(f"== output {name} ==")
        print(m.equation())
        print(rep.summary().replace("free-run:", "coupled free-run:"))
    if cross:
        print(cross_summary(cross))
    if args.plots:
        from ..plots import write_mimo_figures

        paths = write_mimo_figures(reports, model.models, model.outputs, cross, args.plots,
                                   times=record.row_seconds(segments, model.max_lag))
        print(f"figures written to {args.plots}: {', '.join(p.name for p in paths)}")
    if args.report:
        from ..html_report import OutputSection, ReportContent, write_model_report

        times = record.row_seconds(segments, model.max_lag)
        path = write_model_report(args.report, ReportContent(
            title=f"{', '.join(model.outputs)}: coupled model {args.model} validated",
            command=command_line(), data=f"data: {record.source}", cross_tests=cross),
            [OutputSection(name, m, rep, times)
             for name, m, rep in zip(model.outputs, model.models, reports)])
        print(f"report written to {path}")
    return 0


# -- check-data -------------------------------------------------------------------------------


def cmd_check_data(args) -> int:
    from ...core.fit.problem import Problem
    from ...core.validate.excitation import check_problem

    settings = job_settings(args)
    record = load(args)
    settings = settings.for_signals(record.input_names, record.output_name)
    space = settings.term_space
    segments = usable_segments(record, space.max_lag)
    problem = Problem.from_signals(record.u, record.y, space, segments)
    print(f"data: {record.source}, {len(record)} samples in {len(segments)} segment(s); "
          f"term space ny={space.ny}, nu={space.nu}, degree={space.degree}, "
          f"delay={space.delay}{', constant' if space.constant else ''}")
    check = check_problem(problem)  # a hopeless space is refused (DataError: one line)
    print("\n".join(check.lines()))
    if not check.warnings:
        print("no warning: the data can identify this space")
    return 0


# -- propose-lags ----------------------------------------------------------------------------


def cmd_propose_lags(args) -> int:
    from ...core.validate.orders import propose_orders

    record = load(args)
    info = record.segment_info()
    if info.gaps or len(info.bounds) > 1:
        raise UserError(f"{record.source} has gaps or several records; propose lags on one "
                        "contiguous record")
    proposal = propose_orders(record.u, record.y, max_order=args.max_order,
                              max_degree=args.max_degree, delay=args.delay,
                              criterion=args.criterion, inputs=record.input_names)
    print(f"data: {record.source}, {len(record)} samples")
    print(proposal.summary())
    n, d = proposal.order, proposal.degree
    print(f"proposal: --ny {n} --nu {n} --degree {d} --delay {args.delay}")
    return 0


# -- compile ----------------------------------------------------------------------------------


def cmd_compile(args) -> int:
    from ...core.jobs.warmup import compile_all, kernels_are_cached

    before = kernels_are_cached()
    seconds, status = compile_all(report=lambda text: print(text, flush=True))
    print(f"kernels {'loaded from the cache' if before else 'compiled and cached'} in "
          f"{seconds:.1f} s")
    if status:
        print(f"ahead-of-time extension: {status.path}")
    else:
        print(f"no ahead-of-time extension ({status.reason}): commands load numba's JIT "
              "(about 0.7 s more each)")
    return 0


# -- the parsers -----------------------------------------------------------------------------


def add_parsers(sub) -> None:
    """Register ``identify``, ``certify``, ``validate`` and ``propose-lags``."""
    from ...core.fit.criteria import CERTIFIABLE
    from ...core.settings import SETTINGS

    p = sub.add_parser("identify", help="select and fit a NARX model on data")
    add_data_options(p)
    add_schema_options(p, ("term_space", "ga", "criterion", "validation"))
    g = p.add_argument_group("output")
    g.add_argument("--json", metavar="PATH", help="write the model document here")
    g.add_argument("--plots", metavar="DIR", help="write validation figures here")
    g.add_argument("--report", metavar="FILE.html",
                   help="write one self-contained page: equation, coefficients, checks, "
                        "interactive plots (works offline)")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_identify)

    p = sub.add_parser("compile", help="compile the numeric kernels ahead of their first use "
                       "(make setup runs it)")
    p.set_defaults(func=cmd_compile)

    p = sub.add_parser("certify", help="prove the best structure of the whole term space "
                       "(branch and bound; AIC, AICc, BIC), or bound the gap")
    add_data_options(p)
    add_schema_options(p, ("term_space", "ga"))
    g = p.add_argument_group("certification")
    g.add_argument("--criterion", default=SETTINGS["criterion"].default,
                   choices=CERTIFIABLE,
                   help=f"criterion to certify (default {SETTINGS['criterion'].default}, as "
                        "identify's: after identify, certify proves the model it showed)")
    g.add_argument("--seed", type=seed_type, default=1, help="seed of the warm-start GA run")
    g.add_argument("--no-ga", action="store_true",
                   help="warm-start from forward selection instead of a GA run")
    s = SETTINGS["certify_time_limit"]
    g.add_argument(s.option, "--time-limit", dest="certify_time_limit",
                   type=schema_type("certify_time_limit"), default=s.default,
                   help=f"{s.help}; the warm start counts (default {s.default:g})")
    g.add_argument("--node-limit", type=int, default=None, help="nodes before stopping")
    g.add_argument("--threads", type=int, default=None,
                   help="workers searching at once (default: the usable cores, at most 8)")
    g.add_argument("--json", metavar="PATH", help="write the certificate here")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_certify)

    p = sub.add_parser("validate", help="validate a saved model on data")
    p.add_argument("model", metavar="MODEL.json")
    add_data_options(p)
    p.add_argument("--tail", type=float, default=None,
                   help="validate on this final fraction of the data only (e.g. 0.5)")
    p.add_argument("--plots", metavar="DIR", help="write validation figures here")
    p.add_argument("--report", metavar="FILE.html",
                   help="write one self-contained page of the model and this validation")
    p.add_argument("--correlation-lags", "--corr-lags", dest="correlation_lags",
                   type=schema_type("correlation_lags"),
                   default=SETTINGS["correlation_lags"].default,
                   help=SETTINGS["correlation_lags"].help)
    p.add_argument("--horizon", type=schema_type("horizon"), default=0, metavar="K",
                   help="also report K-step-ahead prediction (0: only one-step and free-run)")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("check-data", help="can these data identify this space? excitation, "
                       "conditioning, terms that cannot be identified")
    add_data_options(p)
    add_schema_options(p, ("term_space",))
    p.set_defaults(func=cmd_check_data)

    p = sub.add_parser("propose-lags", help="propose lags and degree from the data")
    add_data_options(p, bag=True)
    p.add_argument("--max-order", type=positive_int, default=10,
                   help="largest lag order (default 10)")
    p.add_argument("--max-degree", type=positive_int, default=3,
                   help="largest degree (default 3)")
    p.add_argument("--delay", type=schema_type("delay"), default=1,
                   help="input delay of the candidates (default 1)")
    p.add_argument("--criterion", choices=("aic", "bic"), default="bic",
                   help="criterion of both scans (default bic)")
    p.set_defaults(func=cmd_propose_lags)

