"""``spm-sysid identify``: select and fit a model on data, validate it, write what is asked."""

from __future__ import annotations

from ...core.errors import SettingsError
from .common import (
    UserError,
    add_data_options,
    add_schema_options,
    announce_compile,
    as_option,
    check_outputs,
    job_settings,
    load,
)
from .outputs import Written, write_outputs
from .progress import PhaseBars

__all__ = ["add_parser", "cmd_identify", "data_notes"]


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
    except KeyboardInterrupt:  # Ctrl-C, SIGTERM: the best model so far, if asked for
        bars.close()
        write_interrupted(args, bars)
        raise
    finally:
        bars.close()
    several = record.n_outputs > 1
    first = result.per_output[0].model
    if several:
        print(f"data: {record.source}, {len(record)} samples, outputs "
              f"{', '.join(record.output_names)} (one coupled model: each output's terms may "
              "use the other outputs' past)")
    else:
        print(f"data: {record.source}, {result.estimation_samples} samples used for "
              "estimation")
    _print_checks(result.data, first.metadata)
    print(result.summary("lines"))
    write_outputs(args, _written(record, result, several))
    return 0


def write_interrupted(args, bars: PhaseBars) -> None:
    """On Ctrl-C: the best model so far to ``--json``, marked interrupted (else nothing).

    The document's ``metadata.interrupted`` says in which phase the job stopped
    and what the model is (the search's best by the criterion, least squares,
    not validated; or the chosen model before its validation).
    """
    import sys

    if not args.json or bars.best_model is None:
        return
    try:
        model = bars.best_model()
    except KeyboardInterrupt:  # a second Ctrl-C: stop now
        return
    if model is None:
        return
    what = ("the chosen model, not validated" if bars.best_phase == "validation" else
            f"the search's best structure so far by {str(model.criterion).upper()}, fitted "
            "by least squares; the selection did not finish")
    model.metadata = {**model.metadata, "interrupted": {
        "phase": bars.last_phase or bars.best_phase, "model": what}}
    model.save(args.json)
    print(f"interrupted during {bars.last_phase or bars.best_phase}: the best model so far "
          f"({what}) written to {args.json}", file=sys.stderr)


def _print_checks(account: dict, metadata: dict) -> None:
    from ...core.validate.excitation import describe_check

    check = describe_check(metadata.get("data_check"))
    if check:
        print(check)
    for note in data_notes(account, metadata):
        print(f"note: {note}")


def _written(record, result, several: bool) -> Written:
    """What ``identify`` writes: the model, a section per output with the job's own rows."""
    from ..html_report import OutputSection

    first = result.per_output[0]
    names = ", ".join(o.name for o in result.per_output)
    title = (f"{names}: identified coupled NARX model" if several else
             f"{names}: identified NARX model")
    data = (f"data: {record.source}, {len(record)} samples" if several else
            f"data: {record.source}, {result.estimation_samples} samples used for estimation")
    return Written(result.model, [OutputSection(o.name, o.model, o.report, result.times,
                                                o.history) for o in result.per_output],
                   result.cross_tests, title, data, result.summary("lines"),
                   data_notes(result.data, first.model.metadata))


def data_notes(account: dict, metadata: dict) -> list[str]:
    """What a user should know about the data an identification used."""
    from ...core.model.decimation import describe_decimation
    from ...core.model.segments import describe_data
    from ...core.validate.spikes import describe_spike_gaps

    notes = [describe_decimation(metadata.get("decimation")),
             describe_spike_gaps(metadata.get("spikes"))]
    if account["gaps"] or account["rejected_samples"] or account["unpaired_samples"] \
            or account.get("spike_samples"):
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
                     f"{first}); is an input constant, two-level, or "
                     "equal to another signal?")
    return [n for n in notes if n]


def add_parser(sub) -> None:
    p = sub.add_parser("identify", help="select and fit a NARX model on data")
    add_data_options(p)
    add_schema_options(p, ("term_space", "ga", "criterion", "validation", "data"))
    g = p.add_argument_group("output")
    g.add_argument("--json", metavar="PATH", help="write the model document here")
    g.add_argument("--plots", metavar="DIR", help="write validation figures here")
    g.add_argument("--report", metavar="FILE.html",
                   help="write one self-contained page: equation, coefficients, checks, "
                        "interactive plots (works offline)")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_identify)
