"""``check-data``, ``propose-lags`` and ``compile``: what the data and the machine can do."""

from __future__ import annotations

from ...core.defaults import AUTO_MAX_TERMS, ROWS_PER_TERM
from ...core.settings import SETTINGS
from .common import (
    UserError,
    add_data_options,
    add_schema_options,
    job_settings,
    load,
    positive_int,
    read_around,
    record_settings,
    schema_type,
    usable_segments,
)

__all__ = ["add_parsers", "cmd_check_data", "cmd_compile", "cmd_propose_lags"]


def cmd_check_data(args) -> int:
    from dataclasses import replace

    from ...core.fit.problem import Problem
    from ...core.validate.excitation import check_problem

    settings = job_settings(args)
    record = load(args, decimate=True)
    settings = record_settings(settings, record)
    space = settings.term_space
    segments = usable_segments(record, space.max_lag)
    u, y, around = _around(record, settings.operating_point, space)
    if u is not record.u:  # the deviations, as identify checks them: the constant a candidate
        space = replace(space, constant=True)
    problem = Problem.from_signals(u, y, space, segments)
    print(f"data: {record.source}, {len(record)} samples in {len(segments)} segment(s); "
          f"term space ny={space.ny}, nu={space.nu}, degree={space.degree}, "
          f"delay={space.delay}{', constant' if space.constant else ''}")
    if around:
        print(around)
    check = check_problem(problem)  # a hopeless space is refused (DataError: one line)
    print("\n".join(check.lines()))
    if not check.warnings:
        print("no warning: the data can identify this space")
    return 0


def cmd_propose_lags(args) -> int:
    from ...core.validate.feedthrough import describe_feedthrough, within_sample
    from ...core.validate.orders import propose_orders

    record = load(args, decimate=True)
    info = record.segment_info()
    if info.gaps or len(info.bounds) > 1:
        raise UserError(f"{record.source} has gaps or several records; propose lags on one "
                        "contiguous record")
    u, y, around = _around(record, args.operating_point, None)
    proposal = propose_orders(u, y, max_order=args.max_order,
                              max_degree=args.max_degree, delay=args.delay,
                              criterion=args.criterion, inputs=record.input_names,
                              focus=args.focus, max_terms=args.max_terms)
    print(f"data: {record.source}, {len(record)} samples")
    if around:
        print(around)
    print(proposal.summary())
    n, d = proposal.order, proposal.degree
    print(f"proposal: --ny {n} --nu {n} --degree {d} --delay {args.delay} --constant"
          "  (as --orders auto identifies: the constant a candidate)")
    names = record.input_names
    within = describe_feedthrough(within_sample(y, u, [args.delay] * len(names), names),
                                  record.output_name)
    if within:  # the proposal's lags start at --delay: say when an earlier one acts
        print(f"warning: {within}")
    return 0


def _around(record, setting: str, space=None):
    """The record's samples, or their deviations from its means, as identify takes them.

    ``space``: the term space checked (its regressors decide too); None: the scans'.
    Returns u, y and what was done ('' when the record is read as it is).
    """
    from ...core.model.terms import TermSpace

    space = space or TermSpace(ny=1, nu=1, degree=1, inputs=record.input_names,
                               output=record.output_name)
    u, y, what = read_around(record, setting, space)
    if u is record.u:
        return u, y, what
    return u, y, f"{what}: read as their deviations, as identify reads them"


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


def add_parsers(sub) -> None:
    """Register ``check-data``, ``propose-lags`` and ``compile``."""
    p = sub.add_parser("compile", help="compile the numeric kernels ahead of their first use "
                       "(make setup runs it)")
    p.set_defaults(func=cmd_compile)

    p = sub.add_parser("check-data", help="can these data identify this space? excitation, "
                       "conditioning, terms that cannot be identified")
    add_data_options(p)
    add_schema_options(p, ("term_space", "data"))
    p.set_defaults(func=cmd_check_data)

    p = sub.add_parser("propose-lags", help="propose lags and degree from the data")
    add_data_options(p, bag=True)
    p.add_argument("--max-order", type=positive_int, default=10,
                   help="largest lag order (default 10)")
    p.add_argument("--max-degree", type=positive_int, default=3,
                   help="largest degree (default 3)")
    p.add_argument("--decimate", type=schema_type("decimate"), default=1,
                   help="propose for the data decimated so, as identify --decimate "
                   "identifies (default 1: the record's rate)")
    p.add_argument("--delay", type=schema_type("delay"), default=1,
                   help="input delay of the candidates (default 1)")
    p.add_argument("--criterion", choices=("aic", "bic"), default="bic",
                   help="criterion of both scans (default bic)")
    p.add_argument("--focus", choices=("prediction", "simulation"), default="prediction",
                   help="what the model is for: spaces compared by the one-step criterion "
                   "(prediction) or by how they simulate held-out samples (simulation), "
                   "as identify --orders auto does with that focus (default prediction)")
    p.add_argument("--operating-point", type=schema_type("operating_point"),
                   choices=SETTINGS["operating_point"].choices, default="auto",
                   help="scan the deviations from the record's means, as identify does "
                   "(default auto: when a signal's mean is farther from zero than its "
                   "standard deviation)")
    p.add_argument("--max-terms", type=positive_int, default=None,
                   help="candidate terms a proposed space may have at most (default "
                   f"{AUTO_MAX_TERMS}, or the quadratic space of order 2 when many inputs "
                   f"make it larger, as identify --orders auto; fewer on records of fewer "
                   f"than {ROWS_PER_TERM} rows per term)")
    p.set_defaults(func=cmd_propose_lags)
