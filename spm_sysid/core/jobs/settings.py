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
from ..settings import check, defaults

__all__ = ["JobSettings"]


_TERM_FIELDS = ("ny", "nu", "degree", "delay", "constant")
_GA_FIELDS = ("population_size", "generations", "crossover_prob", "mutation_prob",
              "spm_fraction", "fitness", "init_terms", "mutation_per_structure", "elitism")


#: The schema's groups whose settings a job carries as options (besides the term space
#: and the GA): a setting added to the schema in one of them reaches every job.
OPTION_GROUPS = ("criterion", "validation", "data")


@dataclass(frozen=True)
class JobSettings:
    """Everything a job needs besides the data; build it with :meth:`from_values`.

    Built once, at the edge (a command's options, a node parameter or goal, the
    Python API), from the settings schema (:mod:`spm_sysid.core.settings`), and
    never checked again after that.

    Attributes
    ----------
    term_space : TermSpace
    ga : GAConfig
    options : dict
        Every other job setting of the schema (groups :data:`OPTION_GROUPS`), by
        its schema name, checked; each is also an attribute (``settings.criterion``,
        ``settings.validation`` ...). ``criterion`` is lower case and registered;
        ``seed`` is None for the schema's -1 (a new random seed).
    """

    term_space: TermSpace = field(default_factory=TermSpace)
    ga: GAConfig = field(default_factory=GAConfig)
    options: dict = field(default_factory=lambda: JobSettings.from_values({}).options)

    def __getattr__(self, name: str) -> Any:
        options = self.__dict__.get("options")
        if name.startswith("__") or options is None or name not in options:
            raise AttributeError(f"JobSettings has no setting {name!r}")
        return options[name]

    @classmethod
    def from_values(cls, values: Mapping[str, Any], inputs: tuple[str, ...] = (),
                    output: str = "y") -> JobSettings:
        """Checked settings from a mapping of schema names (others are ignored).

        Missing names take the schema's defaults; ``nu`` and ``delay`` may be one
        value per input. ``inputs``/``output`` name the signals (their number fixes
        the number of inputs). Raises SettingsError (a ValueError) naming the first
        invalid setting.
        """
        v = defaults((*OPTION_GROUPS, "term_space", "ga"))
        v.update({k: values[k] for k in v if k in values and values[k] is not None})
        options = {name: check(name, v[name]) for name in defaults(OPTION_GROUPS)}
        options["criterion"] = options["criterion"].lower()
        try:
            get_criterion(options["criterion"])
        except (KeyError, ValueError) as exc:
            raise SettingsError(str(exc).strip("'\"")) from None
        if options["seed"] < 0:
            options["seed"] = None
        return cls(
            term_space=TermSpace(**{k: v[k] for k in _TERM_FIELDS}, inputs=tuple(inputs),
                                 output=output),
            ga=GAConfig(**{k: v[k] for k in _GA_FIELDS}),
            options=options,
        )

    def options_for(self, fn) -> dict[str, Any]:
        """The options that ``fn`` takes as keywords of the same name (its signature decides).

        A setting added to the schema reaches a function of the search by its name
        alone: the code that uses it takes a keyword of that name.
        """
        import inspect

        params = inspect.signature(fn).parameters
        return {k: v for k, v in self.options.items() if k in params}

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
