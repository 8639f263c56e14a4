"""What the search reads: one frozen, typed object, passed explicitly to every search.

:class:`SearchOptions` holds the job settings of the schema
(:mod:`spm_sysid.core.settings`) that choose and fit a structure -- criterion,
seed, focus, selection, certification ... -- each a typed field of the same name
and default as its setting (a test holds the two against each other). A job, a
study, the node and the Python API build it once at their edge
(:meth:`SearchOptions.from_values`, or :attr:`JobSettings.search
<spm_sysid.core.jobs.settings.JobSettings.search>`) and pass it to
:func:`~spm_sysid.core.identify.identify_problem`: a setting added to the schema
and here reaches every caller, and a renamed one fails loudly.

Besides the settings, two tuning values of the held-out blocks (how many blocks
and how often they are laid, :mod:`spm_sysid.core.defaults`) are fields too,
for the accuracy benchmark that measures other schemes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

from .defaults import SIMULATION_FOLDS
from .settings import SETTINGS, check

__all__ = ["SEARCH_SETTINGS", "SearchOptions"]


@dataclass(frozen=True)
class SearchOptions:
    """The settings of a search (see the module doc and each setting's help).

    Attributes
    ----------
    criterion : str, Criterion or callable
        A registered name (``aic``, ``aicc``, ``bic``, ``pmic2``), or a user's
        ``f(sse, n, k, coefficients)`` (Python API only).
    seed : int or None
        None: a new random seed each run.
    focus, shortlist, selection, max_terms, polish : see the schema
    auto_certify_time_limit, certify, certify_time_limit : see the schema
    horizon : int
        The k of the k-step prediction that integrating or open-loop unstable
        records are judged on with the simulation focus (0: the default k).
    simulation_folds, simulation_repeats : int
        Held-out blocks of the simulation focus and how many times they are laid
        (not settings of the schema: tuning, :mod:`spm_sysid.core.defaults`);
        repeats None: :data:`~spm_sysid.core.defaults.SIMULATION_REPEATS`, once on
        a long record (:data:`~spm_sysid.core.defaults.LONG_ROWS`).
    """

    criterion: str | Callable[..., Any] = SETTINGS["criterion"].default
    seed: int | None = None
    focus: str = SETTINGS["focus"].default
    shortlist: int = SETTINGS["shortlist"].default
    selection: str = SETTINGS["selection"].default
    max_terms: int = SETTINGS["max_terms"].default
    polish: bool = SETTINGS["polish"].default
    auto_certify_time_limit: float = SETTINGS["auto_certify_time_limit"].default
    certify: bool = SETTINGS["certify"].default
    certify_time_limit: float = SETTINGS["certify_time_limit"].default
    horizon: int = SETTINGS["horizon"].default
    simulation_folds: int = SIMULATION_FOLDS
    simulation_repeats: int | None = None

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> SearchOptions:
        """Checked options from settings by their schema names (others are ignored).

        ``criterion`` may be a callable or a Criterion (not checked by the
        schema); a seed of -1 (the schema's "a new one each run") is None.

        Raises
        ------
        SettingsError
            A value of the wrong type or out of range, named.
        """
        given = {k: values[k] for k in SEARCH_SETTINGS if values.get(k) is not None}
        crit = given.get("criterion")
        if crit is not None and not isinstance(crit, str):
            given.pop("criterion")
        out = {k: check(k, v) for k, v in given.items()}
        if "criterion" in out:
            out["criterion"] = out["criterion"].lower()
        elif crit is not None:
            out["criterion"] = crit
        if out.get("seed") is not None and out["seed"] < 0:
            out["seed"] = None
        for k in ("simulation_folds", "simulation_repeats"):
            if values.get(k) is not None:
                out[k] = int(values[k])
        return cls(**out)

    def with_seed(self, seed: int | None) -> SearchOptions:
        """The same options with another seed (a study's run)."""
        return replace(self, seed=seed)

    @property
    def certify_within(self) -> float | None:
        """Seconds of the asked-for certification, or None when not asked."""
        return self.certify_time_limit if self.certify else None


#: The schema's settings that :class:`SearchOptions` carries (its fields that are settings).
SEARCH_SETTINGS = tuple(f.name for f in fields(SearchOptions) if f.name in SETTINGS)
