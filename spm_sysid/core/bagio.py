"""rosbag2 (MCAP) bags of input/output data: write them, read signals from them.

Writing uses rosbags' :class:`~rosbags.rosbag2.Writer` with the MCAP storage
plugin and bag format version 9, the format ``ros2 bag play`` (Jazzy) reads.
Each sample k becomes one message per topic, both stamped ``start + k / rate``
in ``header.stamp`` and as the bag's log time:

* input u  -> ``/robot_arm/torque``,       ``geometry_msgs/msg/WrenchStamped``, ``wrench.torque.z``
* output y -> ``/robot_arm/acceleration``, ``geometry_msgs/msg/AccelStamped``,  ``accel.linear.x``

The robot-arm data set gives no sampling time; :data:`DEFAULT_RATE_HZ` (100 Hz,
Ts = 0.01 s, the value some third-party examples assume) is a nominal choice.

Reading turns two topics of any supported type and field path into aligned u/y
arrays by pairing header stamps (see :func:`pair_by_stamp`). Every failure is a
:class:`BagError` with a message naming the bag and the problem.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .data import DataError
from .fields import FieldPathError, default_field, extract, message_stamp_ns, parse_path

__all__ = [
    "DEFAULT_INPUT_TOPIC",
    "DEFAULT_OUTPUT_TOPIC",
    "DEFAULT_RATE_HZ",
    "BagError",
    "BagSignals",
    "open_bag",
    "pair_by_stamp",
    "read_bag_signals",
    "typestore",
    "write_io_bag",
]

DEFAULT_RATE_HZ = 100.0
DEFAULT_INPUT_TOPIC = "/robot_arm/torque"
DEFAULT_OUTPUT_TOPIC = "/robot_arm/acceleration"
INPUT_TYPE = "geometry_msgs/msg/WrenchStamped"
OUTPUT_TYPE = "geometry_msgs/msg/AccelStamped"


class BagError(DataError):
    """A bag that cannot be written or read as asked."""


def typestore():
    """The ROS 2 Jazzy message types known to rosbags."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def default_qos():
    """The QoS our recorded publishers offered: reliable, volatile, keep-last 10.

    A default rclpy subscriber (reliable, volatile) matches it.
    """
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    infinite = QosTime(sec=2147483647, nsec=4294967295)
    return Qos(
        history=QosHistory.KEEP_LAST, depth=10, reliability=QosReliability.RELIABLE,
        durability=QosDurability.VOLATILE, deadline=infinite, lifespan=infinite,
        liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=infinite,
        avoid_ros_namespace_conventions=False,
    )


def write_io_bag(
    path: str | Path,
    u: np.ndarray,
    y: np.ndarray,
    *,
    rate_hz: float = DEFAULT_RATE_HZ,
    start_ns: int = 0,
    input_topic: str = DEFAULT_INPUT_TOPIC,
    output_topic: str = DEFAULT_OUTPUT_TOPIC,
    input_frame: str = "robot_arm_base",
    output_frame: str = "robot_arm_tip",
    overwrite: bool = False,
) -> Path:
    """Write u and y as a rosbag2 MCAP bag (format version 9) at directory ``path``.

    Raises
    ------
    BagError
        Bad rate, unequal lengths, non-finite values, or an existing bag without
        ``overwrite``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if not rate_hz > 0:
        raise BagError(f"rate must be positive, got {rate_hz}")
    if len(u) != len(y) or u.ndim != 1:
        raise BagError(f"u and y must be 1-D and equally long, got {u.shape} and {y.shape}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise BagError("u and y must be finite (NaN or inf found)")
    if input_topic == output_topic:
        raise BagError("input and output topics must differ")
    if path.exists():
        if not overwrite:
            raise BagError(f"{path} already exists (use --force to replace it)")
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)

    store = typestore()
    types = store.types
    Header, Time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    Vector3 = types["geometry_msgs/msg/Vector3"]
    WrenchStamped, Wrench = types[INPUT_TYPE], types["geometry_msgs/msg/Wrench"]
    AccelStamped, Accel = types[OUTPUT_TYPE], types["geometry_msgs/msg/Accel"]
    zero = Vector3(x=0.0, y=0.0, z=0.0)
    period_ns = 1e9 / rate_hz

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        qos = [default_qos()]
        c_in = writer.add_connection(input_topic, INPUT_TYPE, typestore=store,
                                     offered_qos_profiles=qos)
        c_out = writer.add_connection(output_topic, OUTPUT_TYPE, typestore=store,
                                      offered_qos_profiles=qos)
        for k in range(len(u)):
            t_ns = start_ns + int(round(k * period_ns))
            stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
            w = WrenchStamped(
                header=Header(stamp=stamp, frame_id=input_frame),
                wrench=Wrench(force=zero, torque=Vector3(x=0.0, y=0.0, z=float(u[k]))),
            )
            a = AccelStamped(
                header=Header(stamp=stamp, frame_id=output_frame),
                accel=Accel(linear=Vector3(x=float(y[k]), y=0.0, z=0.0), angular=zero),
            )
            writer.write(c_in, t_ns, store.serialize_cdr(w, INPUT_TYPE))
            writer.write(c_out, t_ns, store.serialize_cdr(a, OUTPUT_TYPE))
    return path


def pair_by_stamp(
    t_u: np.ndarray, t_y: np.ndarray, tolerance_ns: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(iu, iy)`` pairing each output stamp with the nearest input stamp.

    Pairs are one-to-one and kept only when the stamps differ by at most
    ``tolerance_ns``; both stamp arrays must be sorted.
    """
    t_u = np.asarray(t_u, dtype=np.int64)
    t_y = np.asarray(t_y, dtype=np.int64)
    if len(t_u) == 0 or len(t_y) == 0:
        return np.empty(0, dtype=int), np.empty(0, dtype=int)
    pos = np.searchsorted(t_u, t_y).clip(1, len(t_u) - 1) if len(t_u) > 1 else np.zeros(
        len(t_y), dtype=int)
    left = pos - 1 if len(t_u) > 1 else pos
    nearest = np.where(np.abs(t_u[left] - t_y) <= np.abs(t_u[pos] - t_y), left, pos)
    ok = np.abs(t_u[nearest] - t_y) <= tolerance_ns
    iy = np.flatnonzero(ok)
    iu = nearest[ok]
    # one-to-one: an input sample pairs with its first matching output only
    _, first = np.unique(iu, return_index=True)
    return iu[first], iy[first]


@dataclass
class BagSignals:
    """Aligned signals read from a bag."""

    u: np.ndarray
    y: np.ndarray
    stamps_ns: np.ndarray
    input_count: int
    output_count: int
    topics: dict[str, str] = field(default_factory=dict)

    @property
    def unpaired(self) -> int:
        """Messages on either topic without a partner."""
        return self.input_count + self.output_count - 2 * len(self.u)


def open_bag(path: Path):
    """An open rosbags AnyReader for a bag directory or ``.mcap`` file, or a BagError."""
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise BagError(f"bag not found: {path}")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise BagError(f"{path} is not a rosbag2 bag (no metadata.yaml in the directory)")
    if path.is_file() and path.suffix != ".mcap":
        raise BagError(f"{path} is not a bag (expected a bag directory or an .mcap file)")
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises several types for damaged files
        raise BagError(f"cannot read bag {path}: {exc}") from None
    return reader


def read_bag_signals(
    path: str | Path,
    *,
    input_topic: str = DEFAULT_INPUT_TOPIC,
    output_topic: str = DEFAULT_OUTPUT_TOPIC,
    input_field: str | None = None,
    output_field: str | None = None,
    tolerance_ns: int = 0,
) -> BagSignals:
    """Read u and y from two topics of a bag, paired by header stamp.

    Messages without a header are stamped with their log time. Fields default by
    message type (see :data:`spm_sysid.core.fields.DEFAULT_FIELDS`).

    Raises
    ------
    BagError
        Missing or damaged bag, missing topic, unsupported type or bad field path,
        non-finite values, or no pairs.
    """
    path = Path(path)
    reader = open_bag(path)
    try:
        conns = {c.topic: c for c in reader.connections}
        for topic in (input_topic, output_topic):
            if topic not in conns:
                raise BagError(
                    f"{path} has no topic {topic}; it has: {', '.join(sorted(conns)) or 'none'}"
                )
        series = {}
        for topic, fpath in ((input_topic, input_field), (output_topic, output_field)):
            conn = conns[topic]
            try:
                steps = parse_path(fpath or default_field(conn.msgtype))
            except FieldPathError as exc:
                raise BagError(f"topic {topic} ({conn.msgtype}): {exc}") from None
            stamps, values = [], []
            try:
                for c, log_ns, raw in reader.messages(connections=[conn]):
                    msg = reader.deserialize(raw, c.msgtype)
                    values.append(extract(msg, steps))
                    st = message_stamp_ns(msg)
                    stamps.append(log_ns if st is None else st)
            except FieldPathError as exc:
                raise BagError(f"topic {topic} has type {conn.msgtype}: {exc}") from None
            except BagError:
                raise
            except Exception as exc:
                raise BagError(f"cannot read messages of {topic} from {path}: {exc}") from None
            series[topic] = (np.array(stamps, dtype=np.int64), np.array(values, dtype=float),
                             conn.msgtype)
    finally:
        reader.close()

    (tu, u, type_u), (ty, y, type_y) = series[input_topic], series[output_topic]
    for name, arr in (("input", u), ("output", y)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise BagError(f"{path}: {bad.size} non-finite {name} value(s), first at message "
                           f"{bad[0]}")
    ou, oy = np.argsort(tu, kind="stable"), np.argsort(ty, kind="stable")
    iu, iy = pair_by_stamp(tu[ou], ty[oy], tolerance_ns)
    if len(iu) == 0:
        raise BagError(f"{path}: no input and output messages with matching stamps "
                       f"(tolerance {tolerance_ns} ns)")
    return BagSignals(
        u=u[ou][iu], y=y[oy][iy], stamps_ns=ty[oy][iy], input_count=len(u),
        output_count=len(y), topics={input_topic: type_u, output_topic: type_y},
    )
