"""The robot-arm data set (DaISy 96-009): find it, load it, download it.

It is third-party data that this project never commits. :func:`find_robot_arm`
looks for it in this order: an explicit path, the environment variable
``SPM_SYSID_ROBOT_ARM``, ``../shared/data/robot_arm.dat`` from the project root
(or from the working directory), then the user cache
(``$XDG_CACHE_HOME/spm_sysid/robot_arm.dat``, default ``~/.cache``).
:func:`download_robot_arm` fetches it from DaISy into the cache and checks a
SHA-256 of its numeric content (the parsed values, so the file's layout --
tabs, CRLF -- does not matter).
"""

from __future__ import annotations

import gzip
import hashlib
import os
import urllib.request
from pathlib import Path

import numpy as np

from ..errors import DataError
from .data import load_io, parse_io_text

__all__ = [
    "DAISY_ROBOT_ARM_URL",
    "ROBOT_ARM_SHA256",
    "download_robot_arm",
    "find_robot_arm",
    "load_robot_arm",
    "numeric_sha256",
]


DAISY_ROBOT_ARM_URL = "https://ftp.esat.kuleuven.be/pub/SISTA/data/mechanical/robot_arm.dat.gz"
#: SHA-256 of the 1024 x 2 values as little-endian float64, row-major.
ROBOT_ARM_SHA256 = "5f5115ef4bdf9cb1886170965a326caf66a70019b69e5a3cc96a8408aecdbae6"
ROBOT_ARM_ENV = "SPM_SYSID_ROBOT_ARM"


def numeric_sha256(data: np.ndarray) -> str:
    """SHA-256 of an array's values as little-endian float64 (layout-independent)."""
    return hashlib.sha256(np.ascontiguousarray(data, dtype="<f8").tobytes()).hexdigest()


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "spm_sysid"


def _candidates(explicit: str | os.PathLike | None) -> list[tuple[str, Path]]:
    out: list[tuple[str, Path]] = []
    if explicit:
        out.append(("explicit path", Path(explicit)))
    env = os.environ.get(ROBOT_ARM_ENV)
    if env:
        out.append((f"${ROBOT_ARM_ENV}", Path(env)))
    project_root = Path(__file__).resolve().parents[3]
    shared = project_root.parent / "shared" / "data" / "robot_arm.dat"
    out.append(("project ../shared/data", shared))
    out.append(("working directory ../shared/data",
                Path.cwd().parent / "shared" / "data" / "robot_arm.dat"))
    out.append(("user cache", _cache_dir() / "robot_arm.dat"))
    return out


def find_robot_arm(path: str | os.PathLike | None = None) -> Path:
    """Locate ``robot_arm.dat`` (see the module docstring for the search order).

    Raises
    ------
    DataError
        If an explicit path or the environment variable points nowhere, or the file
        is in none of the places; the message lists where it looked.
    """
    tried = []
    for label, cand in _candidates(path):
        if cand.is_file():
            return cand
        if label in ("explicit path", f"${ROBOT_ARM_ENV}"):
            raise DataError(f"robot-arm data not found at {cand} ({label})")
        tried.append(f"{label}: {cand}")
    raise DataError(
        "robot-arm data (robot_arm.dat) not found; looked in\n  " + "\n  ".join(tried)
        + "\nrun `spm-sysid fetch-data` to download it from DaISy into the user cache"
    )


def load_robot_arm(path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Load the robot-arm data as ``(u, y)`` = (reaction torque, acceleration)."""
    return load_io(find_robot_arm(path))


def download_robot_arm(
    url: str = DAISY_ROBOT_ARM_URL,
    dest: str | os.PathLike | None = None,
    sha256: str = ROBOT_ARM_SHA256,
    timeout: float = 30.0,
) -> Path:
    """Download the robot-arm data (gzip or plain text), verify it, store it.

    The numeric content must match ``sha256`` (see :func:`numeric_sha256`); the
    file is written in the two-column layout to ``dest`` (default: the user cache).

    Raises
    ------
    DataError
        Network failure, unreadable content or a checksum mismatch; nothing is
        written in that case.
    """
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            raw = response.read()
    except OSError as exc:
        raise DataError(f"could not download {url}: {exc}") from None
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except OSError as exc:
            raise DataError(f"{url}: corrupt gzip data: {exc}") from None
    try:
        u, y = parse_io_text(raw.decode("utf-8", errors="strict"), url)
    except UnicodeDecodeError:
        raise DataError(f"{url} did not return text data") from None
    data = np.column_stack([u, y])
    digest = numeric_sha256(data)
    if digest != sha256:
        raise DataError(
            f"{url}: checksum mismatch (got {digest}, expected {sha256}); not saved"
        )
    dest = Path(dest) if dest else _cache_dir() / "robot_arm.dat"
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".part")
    tmp.write_text("".join(f"{a:.7e} {b:.7e}\n" for a, b in data))
    tmp.replace(dest)
    return dest
