"""Channels: which topic, message type and field each model input and output is read from.

A model has one or several outputs and one or several inputs. Each signal is a *channel*:
a topic, its message type, a field path in the message, and a signal name. The
same topic may carry several inputs (``sensor_msgs/msg/JointState`` with fields
``effort[0]`` and ``effort[1]``); inputs on one topic share a stamp, so they are
read from one message and aligned as one stream.

Settings give the channels as comma-separated lists (node parameters are plain
strings, so ``ros2 param`` and YAML files stay simple): one entry for all, or
one per input::

    input_topic: /joint_states            input_field: effort[0],effort[1]
    input_type:  sensor_msgs/msg/JointState   input_names: tau1,tau2

Outputs are given the same way (``output_topic``, ``output_type``,
``output_field``, ``output_names``); several outputs make a coupled model of
several joints (:mod:`spm_sysid.core.model.mimo`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ..errors import FieldPathError
from .fields import default_field, parse_path

__all__ = ["Channel", "check_roles", "parse_channels", "split_list", "stream_order",
           "topic_streams"]


@dataclass(frozen=True)
class Channel:
    """One model input or output: where it is read from and what it is called."""

    topic: str
    msgtype: str | None
    field: str
    name: str


def split_list(value: str | Sequence[str] | None) -> list[str]:
    """A comma-separated string (or a list) as a list of stripped, non-empty items."""
    if value is None:
        return []
    items = value.split(",") if isinstance(value, str) else list(value)
    return [str(v).strip() for v in items if str(v).strip()]


def parse_channels(topics, fields=None, types=None, names=None, role: str = "input"
                   ) -> list[Channel]:
    """The input (or output) channels from per-signal lists (each of length 1 or n).

    Parameters
    ----------
    topics, fields, types, names : str (comma-separated) or sequence of str
        Topics; field paths (empty: the type's default, resolved when the type is
        known); message types (None: unknown yet, e.g. read from a bag); signal
        names (default ``u`` for one input, ``u1, u2, ...`` for several;
        ``y``, ``y1, y2, ...`` for outputs).
    role : {"input", "output"}
        Which signals: names the settings in messages and the default names.

    Raises
    ------
    ValueError
        Lists of different lengths (other than 1), no topic, a bad field path,
        names that are not distinct identifiers.
    """
    r = role
    lists = {f"{r}_topic": split_list(topics), f"{r}_field": split_list(fields),
             f"{r}_type": split_list(types), f"{r}_names": split_list(names)}
    if not lists[f"{r}_topic"]:
        raise ValueError(f"{r}_topic: give at least one topic")
    n = max(len(v) for v in lists.values())
    for label, values in lists.items():
        if len(values) not in (0, 1, n):
            raise ValueError(f"{label} lists {len(values)} entries for {n} {r}s (give one "
                             f"entry for all {r}s, or one per {r})")

    def pick(label: str, i: int) -> str | None:
        values = lists[f"{r}_{label}"]
        return values[0] if len(values) == 1 else (values[i] if values else None)

    names_ = _signal_names(lists[f"{r}_names"], n, r)
    channels = []
    for i in range(n):
        msgtype, field = pick("type", i), pick("field", i) or ""
        try:
            if field:  # an empty field is the type's default, resolved with the type
                parse_path(field)
        except FieldPathError as exc:
            raise ValueError(f"{r} {names_[i]}: {exc}") from None
        channels.append(Channel(pick("topic", i), msgtype, field, names_[i]))
    _check_distinct(channels, n, r)
    return channels


def _signal_names(given: list[str], n: int, r: str) -> list[str]:
    """The names given, or ``u``/``u1, u2, ...`` (``y`` for outputs); distinct identifiers."""
    letter = "u" if r == "input" else "y"
    names = given or ([letter] if n == 1 else [f"{letter}{i + 1}" for i in range(n)])
    if len(names) == 1 and n > 1:
        raise ValueError(f"{r}_names gives one name for {n} {r}s")
    if len(set(names)) != n or not all(nm.isidentifier() for nm in names):
        raise ValueError(f"{r}_names must be distinct identifiers, got {', '.join(names)}")
    return names


def _check_distinct(channels: list[Channel], n: int, r: str) -> None:
    """No field read twice from one topic; one type per topic."""
    if len({(c.topic, c.field) for c in channels}) != n:
        raise ValueError(f"two {r}s read the same field of the same topic")
    for c in channels:
        same = {d.msgtype for d in channels if d.topic == c.topic}
        if len(same) > 1:
            raise ValueError(f"topic {c.topic} is given two types: {', '.join(map(str, same))}")


def topic_streams(channels: Sequence[Channel]) -> list[tuple[str, str | None, list[int]]]:
    """Channels grouped by topic, in order of first appearance: (topic, type, inputs).

    Each group is one stream of the sample buffer; ``inputs`` are the indices of
    its channels, in order (the buffer numbers inputs stream by stream, so the
    model's input order is the order of :func:`stream_order`).
    """
    groups: dict[str, tuple[str | None, list[int]]] = {}
    for i, c in enumerate(channels):
        groups.setdefault(c.topic, (c.msgtype, []))[1].append(i)
    return [(topic, msgtype, idx) for topic, (msgtype, idx) in groups.items()]


def stream_order(channels: Sequence[Channel]) -> list[int]:
    """Channel indices in the buffer's input order (stream by stream)."""
    return [i for _, _, idx in topic_streams(channels) for i in idx]


def check_roles(inputs: Sequence[Channel], outputs: Sequence[Channel],
                msgtypes: Mapping[str, str] | None = None) -> None:
    """Inputs and outputs that can be read together, or a ValueError saying why.

    Their names differ; an output may share a topic with inputs (a
    ``JointState``: efforts in, velocities out) but not a field (a type's
    default field counts as that field), and a topic has one type.
    ``msgtypes`` (topic -> type) gives the types when the channels do not (a
    bag's connections).
    """
    clash = {c.name for c in inputs} & {c.name for c in outputs}
    if clash:
        raise ValueError(f"an input and an output share the name {', '.join(sorted(clash))} "
                         "(set input_names or output_names)")

    def msgtype(c: Channel) -> str | None:
        return c.msgtype or (msgtypes or {}).get(c.topic)

    def field(c: Channel) -> str:
        return c.field or (default_field(msgtype(c)) if msgtype(c) else "")

    for c in outputs:
        if any(d.topic == c.topic and field(d) == field(c) for d in inputs):
            raise ValueError(f"output {c.name} reads the same field of {c.topic} as an input")
        if any(d.topic == c.topic and msgtype(d) != msgtype(c) for d in inputs):
            raise ValueError(f"topic {c.topic} is given two types (input_type and "
                             "output_type)")
