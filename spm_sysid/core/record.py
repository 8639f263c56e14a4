"""One record type and one loader: every way data comes in ends as a :class:`Record`.

A record is what an identification needs of its data: the input and output
samples, the signals' names (in the order the user gave them), the sample
stamps when there are any, and an account of what was dropped on the way
(rejected NaN/inf samples, unpaired messages, stamps never filled in). Several
records (``--data`` given several times) combine into one whose segments keep
them apart.

Where data come from is a :class:`DataSpec` -- data files, a bag, which columns,
topics and fields -- and :func:`load_record` turns any spec into a record:

* data files (:mod:`spm_sysid.core.io.data`): two columns, CSV, chosen columns,
  a time column;
* a rosbag2 bag (:mod:`spm_sysid.core.io.bagio`), topics and fields as the node
  reads them;
* nothing given: the robot-arm data set (:mod:`spm_sysid.core.io.datasets`).

The node's buffer snapshot becomes a record with :meth:`Record.from_samples`.
The command line, ``batch``, ``make-bag``, the benchmarks, the signal publisher
and the ``make run`` pipeline all load through here, so the same input gives the
same record -- and the same model document -- whichever command reads it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .errors import DataError
from .model.segments import SegmentInfo, find_segments
from .settings import BAG_OPTIONS, SETTINGS, check, parse_text

__all__ = ["DataSpec", "Record", "combine", "load_record", "topics_read"]


def default_input_names(m: int) -> tuple[str, ...]:
    """``u`` for one input, ``u1, u2, ...`` for several."""
    return ("u",) if m == 1 else tuple(f"u{i + 1}" for i in range(m))


@dataclass
class Record:
    """The samples of an identification, named and accounted for.

    Attributes
    ----------
    u : ndarray, shape (n,) or (n, m)
        Inputs, oldest first (one column per input, in the user's order).
    y : ndarray, shape (n,) or (n, q)
        The output (one column per output when there are several: a coupled
        model of several joints, :mod:`spm_sysid.core.model.mimo`).
    source : str
        Where the samples came from, for people.
    input_names : tuple of str
        One name per input (default ``u``, or ``u1, u2, ...``).
    output_name : str
        The output's name (several outputs: their names joined by commas).
    output_names : tuple of str
        One name per output (default: ``(output_name,)`` for one output).
    stamps_ns : ndarray of int, or None
        Sample stamps (bags, the node, CSV time columns); gaps and restarts in
        them split the record into segments.
    segments : SegmentInfo or None
        Segments already known (records combined, a time column); None: found
        from the stamps (or one segment without stamps).
    rejected, unpaired, unset_stamps : int
        Samples dropped as NaN/inf, messages without a partner, messages whose
        header stamp was never filled in (their receive/log time used).
    parts : list of dict
        ``{"source", "samples"}`` per data file when files were read.
    notes : list of str
        Things a user should know about this data (printed by the commands).
    decimation : dict or None
        How the samples were decimated (:meth:`decimated`); None: as recorded.
    spikes : dict or None
        The output spikes left out of the segments (:meth:`spikes_as_gaps`):
        ``{"spikes", "samples", "at"}`` (the first 1000 spikes' first samples).
    topics : dict or None
        The topics, fields and names a bag's signals were read from
        (:func:`topics_read`; the node's from its parameters): ``validate --bag``
        reads another bag the same way by default.
    fed_back : tuple of str
        The inputs that are other outputs (a coupled model's view of one output:
        :func:`~spm_sysid.core.jobs.several._view`); their lags start at 1 whatever
        ``--delay`` says, so the data check does not ask about their lag 0.
    """

    u: np.ndarray
    y: np.ndarray
    source: str
    input_names: tuple[str, ...] = ()
    output_name: str = "y"
    stamps_ns: np.ndarray | None = None
    segments: SegmentInfo | None = None
    rejected: int = 0
    unpaired: int = 0
    unset_stamps: int = 0
    parts: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    output_names: tuple[str, ...] = ()
    decimation: dict | None = None
    spikes: dict | None = None
    topics: dict | None = None
    fed_back: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        self.u = np.asarray(self.u, dtype=float)
        self.y = np.asarray(self.y, dtype=float)
        if not self.input_names:
            self.input_names = default_input_names(self.n_inputs)
        if self.y.ndim == 2 and self.y.shape[1] == 1:
            self.y = self.y[:, 0]
        q = 1 if self.y.ndim == 1 else self.y.shape[1]
        if not self.output_names:
            self.output_names = ((self.output_name,) if q == 1 else
                                 tuple(f"y{i + 1}" for i in range(q)))
        self.output_names = tuple(self.output_names)
        if len(self.output_names) != q:
            raise DataError(f"{q} output column(s) but {len(self.output_names)} output "
                            f"name(s) ({', '.join(self.output_names)})")
        if q > 1:
            self.output_name = ",".join(self.output_names)

    @classmethod
    def from_samples(cls, u, y, *, source: str, stamps_ns=None, input_names=(),
                     output_name: str = "y", rejected: int = 0, unpaired: int = 0,
                     unset_stamps: int = 0, output_names=()) -> Record:
        """A record of samples already in memory (the node's buffer, a Python caller).

        ``y`` of shape (n, q) with ``output_names`` is a record of several outputs.
        """
        return cls(u, y, source, tuple(input_names), output_name,
                   None if stamps_ns is None else np.asarray(stamps_ns, dtype=np.int64),
                   rejected=rejected, unpaired=unpaired, unset_stamps=unset_stamps,
                   output_names=tuple(output_names))

    @property
    def n_inputs(self) -> int:
        return 1 if self.u.ndim == 1 else self.u.shape[1]

    @property
    def n_outputs(self) -> int:
        return 1 if self.y.ndim == 1 else self.y.shape[1]

    def require_one_output(self, what: str) -> Record:
        """The record itself, or a DataError when it has several outputs ``what`` cannot take."""
        if self.n_outputs > 1:
            raise DataError(f"{what} takes one output; the data has {self.n_outputs} "
                            f"({', '.join(self.output_names)}): give one output, or identify "
                            "them together with 'spm-sysid identify'")
        return self

    def __len__(self) -> int:
        return len(self.y)

    def segment_info(self, period_ns: int | None = None, gap_factor: float = 1.5
                     ) -> SegmentInfo:
        """How the record splits into contiguous segments.

        The segments given with the record (records combined, a time column); else
        those the stamps show (``period_ns`` given or estimated); else one.
        """
        if self.segments is not None:
            return self.segments
        if self.stamps_ns is None:
            return SegmentInfo([(0, len(self.y))] if len(self.y) else [])
        return find_segments(self.stamps_ns, period_ns, gap_factor)

    def decimated(self, factor: int, period_ns: int | None = None, gap_factor: float = 1.5
                  ) -> Record:
        """The record decimated by ``factor`` (:mod:`spm_sysid.core.model.decimation`).

        Blocks stay inside the segments (:meth:`segment_info` with ``period_ns``
        and ``gap_factor``); the decimated record keeps them as its segments, its
        stamps are the blocks' first, and :attr:`decimation` and a note say what
        was done and how many samples at segment ends were not used. A record
        decimated again is decimated by the product of the factors (exactly so).
        """
        if factor <= 1:
            return self
        from .model.decimation import (
            compose,
            decimate_blocks,
            decimation_doc,
            describe_decimation,
        )

        info = self.segment_info(period_ns, gap_factor)
        u, y, bounds, first = decimate_blocks(self.u, self.y, info.bounds, factor)
        doc = decimation_doc(factor, len(self.y), len(y), info.n_samples)
        if self.decimation:  # decimated before: one decimation by the product
            doc = compose(self.decimation, doc)
        period = None if info.period_ns is None else info.period_ns * factor
        segments = SegmentInfo([b for b in bounds if b[1] > b[0]], period, info.period_source,
                               info.gaps, info.missing_samples, info.restarts)
        stamps = None if self.stamps_ns is None else self.stamps_ns[first]
        return replace(self, u=u, y=y, stamps_ns=stamps, segments=segments, decimation=doc,
                       notes=[*self.notes, describe_decimation(doc)])

    def spikes_as_gaps(self, period_ns: int | None = None, gap_factor: float = 1.5
                       ) -> Record:
        """The record with its outputs' spikes left out of its segments.

        Spikes as the data check finds them
        (:func:`~spm_sysid.core.validate.spikes.output_spikes`), each output's;
        the segments (:meth:`segment_info`) split around them, so no regression
        row uses a spike's samples (the arrays keep them). :attr:`spikes` and a
        note count them; without spikes the record is returned as it is.
        """
        from .validate.spikes import (
            SPIKE_ROUNDS,
            describe_spike_gaps,
            spikes_of_outputs,
            without_spikes,
        )

        info = self.segment_info(period_ns, gap_factor)
        bounds, spans = info.bounds, set()
        for _ in range(SPIKE_ROUNDS):  # a spike hidden by others shows once they are out
            found = spikes_of_outputs(self.y, self.u, bounds)
            if found is None:
                break
            bounds = without_spikes(bounds, found)
            spans |= set(zip(found.starts, found.widths))
        if not spans:
            return self
        left = info.n_samples - sum(b - a for a, b in bounds)
        doc = {"spikes": len(spans), "samples": int(left),
               "at": [t for t, _ in sorted(spans)[:1000]]}
        return replace(self, segments=replace(info, bounds=bounds), spikes=doc,
                       notes=[*self.notes, describe_spike_gaps(doc)])

    def row_seconds(self, segments, lag0: int) -> np.ndarray | None:
        """Seconds (from the first sample) of the regression rows of ``segments``.

        Rows are t = a + ``lag0`` .. b - 1 of each ``[a, b)`` segment, in the
        order validation reports them; None without time stamps (plots then use
        the sample index).
        """
        if self.stamps_ns is None or not len(self.stamps_ns):
            return None
        rows = np.concatenate([np.arange(a + lag0, b) for a, b in segments]) if segments \
            else np.zeros(0, dtype=int)
        return (self.stamps_ns[rows] - self.stamps_ns[0]) / 1e9

    def metadata(self) -> dict:
        """What a model document records of its data: source, files, stamps."""
        out: dict = {"source": self.source}
        if len(self.parts) > 1 or (self.parts and self.parts[0]["source"] != self.source):
            out["records"] = [dict(p) for p in self.parts]
        if self.stamps_ns is not None and len(self.stamps_ns):
            out["first_stamp_ns"] = int(self.stamps_ns[0])
            out["last_stamp_ns"] = int(self.stamps_ns[-1])
        if self.unset_stamps:
            out["unset_stamps"] = int(self.unset_stamps)
        if self.decimation:
            out["decimation"] = dict(self.decimation)
        if self.spikes:
            out["spikes"] = dict(self.spikes)
        if self.topics:
            out["topics"] = dict(self.topics)
        return out


def combine(records: Sequence[Record]) -> Record:
    """Several records as one: arrays concatenated, segments kept apart (offsets).

    Raises
    ------
    DataError
        The records differ in their signals (names or number of inputs).
    """
    if len(records) == 1:
        return records[0]
    if len({(r.input_names, r.output_names, r.u.ndim) for r in records}) > 1:
        raise DataError("the records differ in their signals (columns); give files of the "
                        "same layout")
    bounds, gaps, missing, restarts, start = [], 0, 0, 0, 0
    periods = set()
    for r in records:
        info = r.segment_info()
        bounds += [(a + start, b + start) for a, b in info.bounds]
        gaps, missing, restarts = (gaps + info.gaps, missing + info.missing_samples,
                                   restarts + info.restarts)
        periods.add((info.period_ns, info.period_source))
        start += len(r.y)
    period, how = periods.pop() if len(periods) == 1 else (None, "per record")
    first = records[0]
    return Record(
        np.concatenate([r.u for r in records]), np.concatenate([r.y for r in records]),
        f"{len(records)} records ({', '.join(r.source for r in records)})",
        first.input_names, first.output_name,
        segments=SegmentInfo(bounds, period, how, gaps, missing, restarts),
        rejected=sum(r.rejected for r in records), unpaired=sum(r.unpaired for r in records),
        unset_stamps=sum(r.unset_stamps for r in records),
        parts=[p for r in records for p in r.parts],
        notes=[n for r in records for n in r.notes], output_names=first.output_names,
        topics=first.topics if all(r.topics == first.topics for r in records) else None)


# -- where data come from ---------------------------------------------------------------



@dataclass(frozen=True)
class DataSpec:
    """Where the data of an identification come from (see the module doc).

    Attributes
    ----------
    data : tuple of str
        Data files; several are records combined.
    bag : str or None
        A rosbag2 bag directory or ``.mcap`` file.
    inputs : tuple of str or None
        Input columns of data files, by header name or 0-based index.
    output : str or None
        Output column of data files; a comma list (``q1,q2``) for several outputs.
    bag_options : mapping
        ``input_topic``, ``input_field``, ``input_names``, ``output_topic``,
        ``output_field``, ``output_names`` for bags (None: the defaults; comma
        lists for several inputs or outputs), and ``stamp_tolerance`` (seconds).
    """

    data: tuple[str, ...] = ()
    bag: str | None = None
    inputs: tuple[str, ...] | None = None
    output: str | None = None
    bag_options: Mapping[str, str | None] = field(default_factory=dict)

    @classmethod
    def from_values(cls, values: Mapping, data=None, bag=None) -> DataSpec:
        """A spec from settings-style values (command-line options, per-input YAML).

        ``inputs`` may be a comma-separated string or a list; the bag options
        are read by their settings names.
        """
        inputs = values.get("inputs")
        if isinstance(inputs, str):
            inputs = [c for c in inputs.split(",") if c.strip()]
        files = () if not data else ((data,) if isinstance(data, str) else tuple(data))
        return cls(files, bag, tuple(inputs) if inputs else None, values.get("output"),
                   {k: values.get(k) for k in BAG_OPTIONS if values.get(k) not in (None, "")})

    @classmethod
    def for_path(cls, path: str, values: Mapping) -> DataSpec:
        """The spec of one input path: a bag when it is one, else a data file."""
        from .io.bagio import is_rosbag2_dir

        p = Path(path)
        is_bag = p.suffix == ".mcap" or (p.is_dir() and is_rosbag2_dir(p))
        if is_bag:  # the column options are for the data files among the paths
            values = {k: v for k, v in values.items() if k not in ("inputs", "output")}
        return cls.from_values(values, data=None if is_bag else path,
                               bag=path if is_bag else None)


def load_record(spec: DataSpec | None = None) -> Record:
    """Read the data a spec names (the robot-arm data when it names none).

    Raises
    ------
    DataError
        Both files and a bag, or anything the readers refuse (the message names
        the file, line or topic).
    """
    spec = spec or DataSpec()
    if spec.bag and spec.data:
        raise DataError("give either --data or --bag (data files or a bag), not both")
    if spec.bag:
        if spec.inputs or spec.output:
            raise DataError("--inputs and --output name columns of --data files; a bag's "
                            "signals are chosen with --input-topic/--input-field/"
                            "--input-names and --output-topic/--output-field/--output-names")
        return _load_bag(spec)
    if spec.data:
        return combine([_load_file(p, spec) for p in spec.data])
    from .io.datasets import find_robot_arm

    path = find_robot_arm()
    record = _load_file(str(path), DataSpec())
    return replace(record, source=f"robot-arm data ({path})")


def _load_file(path: str, spec: DataSpec) -> Record:
    from .io.channels import split_list
    from .io.data import load_data

    inputs = list(spec.inputs) if spec.inputs else None
    outputs = split_list(spec.output)
    d = load_data(path, inputs, outputs if len(outputs) > 1 else spec.output)
    stamps = None if d.t is None else np.round(d.t * 1e9).astype(np.int64)
    return Record(d.u, d.y, path, tuple(d.input_names), d.output_name or "y", stamps,
                  rejected=d.rejected, parts=[{"source": path, "samples": int(len(d.y))}],
                  notes=list(d.notes), output_names=d.output_names)


def topics_read(options: Mapping[str, object]) -> dict[str, str]:
    """Where signals were read, as a document keeps it (``metadata.topics``).

    The topics always; the other reading options (:data:`BAG_OPTIONS`) when they are
    not their defaults, so that every command and the node write the same for the
    same reading.
    """
    out = {k: str(SETTINGS[k].default) for k in ("input_topic", "output_topic")}
    for k in BAG_OPTIONS:
        v = options.get(k)
        if v not in (None, "") and str(v) != str(SETTINGS[k].default):
            out[k] = str(v)
    return out


def _load_bag(spec: DataSpec) -> Record:
    from .io.bagio import read_bag_signals

    opts = {k: v for k, v in spec.bag_options.items() if v not in (None, "")}  # 0 s is a value
    if "stamp_tolerance" in opts:  # seconds, as the node's parameter (text from a command)
        text = opts.pop("stamp_tolerance")
        try:
            seconds = check("stamp_tolerance", parse_text(SETTINGS["stamp_tolerance"], text)
                            if isinstance(text, str) else text)
        except ValueError as exc:
            raise DataError(str(exc)) from None
        opts["tolerance_ns"] = int(round(seconds * 1e9))
    sig = read_bag_signals(spec.bag, **opts)
    notes = list(sig.notes)
    if sig.unset_stamps:
        notes.append(f"{sig.unset_stamps} message(s) in {spec.bag} repeat header.stamp 0 (the "
                     "recording driver did not fill it in?); their log times were used")
    return Record(sig.u, sig.y, f"bag {spec.bag}", tuple(sig.input_names),
                  sig.output_names[0] if len(sig.output_names) == 1 else "y", sig.stamps_ns,
                  rejected=sig.rejected_nonfinite, unpaired=sig.unpaired,
                  unset_stamps=sig.unset_stamps, notes=notes,
                  output_names=sig.output_names if len(sig.output_names) > 1 else (),
                  topics=topics_read(spec.bag_options))
