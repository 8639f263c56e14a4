"""``spm-sysid certify``: prove the best structure of the whole space, or bound the gap."""

from __future__ import annotations

from .common import (
    UserError,
    add_data_options,
    add_schema_options,
    check_outputs,
    job_settings,
    load,
    read_around,
    record_settings,
    schema_type,
    seed_type,
    usable_segments,
)
from .progress import PhaseBars

__all__ = ["add_parser", "cmd_certify"]


def cmd_certify(args) -> int:
    """``spm-sysid certify``: the GA's best as warm start, then the branch and bound."""
    import time
    from dataclasses import replace

    from ...core.files import atomic_write_text, document_json
    from ...core.search.certify import check_certify_memory, describe_certificate
    from ...core.search.explain import explain_table
    from ...core.search.split import certify_data

    settings = _checked_settings(args)
    time_limit = settings.search.certify_time_limit
    check_outputs(args)
    record = load(args, decimate=True)
    settings = record_settings(settings, record)
    space = settings.term_space
    segments = usable_segments(record, space.max_lag)
    u, y, around = _around(settings, record, segments)
    if u is not record.u:  # the deviations' space, as identify searches it: the constant
        space = replace(space, constant=True)  # a candidate
        settings = replace(settings, term_space=space)
    check_certify_memory(sum(b - a - space.max_lag for a, b in segments),
                         space.n_terms)  # before the GA: nothing wasted
    print(f"data: {record.source}, {len(record)} samples; "
          f"{space.n_terms} candidate terms, {args.criterion.upper()}")
    if around:
        print(around)
    _compile_first()
    started = time.perf_counter()  # the time limit covers the warm start and the proof
    bars = PhaseBars(not args.quiet).for_generations(settings.ga.generations)
    try:
        warm = None if args.no_ga else _warm_start(args, (u, y), settings, segments, bars,
                                                   started)
        cert = certify_data(u, y, term_space=space, criterion=args.criterion,
                            segments=segments, warm_start=warm, time_limit=time_limit,
                            node_limit=args.node_limit, progress=bars.nodes,
                            threads=args.threads, started=started, explain=args.explain)
    finally:
        bars.close()
    doc = cert.to_dict()
    print(f"status: {cert.status}" + (f" ({cert.reason})" if cert.reason else ""))
    print(f"value: {cert.value:.4f}   lower bound: {cert.lower_bound:.4f}   gap: {cert.gap:.4f}")
    print(f"terms ({len(cert.terms)}): {' + '.join(cert.terms)}")
    print(f"{describe_certificate(doc)}; bounds: {cert.bound}; time limit {time_limit:g} s "
          "(warm start included)")
    if args.explain:
        print(explain_table(doc.get("weakest", []), cert.value))
    elif cert.status == "limit":
        print("what holds the bound: run again with --explain")
    if args.json:
        doc = {**doc, "criterion": args.criterion, "source": record.source,
               "term_space": space.to_dict()}
        path = atomic_write_text(args.json, document_json(doc) + "\n")
        print(f"certificate written to {path}")
    return 0


def _checked_settings(args):
    """The job settings, once criterion, threads, node and time limits are possible."""
    from ...core.search.certify import CERTIFIABLE

    if args.criterion not in CERTIFIABLE:
        raise UserError(f"--criterion {args.criterion} cannot be certified (its value depends "
                        f"on the coefficients); certifiable: {', '.join(CERTIFIABLE)}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be at least 1, got {args.threads}")
    if args.explain is not None and args.explain < 0:
        raise UserError(f"--explain must be 0 or more nodes, got {args.explain}")
    if args.node_limit is not None and args.node_limit < 1:
        raise UserError(f"--node-limit must be at least 1, got {args.node_limit}")
    settings = job_settings(args)
    time_limit = settings.search.certify_time_limit
    if not time_limit > 0:
        raise UserError(f"--certify-time-limit (--time-limit) must be > 0 seconds, got "
                        f"{time_limit:g}")
    return settings


def _compile_first() -> None:
    """The first use on a machine compiles the branch and bound, said, before any clock."""
    from ...core.search.certify import ensure_compiled, search_is_compiled

    if not search_is_compiled():
        print("compiling the branch and bound (the first use on this machine, about 20 s; "
              "cached after; not counted in the time limit; `spm-sysid compile` does it "
              "ahead) ...", flush=True)
        ensure_compiled()


def _around(settings, record, segments):
    """The samples certify reads (the record's, or their deviations from its means), and why."""
    import numpy as np

    rows = np.concatenate([np.arange(a, b) for a, b in segments])
    u, y, what = read_around(record, settings.operating_point, settings.term_space, rows,
                             "the estimation data's")
    if u is record.u:
        return u, y, what
    return u, y, (f"{what}: the structures certified are of the deviations from them, the "
                  "constant a candidate, as identify selects them (--operating-point none: "
                  "of the record as it is)")


def _warm_start(args, signals, settings, segments, bars, started: float):
    """The GA's best structure by the criterion on ``signals`` (u, y), within half the limit."""
    import time

    from ...core.identify import identify

    time_limit = settings.search.certify_time_limit

    def on_generation(stats):
        bars.generation(stats)
        # the warm start may take half the time limit; the proof gets the rest
        return time.perf_counter() - started < 0.5 * time_limit

    # the criterion's best is the warm start (not a validated selection's
    # choice), and the proof below is the only certification
    res = identify(u=signals[0], y=signals[1], term_space=settings.term_space,
                   criterion=args.criterion, ga=settings.ga, seed=settings.seed,
                   segments=segments, callback=on_generation, selection="criterion",
                   auto_certify_time_limit=0, operating_point="none")
    warm = res.model.mask
    stopped = (f", stopped at generation {len(res.ga.history) - 1} by half the time "
               "limit" if res.ga.stopped_early else "")
    bars.close_bar()
    print(f"warm start: the GA's best, {args.criterion.upper()} "
          f"{res.ga.best_score:.2f} ({int(warm.sum())} terms, {res.ga.elapsed:.2f} s"
          f"{stopped})")
    return warm


def add_parser(sub) -> None:
    from ...core.fit.criteria import CERTIFIABLE
    from ...core.settings import SETTINGS

    p = sub.add_parser("certify", help="prove the best structure of the whole term space "
                       "(branch and bound; AIC, AICc, BIC), or bound the gap")
    add_data_options(p)
    add_schema_options(p, ("term_space", "ga", "data"))
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
    g.add_argument("--explain", type=int, nargs="?", const=10, default=0, metavar="N",
                   help="when not proved: print the N weakest open nodes (default 10), each "
                        "bounded again size by size: what holds the lower bound")
    g.add_argument("--json", metavar="PATH", help="write the certificate here")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_certify)
