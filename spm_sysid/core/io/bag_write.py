"""Writing input/output data as a rosbag2 MCAP bag (format version 9).

Writing uses rosbags' :class:`~rosbags.rosbag2.Writer` with the MCAP storage
plugin and bag format version 9, the format ``ros2 bag play`` (Jazzy) reads.
Each sample k becomes one message per topic, both stamped ``start + k / rate``
in ``header.stamp`` and as the bag's log time:

* input u  -> ``/robot_arm/torque``,       ``geometry_msgs/msg/WrenchStamped``, ``wrench.torque.z``
* output y -> ``/robot_arm/acceleration``, ``geometry_msgs/msg/AccelStamped``,  ``accel.linear.x``

The robot-arm data set gives no sampling time; :data:`DEFAULT_RATE_HZ` (100 Hz,
Ts = 0.01 s, the value some third-party examples assume) is a nominal choice.

The MCAP file is written by the ``mcap`` library (through a small rosbags
storage plugin, so rosbags still writes ``metadata.yaml``) with a CRC-32 of
every chunk, of the data section and of the summary.

A bag is never half-written or destroyed: it is written into a temporary
directory beside the destination and moved into place when complete;
``overwrite`` replaces only a directory that is a rosbag2 bag and holds nothing
but the bag's own files (``metadata.yaml`` and its storage files): a directory
that also keeps notes, sub-folders or other results is refused, untouched.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import BagError
from .bag_files import (
    DEFAULT_INPUT_TOPIC,
    DEFAULT_OUTPUT_TOPIC,
    DEFAULT_RATE_HZ,
    INPUT_TYPE,
    JOINT_TYPE,
    OUTPUT_TYPE,
    default_qos,
    foreign_files,
    is_rosbag2_dir,
    typestore,
)

__all__ = ["write_io_bag"]


class _CrcMcapStorage:
    """rosbags storage plugin writing MCAP with the ``mcap`` library, CRCs on.

    rosbags' own MCAP writer leaves every CRC field 0 (unchecked); this one keeps
    rosbags' bag layout and ``metadata.yaml`` and lets ``mcap`` checksum every
    chunk, the data section and the summary.
    """

    def __init__(self, path: Path, compression) -> None:
        from mcap.writer import CompressionType, Writer

        from ... import __version__

        self.path = path / f"{path.name}.mcap"
        self._file = self.path.open("xb")
        self._writer = Writer(self._file, compression=CompressionType.NONE, enable_crcs=True,
                              enable_data_crcs=True)
        self._writer.start(profile="ros2", library=f"spm_sysid {__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[int, int] = {}

    def add_msgtype(self, connection) -> None:
        fmt = "ros2idl" if connection.msgdef.data.startswith("=" * 80 + "\nIDL: ") \
            else "ros2msg"
        self._schemas[connection.msgtype] = self._writer.register_schema(
            name=connection.msgtype, encoding=fmt, data=connection.msgdef.data.encode())

    def add_connection(self, connection, offered_qos_profiles: str) -> None:
        self._channels[connection.id] = self._writer.register_channel(
            topic=connection.topic,
            message_encoding=connection.ext.serialization_format,
            schema_id=self._schemas[connection.msgtype],
            metadata={"offered_qos_profiles": offered_qos_profiles})

    def write(self, connection, timestamp: int, data) -> None:
        self._writer.add_message(channel_id=self._channels[connection.id], log_time=timestamp,
                                 data=bytes(data), publish_time=timestamp)

    def close(self, version: int, metadata: str) -> None:
        self._writer.add_metadata("rosbag2", {"serialized_metadata": metadata})
        self._writer.finish()
        self._file.close()

    def abort(self) -> None:
        self._file.close()


def write_io_bag(
    path: str | Path,
    u: np.ndarray,
    y: np.ndarray,
    *,
    rate_hz: float = DEFAULT_RATE_HZ,
    start_ns: int = 0,
    input_topic: str = DEFAULT_INPUT_TOPIC,
    output_topic: str | Sequence[str] = DEFAULT_OUTPUT_TOPIC,
    input_frame: str = "robot_arm_base",
    output_frame: str = "robot_arm_tip",
    input_names: Sequence[str] | None = None,
    overwrite: bool = False,
    output_names: Sequence[str] | None = None,
) -> Path:
    """Write u and y as a rosbag2 MCAP bag (format version 9) at directory ``path``.

    One input (``u`` of shape (n,)) is written as ``geometry_msgs/msg/WrenchStamped``
    (torque.z), several (shape (n, m)) as ``sensor_msgs/msg/JointState`` with
    ``effort[i]`` = input i and joint names ``input_names`` (default u1, u2, ...);
    the output as ``geometry_msgs/msg/AccelStamped`` (linear.x). Several outputs
    (``y`` of shape (n, q)): one ``AccelStamped`` topic per output when
    ``output_topic`` lists q topics (comma list or sequence), else one
    ``JointState`` topic with ``velocity[i]`` = output i (joint names
    ``output_names``, default y1, y2, ...).

    Everything is checked before anything is touched; the bag is written into a
    temporary directory beside ``path`` and moved into place when complete, so
    a failure leaves an existing bag as it was.

    Raises
    ------
    BagError
        Bad rate or start, unequal lengths, non-finite values, an existing bag
        without ``overwrite``, or an existing path that is not a rosbag2 bag.
    """
    path = Path(path)
    u, y = _checked_signals(u, y, rate_hz, start_ns)
    out_topics, out_joints = _output_layout(y, output_topic, output_names)
    joints = None
    if u.ndim == 2:
        joints = list(input_names or [f"u{i + 1}" for i in range(u.shape[1])])
        if len(joints) != u.shape[1]:
            raise BagError(f"{len(joints)} input names for {u.shape[1]} inputs")
    if input_topic in out_topics:
        raise BagError("input and output topics must differ")
    path = _replaceable(path, overwrite)
    stage, tmp = _stage(path)
    try:
        _write_messages(tmp, u, y, start_ns=start_ns, period_ns=1e9 / rate_hz,
                        topics=(input_topic, out_topics), frames=(input_frame, output_frame),
                        joints=(joints, out_joints))
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        if isinstance(exc, (OSError, ValueError)) and not isinstance(exc, BagError):
            raise BagError(f"could not write the bag {path}: {exc}") from None
        raise
    _move_into_place(stage, tmp, path)
    return path


def _stage(path: Path) -> tuple[Path, Path]:
    """An empty STAGE directory beside ``path`` and STAGE/NAME, where the bag is written.

    Every file name inside (metadata.yaml and the rosbag2 record in the MCAP file)
    is then already the final one.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    stage = path.parent / f".{path.name}.partial-{os.getpid()}"
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir()
    return stage, stage / path.name


def _move_into_place(stage: Path, tmp: Path, path: Path) -> None:
    """The complete bag replaces ``path`` (an old bag is removed only after)."""
    if path.exists():
        old = path.parent / f".{path.name}.old-{os.getpid()}"
        path.rename(old)
        tmp.rename(path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(path)
    stage.rmdir()


def _checked_signals(u: np.ndarray, y: np.ndarray, rate_hz: float,
                     start_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """The signals as float arrays (one column: a vector), or a BagError naming the problem."""
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise BagError(f"rate must be a positive, finite number of Hz, got {rate_hz}")
    if not (isinstance(start_ns, (int, np.integer)) and 0 <= start_ns < 2**63 - 2**62):
        raise BagError(f"start must be >= 0 seconds (a ROS time), got {start_ns / 1e9:g} s")
    if u.ndim == 2 and u.shape[1] == 1:
        u = u[:, 0]
    if y.ndim == 2 and y.shape[1] == 1:
        y = y[:, 0]
    if len(u) != len(y) or u.ndim not in (1, 2) or y.ndim not in (1, 2):
        raise BagError(f"u must be (n,) or (n, inputs) and y (n,) or (n, outputs), got "
                       f"{u.shape} and {y.shape}")
    if len(u) == 0:
        raise BagError("no samples to write")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise BagError("u and y must be finite (NaN or inf found)")
    return u, y


def _output_layout(y: np.ndarray, output_topic: str | Sequence[str],
                   output_names: Sequence[str] | None) -> tuple[list[str], list[str] | None]:
    """The output topics, and the joint names when several outputs share one JointState."""
    out_topics = ([t.strip() for t in output_topic.split(",") if t.strip()]
                  if isinstance(output_topic, str) else list(output_topic))
    out_joints = None
    if y.ndim == 2 and len(out_topics) == 1:  # several outputs on one JointState topic
        out_joints = list(output_names or [f"y{i + 1}" for i in range(y.shape[1])])
        if len(out_joints) != y.shape[1]:
            raise BagError(f"{len(out_joints)} output names for {y.shape[1]} outputs")
    elif len(out_topics) != (1 if y.ndim == 1 else y.shape[1]):
        raise BagError(f"{len(out_topics)} output topics for "
                       f"{1 if y.ndim == 1 else y.shape[1]} outputs (give one topic, or one "
                       "per output)")
    if len(set(out_topics)) != len(out_topics):
        raise BagError("the output topics must differ")
    return out_topics, out_joints


def _replaceable(path: Path, overwrite: bool) -> Path:
    """Where the bag goes: ``path``, or the bag a link names; refused if not ours to replace."""
    if not (path.exists() or path.is_symlink()):
        return path
    if not overwrite:
        raise BagError(f"{path} already exists (use --force to replace it)")
    if not is_rosbag2_dir(path):
        raise BagError(f"{path} exists and is not a rosbag2 bag (no rosbag2 metadata.yaml);"
                       " refusing to replace it, nothing was changed")
    foreign = foreign_files(path)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more"
                                          if len(foreign) > 5 else "")
        raise BagError(f"{path} holds files that are not part of the bag ({shown}); "
                       "refusing to replace it, nothing was changed (move them out or "
                       "choose another output)")
    if path.is_symlink():  # the bag the link names is replaced; the link stays
        return Path(os.path.realpath(path))
    return path


def _write_messages(tmp: Path, u: np.ndarray, y: np.ndarray, *, start_ns: int,
                    period_ns: float, topics: tuple[str, list[str]], frames: tuple[str, str],
                    joints: tuple[list[str] | None, list[str] | None]) -> None:
    """One message per topic and sample into a new bag at ``tmp``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    messages = _Messages(store, frames, joints)
    writer = Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.STORAGE_PLUGINS = {StoragePlugin.MCAP: _CrcMcapStorage}
    with writer:
        qos = [default_qos()]
        c_in = writer.add_connection(topics[0], messages.in_type, typestore=store,
                                     offered_qos_profiles=qos)
        c_outs = [writer.add_connection(t, messages.out_type, typestore=store,
                                        offered_qos_profiles=qos) for t in topics[1]]
        ys = y[:, None] if y.ndim == 1 else y
        for k in range(len(u)):
            t_ns = start_ns + int(round(k * period_ns))
            stamp = messages.Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
            writer.write(c_in, t_ns, messages.input(stamp, u[k]))
            if joints[1] is not None:
                writer.write(c_outs[0], t_ns, messages.outputs(stamp, ys[k]))
                continue
            for c_out, value in zip(c_outs, ys[k]):
                writer.write(c_out, t_ns, messages.output(stamp, value))


class _Messages:
    """Serialised messages of one sample: WrenchStamped/AccelStamped, or JointState."""

    def __init__(self, store, frames: tuple[str, str],
                 joints: tuple[list[str] | None, list[str] | None]) -> None:
        self.store = store
        types = store.types
        self.Header, self.Time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
        self.Vector3 = types["geometry_msgs/msg/Vector3"]
        self.types = types
        self.frames, self.joints = frames, joints
        self.in_type = INPUT_TYPE if joints[0] is None else JOINT_TYPE
        self.out_type = OUTPUT_TYPE if joints[1] is None else JOINT_TYPE
        self.zero = self.Vector3(x=0.0, y=0.0, z=0.0)
        self.empty = np.zeros(0)

    def input(self, stamp, value) -> bytes:
        """The input of one sample (torque.z, or the efforts of the joints)."""
        header = self.Header(stamp=stamp, frame_id=self.frames[0])
        if self.joints[0] is None:
            wrench = self.types["geometry_msgs/msg/Wrench"](
                force=self.zero, torque=self.Vector3(x=0.0, y=0.0, z=float(value)))
            msg = self.types[INPUT_TYPE](header=header, wrench=wrench)
        else:
            msg = self.types[JOINT_TYPE](header=header, name=self.joints[0], position=self.empty,
                                         velocity=self.empty,
                                         effort=np.ascontiguousarray(value))
        return self.store.serialize_cdr(msg, self.in_type)

    def outputs(self, stamp, values) -> bytes:
        """Several outputs as the velocities of one JointState."""
        msg = self.types[JOINT_TYPE](header=self.Header(stamp=stamp, frame_id=self.frames[1]),
                                     name=self.joints[1], position=self.empty,
                                     velocity=np.ascontiguousarray(values), effort=self.empty)
        return self.store.serialize_cdr(msg, JOINT_TYPE)

    def output(self, stamp, value) -> bytes:
        """One output as an AccelStamped's linear.x."""
        msg = self.types[OUTPUT_TYPE](
            header=self.Header(stamp=stamp, frame_id=self.frames[1]),
            accel=self.types["geometry_msgs/msg/Accel"](
                linear=self.Vector3(x=float(value), y=0.0, z=0.0), angular=self.zero))
        return self.store.serialize_cdr(msg, OUTPUT_TYPE)
