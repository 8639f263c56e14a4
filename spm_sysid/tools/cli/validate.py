"""``spm-sysid validate``: a saved model, of one output or several, on any data."""

from __future__ import annotations

import argparse

from .common import (
    UserError,
    add_data_options,
    check_correlation_lags_option,
    check_outputs,
    load,
    schema_type,
    usable_segments,
)
from .outputs import Written, write_outputs

__all__ = ["add_parser", "at_model_rate", "bag_as_identified", "cmd_validate", "load_by_names"]


def cmd_validate(args) -> int:
    from ...core.errors import ModelFormatError
    from ...core.model.mimo import MimoModel, read_model_document

    if args.tail is not None and not 0 < args.tail < 1:
        raise UserError(f"--tail must be between 0 and 1, got {args.tail}")
    if args.errors_from < 0:
        raise UserError(f"--errors-from must be 0 or more, got {args.errors_from}")
    check_outputs(args)
    try:
        model, _ = read_model_document(args.model)
    except ModelFormatError as exc:
        raise UserError(str(exc)) from None
    args = bag_as_identified(args, model.metadata)
    if isinstance(model, MimoModel):
        return _validate_several(args, model)
    return _validate_one(args, model)


def bag_as_identified(args, metadata: dict):
    """``--bag`` read on the model's own topics, fields and names when none is given.

    A model identified from a bag's ``/joint_states`` efforts and positions
    validates on another recording of the same topics without repeating the
    options (``metadata.topics``: written by ``identify --bag`` and by the node); a
    note says which were used.
    """
    from ...core.settings import BAG_OPTIONS, SETTINGS

    known = metadata.get("topics") or {}
    if getattr(args, "bag", None) is None or not known:
        return args
    given = [k for k in BAG_OPTIONS if getattr(args, k, None) != (SETTINGS[k].default or None)]
    if given:
        return args
    shown = ", ".join(f"{SETTINGS[k].option} {known[k]}" for k in BAG_OPTIONS if k in known)
    print(f"note: the bag is read on the model's topics and fields: {shown}")
    return argparse.Namespace(**{**vars(args), **{k: v for k, v in known.items()
                                                  if k in BAG_OPTIONS}})


def _validate_one(args, model) -> int:
    from ...core.validate.validation import validate_model
    from ..html_report import OutputSection

    record, spiked = _spikes(args, load_by_names(args, model.term_space.inputs,
                                                 (model.term_space.output,)))
    record = at_model_rate(record, model.metadata)
    segments = validated_segments(args, record, model.term_space.max_lag)
    print(f"model: {args.model}")
    print(model.equation())
    print(model.coefficient_table())
    for w in model.metadata.get("warnings") or []:
        print(f"warning (from identification): {w}")
    if spiked:
        print(spiked)
    print(f"data: {record.source}" + (f", last {args.tail:.0%}" if args.tail is not None
                                      else ""))
    notes = _beyond(model.metadata, record, segments, model.term_space.inputs,
                    (model.term_space.output,))
    report = validate_model(model, record.u, record.y, correlation_lags=args.correlation_lags,
                            segment="holdout" if args.tail is not None else "supplied",
                            segments=segments, horizon=args.horizon or None,
                            errors_from=args.errors_from)
    model.metadata["validation"] = report.to_dict()
    print(report.summary())
    _explained(model, report)
    times = record.row_seconds(segments, model.term_space.max_lag)
    write_outputs(args, Written(None, [OutputSection(model.term_space.output, model, report,
                                                     times)], [],
                                f"{model.term_space.output}: model {args.model} validated",
                                f"data: {record.source}",
                                "".join(n + "\n" for n in notes) + report.summary()))
    return 0


def _beyond(metadata: dict, record, segments, inputs, outputs) -> list[str]:
    """Printed notes on each signal of the data beyond the range the model was fitted on."""
    from ...core.validate.envelope import range_notes

    notes = [f"note: {n}" for n in range_notes(metadata.get("ranges"), record.u, record.y,
                                               segments, inputs, outputs)]
    for n in notes:
        print(n)
    return notes


def _validate_several(args, model) -> int:
    """A coupled model of several outputs.

    Each output's report with the coupled free run, the residuals'
    cross-correlation, a panel per output.
    """
    from ...core.jobs.several import couple_reports, coupled_rows, cross_summary
    from ...core.model.mimo import augmented_inputs
    from ...core.validate.validation import validate_model
    from ..html_report import OutputSection

    record, spiked = _spikes(args, load_by_names(args, model.inputs, model.outputs,
                                                 several=True))
    record = at_model_rate(record, model.metadata)
    if spiked:
        print(spiked)
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
    _beyond(model.metadata, record, segments, model.inputs, model.outputs)
    reports = []
    for i, m in enumerate(model.models):  # each from the coupled run's first rows
        shift = model.max_lag - m.term_space.max_lag
        rep = validate_model(m, augmented_inputs(u, Y, i), Y[:, i],
                             correlation_lags=args.correlation_lags,
                             segment="holdout" if args.tail is not None else "supplied",
                             segments=coupled_rows(model, i, segments),
                             horizon=args.horizon or None,
                             errors_from=max(args.errors_from - shift, 0))
        rep.errors_from = args.errors_from  # of the segments as given
        reports.append(rep)
    cross = couple_reports(model, u, Y, segments, reports, args.correlation_lags)
    for name, m, rep in zip(model.outputs, model.models, reports):
        print(f"== output {name} ==")
        print(m.equation())
        print(rep.summary().replace("free-run:", "coupled free-run:"))
        _explained(m, rep)
    if cross:
        print(cross_summary(cross))
    times = record.row_seconds(segments, model.max_lag)
    write_outputs(args, Written(None, [OutputSection(name, m, rep, times) for name, m, rep in
                                       zip(model.outputs, model.models, reports)], cross,
                                f"{', '.join(model.outputs)}: coupled model {args.model} "
                                "validated", f"data: {record.source}"))
    return 0


def _explained(model, report) -> None:
    """A warning line when the model explains little of these data (its focus run's fit).

    The model's warnings (in memory: the page's) then hold it in place of the
    identification's own.
    """
    from ...core.validate.explained import OTHER_DATA, set_explained_warning

    said = set_explained_warning(model.metadata, advice=OTHER_DATA,
                                 validation=report.to_dict())
    if said:
        print(f"warning: {said}")


def load_by_names(args, inputs, outputs, several: bool = False):
    """The data, its columns chosen by the model's signal names when the options do not.

    A model identified on columns ``tau``, ``acc`` (or ``u1``, ``u2``, ``y``) validates
    on a file's columns of those names; a file without them (no header, other
    names) is read in its default layout, and a note says so. A model of one input
    ``u`` and output ``y`` reads the default layout, which takes those columns.
    """
    from ...core.errors import DataError

    given = getattr(args, "inputs", None) or getattr(args, "output_column", None)
    if given or getattr(args, "data", None) is None or (tuple(inputs), tuple(outputs)) == (
            ("u",), ("y",)):
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


def at_model_rate(record, metadata: dict):
    """The record decimated as the model's data were (``metadata.decimation``), said in a note.

    A model identified at a slower rate predicts and simulates samples of that
    rate; validating it on the record's own would compare it with the wrong steps.
    """
    from ...core.model.decimation import decimation_factor, describe_decimation

    factor = decimation_factor(metadata)
    if factor <= 1:
        return record
    record = record.decimated(factor)
    print(f"note: the model runs at 1/{factor} of the data's rate (it was identified so); "
          f"the data {describe_decimation(record.decimation)}")
    return record


def _spikes(args, record):
    """The record with its output spikes left out (``--spikes gaps``), and what to print.

    Without the option, a warning when the data have spikes: the errors include them.
    """
    from ...core.validate.spikes import describe_spike_gaps, spikes_of_outputs

    if args.spikes == "gaps":
        record = record.spikes_as_gaps()
        return record, f"note: {describe_spike_gaps(record.spikes)}" if record.spikes else ""
    found = spikes_of_outputs(record.y, record.u, record.segment_info().bounds)
    if found is None:
        return record, ""
    starts = found.starts
    return record, (f"warning: the output of these data has {len(starts)} spike(s) "
                    f"(at sample {', '.join(str(t) for t in starts[:5])}"
                    f"{', ...' if len(starts) > 5 else ''}): the errors below include "
                    "them; --spikes gaps leaves them out")


def validated_segments(args, record, lag0: int) -> list[tuple[int, int]]:
    """The segments ``validate`` runs on: the usable ones, their last ``--tail``."""
    from ...core.validate.validation import split_segments

    segments = usable_segments(record, lag0)
    if args.tail is not None:
        _, segments = split_segments(segments, len(record), 1.0 - args.tail, lag0)
    check_correlation_lags_option(args.correlation_lags,
                                  sum(b - a - lag0 for a, b in segments))
    return segments


def add_parser(sub) -> None:
    from ...core.settings import SETTINGS

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
    p.add_argument("--errors-from", type=int, default=0, metavar="N",
                   help="leave each segment's first N samples (at the model's rate) out of "
                        "the error figures; the simulation still starts from its first "
                        "samples (the nonlinear benchmarks' convention: 50)")
    p.add_argument("--spikes", type=schema_type("spikes"), default="warn",
                   help="output spikes in these data (as identify finds them): warn, or "
                        "gaps (left out of the error figures, counted)")
    p.set_defaults(func=cmd_validate)
