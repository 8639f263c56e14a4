"""Reading one number out of a ROS message by a field path.

A field path is dotted attribute access with optional indices, e.g.
``wrench.torque.z``, ``linear_acceleration.x`` or ``effort[0]``. An index may be
a name, ``effort[elbow_joint]``: the position of that name in the message's
``name`` (or ``joint_names``) list, message by message, as a ``JointState``
names its joints (their order is the publisher's; a message that does not name
the joint, another publisher's on the same topic, raises :class:`MissingNameError`,
which readers count and skip). The same code reads rosbags' message objects
(bags) and rclpy's message objects (live topics), so the node and the bag
reader agree on what a path means.
"""

from __future__ import annotations

import re

from ..errors import FieldPathError

__all__ = ["DEFAULT_FIELDS", "MissingNameError", "Name", "UnsetStamps", "default_field",
           "extract", "message_stamp_ns"]

#: Field used when none is given, per message type.
DEFAULT_FIELDS = {
    "geometry_msgs/msg/WrenchStamped": "wrench.torque.z",
    "geometry_msgs/msg/Wrench": "torque.z",
    "geometry_msgs/msg/AccelStamped": "accel.linear.x",
    "geometry_msgs/msg/Accel": "linear.x",
    "sensor_msgs/msg/Imu": "linear_acceleration.x",
    "sensor_msgs/msg/JointState": "effort[0]",
    "std_msgs/msg/Float64": "data",
    "std_msgs/msg/Float32": "data",
}

_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[[A-Za-z0-9_/-]+\])*)")

#: The lists a message names its array entries by (``JointState.name``,
#: ``MultiDOFJointState.joint_names``, ``JointTrajectoryControllerState.joint_names``).
_NAME_LISTS = ("name", "joint_names")


class Name(str):
    """An index given by name in a field path (``effort[elbow_joint]``)."""


class MissingNameError(FieldPathError):
    """A message does not name the entry a path asks for (counted and skipped)."""


def default_field(msgtype: str) -> str:
    """The default field path for a message type, or a clear error."""
    try:
        return DEFAULT_FIELDS[msgtype]
    except KeyError:
        raise FieldPathError(
            f"no default field for message type {msgtype}; give a field path "
            f"(types with defaults: {', '.join(sorted(DEFAULT_FIELDS))})"
        ) from None


def parse_path(path: str) -> list[str | int]:
    """Split ``a.b[2].c`` into ``['a', 'b', 2, 'c']``."""
    steps: list[str | int] = []
    for part in path.split("."):
        m = _STEP.fullmatch(part)
        if not m:
            raise FieldPathError(f"malformed field path {path!r} (at {part!r})")
        steps.append(m.group(1))
        steps.extend(int(i) if i.isdigit() else Name(i)
                     for i in re.findall(r"\[([^\]]+)\]", m.group(2)))
    return steps


def _position(owner: object, name: Name, steps: list) -> int:
    """Where ``owner``'s name list holds ``name`` (:class:`MissingNameError` when it does not)."""
    kind = getattr(owner, "__msgtype__", type(owner).__name__)  # rosbags' name, or rclpy's
    for attr in _NAME_LISTS:
        names = getattr(owner, attr, None)
        if names is not None and not isinstance(names, str):
            names = list(names)
            if name in names:
                return names.index(name)
            raise MissingNameError(f"field path {_show(steps)!r}: this {kind} message does "
                                   f"not name {name!r} (its {attr}: "
                                   f"{', '.join(map(str, names[:8])) or 'empty'}"
                                   f"{', ...' if len(names) > 8 else ''})")
    raise FieldPathError(f"field path {_show(steps)!r}: a {kind} message has "
                         f"no name list ({' or '.join(_NAME_LISTS)}) to find {name!r} in; "
                         "give the index as a number")


def extract(msg: object, path: str | list[str | int]) -> float:
    """The number at ``path`` in ``msg``.

    Raises
    ------
    FieldPathError
        The path does not exist in the message, or does not lead to a number.
    """
    steps = parse_path(path) if isinstance(path, str) else path
    value = owner = msg
    for step in steps:
        if isinstance(step, Name):
            step = _position(owner, step, steps)
        elif isinstance(step, str):
            owner = value
        try:
            value = value[step] if isinstance(step, int) else getattr(value, step)
        except (AttributeError, IndexError, TypeError):
            where = type(msg).__name__
            raise FieldPathError(
                f"field path {_show(steps)!r} does not exist in a {where} message "
                f"(failed at {step!r})"
            ) from None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise FieldPathError(
            f"field path {_show(steps)!r} leads to {type(value).__name__}, not a number"
        ) from None


def message_stamp_ns(msg: object) -> int | None:
    """``header.stamp`` in nanoseconds, or None for a message without a header."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    return int(stamp.sec) * 1_000_000_000 + int(getattr(stamp, "nanosec", 0))


class UnsetStamps:
    """Tells stamps a publisher never filled in from real ones, per stream.

    A header stamp of 0 may be a real time (a synthetic record starting at 0),
    but a stream whose stamp is 0 again right after a 0 has stamps that never
    change: they were never filled in (a common driver default), and cannot
    order or pair samples. From the second such message on, :meth:`stamp`
    returns None (the caller then uses the receive or log time) and
    :attr:`count` counts them.
    """

    def __init__(self) -> None:
        self.count = 0
        self._last: dict[object, int | None] = {}

    def stamp(self, stream: object, msg: object) -> int | None:
        """The message's stamp, or None when it has none or it was never set."""
        ns = message_stamp_ns(msg)
        last, self._last[stream] = self._last.get(stream), ns
        if ns == 0 and last == 0:
            self.count += 1
            return None
        return ns


def _show(steps: list[str | int]) -> str:
    out = ""
    for s in steps:
        out += f"[{s}]" if isinstance(s, (int, Name)) else (f".{s}" if out else s)
    return out
