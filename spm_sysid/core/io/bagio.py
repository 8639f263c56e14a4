"""rosbag2 (MCAP) bags of input/output data: write them, read signals from them.

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
every chunk, of the data section and of the summary. Reading checks them
(:func:`verify_mcap`) before any message is used: a damaged bag is an error,
never a silently different model. Bags written without CRCs (fields 0) can't
be checked; :class:`BagSignals` says so.

A bag is never half-written or destroyed: it is written into a temporary
directory beside the destination and moved into place when complete;
``overwrite`` replaces only a directory that is a rosbag2 bag and holds nothing
but the bag's own files (``metadata.yaml`` and its storage files): a directory
that also keeps notes, sub-folders or other results is refused, untouched.

Reading turns two topics of any supported type and field path into aligned u/y
arrays by pairing header stamps with the node's own rule
(:func:`spm_sysid.core.stream.buffer.pair_streams`, the node's default
tolerance), so a bag pairs the same offline and in the node. Every failure is a
:class:`BagError` with a message naming the bag and the problem.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import BagError, FieldPathError
from ..files import file_kind
from ..settings import SETTINGS
from ..stream.buffer import pair_streams
from .channels import check_roles, parse_channels, stream_order, topic_streams
from .fields import UnsetStamps, default_field, extract, parse_path

__all__ = [
    "DEFAULT_INPUT_TOPIC",
    "DEFAULT_OUTPUT_TOPIC",
    "DEFAULT_RATE_HZ",
    "BagSignals",
    "open_bag",
    "read_bag_signals",
    "is_rosbag2_dir",
    "typestore",
    "verify_mcap",
    "write_io_bag",
]

DEFAULT_RATE_HZ = 100.0
DEFAULT_INPUT_TOPIC = "/robot_arm/torque"
DEFAULT_OUTPUT_TOPIC = "/robot_arm/acceleration"
INPUT_TYPE = "geometry_msgs/msg/WrenchStamped"
OUTPUT_TYPE = "geometry_msgs/msg/AccelStamped"
JOINT_TYPE = "sensor_msgs/msg/JointState"


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


def is_rosbag2_dir(path: Path) -> bool:
    """True for a directory holding a rosbag2 ``metadata.yaml``."""
    meta = Path(path) / "metadata.yaml"
    if not (Path(path).is_dir() and meta.is_file()):
        return False
    try:
        head = meta.read_text(errors="replace")[:4096]
    except OSError:
        return False
    return "rosbag2_bagfile_information" in head


def _listed_files(path: Path) -> set[str]:
    """The files a bag directory's ``metadata.yaml`` lists (none when it cannot be read).

    Only a regular ``metadata.yaml`` is opened (a pipe would block).
    """
    import yaml

    if _kind(path / "metadata.yaml") != "a regular file":
        return set()
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text(errors="replace"))
        return {str(p) for p in meta["rosbag2_bagfile_information"]["relative_file_paths"]}
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return set()  # rosbags' reader names what is wrong with the metadata


def _foreign_files(path: Path) -> list[str]:
    """Entries of a bag directory that are not the bag's own files."""
    own = {"metadata.yaml"} | _listed_files(path)
    out = []
    for entry in sorted(path.iterdir()):
        if entry.name in own and entry.is_file() and not entry.is_symlink():
            continue  # only what metadata.yaml lists is the bag's (another .mcap is not)
        out.append(entry.name + ("/" if entry.is_dir() else ""))
    return out


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
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
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
    joints = None
    if u.ndim == 2:
        joints = list(input_names or [f"u{i + 1}" for i in range(u.shape[1])])
        if len(joints) != u.shape[1]:
            raise BagError(f"{len(joints)} input names for {u.shape[1]} inputs")
    if len(u) == 0:
        raise BagError("no samples to write")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise BagError("u and y must be finite (NaN or inf found)")
    if input_topic in out_topics:
        raise BagError("input and output topics must differ")
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BagError(f"{path} already exists (use --force to replace it)")
        if not is_rosbag2_dir(path):
            raise BagError(f"{path} exists and is not a rosbag2 bag (no rosbag2 metadata.yaml);"
                           " refusing to replace it, nothing was changed")
        foreign = _foreign_files(path)
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more"
                                              if len(foreign) > 5 else "")
            raise BagError(f"{path} holds files that are not part of the bag ({shown}); "
                           "refusing to replace it, nothing was changed (move them out or "
                           "choose another output)")
        if path.is_symlink():  # the bag the link names is replaced; the link stays
            path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    # written as STAGE/NAME, so every file name inside (metadata.yaml and the rosbag2
    # record in the MCAP file) is already the final one; then moved into place
    stage = path.parent / f".{path.name}.partial-{os.getpid()}"
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir()
    tmp = stage / path.name

    store = typestore()
    types = store.types
    Header, Time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    Vector3 = types["geometry_msgs/msg/Vector3"]
    WrenchStamped, Wrench = types[INPUT_TYPE], types["geometry_msgs/msg/Wrench"]
    AccelStamped, Accel = types[OUTPUT_TYPE], types["geometry_msgs/msg/Accel"]
    JointState = types[JOINT_TYPE]
    in_type = INPUT_TYPE if joints is None else JOINT_TYPE
    zero = Vector3(x=0.0, y=0.0, z=0.0)
    empty = np.zeros(0)
    period_ns = 1e9 / rate_hz

    try:
        writer = Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.STORAGE_PLUGINS = {StoragePlugin.MCAP: _CrcMcapStorage}
        with writer:
            qos = [default_qos()]
            c_in = writer.add_connection(input_topic, in_type, typestore=store,
                                         offered_qos_profiles=qos)
            out_type = OUTPUT_TYPE if out_joints is None else JOINT_TYPE
            c_outs = [writer.add_connection(t, out_type, typestore=store,
                                            offered_qos_profiles=qos) for t in out_topics]
            ys = y[:, None] if y.ndim == 1 else y
            for k in range(len(u)):
                t_ns = start_ns + int(round(k * period_ns))
                stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
                if joints is None:
                    w = WrenchStamped(
                        header=Header(stamp=stamp, frame_id=input_frame),
                        wrench=Wrench(force=zero, torque=Vector3(x=0.0, y=0.0, z=float(u[k]))),
                    )
                else:
                    w = JointState(header=Header(stamp=stamp, frame_id=input_frame),
                                   name=joints, position=empty, velocity=empty,
                                   effort=np.ascontiguousarray(u[k]))
                writer.write(c_in, t_ns, store.serialize_cdr(w, in_type))
                if out_joints is not None:
                    a = JointState(header=Header(stamp=stamp, frame_id=output_frame),
                                   name=out_joints, position=empty,
                                   velocity=np.ascontiguousarray(ys[k]), effort=empty)
                    writer.write(c_outs[0], t_ns, store.serialize_cdr(a, JOINT_TYPE))
                    continue
                for c_out, value in zip(c_outs, ys[k]):
                    a = AccelStamped(
                        header=Header(stamp=stamp, frame_id=output_frame),
                        accel=Accel(linear=Vector3(x=float(value), y=0.0, z=0.0),
                                    angular=zero),
                    )
                    writer.write(c_out, t_ns, store.serialize_cdr(a, OUTPUT_TYPE))
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        if isinstance(exc, (OSError, ValueError)) and not isinstance(exc, BagError):
            raise BagError(f"could not write the bag {path}: {exc}") from None
        raise
    if path.exists():
        old = path.parent / f".{path.name}.old-{os.getpid()}"
        path.rename(old)
        tmp.rename(path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(path)
    stage.rmdir()
    return path


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

    @property
    def unpaired(self) -> int:
        """Finite messages on any stream that are not part of an aligned sample."""
        return (self.input_count + self.output_count - self.rejected_nonfinite
                - (self.streams or len(self.topics)) * len(self.u))


_MAGIC = b"\x89MCAP0\r\n"
_FOOTER = struct.Struct("<BQQQI")  # opcode, record length, summary start, offsets, crc


def _kind(path: Path) -> str | None:
    """What ``path`` is (symlinks followed), in words; None when it does not exist.

    ``stat`` never blocks on a pipe, where ``open`` would wait for a writer.
    """
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as exc:
        raise BagError(f"cannot read bag {path}: {exc.strerror or exc}") from None
    return file_kind(mode)


def _check_bag_files(path: Path) -> None:
    """Refuse a bag directory whose ``metadata.yaml`` or data files are not regular files.

    A pipe named ``*.mcap`` (or the metadata) would block the reader forever.
    """
    names = {"metadata.yaml"} | {e.name for e in path.glob("*.mcap")} | {
        e.name for e in path.glob("*.db3")} | _listed_files(path)
    for name in sorted(names):
        kind = _kind(path / name)
        if kind is not None and kind != "a regular file":
            raise BagError(f"{path / name} is {kind}, not a bag file: a bag's files must be "
                           "regular files (nothing was read)")


def verify_mcap(path: Path) -> bool:
    """Check an MCAP file's CRCs: every chunk, the data section and the summary.

    Returns True when the file carries CRCs and all match, False when it has none
    (every CRC field 0: written without them, nothing to check).

    Raises
    ------
    BagError
        A CRC mismatch, a truncated file or a record that cannot be read.
    """
    from mcap.exceptions import McapError
    from mcap.records import Chunk, DataEnd
    from mcap.stream_reader import StreamReader

    path = Path(path)
    checked = False
    try:
        size = path.stat().st_size
        with path.open("rb") as f:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Chunk) and record.uncompressed_crc:
                    checked = True
                if isinstance(record, DataEnd) and record.data_section_crc:
                    checked = True
            f.seek(size - len(_MAGIC) - _FOOTER.size)
            opcode, _, summary_start, _, summary_crc = _FOOTER.unpack(f.read(_FOOTER.size))
            if opcode != 0x02:
                raise BagError(f"cannot read bag {path}: the file is damaged (no MCAP footer at "
                               "the end)")
            if summary_crc and summary_start:
                f.seek(summary_start)
                body = f.read(size - len(_MAGIC) - 4 - summary_start)
                if zlib.crc32(body) != summary_crc:
                    raise BagError(f"cannot read bag {path}: the file is damaged (the summary "
                                   "section's CRC does not match)")
                checked = True
    except BagError:
        raise
    except EOFError:
        raise BagError(f"cannot read bag {path}: the file ends early (truncated)") from None
    except (McapError, OSError, ValueError, struct.error) as exc:
        raise BagError(f"cannot read bag {path}: the file is damaged ({exc})") from None
    return checked


def open_bag(path: Path, verify: bool = True):
    """An open rosbags AnyReader for a bag directory or ``.mcap`` file, or a BagError.

    With ``verify`` every MCAP file of the bag has its CRCs checked first
    (:func:`verify_mcap`); the reader's ``crc_checked`` attribute says whether
    all of them carried CRCs.
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    kind = _kind(path)
    if kind is None:
        raise BagError(f"bag not found: {path}")
    if kind not in ("a regular file", "a directory"):
        raise BagError(f"{path} is {kind}, not a bag: a bag is a directory or an .mcap file "
                       "(nothing was read)")
    if kind == "a directory" and not (path / "metadata.yaml").exists():
        raise BagError(f"{path} is not a rosbag2 bag (no metadata.yaml in the directory)")
    if kind == "a regular file" and path.suffix != ".mcap":
        raise BagError(f"{path} is not a bag (expected a bag directory or an .mcap file)")
    if kind == "a directory":
        _check_bag_files(path)
    files = sorted(path.glob("*.mcap")) if kind == "a directory" else [path]
    crc_checked = bool(files) and all(verify_mcap(f) for f in files) if verify else False
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises several types for damaged files
        raise BagError(f"cannot read bag {path}: {exc}") from None
    reader.crc_checked = crc_checked
    return reader


def read_bag_signals(
    path: str | Path,
    *,
    input_topic: str | Sequence[str] = DEFAULT_INPUT_TOPIC,
    output_topic: str | Sequence[str] = DEFAULT_OUTPUT_TOPIC,
    input_field: str | Sequence[str] | None = None,
    output_field: str | Sequence[str] | None = None,
    input_names: str | Sequence[str] | None = None,
    tolerance_ns: int | None = None,
    output_names: str | Sequence[str] | None = None,
) -> BagSignals:
    """Read the inputs and outputs from topics of a bag, aligned by header stamp as the node does.

    Several inputs: ``input_topic``, ``input_field`` and ``input_names`` are
    comma-separated lists (one entry for all inputs, or one per input; see
    :func:`spm_sysid.core.io.channels.parse_channels`), e.g. one
    ``sensor_msgs/msg/JointState`` topic with fields ``effort[0],effort[1]``.
    Several outputs likewise (``output_topic``, ``output_field``,
    ``output_names``): two topics, or ``velocity[0],velocity[1]`` of one
    ``JointState`` topic; ``y`` then has one column per output.
    Messages without a header are stamped with their log time. Fields default by
    message type (see :data:`spm_sysid.core.io.fields.DEFAULT_FIELDS`). Messages
    go through the node's alignment rule in log-time order
    (:func:`spm_sysid.core.stream.buffer.pair_streams`; ``tolerance_ns`` defaults to
    the node's ``stamp_tolerance``): NaN/inf values are rejected and counted, stamps
    that go back start a new segment, and the holes show in the stamps
    (:func:`spm_sysid.core.model.segments.find_segments`). Header stamps that stay
    zero (never filled in; :class:`~spm_sysid.core.io.fields.UnsetStamps`) are
    not times: those messages' log times are used instead, and they are counted
    (``unset_stamps``).

    Raises
    ------
    BagError
        Missing or damaged bag (CRC mismatch), missing topic, unsupported type or
        bad field path, inconsistent input lists, or no aligned samples.
    """
    if tolerance_ns is None:
        tolerance_ns = int(round(SETTINGS["stamp_tolerance"].default * 1e9))
    try:
        channels = parse_channels(input_topic, input_field, None, input_names)
        out_channels = parse_channels(output_topic, output_field, None, output_names,
                                      role="output")
    except ValueError as exc:
        raise BagError(str(exc)) from None
    groups = topic_streams(channels)
    out_groups = topic_streams(out_channels)
    path = Path(path)
    reader = open_bag(path)
    crc_checked = reader.crc_checked
    try:
        conns = {c.topic: c for c in reader.connections}
        for topic in [g[0] for g in groups] + [g[0] for g in out_groups]:
            if topic not in conns:
                raise BagError(
                    f"{path} has no topic {topic}; it has: {', '.join(sorted(conns)) or 'none'}"
                )
        try:  # one topic may carry both (JointState: effort in, velocity out)
            check_roles(channels, out_channels, {t: c.msgtype for t, c in conns.items()})
        except ValueError as exc:
            raise BagError(str(exc)) from None
        # per topic its streams: ("y", k) for output stream k, or the index of the input
        # stream; steps: one field path per value
        streams: dict[str, list[tuple[tuple | int, list]]] = {}
        try:
            for role, gs, chans in ((0, groups, channels), (1, out_groups, out_channels)):
                for i, (topic, _, idx) in enumerate(gs):
                    msgtype = conns[topic].msgtype
                    streams.setdefault(topic, []).append((("y", i) if role else i, [
                        parse_path(chans[j].field or default_field(msgtype)) for j in idx]))
        except FieldPathError as exc:
            raise BagError(f"topic {topic} ({conns[topic].msgtype}): {exc}") from None
        events = []
        unset = UnsetStamps()
        try:
            for c, log_ns, raw in reader.messages(connections=[conns[t] for t in streams]):
                msg = reader.deserialize(raw, c.msgtype)
                st = unset.stamp(c.topic, msg)
                for stream, steps in streams[c.topic]:
                    events.append((stream, log_ns if st is None else st,
                                   [extract(msg, s) for s in steps]))
        except FieldPathError as exc:
            raise BagError(f"topic {c.topic} has type {c.msgtype}: {exc}") from None
        except Exception as exc:
            raise BagError(f"cannot read messages from {path}: {exc}") from None
    finally:
        reader.close()
    stamps, u, y, stats = pair_streams(events, tolerance_ns,
                                       input_widths=[len(g[2]) for g in groups],
                                       output_widths=[len(g[2]) for g in out_groups])
    if len(u) == 0:
        raise BagError(f"{path}: no input and output messages with matching stamps "
                       f"(tolerance {tolerance_ns} ns)")
    if u.ndim == 2:  # the buffer numbers inputs topic by topic: back to the given order
        u = u[:, np.argsort(stream_order(channels))]
    if y.ndim == 2:
        y = y[:, np.argsort(stream_order(out_channels))]
    return BagSignals(
        u=u, y=y, stamps_ns=stamps, input_count=stats.received_inputs,
        output_count=stats.received_outputs,
        topics={t: conns[t].msgtype for t in streams},
        streams=sum(len(v) for v in streams.values()),
        rejected_nonfinite=stats.rejected_nonfinite, crc_checked=crc_checked,
        input_names=tuple(c.name for c in channels), unset_stamps=unset.count,
        output_names=tuple(c.name for c in out_channels),
    )
