"""Reading one number out of a ROS message by a field path.

A field path is dotted attribute access with optional indices, e.g.
``wrench.torque.z``, ``linear_acceleration.x`` or ``effort[0]``. The same code
reads rosbags' message objects (bags) and rclpy's message objects (live
topics), so the node and the bag reader agree on what a path means.
"""

from __future__ import annotations

import re

from ..errors import FieldPathError

__all__ = ["DEFAULT_FIELDS", "default_field", "extract", "has_unset_stamp", "message_stamp_ns"]

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

_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)")


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
        steps.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    return steps


def extract(msg: object, path: str | list[str | int]) -> float:
    """The number at ``path`` in ``msg``.

    Raises
    ------
    FieldPathError
        The path does not exist in the message, or does not lead to a number.
    """
    steps = parse_path(path) if isinstance(path, str) else path
    value = msg
    for step in steps:
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
    """``header.stamp`` in nanoseconds; None without a header or with a zero stamp.

    A zero stamp is a header the publisher never filled in (a common driver
    default), not a time: callers then use the receive (or bag log) time and
    count such messages (:func:`has_unset_stamp`).
    """
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    ns = int(stamp.sec) * 1_000_000_000 + int(getattr(stamp, "nanosec", 0))
    return ns or None


def has_unset_stamp(msg: object) -> bool:
    """True for a message whose header stamp is zero (never filled in)."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    return stamp is not None and int(stamp.sec) == 0 and int(getattr(stamp, "nanosec", 0)) == 0


def _show(steps: list[str | int]) -> str:
    out = ""
    for s in steps:
        out += f"[{s}]" if isinstance(s, int) else (f".{s}" if out else s)
    return out
