"""The regression problem of an identification: candidate columns the search may use.

A candidate term whose column is zero on every row (a term of an input that is
zero), or proportional to an earlier candidate's column (every lag of a
constant input; an input equal to the output), can never be part of an
identifiable structure with that other term: such columns are left out of the
search, once, here, and the result names them.
"""

from __future__ import annotations

import numpy as np

__all__ = ["excluded_columns"]

#: Columns equal after normalisation to this many bits are the same column.
_BITS = 36


def excluded_columns(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns to leave out of the search.

    Returns
    -------
    zero : ndarray of bool, shape (M,)
        Columns that are zero on every row.
    duplicate_of : ndarray of int, shape (M,)
        For a non-zero column proportional to an earlier non-zero column (equal
        after scaling to unit norm and fixing the sign, to about 1e-11), the index
        of the first such column; -1 otherwise.

    Notes
    -----
    Columns are compared by hashing their normalised values rounded to
    ``_BITS`` bits, O(N M); a pair that rounding splits stays in, and the
    evaluator's rank test still scores structures holding both as rank-deficient.
    """
    P = np.asarray(P, dtype=float)
    norms = np.linalg.norm(P, axis=0)
    zero = norms == 0
    duplicate_of = np.full(P.shape[1], -1)
    first: dict[bytes, int] = {}
    for j in np.flatnonzero(~zero):
        col = P[:, j] / norms[j]
        pivot = col[int(np.argmax(np.abs(col)))]
        key = np.round(np.ldexp(col * np.sign(pivot), _BITS)).astype(np.int64).tobytes()
        if key in first:
            duplicate_of[j] = first[key]
        else:
            first[key] = j
    return zero, duplicate_of
