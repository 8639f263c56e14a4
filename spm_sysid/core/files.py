"""Writing result files safely: check destinations first, replace files atomically.

A long search must not end in "cannot write": destinations are checked
before it starts (:func:`check_writable_file`, :func:`check_writable_dir`).
Files are written to a temporary file in the same directory and moved into
place with :func:`os.replace`, so a reader never sees half a file and a failed
write leaves the old file as it was.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import FileCheckError

__all__ = ["FileCheckError", "atomic_write_bytes", "atomic_write_text",
           "check_writable_dir", "check_writable_file"]


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_writable_dir(path: str | os.PathLike, what: str = "directory") -> Path:
    """Check that ``path`` is (or can be created as) a writable directory.

    Raises
    ------
    FileCheckError
        It is a file, or it (or the nearest existing parent) is not writable.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FileCheckError(f"{what} {path} exists and is not a directory")
    base = _nearest_existing(path)
    if not base.is_dir():
        raise FileCheckError(f"cannot create {what} {path}: {base} is not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise FileCheckError(f"cannot write {what} {path}: {base} is not writable")
    return path


def check_writable_file(path: str | os.PathLike, what: str = "file") -> Path:
    """Check that a file can be written (created or replaced) at ``path``.

    Raises
    ------
    FileCheckError
        Empty path, a directory, or a location that is not writable.
    """
    if not str(path).strip():
        raise FileCheckError(f"{what} path is empty")
    path = Path(path)
    if path.is_dir():
        raise FileCheckError(f"{what} {path} is a directory")
    if path.exists() and not os.access(path, os.W_OK):
        raise FileCheckError(f"cannot write {what} {path}: the file is read-only")
    check_writable_dir(path.parent, f"the directory of {what}")
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` all at once (temporary file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` all at once."""
    return atomic_write_bytes(path, text.encode("utf-8"))
