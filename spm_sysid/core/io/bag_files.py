"""rosbag2 bags on disk: what a bag directory holds, its MCAP files' CRCs, opening it.

The MCAP file is written (:mod:`.bag_write`) with a CRC-32 of every chunk, of
the data section and of the summary. Reading checks them (:func:`verify_mcap`)
before any message is used: a damaged bag is an error, never a silently
different model. Bags written without CRCs (fields 0) can't be checked. Every
failure is a :class:`BagError` naming the bag and the problem; a pipe where a
bag file should be is refused, never opened (it would block).
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

from ..errors import BagError
from ..files import file_kind

__all__ = ["DEFAULT_INPUT_TOPIC", "DEFAULT_OUTPUT_TOPIC", "DEFAULT_RATE_HZ", "INPUT_TYPE",
           "JOINT_TYPE", "OUTPUT_TYPE", "default_qos", "foreign_files", "is_rosbag2_dir",
           "open_bag", "typestore", "verify_mcap"]

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


def foreign_files(path: Path) -> list[str]:
    """Entries of a bag directory that are not the bag's own files."""
    own = {"metadata.yaml"} | _listed_files(path)
    out = []
    for entry in sorted(path.iterdir()):
        if entry.name in own and entry.is_file() and not entry.is_symlink():
            continue  # only what metadata.yaml lists is the bag's (another .mcap is not)
        out.append(entry.name + ("/" if entry.is_dir() else ""))
    return out


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
        hint = (f"; give its folder, {path.parent}, which holds metadata.yaml"
                if (path.parent / "metadata.yaml").is_file() else "")
        raise BagError(f"{path} is not a bag (expected a bag directory or an .mcap file)"
                       + hint)
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
