"""Reading aligned input/output signals from a rosbag2 bag.

Reading turns topics of any supported type and field path into aligned u/y
arrays by pairing header stamps with the node's own rule
(:func:`spm_sysid.core.stream.buffer.pair_streams`, the node's default
tolerance), so a bag pairs the same offline and in the node: messages go
through it in log-time order, NaN/inf values are rejected and counted, stamps
that go back start a new segment, and the holes show in the stamps
(:func:`spm_sysid.core.model.segments.find_segments`). Messages without a
header are stamped with their log time; header stamps that stay zero (never
filled in; :class:`~spm_sysid.core.io.fields.UnsetStamps`) are not times:
those messages' log times are used instead, and they are counted
(``unset_stamps``). Every failure is a
:class:`BagError` with a message naming the bag and the problem. The bag's
files and CRCs are checked first (:mod:`.bag_files`); writing is
:mod:`.bag_write`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import BagError, FieldPathError
from ..settings import SETTINGS
from ..stream.buffer import pair_streams
from .bag_files import (
    DEFAULT_INPUT_TOPIC,
    DEFAULT_OUTPUT_TOPIC,
    DEFAULT_RATE_HZ,
    INPUT_TYPE,
    OUTPUT_TYPE,
    is_rosbag2_dir,
    open_bag,
    typestore,
    verify_mcap,
)
from .bag_write import write_io_bag
from .channels import check_roles, parse_channels, stream_order, topic_streams
from .fields import MissingNameError, UnsetStamps, default_field, extract, parse_path

__all__ = [
    "DEFAULT_INPUT_TOPIC",
    "DEFAULT_OUTPUT_TOPIC",
    "DEFAULT_RATE_HZ",
    "INPUT_TYPE",
    "OUTPUT_TYPE",
    "BagSignals",
    "open_bag",
    "read_bag_signals",
    "is_rosbag2_dir",
    "typestore",
    "verify_mcap",
    "write_io_bag",
]


@dataclass
class BagSignals:
    """Aligned signals read from a bag."""

    u: np.ndarray
    y: np.ndarray
    stamps_ns: np.ndarray
    input_count: int
    output_count: int
    topics: dict[str, str] = field(default_factory=dict)
    rejected_nonfinite: int = 0
    crc_checked: bool = False
    input_names: tuple[str, ...] = ("u",)
    unset_stamps: int = 0  # messages whose header.stamp was zero: their log time was used
    output_names: tuple[str, ...] = ("y",)  # several: y has one column per output
    streams: int = 0  # aligned streams (a topic read for inputs and outputs counts twice)
    unnamed: dict[str, int] = field(default_factory=dict)  # per topic: skipped, see notes
    notes: list[str] = field(default_factory=list)  # what a user should know of the reading

    @property
    def unpaired(self) -> int:
        """Finite messages on any stream that are not part of an aligned sample."""
        return (self.input_count + self.output_count - self.rejected_nonfinite
                - (self.streams or len(self.topics)) * len(self.u))


def read_bag_signals(
    path: str | Path, *, input_topic: str | Sequence[str] = DEFAULT_INPUT_TOPIC,
    output_topic: str | Sequence[str] = DEFAULT_OUTPUT_TOPIC,
    input_field: str | Sequence[str] | None = None,
    output_field: str | Sequence[str] | None = None,
    input_names: str | Sequence[str] | None = None, tolerance_ns: int | None = None,
    output_names: str | Sequence[str] | None = None,
) -> BagSignals:
    """Read the inputs and outputs from topics of a bag, aligned by header stamp as the node does.

    Several inputs: ``input_topic``, ``input_field`` and ``input_names`` are
    comma-separated lists (one entry for all inputs, or one per input; see
    :func:`spm_sysid.core.io.channels.parse_channels`), e.g. one
    ``sensor_msgs/msg/JointState`` topic with fields ``effort[0],effort[1]``.
    Several outputs likewise; ``y`` then has one column per output. Fields
    default by message type (:data:`spm_sysid.core.io.fields.DEFAULT_FIELDS`);
    ``tolerance_ns`` defaults to the node's ``stamp_tolerance``. The alignment
    and what it counts: the module doc.

    Raises
    ------
    BagError
        Missing or damaged bag (CRC mismatch), missing topic, unsupported type or
        bad field path, inconsistent input lists, or no aligned samples.
    """
    if tolerance_ns is None:
        tolerance_ns = int(round(SETTINGS["stamp_tolerance"].default * 1e9))
    channels, out_channels = _parse_channels((input_topic, input_field, input_names),
                                             (output_topic, output_field, output_names))
    groups = topic_streams(channels)
    out_groups = topic_streams(out_channels)
    path = Path(path)
    reader = open_bag(path)
    crc_checked = reader.crc_checked
    try:
        conns = {c.topic: c for c in reader.connections}
        streams = _topic_streams(path, conns, (channels, groups), (out_channels, out_groups))
        events, unset, unnamed = _stream_events(path, reader, conns, streams)
    finally:
        reader.close()
    stamps, u, y, stats = pair_streams(events, tolerance_ns,
                                       input_widths=[len(g[2]) for g in groups],
                                       output_widths=[len(g[2]) for g in out_groups])
    if len(u) == 0:
        raise _nothing_paired(path, events, tolerance_ns, unnamed)
    # the buffer numbers inputs topic by topic: back to the given order
    u, y = _in_given_order(u, channels), _in_given_order(y, out_channels)
    return BagSignals(
        u=u, y=y, stamps_ns=stamps, input_count=stats.received_inputs,
        output_count=stats.received_outputs,
        topics={t: conns[t].msgtype for t in streams},
        streams=sum(len(v) for v in streams.values()),
        rejected_nonfinite=stats.rejected_nonfinite, crc_checked=crc_checked,
        input_names=tuple(c.name for c in channels), unset_stamps=unset.count,
        output_names=tuple(c.name for c in out_channels),
        unnamed={t: n for t, (n, _) in unnamed.items()},
        notes=[f"{n} message(s) on {t} skipped: {first} (another publisher on that topic?)"
               for t, (n, first) in unnamed.items()],
    )


def _nothing_paired(path: Path, events: list, tolerance_ns: int, unnamed: dict) -> BagError:
    """The error of a bag whose inputs and outputs never pair: why, and what pairs them."""
    return BagError(f"{path}: no input and output messages with matching stamps (tolerance "
                    f"{tolerance_ns} ns)" + _offset_hint(events, tolerance_ns)
                    + "".join(f"; {n} message(s) on {t} skipped: {first}"
                              for t, (n, first) in unnamed.items()))


def _offset_hint(events: list, tolerance_ns: int) -> str:
    """How far the outputs' stamps lie from the nearest input's, when beyond the tolerance.

    Two drivers or clocks out of step stamp the same instant differently; the
    median distance says what ``stamp_tolerance`` would pair them ('' when no
    stamps of both kinds, or within the tolerance).
    """
    out = np.array([st for stream, st, _ in events if stream == "y" or (
        isinstance(stream, tuple) and stream[1] == 0)], dtype=np.int64)
    inp = np.sort(np.array([st for stream, st, _ in events if stream in ("u", 0)],
                           dtype=np.int64))
    if not out.size or not inp.size:
        return ""
    at = np.clip(np.searchsorted(inp, out), 1, len(inp) - 1) if len(inp) > 1 else \
        np.zeros(len(out), dtype=np.int64)
    nearest = np.abs(out - inp[at])
    if len(inp) > 1:
        nearest = np.minimum(nearest, np.abs(out - inp[at - 1]))
    gap = float(np.median(nearest))
    if gap <= tolerance_ns:
        return ""
    return (f"; each output's stamp lies a median {gap / 1e6:.3g} ms from the nearest input's "
            f"(two drivers or clocks out of step?): --stamp-tolerance {1.5 * gap / 1e9:.3g} "
            "(the node's stamp_tolerance) would pair them")


def _parse_channels(inputs: tuple, outputs: tuple) -> tuple[list, list]:
    """The input and output channels from (topics, fields, names), or a BagError."""
    try:
        return (parse_channels(inputs[0], inputs[1], None, inputs[2]),
                parse_channels(outputs[0], outputs[1], None, outputs[2], role="output"))
    except ValueError as exc:
        raise BagError(str(exc)) from None


def _in_given_order(values: np.ndarray, channels: list) -> np.ndarray:
    """Columns in the channels' given order (the buffer numbers them topic by topic)."""
    return values[:, np.argsort(stream_order(channels))] if values.ndim == 2 else values


def _topic_streams(path: Path, conns: dict, inputs: tuple, outputs: tuple) -> dict:
    """Per topic its streams: ``(stream, field paths)``, or a BagError naming the topic.

    A stream is ``("y", k)`` for output stream k, or the index of the input
    stream; one field path per value. ``inputs`` and ``outputs`` are (channels,
    their topic groups). One topic may carry both (JointState: effort in,
    velocity out).
    """
    for topic in [g[0] for g in inputs[1]] + [g[0] for g in outputs[1]]:
        if topic not in conns:
            raise BagError(
                f"{path} has no topic {topic}; it has: {', '.join(sorted(conns)) or 'none'}")
    try:
        check_roles(inputs[0], outputs[0], {t: c.msgtype for t, c in conns.items()})
    except ValueError as exc:
        raise BagError(str(exc)) from None
    streams: dict[str, list[tuple[tuple | int, list]]] = {}
    try:
        for role, (chans, gs) in enumerate((inputs, outputs)):
            for i, (topic, _, idx) in enumerate(gs):
                msgtype = conns[topic].msgtype
                streams.setdefault(topic, []).append((("y", i) if role else i, [
                    parse_path(chans[j].field or default_field(msgtype)) for j in idx]))
    except FieldPathError as exc:
        raise BagError(f"topic {topic} ({conns[topic].msgtype}): {exc}") from None
    return streams


def _stream_events(path: Path, reader, conns: dict,
                   streams: dict) -> tuple[list, UnsetStamps, dict[str, tuple[int, str]]]:
    """Every message's ``(stream, stamp, values)`` in log-time order; the unset stamps.

    Third: per topic, the messages that do not name an entry a path asks for by
    name (how many, the first one's error): skipped, as another publisher's.
    """
    events = []
    unset = UnsetStamps()
    unnamed: dict[str, tuple[int, str]] = {}
    try:
        for c, log_ns, raw in reader.messages(connections=[conns[t] for t in streams]):
            msg = reader.deserialize(raw, c.msgtype)
            st = unset.stamp(c.topic, msg)
            for stream, steps in streams[c.topic]:
                try:
                    values = [extract(msg, s) for s in steps]
                except MissingNameError as exc:
                    count, first = unnamed.get(c.topic, (0, str(exc)))
                    unnamed[c.topic] = (count + 1, first)
                    continue
                events.append((stream, log_ns if st is None else st, values))
    except FieldPathError as exc:
        raise BagError(f"topic {c.topic} has type {c.msgtype}: {exc}") from None
    except Exception as exc:
        raise BagError(f"cannot read messages from {path}: {exc}") from None
    return events, unset, unnamed
