"""Reading inputs and writing results safely: files that are only ever files.

Writing. A long search must not end in "cannot write": destinations are
checked before it starts (:func:`check_writable_file`, :func:`check_writable_dir`).
A destination is a regular file or a path where none exists yet; a symbolic
link is followed to the file it names (that file is replaced, the link stays);
anything else -- a character device such as ``/dev/null``, a pipe, a socket,
a directory -- is refused, so saving never replaces a device or a link with a
regular file. Files are written to a temporary file in the same directory and
moved into place with :func:`os.replace`, so a reader never sees half a file
and a failed write leaves the old file as it was. Where the file cannot be
replaced because it is a mount point of its own (a file bind-mounted into a
container: ``docker -v model.json:/out/model.json``), it is written in place.

Reading (:func:`read_bytes`). A path is opened once and read from that one
handle, so a pipe (``<(cat f)``, ``/dev/stdin``) loses nothing; only regular
files and pipes are read (``/dev/zero`` would never end), and what is read is
checked against the memory bound as it grows.
"""

from __future__ import annotations

import errno
import math
import os
import stat
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

from .errors import DataError, FileCheckError

__all__ = ["FileCheckError", "atomic_write_bytes", "atomic_write_text", "check_destinations",
           "check_writable_dir", "check_writable_file", "document_json", "file_kind",
           "json_float", "json_ready", "read_bytes", "resolve_destination", "same_file"]

#: Bytes read at a time from a pipe.
_CHUNK = 1 << 22


def file_kind(mode: int) -> str:
    """What a file is, in words (``a character device``, ``a pipe`` ...)."""
    for test, text in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a directory"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a pipe"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return text
    return "not a regular file"


def read_bytes(path: str | os.PathLike, what: str = "file", factor: float = 1.0,
               error: type[ValueError] = DataError) -> bytes:
    """All bytes of a regular file or a pipe, read once from one handle.

    ``factor`` is the memory a byte read will need in the end (parsing makes
    copies); the total is checked against the memory bound before a regular
    file is read and as a pipe's bytes arrive.

    Raises
    ------
    error (DataError by default)
        Not found, a directory, not readable, or neither a regular file nor a pipe.
    MemoryLimitError
        More bytes than the memory bound allows.
    """
    from .memory import check_memory

    path = Path(path)
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below; fstat needs the handle
    except FileNotFoundError:
        raise error(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise error(f"{path} is a directory, not a {what}") from None
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    with f:
        mode = os.fstat(f.fileno()).st_mode
        if stat.S_ISDIR(mode):
            raise error(f"{path} is a directory, not a {what}")
        if not (stat.S_ISREG(mode) or stat.S_ISFIFO(mode)):
            raise error(f"{path} is {file_kind(mode)}, not a {what}: only regular files and "
                        "pipes are read")
        label = f"reading {path}"
        if stat.S_ISREG(mode):
            size = os.fstat(f.fileno()).st_size
            check_memory(size * factor, f"{label} ({size / 1e6:.0f} MB)")
        parts, total = [], 0
        try:
            while chunk := f.read(_CHUNK):
                parts.append(chunk)
                total += len(chunk)
                check_memory(total * factor, f"{label} (more than {total / 1e6:.0f} MB so far)")
        except OSError as exc:
            raise error(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    return b"".join(parts)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when both paths name one existing file (links and symlinks followed)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


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


def resolve_destination(path: str | os.PathLike, what: str = "file") -> Path:
    """The regular file a result goes to: symlinks followed; anything else refused.

    Raises
    ------
    FileCheckError
        Empty path; an existing directory, device, pipe or socket; a read-only
        file; a symlink loop.
    """
    if not str(path).strip():
        raise FileCheckError(f"{what} path is empty")
    given = Path(path)
    try:
        real = Path(os.path.realpath(given, strict=False))
    except OSError as exc:  # e.g. a symlink loop
        raise FileCheckError(f"cannot write {what} {given}: {exc.strerror or exc}") from None
    try:
        mode = os.stat(real).st_mode
    except (FileNotFoundError, NotADirectoryError):  # the directory check names the cause
        return real
    except OSError as exc:
        raise FileCheckError(f"cannot write {what} {given}: {exc.strerror or exc}") from None
    via = f" (a link to {real})" if real != given.absolute() else ""
    if stat.S_ISDIR(mode):
        raise FileCheckError(f"{what} {given}{via} is a directory")
    if not stat.S_ISREG(mode):
        raise FileCheckError(f"{what} {given}{via} is {file_kind(mode)}, not a regular file; "
                             "results are written to regular files only (nothing was changed)")
    if not os.access(real, os.W_OK):
        raise FileCheckError(f"cannot write {what} {given}: the file is read-only")
    return real


def check_writable_file(path: str | os.PathLike, what: str = "file") -> Path:
    """Check that a file can be written (created or replaced) at ``path``.

    Returns the file that will be written (symlinks followed).

    Raises
    ------
    FileCheckError
        See :func:`resolve_destination`; also a directory that cannot be written.
    """
    real = resolve_destination(path, what)
    check_writable_dir(real.parent, f"the directory of {what}")
    return real


def check_destinations(outputs: Mapping[str, str | os.PathLike | None],
                       inputs: Iterable[str | os.PathLike | None] = ()) -> dict[str, Path]:
    """One check for every file a command will write, run before any work.

    Each destination (``{"--json": path, "--report": path}``; None: not asked
    for) must be: a path; not a symbolic link (a link may name an input or a
    file elsewhere, and the write would go through it); a regular file or
    absent, writable, in a writable directory (:func:`check_writable_file`:
    no pipe, device or directory); none of ``inputs``; and not the file of
    another destination of the same run.

    Returns
    -------
    dict
        The destinations asked for, by label.

    Raises
    ------
    FileCheckError
        The first destination that fails, named by its label, and why.
    """
    out: dict[str, Path] = {}
    sources = [Path(p) for p in inputs if p]
    for what, path in outputs.items():
        if path is None:
            continue
        given = Path(path)
        if not str(path).strip():
            raise FileCheckError(f"{what} path is empty")
        if given.is_symlink():
            raise FileCheckError(
                f"{what} {given} is a symbolic link (to {os.readlink(given)}); results are "
                "not written through links, which could name an input or a file elsewhere: "
                "give the file's own path (nothing was changed)")
        check_writable_file(given, what)
        for source in sources:
            if same_file(given, source):
                raise FileCheckError(f"{what} {given} is the input {source}: it would be "
                                     "overwritten; give another path (nothing was changed)")
        for other, taken in out.items():
            if given.absolute() == taken.absolute() or same_file(given, taken):
                raise FileCheckError(f"{what} {given} and {other} {taken} are the same file: "
                                     "one would overwrite the other; give two paths")
        out[what] = given
    return out


def atomic_write_bytes(path: str | os.PathLike, data: bytes,
                       follow_links: bool = True) -> Path:
    """Write ``data`` to ``path`` all at once (temporary file + rename).

    ``path`` is checked as :func:`resolve_destination` does: a symlink is
    followed (the file it names is replaced, the link stays), a device, pipe or
    directory is refused. With ``follow_links=False`` a symlink at ``path`` is
    itself replaced by the regular file and what it named is left alone (a
    folder of results writes only inside itself). A file that is a mount point
    of its own (bind-mounted) cannot be renamed over and is written in place
    instead. Returns ``path``.
    """
    given = Path(path)
    real = (given.absolute() if not follow_links and given.is_symlink()
            else resolve_destination(path))
    real.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{real.name}.", suffix=".tmp", dir=real.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        try:
            os.replace(tmp, real)
        except OSError as exc:
            if exc.errno not in (errno.EBUSY, errno.EXDEV) or not real.is_file():
                raise
            _write_in_place(real, data)  # a bind-mounted file: rename cannot replace it
            Path(tmp).unlink(missing_ok=True)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(path)


def _write_in_place(path: Path, data: bytes) -> None:
    with open(path, "r+b") as f:
        f.write(data)
        f.truncate()
        f.flush()
        os.fsync(f.fileno())


def atomic_write_text(path: str | os.PathLike, text: str, follow_links: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path`` all at once (see :func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode("utf-8"), follow_links)


def json_ready(value):
    """A value as a JSON document can hold it, whatever a job put in it.

    Every number that is not finite (inf, -inf, NaN: a diverged run, a scan that
    could not be fitted, an overflow) becomes ``null``; numpy scalars and arrays
    become numbers and lists, tuples lists. Documents are written through this
    one function (:func:`document_json`), so a result is never lost because one
    of its numbers has no JSON form.
    """
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return _numpy_ready(value)


def _numpy_ready(value):
    """Arrays and scalars of numpy as :func:`json_ready` gives them; anything else as it is."""
    try:  # without importing numpy at this module's import
        import numpy as np
    except ImportError:  # pragma: no cover - numpy is a dependency
        return value
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return json_ready(float(value))
    return value


def document_json(doc, indent: int | None = 2) -> str:
    """The one writer of JSON documents: :func:`json_ready`, then strict JSON."""
    import json

    return json.dumps(json_ready(doc), indent=indent, allow_nan=False)


def json_float(x: float | None) -> float | None:
    """A number for a JSON document: inf and NaN (which JSON has not) become None."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None
