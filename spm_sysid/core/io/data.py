"""Loading input/output data: two-column text files and CSV, one reader and one parser.

Supported layouts
-----------------
* Two whitespace-separated numeric columns, no header (DaISy layout: column 1
  is the input u, column 2 the output y). Lines starting with ``#`` or ``%`` are
  comments.
* CSV (or whitespace-separated columns) with a header line. Columns named ``u``
  and ``y`` are used when present; otherwise the file must have exactly two
  data columns (input first). A column named ``t``, ``time``, ``stamp``,
  ``timestamp`` or ``__time`` gives each row its time (seconds; nanoseconds,
  microseconds or milliseconds since 1970, or nanoseconds from the start, are told
  from their size and said in :attr:`IOData.notes`; a unit in the header, ``time
  [ms]`` or ``timestamp_ns``, is used as written): then rows with a missing,
  NaN or inf ``u`` or ``y`` are dropped and counted, and the gaps they (or
  missing rows) leave are found from the times, so identification never fits
  across them.
* Any number of columns when the inputs and the output are chosen by header
  name or 0-based index (:func:`load_data`'s ``inputs`` and ``output``).
* Fields separated by commas, semicolons or whitespace (tabs); with semicolons
  or whitespace, numbers may have decimal commas (``0,25;1,5``: a spreadsheet's
  export in many locales), read as decimal points.
* MATLAB files (``.mat``, versions 4 to 7): their variables are the columns
  (:mod:`spm_sysid.core.io.matfile`); the same rules then apply.

Reading (:func:`read_text`) opens the path once and reads it from that one
handle, so a pipe (``--data <(cat f)``, ``--data /dev/stdin``) loses nothing.
Only regular files and pipes are read; a device such as ``/dev/zero`` is
refused. The text a read may produce is capped by the memory bound of
:mod:`spm_sysid.core.memory` (a regular file is checked by its size before
reading; a pipe or a gzip stream as it is read -- gzip's size field is never
trusted). The text is decoded as UTF-8 with an optional byte-order mark
(Excel's "CSV UTF-8").

Parsing is one routine (:func:`parse_table`): numpy's C reader does the work;
only when it fails is the text scanned line by line to name the first bad
line. Every problem is a :class:`DataError` naming the file, line and value,
never a bare numpy traceback.

Finding and downloading the robot-arm data set: :mod:`spm_sysid.core.io.datasets`.
"""

from __future__ import annotations

import csv
import gzip
import io
import math
import os
import re
import warnings
import zlib
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..files import read_bytes

__all__ = ["IOData", "TIME_COLUMNS", "Table", "load_data", "load_io", "parse_data_text",
           "parse_io_text", "parse_table", "read_text", "signal_name", "table_data",
           "time_column_unit"]

#: Header names of a time column (seconds, unless their size says otherwise: _CLOCKS).
TIME_COLUMNS = ("t", "time", "stamp", "timestamp", "__time")  # __time: PlotJuggler's

#: Time columns in other units than seconds, told from their values: (the least
#: magnitude of such a clock since 1970, seconds per unit, the unit's name). Seconds
#: since 1970 stay below 1e11 until the year 5138; ROS stamps are nanoseconds.
_CLOCKS = ((1e17, 1e-9, "nanoseconds"), (1e14, 1e-6, "microseconds"),
           (1e11, 1e-3, "milliseconds"))

#: A median step beyond this many "seconds" (more than a day between samples) is a
#: clock that counts nanoseconds from the record's start.
_NANOSECOND_STEP = 1e5

#: Units a time column's header may name, in seconds: ``time [ms]``, ``t (s)``,
#: ``timestamp_ns``.
_TIME_UNITS = {"s": 1.0, "sec": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "ns": 1e-9,
               "min": 60.0, "h": 3600.0}
_TIME_HEADER = re.compile(r"(t|time|stamp|timestamp|__time)(?:\s*[\[(]\s*(\S+?)\s*[\])]|_(\w+))")


def time_column_unit(name: str) -> tuple[bool, float | None]:
    """Whether a column of this (lower-case) name holds times; its unit in seconds if named.

    ``time`` (and :data:`TIME_COLUMNS`): times of a unit told from their values
    (None); ``time [ms]``, ``t (s)``, ``timestamp_ns``: that unit.
    """
    if name in TIME_COLUMNS:
        return True, None
    m = _TIME_HEADER.fullmatch(name.strip())
    unit = m and (m.group(2) or m.group(3))
    if unit in _TIME_UNITS:
        return True, _TIME_UNITS[unit]
    return False, None

#: Bytes of memory per byte of text while parsing: the bytes, the text, its lines (a
#: Python string each) and the numbers; 5.5 measured on 10^6 rows of two short numbers.
PARSE_FACTOR = 6

_COMMENT = ("#", "%")
_GZIP_MAGIC = b"\x1f\x8b"


# -- reading --------------------------------------------------------------------------


def read_text(path: str | os.PathLike) -> str:
    """The text of a data file or pipe (gzip-compressed or not), read once, bounded.

    Raises
    ------
    DataError
        Not found, a directory, a device, not UTF-8 text, or a corrupt gzip file.
    MemoryLimitError
        The text would need more memory than the bound.
    """
    path = Path(path)
    return _decode(read_bytes(path, "data file", factor=PARSE_FACTOR), path)[0]


#: Binary formats users export tables in, by their first bytes: what to do instead.
_BINARY_TABLES = ((b"PK\x03\x04", "a ZIP archive, as an Excel workbook (.xlsx) is: save the "
                   "sheet as CSV (CSV UTF-8)"),
                  (b"\xd0\xcf\x11\xe0", "an Excel 97-2003 workbook (.xls): save the sheet as "
                   "CSV (CSV UTF-8)"),
                  (b"PAR1", "a Parquet file: write it as CSV (pandas: df.to_csv)"),
                  (b"ARROW1", "an Arrow/Feather file: write it as CSV (pandas: df.to_csv)"),
                  (b"\x89HDF", "an HDF5 file (MATLAB -v7.3 saves these): save with '-v7' or "
                   "export a CSV"))


def _decode(raw: bytes, path: Path) -> tuple[str, str]:
    """The text of a file's bytes (gunzipped when they are gzip's), and how it was decoded.

    UTF-8 (with or without Excel's byte-order mark); else, for text without NUL
    bytes, Windows-1252, which spreadsheets in Western locales write ("°C",
    "µm") -- said in the second value ('' for UTF-8).
    """
    if path.suffix == ".gz" or raw[:2] == _GZIP_MAGIC:
        raw = _gunzip(raw, path)
    binary = b"\x00" in raw[:4096]  # text has no NUL bytes (nor does "PAR1,..." in a header)
    for magic, what in _BINARY_TABLES:
        if binary and raw.startswith(magic):
            raise DataError(f"{path} is {what}")
    try:
        return raw.decode("utf-8-sig"), ""
    except UnicodeDecodeError:
        pass
    if b"\x00" not in raw:
        try:
            return raw.decode("cp1252"), "Windows-1252"
        except UnicodeDecodeError:
            pass
    raise DataError(f"{path} is not a text file (not UTF-8)")


def _gunzip(raw: bytes, path: Path) -> bytes:
    """Decompress in pieces, checking the growing text against the memory bound."""
    from ..memory import check_memory

    out = io.BytesIO()
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as f:
            while chunk := f.read(1 << 22):
                out.write(chunk)
                check_memory(out.tell() * PARSE_FACTOR,
                             f"reading {path} (more than {out.tell() / 1e6:.0f} MB of text "
                             "once decompressed)")
    except (OSError, EOFError, zlib.error) as exc:
        reason = "it ends early" if isinstance(exc, EOFError) else str(exc)
        raise DataError(f"{path} is not a readable gzip file (truncated or corrupt: "
                        f"{reason})") from None
    return out.getvalue()


# -- parsing ----------------------------------------------------------------------------


@dataclass
class Table:
    """Numbers of a text table.

    Attributes
    ----------
    names : list of str or None
        Lower-case header names (None: no header).
    header_names : list of str or None
        The header as written (for messages).
    values : ndarray, shape (rows, columns)
        NaN where a field is empty (or NaN in the file).
    lines : ndarray of int, shape (rows,)
        1-based line number of each row, for messages.
    header_line : int
        Line of the header (0: none).
    separator : str or None
        ``","``, ``";"`` or None (whitespace).
    tokens : callable
        ``tokens(row)`` -> the row's fields as written (for messages).
    row_word : str
        What ``lines`` count, for messages: ``"line"`` of a text file, ``"row"`` of
        a table read from a MATLAB file (:mod:`spm_sysid.core.io.matfile`).
    """

    names: list[str] | None
    header_names: list[str] | None
    values: np.ndarray
    lines: np.ndarray
    header_line: int
    separator: str | None
    source: str
    _text_lines: list[str] | None
    row_word: str = "line"

    @property
    def width(self) -> int:
        return self.values.shape[1]

    def tokens(self, row: int) -> list[str]:
        if self._text_lines is None:  # no text: the numbers as Python writes them
            return [repr(float(v)) for v in self.values[row]]
        return _split(self._text_lines[int(self.lines[row]) - 1], self.separator)

    def where(self, row: int) -> str:
        """``"<source>, line N"`` of a row, for messages."""
        return f"{self.source}, {self.row_word} {self.lines[row]}"


def _show(token: str) -> str:
    """A field for a message (a very long one shortened)."""
    return repr(token) if len(token) <= 40 else f"{token[:20]!r}... ({len(token)} characters)"


#: Cells that spreadsheets, R and databases write for a missing value: read as NaN,
#: as an empty cell is (a row with one is a gap where the table has a time column).
MISSING = frozenset({"na", "n/a", "#n/a", "null", "none", "-"})


def is_missing(token: str) -> bool:
    """Whether a cell says that its value is missing (empty, ``NA``, ``#N/A``, ``null`` ...)."""
    return not token.strip() or token.strip().lower() in MISSING


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


#: A number written with a decimal comma (``-0,25``, ``1,5e-3``): what spreadsheets in
#: many locales export, with semicolons or tabs between the fields.
_DECIMAL_COMMA = re.compile(r"[+-]?\d*,\d+(?:[eE][+-]?\d+)?")


def _separator(line: str) -> tuple[str | None, bool]:
    """The separator of a first content line, and whether its numbers have decimal commas.

    A comma, unless the line has semicolons and each of its commas stands between
    digits (``0,5;1,25``: semicolons separate, commas are decimal marks); a
    semicolon; else whitespace, where fields like ``0,5`` are decimal commas too.
    """
    cells = _split(line, ";")
    if ";" in line and any(_DECIMAL_COMMA.fullmatch(c) for c in cells) and not any(
            "," in c and not _DECIMAL_COMMA.fullmatch(c) for c in cells):
        return ";", True
    words = _split(line, None)
    if "," in line and ";" not in line and len(words) > 1 and all(
            _DECIMAL_COMMA.fullmatch(c) or _is_number(c) for c in words):
        return None, True
    return ("," if "," in line else (";" if ";" in line else None)), False


#: Where a comment starts: a ``#`` that does not begin a spreadsheet's ``#N/A``.
_COMMENT_START = re.compile(r"#(?!n/a)", re.IGNORECASE)


def _split(line: str, sep: str | None) -> list[str]:
    line = _COMMENT_START.split(line, 1)[0]  # a comment after the values
    if sep and '"' in line:  # a quoted field may hold the separator ("torque, Nm")
        cells = next(csv.reader([line], delimiter=sep), [])
    else:
        cells = line.split(sep) if sep else line.split()
    return [c.strip().strip('"').strip() for c in cells]


def _content_lines(lines: list[str]):
    """(1-based number, line) of the lines that are neither blank nor comments."""
    for number, line in enumerate(lines, start=1):
        s = line.strip()
        if s and (s[0] not in _COMMENT or s[:4].lower() == "#n/a"):  # #N/A: a missing value
            yield number, line


def parse_table(text: str, source: str = "<text>") -> Table:
    """Parse a text table: separator and header detected, numbers read, NaN for empties.

    The separator is a comma when the first content line has one, a semicolon
    when it has one and no comma, else whitespace. A first line with a field
    that is not a number is the header.

    Raises
    ------
    DataError
        Empty text, a header without rows, a row with another number of fields,
        or a field that is not a number (line and value named).
    """
    lines = text.splitlines()
    content = _content_lines(lines)
    first = next(content, None)
    if first is None:
        raise DataError(f"{source}: no data (the file is empty)")
    number, line = first
    sep, comma = _separator(line)
    cells = _split(line, sep)
    header = not all(_is_number(c) or (comma and _DECIMAL_COMMA.fullmatch(c))
                     for c in cells if c)
    names = header_names = None
    header_line = 0
    if header:
        header_names, names, header_line = cells, [c.lower() for c in cells], number
    width = len(cells)
    rows = [] if header else [first]
    rows.extend(content)
    if not rows:
        raise DataError(f"{source}: the CSV file has a header but no data rows")
    if sep != "," and not comma:  # a header, or whole numbers first: the first rows tell
        comma = any(_DECIMAL_COMMA.fullmatch(c) for _, ln in rows[:100] for c in _split(ln, sep))
    if comma:  # decimal commas read as decimal points
        rows = [(n, ln.replace(",", ".")) for n, ln in rows]
    line_numbers = np.fromiter((n for n, _ in rows), dtype=np.int64, count=len(rows))
    # a time column may hold ISO 8601 date-times (pandas' to_csv, loggers)
    it = next((k for k, n in enumerate(names or []) if time_column_unit(n)[0]), None)
    try:
        values = _read_numbers(rows, sep, width)
    except ValueError:  # date-times; else an empty field, a bad value, a short row
        try:
            if it is None:
                raise
            values = _read_with_date_times(rows, sep, width, it)
        except ValueError:  # line by line, naming the first bad one
            values = _parse_rows(rows, sep, width, source, names is None, header_line, it)
    return Table(names, header_names, values, line_numbers, header_line, sep, source, lines)


def _read_numbers(rows, sep, width, usecols=None, dtype=float) -> np.ndarray:
    """The rows read by numpy's C reader (ValueError for anything but a full table)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # numpy reads the lines themselves (a joined copy of the text, and a
        # StringIO of it, held 4x the file's size more at 10^6 rows)
        values = np.loadtxt((ln for _, ln in rows), delimiter=sep, ndmin=2, dtype=dtype,
                            comments="#", quotechar='"' if sep else None, usecols=usecols)
    if values.shape != (len(rows), width if usecols is None else len(usecols)):
        raise ValueError("shape")
    return values


def _read_with_date_times(rows, sep, width: int, it: int) -> np.ndarray:
    """The table with its time column's ISO 8601 date-times as seconds since 1970 (UTC).

    numpy parses the date-times in C (a converter per row took 13x as long);
    anything it cannot parse raises ValueError, and the slow path names it.
    """
    others = [j for j in range(width) if j != it]
    values = np.empty((len(rows), width))
    if others:
        values[:, others] = _read_numbers(rows, sep, width, others)
    text = np.char.strip(_read_numbers(rows, sep, width, [it], dtype=str)[:, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpy warns of offsets (+02:00), and applies them
        stamps = text.astype("datetime64[ns]")
    ns = stamps.astype(np.int64).astype(float)
    values[:, it] = np.where(np.isnat(stamps), np.nan, ns * 1e-9)
    return values


def _time_value(token: str) -> float:
    """A time column's field in seconds: a number, or an ISO 8601 date-time; NaN if empty.

    A date-time without an offset is taken as UTC; anything else raises ValueError.
    """
    try:
        return float(token)
    except ValueError:
        pass
    text = token.strip().strip('"').strip()
    if not text:
        return math.nan
    stamp = datetime.fromisoformat(text)
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    return stamp.timestamp()


def _parse_rows(rows, sep, width, source, two_column_hint, header_line: int = 0,
                time_column: int | None = None) -> np.ndarray:
    """The slow path: every field read in Python; names the first bad line.

    A first row after the header with no number at all (units, say) is named as
    what it likely is: a second header line, which is not data.
    """
    values = np.empty((len(rows), width))
    for i, (number, line) in enumerate(rows):
        cells = _split(line, sep)
        where = f"{source}, line {number}"
        if len(cells) != width:
            hint = " (input u, output y)" if two_column_hint and width == 2 else ""
            raise DataError(f"{where}: expected {width} columns{hint}, found {len(cells)}")
        if i == 0 and header_line and not any(_is_number(c) for c in cells if c):
            first = next((c for c in cells if c), "")
            raise DataError(f"{where}: {_show(first)} is not a number; line {number} holds no "
                            "number at all: a second header line (units?) is not data: "
                            "delete it or start it with #")
        for j, c in enumerate(cells):
            if is_missing(c):
                values[i, j] = math.nan
                continue
            try:
                values[i, j] = _time_value(c) if j == time_column else float(c)
            except ValueError:
                if j == time_column:
                    raise DataError(f"{where}: the time column holds {_show(c)}, neither a "
                                    "number nor an ISO 8601 date-time (such as "
                                    "2024-05-01T12:00:00.001)") from None
                raise DataError(f"{where}: {_show(c)} is not a number") from None
    return values


# -- choosing the columns ------------------------------------------------------------------


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
    output_names : tuple of str
        Several outputs (``y`` of shape (n, q)): their names; empty for one.
    notes : tuple of str
        What a user should know of how the file was read (the time column's unit).
    """

    u: np.ndarray
    y: np.ndarray
    t: np.ndarray | None = None
    rejected: int = 0
    source: str = ""
    input_names: tuple[str, ...] = ()
    output_name: str = "y"
    output_names: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


def parse_data_text(text: str, source: str = "<text>", inputs: list[str] | None = None,
                    output: str | list[str] | None = None) -> IOData:
    """Parse data text into :class:`IOData`; see :func:`load_data` for the columns.

    ``output`` a list of several columns: ``y`` has one column per output (rows
    with any value missing are dropped together, with a time column).
    """
    return table_data(parse_table(text, source), source, inputs, output)


def table_data(table: Table, source: str, inputs: list[str] | None = None,
               output: str | list[str] | None = None) -> IOData:
    """The samples of a parsed table as :class:`IOData`; see :func:`load_data`."""
    names = table.names
    it = next((k for k, n in enumerate(names or []) if time_column_unit(n)[0]), None)
    outputs = [output] if isinstance(output, str) else list(output or [])
    chosen = inputs is not None or bool(outputs)
    iu, iys = _signal_columns(table, source, it, inputs, outputs)
    values = table.values
    signals = values[:, iu + iys]
    t = None
    rejected = 0
    notes: tuple[str, ...] = ()
    if it is not None:  # rows with missing values are dropped and counted (gaps by time)
        t, signals, rejected, repeated = _timed_rows(table, source, it, signals)
        if repeated:
            notes += (f"{source}: {repeated} row(s) repeating the row before (the same time "
                      "and values: a logger's duplicates?) dropped",)
        scale = time_column_unit(names[it])[1]
        t, unit = (t * scale, "") if scale is not None else _seconds(t)
        if unit:
            notes += (f"{source}: the time column '{(table.header_names or names)[it]}' read "
                     f"as {unit} ({_step_text(t)} between samples): as seconds its values "
                     "would be dates past the year 5000 or days apart",)
    else:
        _check_all_finite(table, source, signals, iu + iys)
    if not chosen and names and not ("u" in names and "y" in names):  # the two-column layout
        notes += tuple(f"{source}: column {k} ({table.header_names[k]!r}: {why}) left out"
                       for k, why in left_out(table).items())
    if len(signals) == 0:
        raise DataError(f"{source}: no rows with all values present")
    m = len(iu)
    u = signals[:, :m] if m > 1 else signals[:, 0]
    y = signals[:, m:] if len(iys) > 1 else signals[:, m]

    # lower-case names (as before), or as written where two chosen differ only by case;
    # a unit in the header is not part of the signal's name ("torque [Nm]": torque)
    written = bool(names) and len({signal_name(names[j]) for j in [*iu, *iys]}) < len(
        iu) + len(iys)
    shown = [signal_name(h) for h in (table.header_names if written else names or [])]
    if shown and len({shown[j] for j in [*iu, *iys]}) < len(iu) + len(iys):
        shown = [""] * len(shown)  # two chosen columns of one name ("q [rad]", "q [deg]")

    def label(j: int, default: str) -> str:
        return shown[j] if chosen and names and shown[j].isidentifier() else default

    in_names = tuple(label(j, f"u{k + 1}" if m > 1 else "u") for k, j in enumerate(iu))
    out_names = tuple(label(j, f"y{k + 1}" if len(iys) > 1 else "y")
                      for k, j in enumerate(iys))
    return IOData(np.ascontiguousarray(u), np.ascontiguousarray(y), t, rejected,
                  source, in_names if chosen else (), ",".join(out_names),
                  out_names if len(iys) > 1 else (), notes)


def _seconds(t: np.ndarray) -> tuple[np.ndarray, str]:
    """The times in seconds, and the unit they were in ('' when seconds already).

    Nanoseconds (ROS stamps), microseconds or milliseconds since 1970 are told by
    their size (:data:`_CLOCKS`); a clock from the record's start by its step
    (:data:`_NANOSECOND_STEP`: nanoseconds).
    """
    if not t.size:
        return t, ""
    largest = float(np.max(np.abs(t)))
    for least, scale, unit in _CLOCKS:
        if largest >= least:
            return t * scale, unit
    if t.size > 1 and float(np.median(np.diff(t))) >= _NANOSECOND_STEP:
        return t * 1e-9, "nanoseconds"
    return t, ""


def _step_text(t: np.ndarray) -> str:
    """The median step of times in seconds, for a note (``1 ms``)."""
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    for scale, unit in ((1.0, "s"), (1e-3, "ms"), (1e-6, "us")):
        if step >= scale:
            return f"{step / scale:.4g} {unit}"
    return f"{step * 1e9:.4g} ns"


def _signal_columns(table: Table, source: str, it: int | None, inputs: list[str] | None,
                    outputs: list) -> tuple[list[int], list[int]]:
    """The input and output columns: as chosen, named u and y, or the two besides time."""
    names, width = table.names, table.width
    if inputs is not None or outputs:
        iys = ([_column(table, c) for c in outputs] if outputs
               else [names.index("y") if names and "y" in names else width - 1])
        iu = ([_column(table, c) for c in inputs] if inputs
              else [k for k in range(width) if k not in iys and k != it])
        if not iu or set(iys) & set(iu) or len(set(iu)) != len(iu) or len(set(iys)) != len(
                iys) or (it is not None and (it in iu or it in iys)):
            shown = ", ".join(str(c) for c in [*(inputs or []), *outputs])
            raise DataError(f"{source}: choose distinct input and output columns (the "
                            f"columns asked for, {shown}, name a column twice or the time "
                            "column)")
        return iu, iys
    if names and "u" in names and "y" in names:
        return [names.index("u")], [names.index("y")]
    skipped = left_out(table)
    others = [k for k in range(width) if k != it and k not in skipped]
    if len(others) != 2:
        where = (f"{source}, line {table.header_line}" if table.header_line
                 else table.where(0))
        if names is None:
            raise DataError(f"{where}: expected 2 columns (input u, output y), "
                            f"found {width}")
        if it is not None:
            raise DataError(f"{source}: with a time column the CSV needs columns named "
                            f"'u' and 'y' or exactly two more columns, found {names}")
        raise DataError(f"{where}: CSV header {table.header_names} needs columns named "
                        f"'u' and 'y' or exactly 2 columns, found {width}")
    return [others[0]], [others[1]]


def left_out(table: Table) -> dict[int, str]:
    """Columns the two-column layout leaves out, and why.

    A first column of row numbers (pandas' ``to_csv`` writes its index without a
    name, ``Unnamed: 0`` once read back and written again), and unnamed columns
    without a value (a separator at the end of every line).
    """
    names = table.names or []
    out = {}
    for k, name in enumerate(names):
        if k == 0 and (name == "" or re.fullmatch(r"unnamed: \d+", name)):
            out[k] = "a row number, pandas' index?"
        elif name == "" and not np.isfinite(table.values[:, k]).any():
            out[k] = "empty: a separator at the end of each line?"
    return out


def _timed_rows(table: Table, source: str, it: int,
                signals: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Times, the rows with every value present, and how many rows were dropped.

    Third: rows with a missing value (gaps by time); fourth: rows that repeat the
    row before exactly, time and values (a logger's duplicates), said in a note.
    """
    values = table.values
    bad_t = np.flatnonzero(~np.isfinite(values[:, it]))
    if bad_t.size:
        raise DataError(f"{table.where(bad_t[0])}: the time column has a "
                        "missing or non-finite value")
    ok = np.all(np.isfinite(signals), axis=1)
    rejected = int((~ok).sum())
    kept = np.flatnonzero(ok)
    repeat = np.zeros(len(kept), dtype=bool)
    repeat[1:] = (np.all(signals[kept[1:]] == signals[kept[:-1]], axis=1)
                  & (values[kept[1:], it] == values[kept[:-1], it]))
    ok[kept[repeat]] = False
    values, signals = values[ok], signals[ok]
    t = values[:, it].copy()
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0])
        raise DataError(f"{table.where(np.flatnonzero(ok)[k + 1])}: the time column must "
                        f"increase; time "
                        f"{t[k + 1]:g} follows {t[k]:g}")
    return t, signals, rejected, int(repeat.sum())


def _check_all_finite(table: Table, source: str, signals: np.ndarray, cols: list[int]) -> None:
    """Without a time column every value must be there: else the line and the token."""
    bad = np.flatnonzero(~np.all(np.isfinite(signals), axis=1))
    if not bad.size:
        return
    row = int(bad[0])
    cells = table.tokens(row)
    token = next((cells[j] for j in cols if j < len(cells)
                  and not (not is_missing(cells[j]) and math.isfinite(float(cells[j])))), "")
    where = table.where(row)
    if token and is_missing(token):
        raise DataError(f"{where}: a value is missing ({_show(token)}; add a time column to "
                        "have such rows dropped as gaps)")
    if token:
        raise DataError(f"{where}: value {_show(token)} is not finite (NaN or inf are not "
                        "allowed; add a time column to have such rows dropped as gaps)")
    raise DataError(f"{where}: a value is missing (add a time column to have such "
                    "rows dropped as gaps)")


_UNIT_SUFFIX = re.compile(r"\s*[\[(][^\])]*[\])]\s*$")


def signal_name(header: str) -> str:
    """A column's header as a signal's name: a trailing unit left out, spaces as ``_``.

    ``torque [Nm]`` and ``Position (rad)`` name ``torque`` and ``Position``, so a
    model's terms read ``torque(t-1)`` and ``validate`` finds the column again.
    """
    return re.sub(r"\s+", "_", _UNIT_SUFFIX.sub("", header).strip())


def _column(table: Table, sel) -> int:
    sel = str(sel).strip()
    names, width = table.names, table.width
    if table.header_names and sel in table.header_names:  # as written: q1 and Q1 differ
        return table.header_names.index(sel)
    if names and names.count(sel.lower()) > 1:
        raise DataError(f"{table.source}: {sel!r} matches the columns "
                        f"{[h for h in table.header_names if h.lower() == sel.lower()]} "
                        "but none exactly (names differ only by case): spell it as written")
    if names and sel.lower() in names:
        return names.index(sel.lower())
    bare = [k for k, n in enumerate(names or []) if signal_name(n) == sel.lower()]
    if len(bare) == 1:  # "torque" names the column "torque [Nm]"
        return bare[0]
    if len(bare) > 1:
        raise DataError(f"{table.source}: {sel!r} names the columns "
                        f"{[table.header_names[k] for k in bare]} (their units apart): "
                        "give one as written")
    try:
        j = int(sel)
    except ValueError:
        have = ", ".join(names) if names else f"{width} unnamed columns"
        raise DataError(f"{table.source}: no column {sel!r} (it has {have})") from None
    if not 0 <= j < width:
        raise DataError(f"{table.source}: column index {j} outside 0..{width - 1}")
    return j


def load_data(path: str | os.PathLike, inputs: list[str] | None = None,
              output: str | list[str] | None = None) -> IOData:
    """Read a data file into :class:`IOData` (u, y and, with a time column, t).

    ``inputs`` and ``output`` choose columns by header name (CSV) or by 0-based
    index (any layout); with them a file may have any number of columns. Several
    ``output`` columns (a list) give ``y`` one column per output. Without
    them the two-column layouts of the module docstring apply. Default output
    with ``inputs`` given: the column named ``y``, else the last one.

    A MATLAB file (``.mat``, versions 4 to 7) is a table of its signals, named
    after its variables (:mod:`spm_sysid.core.io.matfile`).

    Raises
    ------
    DataError
        Missing file, wrong column count, non-numeric or non-finite values (except
        as described for time columns), a corrupt gzip or MATLAB file, a device, or
        a file too large for the memory bound.
    """
    from .matfile import is_mat, mat_signals

    path = Path(path)
    raw = read_bytes(path, "data file", factor=PARSE_FACTOR)
    if is_mat(path, raw):
        outputs = [output] if isinstance(output, str) else list(output or [])
        names, values = mat_signals(raw, str(path), [*(inputs or []), *outputs], TIME_COLUMNS)
        table = Table([k.lower() for k in names], names, values,
                      np.arange(1, len(values) + 1), 0, None, str(path), None, row_word="row")
        return table_data(table, str(path), inputs, output)
    text, encoding = _decode(raw, path)
    data = parse_data_text(text, str(path), inputs, output)
    if encoding:
        data.notes += (f"{path}: not UTF-8; read as {encoding} (a spreadsheet's export)",)
    return data


def parse_io_text(text: str, source: str = "<text>") -> tuple[np.ndarray, np.ndarray]:
    """Parse two-column or CSV text into ``(u, y)``; see the module docstring."""
    data = parse_data_text(text, source)
    return data.u, data.y


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
