"""Forward selection: terms added one at a time, the best addition each step.

A greedy search that the lag and degree proposal (:mod:`spm_sysid.core.validate.orders`)
uses to estimate the best criterion a space can reach, the certification uses for
a first incumbent, and validated selection uses for small candidate structures
the GA may never visit.
"""

from __future__ import annotations

import numpy as np

from .local import local_search

__all__ = ["forward_selection", "forward_selection_path"]


def forward_selection(evaluator, max_terms: int = 60, patience: int = 3,
                      deadline: float | None = None) -> tuple[float, np.ndarray]:
    """Greedy forward selection; the best criterion value found and its structure.

    From the empty structure, the term whose addition scores best is added,
    step by step (:func:`~spm_sysid.core.search.local.local_search` with additions
    only), continuing ``patience`` steps past the last improvement; at most
    ``max_terms`` steps, stopping at ``deadline`` (``time.perf_counter()``).
    For AIC and BIC the best addition is the one that lowers the SSE most.

    Parameters
    ----------
    evaluator : StructureEvaluator
        Scores the structures (its criterion, its columns).
    max_terms : int
        Most terms added.
    patience : int
        Additions past the last improvement before it stops.
    deadline : float, optional
        ``time.perf_counter()`` at which to stop with the best so far.
    """
    empty = np.zeros(evaluator.n_terms, dtype=bool)
    res = local_search(evaluator.score, empty, ~evaluator.zero_columns, moves=("add",),
                       patience=patience, max_steps=max_terms, deadline=deadline, min_steps=1)
    return res.value, res.mask


def forward_selection_path(evaluator, max_terms: int = 60,
                           allowed: np.ndarray | None = None) -> np.ndarray:
    """Every structure forward selection passes through, smallest first (masks).

    The greedy additions of :func:`forward_selection`, without stopping at the
    criterion's minimum: one structure of each size up to ``max_terms`` (the
    small sizes a validated selection should judge too). ``allowed`` restricts
    the terms it may add (e.g. to the linear ones).
    """
    path: list[np.ndarray] = []
    empty = np.zeros(evaluator.n_terms, dtype=bool)
    ok = ~evaluator.zero_columns if allowed is None else (allowed & ~evaluator.zero_columns)
    local_search(evaluator.score, empty, ok, moves=("add",),
                 patience=max_terms + 1, max_steps=max_terms,
                 on_step=lambda mask, value: path.append(mask.copy()))
    return np.array(path, dtype=bool).reshape(len(path), evaluator.n_terms)
