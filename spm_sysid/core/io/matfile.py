"""MATLAB data files (``.mat``, versions 4 to 7) read as a table of signals.

Control engineers keep their records in MATLAB files, and the public
benchmarks ship as such. Every variable that is a numeric vector of two or
more samples becomes a column named after it; a matrix becomes one column per
column, ``name[0]``, ``name[1]``, ... (per row when it has fewer rows than
columns: MATLAB code often stores a signal per row); struct fields are named
with dots, ``data.u``, down to :data:`MAX_DEPTH` levels. Numbers (a sample
time), text, cells and complex values are not signals: they are left out and
counted in messages.

The signals returned are those of one length: that of the signals asked for,
else of ``u`` and ``y``, else of the only two signals of a length (time
variables aside). :mod:`spm_sysid.core.io.data` reads them as a table's
columns, so a variable named ``t``, ``time``, ``stamp`` or ``timestamp`` of that
length gives the samples' times, as a CSV column of that name does.

Version 7.3 files are HDF5 and are refused with how to save them otherwise:
reading them would need h5py, a dependency for a format MATLAB writes only when
asked to (or beyond 2 GB per variable).
"""

from __future__ import annotations

import io
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from ..errors import DataError

__all__ = ["MAT_MAGIC", "is_mat", "mat_signals"]

#: The first bytes of a MATLAB 5-7.3 file (version 4 files have no such header).
MAT_MAGIC = b"MATLAB "

#: Levels of nested structs whose fields become columns.
MAX_DEPTH = 3


def is_mat(path: Path, raw: bytes) -> bool:
    """A binary MATLAB file: by its header, or a ``.mat`` name and binary bytes.

    Version 4 has no header; text that MATLAB's ``save -ascii`` wrote under a
    ``.mat`` name has no zero byte and is read as text.
    """
    if raw[:7] == MAT_MAGIC and b"MAT-file" in raw[:40]:
        return True
    return path.suffix.lower() == ".mat" and b"\0" in raw[:128]


def mat_signals(raw: bytes, source: str, wanted: list[str], time_names: tuple[str, ...]
                ) -> tuple[list[str], np.ndarray]:
    """The names and the samples (rows x signals) of a MATLAB file's signals of one length.

    ``wanted``: the signals asked for (names); they decide the length. ``time_names``:
    names (lower case) of time variables, which the default choice leaves aside.

    Raises
    ------
    DataError
        Not a MATLAB file, a version 7.3 (HDF5) file, no signal, a signal asked
        for that the file does not hold, or signals of different lengths.
    """
    columns, others = _signals(_variables(raw, source))
    listing = _listing(columns, others)
    if not columns:
        raise DataError(f"{source}: no signal (a numeric vector of two or more samples) in "
                        f"the file; {listing}")
    n = _length(columns, wanted, source, listing, time_names)
    names = [k for k, v in columns.items() if len(v) == n]
    return names, np.column_stack([columns[k] for k in names])


def _variables(raw: bytes, source: str) -> dict:
    """The file's variables (scipy's reader; structs as dicts)."""
    from scipy.io import loadmat

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            variables = loadmat(io.BytesIO(raw), simplify_cells=True)
    except MemoryError:
        raise
    except NotImplementedError:  # scipy's answer to version 7.3
        raise DataError(f"{source} is a MATLAB version 7.3 (HDF5) file, which is not read "
                        "here: save it with save(file, ..., '-v7') or export a CSV "
                        "(writetable)") from None
    except Exception as exc:  # noqa: BLE001 - any reader failure is a damaged file
        raise DataError(f"{source} is not a readable MATLAB file "
                        f"({type(exc).__name__}: {str(exc)[:200]})") from None
    return {k: v for k, v in variables.items() if not k.startswith("__")}


def _signals(variables: dict, prefix: str = "", depth: int = 0,
             others: list[str] | None = None) -> tuple[dict[str, np.ndarray], list[str]]:
    """(column name -> samples as float, names of the variables that are not signals)."""
    columns: dict[str, np.ndarray] = {}
    others = [] if others is None else others
    for name, value in variables.items():
        key = prefix + name
        if isinstance(value, dict):
            if depth < MAX_DEPTH:
                columns.update(_signals(value, key + ".", depth + 1, others)[0])
            else:
                others.append(key)
            continue
        a = value if isinstance(value, np.ndarray) else None
        if a is None or a.dtype.kind not in "biuf" or a.ndim > 2 or a.size < 2:
            others.append(key)
        elif a.ndim == 1:
            columns[key] = a.astype(float)
        else:
            a = a.T if a.shape[0] < a.shape[1] else a
            for j in range(a.shape[1]):
                columns[f"{key}[{j}]"] = a[:, j].astype(float)
    return columns, others


def _listing(columns: dict[str, np.ndarray], others: list[str]) -> str:
    """What the file holds, for messages."""
    shown = ", ".join(f"{k} ({len(v)} samples)" for k, v in list(columns.items())[:20])
    more = f" and {len(columns) - 20} more" if len(columns) > 20 else ""
    rest = (f"; not signals (numbers, text, cells, complex or deeper structs): "
            f"{', '.join(others[:10])}{' ...' if len(others) > 10 else ''}" if others else "")
    return f"it holds {shown or 'no signal'}{more}{rest}"


def _find(columns: dict[str, np.ndarray], name: str) -> str | None:
    """The column a name asks for: as written, else the one matching in lower case."""
    if name in columns:
        return name
    match = [k for k in columns if k.lower() == name.lower()]
    return match[0] if len(match) == 1 else None


def _length(columns: dict[str, np.ndarray], wanted: list[str], source: str,
            listing: str, time_names: tuple[str, ...]) -> int:
    """The table's length: the signals asked for, else u and y, else the only two signals."""
    wanted = [str(w).strip() for w in wanted]
    if not wanted and _find(columns, "u") and _find(columns, "y"):
        wanted = ["u", "y"]
    if wanted:
        found = {}
        for w in wanted:
            k = _find(columns, w)
            if k is None:
                raise DataError(f"{source}: no signal {w!r} ({listing})")
            found[k] = len(columns[k])
        if len(set(found.values())) > 1:
            sizes = ", ".join(f"{k} {n}" for k, n in found.items())
            raise DataError(f"{source}: the signals differ in length ({sizes} "
                            "samples): they must be samples of the same times")
        return next(iter(found.values()))
    counts = Counter(len(v) for k, v in columns.items() if k.lower() not in time_names)
    pairs = [n for n, c in counts.items() if c >= 2]
    if len(pairs) == 1 and counts[pairs[0]] == 2:
        return pairs[0]
    raise DataError(f"{source}: name the input and the output (--inputs and --output on the "
                    "command line; signals named u and y, or the only two signals of one "
                    f"length, are taken without); {listing}")
