"""A job's settings: one frozen, typed object built once, at the edge, from the schema.

:class:`JobSettings` is what a job needs besides the data: the term space, the GA,
the search (:class:`~spm_sysid.core.options.SearchOptions`), how the orders are
chosen, the validation and the data's timeline. It is checked once when built
(:meth:`JobSettings.from_values`) and nothing after it checks again. Every
field has the name of its setting in the schema (:mod:`spm_sysid.core.settings`);
a test holds the two against each other, so a setting added to the schema must
be added here (and reaches every caller), and none is passed on by a name that
happens to match.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from ..errors import SettingsError
from ..fit.criteria import get_criterion
from ..model.terms import TermSpace
from ..options import SEARCH_SETTINGS, SearchOptions
from ..search.ga import GAConfig
from ..settings import SETTINGS, check

__all__ = ["JOB_FIELDS", "JobSettings"]


_TERM_FIELDS = ("ny", "nu", "degree", "delay", "constant")
_GA_FIELDS = ("population_size", "generations", "crossover_prob", "mutation_prob",
              "spm_fraction", "fitness", "init_terms", "mutation_per_structure", "elitism")


@dataclass(frozen=True)
class JobSettings:
    """Everything a job needs besides the data; build it with :meth:`from_values`.

    Attributes
    ----------
    term_space : TermSpace
    ga : GAConfig
    search : SearchOptions
        How the structure is searched, chosen and fitted.
    orders : str
        ``given`` or ``auto`` (the lags and degree proposed from the data).
    validation, validation_split, correlation_lags : see the schema
    sample_period, gap_factor, decimate, spikes : see the schema
    regressors : str
        As given (``;``-separated); the job expands them with the record's
        signals (:meth:`with_regressors`).
    operating_point : str
        ``auto``, ``mean`` or ``none``
        (:mod:`~spm_sysid.core.model.operating_point`).
    """

    term_space: TermSpace = field(default_factory=TermSpace)
    ga: GAConfig = field(default_factory=GAConfig)
    search: SearchOptions = field(default_factory=SearchOptions)
    orders: str = SETTINGS["orders"].default
    validation: str = SETTINGS["validation"].default
    validation_split: float = SETTINGS["validation_split"].default
    correlation_lags: int = SETTINGS["correlation_lags"].default
    sample_period: float = SETTINGS["sample_period"].default
    gap_factor: float = SETTINGS["gap_factor"].default
    decimate: int = SETTINGS["decimate"].default
    spikes: str = SETTINGS["spikes"].default
    regressors: str = SETTINGS["regressors"].default
    operating_point: str = SETTINGS["operating_point"].default

    # the search's settings the rest of a job reads too (read-only views)
    @property
    def criterion(self) -> str:
        return self.search.criterion

    @property
    def seed(self) -> int | None:
        return self.search.seed

    @property
    def focus(self) -> str:
        return self.search.focus

    @property
    def horizon(self) -> int:
        return self.search.horizon

    @classmethod
    def from_values(cls, values: Mapping[str, Any], inputs: tuple[str, ...] = (),
                    output: str = "y") -> JobSettings:
        """Checked settings from a mapping of schema names (others are ignored).

        Missing names take the schema's defaults; ``nu`` and ``delay`` may be one
        value per input. ``inputs``/``output`` name the signals (their number fixes
        the number of inputs). Raises SettingsError (a ValueError) naming the first
        invalid setting.
        """
        given = {k: v for k, v in values.items() if v is not None}

        def value(name: str):
            return check(name, given[name]) if name in given else SETTINGS[name].default

        def raw(name: str):  # the term space and the GA check their own (nu per input ...)
            return given.get(name, SETTINGS[name].default)

        search = SearchOptions.from_values({**{k: value(k) for k in SEARCH_SETTINGS},
                                            **{k: given[k] for k in ("simulation_folds",
                                                                     "simulation_repeats")
                                               if k in given}})
        try:
            get_criterion(search.criterion)
        except (KeyError, ValueError) as exc:
            raise SettingsError(str(exc).strip("'\"")) from None
        own = {f.name: value(f.name) for f in fields(cls) if f.name in SETTINGS}
        return cls(
            term_space=TermSpace(**{k: raw(k) for k in _TERM_FIELDS}, inputs=tuple(inputs),
                                 output=output),
            ga=GAConfig(**{k: raw(k) for k in _GA_FIELDS}), search=search, **own)

    def with_regressors(self, y, u=None, own_sign: bool | None = None) -> JobSettings:
        """These settings with the term space holding the regressors (presets expanded on y, u).

        ``own_sign``: whether ``friction`` adds the output's own sign (None: from the
        data; False for samples around an operating point; :mod:`..model.presets`).

        Raises
        ------
        SettingsError
            A regressor outside the grammar, or naming a signal the record lacks.
        """
        items = [t.strip() for t in self.regressors.split(";") if t.strip()]
        if not items:
            return self
        from ..model.presets import expand_presets, preset_inputs

        try:
            texts = expand_presets(items, self.term_space.output, y,
                                   preset_inputs(self.term_space, u), self.term_space.ny,
                                   own_sign)
            space = replace(self.term_space, regressors=tuple(texts))
        except ValueError as exc:
            raise SettingsError(f"regressors: {exc}") from None
        return replace(self, term_space=space)

    def for_signals(self, inputs: tuple[str, ...], output: str) -> JobSettings:
        """These settings with the term space naming a record's signals.

        Raises
        ------
        SettingsError
            Per-input settings (``nu``, ``delay``) that do not fit the number of
            inputs.
        """
        if (tuple(inputs), output) == (self.term_space.inputs, self.term_space.output):
            return self
        try:
            space = replace(self.term_space, inputs=tuple(inputs), output=output)
        except ValueError as exc:
            raise SettingsError(str(exc)) from None
        return replace(self, term_space=space)


#: Every job setting of the schema, by where :class:`JobSettings` keeps it.
JOB_FIELDS = {"term_space": _TERM_FIELDS, "ga": _GA_FIELDS, "search": SEARCH_SETTINGS,
              "job": tuple(f.name for f in fields(JobSettings) if f.name in SETTINGS)}
