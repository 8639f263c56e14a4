"""A job's settings: one frozen object built once, at the edge, from the settings schema.

:class:`JobSettings` is what a job needs besides the data (term space, GA,
criterion, validation, selection, certification); it is checked once when
built (:meth:`JobSettings.from_values`) and nothing after it checks again.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import SettingsError
from ..fit.criteria import get_criterion
from ..model.terms import TermSpace
from ..search.ga import GAConfig
from ..settings import JOB_GROUPS, check, defaults

__all__ = ["JobSettings"]


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
    criterion : str
        A registered criterion name (``aic``, ``bic``, ``pmic2``, ...).
    seed : int or None
        None: a new random seed (the schema's -1).
    validation : str
        ``estimation``, ``holdout`` or ``none``.
    validation_split, correlation_lags, sample_period, gap_factor
        See the settings schema.
    """

    term_space: TermSpace = field(default_factory=TermSpace)
    ga: GAConfig = field(default_factory=GAConfig)
    criterion: str = "aic"
    seed: int | None = None
    validation: str = "estimation"
    validation_split: float = 0.5
    correlation_lags: int = 20
    sample_period: float = 0.0
    gap_factor: float = 1.5
    focus: str = "prediction"
    shortlist: int = 20
    selection: str = "auto"
    max_terms: int = 0
    horizon: int = 0
    certify: bool = False
    certify_time_limit: float = 60.0
    polish: bool = True
    auto_certify_time_limit: float = 10.0

    @classmethod
    def from_values(cls, values: Mapping[str, Any], inputs: tuple[str, ...] = (),
                    output: str = "y") -> JobSettings:
        """Checked settings from a mapping of schema names (others are ignored).

        Missing names take the schema's defaults; ``nu`` and ``delay`` may be one
        value per input. ``inputs``/``output`` name the signals (their number fixes
        the number of inputs). Raises SettingsError (a ValueError) naming the first
        invalid setting.
        """
        v = defaults(JOB_GROUPS)
        v.update({k: values[k] for k in v if k in values and values[k] is not None})
        for name in ("criterion", "seed", "validation", "validation_split",
                     "correlation_lags", "sample_period", "gap_factor", "focus", "shortlist",
                     "selection", "max_terms", "horizon", "certify", "certify_time_limit",
                     "polish", "auto_certify_time_limit"):
            v[name] = check(name, v[name])
        criterion = v["criterion"].lower()
        try:
            get_criterion(criterion)
        except (KeyError, ValueError) as exc:
            raise SettingsError(str(exc).strip("'\"")) from None
        return cls(
            term_space=TermSpace(**{k: v[k] for k in _TERM_FIELDS}, inputs=tuple(inputs),
                                 output=output),
            ga=GAConfig(**{k: v[k] for k in _GA_FIELDS}),
            criterion=criterion,
            seed=None if v["seed"] < 0 else v["seed"],
            validation=v["validation"],
            validation_split=v["validation_split"],
            correlation_lags=v["correlation_lags"],
            sample_period=v["sample_period"],
            gap_factor=v["gap_factor"],
            focus=v["focus"],
            shortlist=v["shortlist"],
            selection=v["selection"],
            max_terms=v["max_terms"],
            horizon=v["horizon"],
            certify=v["certify"],
            certify_time_limit=v["certify_time_limit"],
            polish=v["polish"],
            auto_certify_time_limit=v["auto_certify_time_limit"],
        )

    def for_signals(self, inputs: tuple[str, ...], output: str) -> JobSettings:
        """These settings with the term space naming a record's signals.

        Raises
        ------
        SettingsError
            Per-input settings (``nu``, ``delay``) that do not fit the number of
            inputs.
        """
        from dataclasses import replace

        if (tuple(inputs), output) == (self.term_space.inputs, self.term_space.output):
            return self
        try:
            space = replace(self.term_space, inputs=tuple(inputs), output=output)
        except ValueError as exc:
            raise SettingsError(str(exc)) from None
        return replace(self, term_space=space)
