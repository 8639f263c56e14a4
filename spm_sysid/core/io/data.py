"""Loading input/output data: two-column text files and CSV.

Supported layouts
-----------------
* Two whitespace-separated numeric columns, no header (DaISy layout: column 1
  is the input u, column 2 the output y). Lines starting with ``#`` or ``%`` are
  comments.
* CSV with a header line. Columns named ``u`` and ``y`` are used when present;
  otherwise the file must have exactly two columns (input first). A column
  named ``t``, ``time``, ``stamp`` or ``timestamp`` (seconds) gives each row its
  time: then rows with a missing, NaN or inf ``u`` or ``y`` are dropped and
  counted, and the gaps they (or missing rows) leave are found from the times,
  so identification never fits across them (:func:`load_data`).

Files are parsed by numpy's C reader; only when that fails is the file
scanned line by line to name the first bad line. Before reading, the memory
the file would need is estimated and checked against the bound of
:mod:`spm_sysid.core.memory`, so a huge file fails early with a clear message.

Every problem is reported as a :class:`DataError` naming the file, line and
value, never as a bare numpy traceback.

Finding and downloading the robot-arm data set: :mod:`spm_sysid.core.io.datasets`.
"""

from __future__ import annotations

import csv
import gzip
import io
import math
import os
import struct
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..memory import check_memory

__all__ = ["IOData", "load_data", "load_io", "parse_columns", "parse_data_text",
           "parse_io_text"]


def _parse_float(token: str, where: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise DataError(f"{where}: {token!r} is not a number") from None
    if not math.isfinite(value):
        raise DataError(f"{where}: value {token!r} is not finite (NaN or inf are not allowed)")
    return value


def parse_io_text(text: str, source: str = "<text>") -> tuple[np.ndarray, np.ndarray]:
    """Parse two-column or CSV text into ``(u, y)``; see the module docstring."""
    lines = text.splitlines()
    first = next((ln for ln in lines if ln.strip() and ln.lstrip()[0] not in "#%"), None)
    if first is None:
        raise DataError(f"{source}: no data (the file is empty)")
    header = not all(_is_number(tok) for tok in first.replace(",", " ").split())
    if "," in first or header:
        return _parse_csv(text, source, header)
    rows = []
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped or stripped[0] in "#%":
            continue
        tokens = stripped.split()
        where = f"{source}, line {number}"
        if len(tokens) != 2:
            raise DataError(
                f"{where}: expected 2 columns (input u, output y), found {len(tokens)}"
            )
        rows.append([_parse_float(tok, where) for tok in tokens])
    data = np.array(rows, dtype=float)
    return data[:, 0].copy(), data[:, 1].copy()


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _parse_csv(text: str, source: str, has_header: bool) -> tuple[np.ndarray, np.ndarray]:
    reader = csv.reader(io.StringIO(text))
    rows = [(n, r) for n, r in enumerate(reader, start=1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith(("#", "%"))]
    if has_header:
        (hline, header), body = rows[0], rows[1:]
    else:
        hline, header, body = 0, ["u", "y"][: len(rows[0][1])] + ["?"] * (len(rows[0][1]) - 2), rows
    names = [h.strip().lower() for h in header]
    if not has_header and len(names) != 2:
        raise DataError(f"{source}, line {rows[0][0]}: expected 2 columns (input u, output y), "
                        f"found {len(names)}")
    if "u" in names and "y" in names:
        iu, iy = names.index("u"), names.index("y")
    elif len(names) == 2:
        iu, iy = 0, 1
    else:
        raise DataError(
            f"{source}, line {hline}: CSV header {header} needs columns named 'u' and 'y' "
            f"or exactly 2 columns, found {len(names)}"
        )
    if not body:
        raise DataError(f"{source}: the CSV file has a header but no data rows")
    u, y = [], []
    for number, row in body:
        where = f"{source}, line {number}"
        if len(row) != len(names):
            raise DataError(f"{where}: expected {len(names)} columns, found {len(row)}")
        u.append(_parse_float(row[iu].strip(), where))
        y.append(_parse_float(row[iy].strip(), where))
    return np.array(u), np.array(y)


TIME_COLUMNS = ("t", "time", "stamp", "timestamp")


@dataclass
class IOData:
    """Samples read from a data file.

    Attributes
    ----------
    u : ndarray, shape (n,) or (n, m)
        One column per input when several were selected.
    y : ndarray, shape (n,)
    t : ndarray of float, shape (n,), or None
        Row times in seconds when the file has a time column.
    rejected : int
        Rows dropped because u or y was missing, NaN or inf (time column only).
    source : str
    input_names, output_name : str
        Signal names from the file's header (empty: unnamed).
    """

    u: np.ndarray
    y: np.ndarray
    t: np.ndarray | None = None
    rejected: int = 0
    source: str = ""
    input_names: tuple[str, ...] = ()
    output_name: str = "y"


def _read_bytes(path: Path) -> bytes:
    if not path.exists():
        raise DataError(f"data file not found: {path}")
    if path.is_dir():
        raise DataError(f"{path} is a directory, not a data file")
    size = path.stat().st_size
    gz = path.suffix == ".gz"
    with path.open("rb") as f:
        head = f.read(2)
        gz = gz or head == b"\x1f\x8b"
        text_size = size
        if gz and size >= 18:
            f.seek(-4, os.SEEK_END)  # gzip stores the uncompressed size mod 2**32
            text_size = max(struct.unpack("<I", f.read(4))[0], size)
    # parsing keeps the text and about three numbers of 8 bytes per ~12 characters
    check_memory(text_size * 3, f"reading {path} ({text_size / 1e6:.0f} MB of text)")
    raw = path.read_bytes()
    if gz:
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as exc:
            raise DataError(f"{path} is not a readable gzip file (truncated or corrupt: "
                            f"{exc})") from None
    return raw


def load_data(path: str | os.PathLike, inputs: list[str] | None = None,
              output: str | None = None) -> IOData:
    """Read a data file into :class:`IOData` (u, y and, for CSV with a time column, t).

    ``inputs`` and ``output`` choose columns by header name (CSV) or by 0-based
    index (any layout); with them a file may have any number of columns. Without
    them the two-column layouts of the module docstring apply. Default output
    with ``inputs`` given: the column named ``y``, else the last one.

    Raises
    ------
    DataError
        Missing file, wrong column count, non-numeric or non-finite values (except
        as described for time columns), a corrupt gzip file, or a file too large
        for the memory bound.
    """
    path = Path(path)
    raw = _read_bytes(path)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise DataError(f"{path} is not a text file (not UTF-8)") from None
    del raw
    if inputs is None and output is None:
        return parse_data_text(text, str(path))
    return parse_columns(text, str(path), inputs, output)


def parse_columns(text: str, source: str, inputs: list[str] | None,
                  output: str | None) -> IOData:
    """Several columns chosen by name or index; see :func:`load_data`."""
    rows = [ln for ln in text.splitlines() if ln.strip() and ln.lstrip()[0] not in "#%"]
    if not rows:
        raise DataError(f"{source}: no data (the file is empty)")
    sep = "," if "," in rows[0] else None
    first = [c.strip() for c in (rows[0].split(sep))]
    header = not all(_is_number(c) for c in first)
    names = [c.lower() for c in first] if header else None
    body = rows[1:] if header else rows
    width = len(first)
    table = np.full((len(body), width), np.nan)
    for i, line in enumerate(body):
        cells = [c.strip() for c in line.split(sep)]
        if len(cells) != width:
            raise DataError(f"{source}: row {i + 1 + header} has {len(cells)} columns, "
                            f"expected {width}")
        for j, c in enumerate(cells):
            if c:
                try:
                    table[i, j] = float(c)
                except ValueError:
                    raise DataError(f"{source}: row {i + 1 + header}: {c!r} is not a "
                                    "number") from None

    def column(sel: str) -> int:
        sel = str(sel).strip()
        if names and sel.lower() in names:
            return names.index(sel.lower())
        try:
            j = int(sel)
        except ValueError:
            have = ", ".join(names) if names else f"{width} unnamed columns"
            raise DataError(f"{source}: no column {sel!r} (it has {have})") from None
        if not 0 <= j < width:
            raise DataError(f"{source}: column index {j} outside 0..{width - 1}")
        return j

    it = next((k for k, n in enumerate(names or []) if n in TIME_COLUMNS), None)
    iy = column(output) if output is not None else (
        names.index("y") if names and "y" in names else width - 1)
    iu = [column(c) for c in inputs] if inputs else [
        k for k in range(width) if k not in (iy, it)]
    if not iu or iy in iu or (it is not None and (it in iu or it == iy)):
        raise DataError(f"{source}: choose distinct input and output columns")
    t = None
    rejected = 0
    data = table
    if it is not None:  # rows with missing values are dropped and counted (gaps by time)
        if not np.all(np.isfinite(table[:, it])):
            raise DataError(f"{source}: the time column has missing or non-numeric values")
        ok = np.all(np.isfinite(table[:, iu + [iy]]), axis=1)
        rejected = int((~ok).sum())
        data = table[ok]
        t = data[:, it]
        if np.any(np.diff(t) <= 0):
            raise DataError(f"{source}: the time column must increase")
    elif not np.all(np.isfinite(table[:, iu + [iy]])):
        r = int(np.flatnonzero(~np.all(np.isfinite(table[:, iu + [iy]]), axis=1))[0])
        raise DataError(f"{source}: row {r + 1 + header} has a missing or non-finite value "
                        "(add a time column to have such rows dropped as gaps)")
    u = data[:, iu] if len(iu) > 1 else data[:, iu[0]]

    def label(j: int, default: str) -> str:
        return names[j] if names and names[j].isidentifier() else default

    in_names = tuple(label(j, f"u{k + 1}" if len(iu) > 1 else "u") for k, j in enumerate(iu))
    return IOData(np.ascontiguousarray(u), data[:, iy].copy(), t, rejected, source,
                  in_names, label(iy, "y"))


def parse_data_text(text: str, source: str = "<text>") -> IOData:
    """Parse two-column or CSV text into :class:`IOData` (fast, exact messages on error)."""
    lines_iter = (ln for ln in text.splitlines() if ln.strip() and ln.lstrip()[0] not in "#%")
    first = next(lines_iter, None)
    if first is None:
        raise DataError(f"{source}: no data (the file is empty)")
    header = not all(_is_number(tok) for tok in first.replace(",", " ").split())
    if header:
        names = [h.strip().lower() for h in next(csv.reader([first]))]
        times = [n for n in names if n in TIME_COLUMNS]
        if times:
            return _parse_timed_csv(text, source, names, names.index(times[0]))
    try:
        if "," in first or header:
            data = _fast_csv(text, first, header)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                data = np.loadtxt(io.StringIO(text), comments=("#", "%"), ndmin=2)
            if data.shape[1] != 2:
                raise ValueError("columns")
        if data.shape[0] == 0 or not np.all(np.isfinite(data)):
            raise ValueError("values")
    except (ValueError, IndexError):
        u, y = parse_io_text(text, source)  # slow, line by line: names the bad line
        return IOData(u, y, source=source)
    return IOData(np.ascontiguousarray(data[:, 0]), np.ascontiguousarray(data[:, 1]),
                  source=source)


def _fast_csv(text: str, first: str, header: bool) -> np.ndarray:
    names = [h.strip().lower() for h in next(csv.reader([first]))]
    cols = (names.index("u"), names.index("y")) if header and "u" in names and "y" in names \
        else (0, 1)
    if len(names) != 2 and cols == (0, 1):
        raise ValueError("columns")
    body = io.StringIO(text)
    if header:  # skip up to and including the header line
        for line in body:
            if line.strip() and line.lstrip()[0] not in "#%":
                break
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no data" is reported as an error below
        return np.loadtxt(body, delimiter=",", comments=("#", "%"), ndmin=2, usecols=cols)


def _parse_timed_csv(text: str, source: str, names: list[str], it: int) -> IOData:
    """CSV with a time column: rows with missing/non-finite u or y are dropped, counted."""
    if "u" in names and "y" in names:
        iu, iy = names.index("u"), names.index("y")
    else:
        others = [i for i in range(len(names)) if i != it]
        if len(others) != 2:
            raise DataError(f"{source}: with a time column the CSV needs columns named 'u' "
                            f"and 'y' or exactly two more columns, found {names}")
        iu, iy = others
    t, u, y = [], [], []
    rows = csv.reader(io.StringIO(text))
    seen_header = False
    for number, row in enumerate(rows, start=1):
        if not row or not any(c.strip() for c in row) or row[0].lstrip().startswith(("#", "%")):
            continue
        if not seen_header:
            seen_header = True
            continue
        where = f"{source}, line {number}"
        if len(row) != len(names):
            raise DataError(f"{where}: expected {len(names)} columns, found {len(row)}")
        t.append(_parse_float(row[it].strip(), where))
        u.append(_parse_optional(row[iu].strip(), where))
        y.append(_parse_optional(row[iy].strip(), where))
    if not t:
        raise DataError(f"{source}: the CSV file has a header but no data rows")
    t_arr, u_arr, y_arr = np.array(t), np.array(u), np.array(y)
    if np.any(np.diff(t_arr) <= 0):
        k = int(np.flatnonzero(np.diff(t_arr) <= 0)[0])
        raise DataError(f"{source}: the time column must increase; row {k + 2} has time "
                        f"{t_arr[k + 1]:g} after {t_arr[k]:g}")
    ok = np.isfinite(u_arr) & np.isfinite(y_arr)
    return IOData(u_arr[ok], y_arr[ok], t_arr[ok], int((~ok).sum()), source)


def _parse_optional(token: str, where: str) -> float:
    """A number, or NaN for an empty field; a non-number is an error."""
    if not token:
        return float("nan")
    try:
        return float(token)
    except ValueError:
        raise DataError(f"{where}: {token!r} is not a number") from None


def load_io(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read input u and output y from a two-column text file or a CSV file.

    Raises
    ------
    DataError
        Missing file, wrong column count, non-numeric or non-finite values, or
        (for a file with a time column) rows that had to be dropped: use
        :func:`load_data`, which keeps the times so gaps are respected.
    """
    data = load_data(path)
    if data.rejected or data.t is not None and len(data.t) > 1 and _has_gaps(data.t):
        raise DataError(f"{path}: {data.rejected} row(s) dropped or missing: the samples are "
                        "not equally spaced (use load_data, which keeps the times)")
    return data.u, data.y


def _has_gaps(t: np.ndarray) -> bool:
    d = np.diff(t)
    return bool(np.any(d > 1.5 * np.median(d)))
