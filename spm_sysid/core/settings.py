"""Every setting, declared once: name, type, default, range or choices, help, where it applies.

The command line options, the node's parameters (with their descriptors),
``config/sysid_node.yaml``, the experiment configuration and the validation of
every value all come from :data:`SETTINGS` (in the spirit of scikit-learn's
``_parameter_constraints``). One name per setting across layers: the node
parameter, the YAML key, the Python keyword and the long option
(``population_size`` is ``--population-size``); older option spellings stay as
aliases. A value is checked where it enters (an option, a parameter, a YAML
file, a Python constructor) with :func:`check`, which names the setting and
the rule it broke.

This module sits at the bottom of the core (it imports nothing of the
package but its errors), so the model's own settings classes
(:class:`~spm_sysid.core.model.terms.TermSpace`,
:class:`~spm_sysid.core.search.ga.GAConfig`) validate through it too.
"""

from __future__ import annotations

import math
import numbers
import operator
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from .defaults import AUTO_CERTIFY_TERMS, ROWS_PER_TERM
from .errors import SettingsError

__all__ = ["SETTINGS", "Setting", "check", "check_all", "defaults", "node_settings", "parse_text",
           "node_yaml", "settings_table"]


@dataclass(frozen=True)
class Setting:
    """One setting.

    Attributes
    ----------
    name : str
        The one name: node parameter, YAML key, Python keyword.
    kind : type
        ``int``, ``float``, ``bool`` or ``str``.
    default : object
    help : str
    group : str
        ``term_space``, ``ga``, ``criterion``, ``validation``, ``data`` (the job) or
        ``node`` (the node's own: topics, buffer, files).
    low, high : float, optional
        Inclusive range of numbers.
    choices : tuple of str, optional
        Allowed values of text settings.
    aliases : tuple of str
        Older command-line spellings still accepted (``--population``).
    cli : bool
        Offered by ``spm-sysid identify`` (and the commands sharing its options;
        the signal topics and fields there read bags).
    node : bool
        A parameter of ``sysid_node``.
    read_only : bool
        Node parameter set at start only.
    many : bool
        Several values in one text, separated by ``;`` (the command line takes
        them as separate words).
    """

    name: str
    kind: type
    default: Any
    help: str
    group: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    aliases: tuple[str, ...] = ()
    cli: bool = True
    node: bool = True
    read_only: bool = False
    many: bool = False

    @property
    def option(self) -> str:
        """The long command-line option, e.g. ``--population-size``."""
        return "--" + self.name.replace("_", "-")

    def describe_range(self) -> str:
        """The rule in words: ``between 1 and 100``, ``one of a, b``, or empty."""
        def show(x):
            return str(int(x)) if self.kind is int else f"{x:g}"

        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.low is not None and self.high is not None:
            return f"between {show(self.low)} and {show(self.high)}"
        if self.low is not None:
            return f">= {show(self.low)}"
        return ""


#: The data options of a bag (and of a DataSpec), by their settings names.
BAG_OPTIONS = ("input_topic", "input_field", "input_names", "output_topic", "output_field",
               "output_names", "stamp_tolerance")

def _s(name, kind, default, help, group, **kw) -> Setting:  # noqa: A002 - a field name
    return Setting(name, kind, default, help, group, **kw)


_LIST = [
    # -- the candidate terms -------------------------------------------------------------
    _s("ny", int, 4, "output lags 1..ny", "term_space", low=0, high=100),
    _s("nu", int, 4, "number of input lags (delay .. delay+nu-1)", "term_space", low=0,
       high=100),
    _s("degree", int, 2, "polynomial degree (the paper's nonlinearity)", "term_space", low=1,
       high=5),
    _s("delay", int, 1, "input delay, the smallest input lag (0: u(t) acts on y(t))",
       "term_space", low=0, high=100),
    _s("constant", bool, False, "include a constant candidate term", "term_space"),
    _s("regressors", str, "", "regressors beside the polynomial terms: 'friction' (the "
       "sign, the absolute value and a smooth sign of the output's last step; of a speed, "
       "its own sign and a smooth one), 'saturation' "
       "(each input's lags clipped at the level the data prefer) or expressions such as "
       "'sign(y(t-1)-y(t-2))', separated by ';' (docs/model_format.md)",
       "term_space", many=True),
    _s("operating_point", str, "auto", "identify the deviations from the estimation data's "
       "means, the model written in the record's units (docs/method.md): auto (when some "
       "signal's mean is farther from zero than its standard deviation), mean (always) or "
       "none (the record as it is)", "term_space", choices=("auto", "mean", "none")),
    # -- the genetic algorithm -------------------------------------------------------------
    _s("population_size", int, 200, "GA population (paper: 200 and 100)", "ga", low=2,
       high=100_000, aliases=("--population",)),
    _s("generations", int, 300, "GA generations (paper: 300)", "ga", low=0, high=1_000_000),
    _s("crossover_prob", float, 0.6, "single-point crossover probability", "ga", low=0.0,
       high=1.0, aliases=("--crossover",)),
    _s("mutation_prob", float, 0.01, "per-bit mutation probability", "ga", low=0.0, high=1.0,
       aliases=("--mutation",)),
    _s("spm_fraction", float, 0.15, "single parent mating fraction s (0: plain GA)", "ga",
       low=0.0, high=0.5, aliases=("--spm",)),
    _s("fitness", str, "akaike", "roulette fitness transform (docs/method.md)", "ga",
       choices=("akaike", "rank", "window")),
    _s("init_terms", float, 22.0, "expected terms in a random initial structure (the "
       "probability of each term is min(0.5, init_terms / M): the paper's 0.5 for its 44 "
       "terms)", "ga", low=0.0, high=100_000.0),
    _s("mutation_per_structure", float, 0.44, "most expected bit flips per child (the "
       "per-bit rate is min(mutation_prob, mutation_per_structure / M): the paper's 0.01 "
       "for its 44 terms)", "ga", low=0.0, high=100_000.0),
    _s("elitism", bool, True, "carry the best structure into the next generation", "ga",
       cli=False, node=False),
    # -- criterion and seed ----------------------------------------------------------------
    _s("criterion", str, "aic", "information criterion: aic, aicc (small-sample AIC), bic, "
       f"pmic2 (or a registered name); with fewer than {ROWS_PER_TERM} rows per candidate "
       "term prefer bic "
       "or aicc (aic's weak penalty admits far too many terms)", "criterion"),
    _s("seed", int, -1, "random seed; -1: a new random seed each run", "criterion", low=-1,
       high=2**31 - 1),
    # -- what the model is for -------------------------------------------------------------
    _s("focus", str, "prediction", "prediction (the paper's: one-step least squares) or "
       "simulation (free-run error: refined coefficients, structure by the criterion on "
       "the simulation error; docs/method.md)", "criterion",
       choices=("prediction", "simulation")),
    _s("shortlist", int, 20, "the GA's best structures judged further (focus simulation, "
       "validated selection)", "criterion", low=1, high=10_000),
    _s("orders", str, "given", "the lags and the degree: given (ny, nu, degree as set) or "
       "auto (proposed from the estimation data as propose-lags does -- the order by the "
       "criterion of the full linear models, the degree by forward selection -- then "
       "identified in that space; for several outputs each output in its own proposal)",
       "criterion", choices=("given", "auto")),
    _s("selection", str, "auto", "how the structure is chosen: criterion (on the estimation "
       "data, the paper's), validated (by its error on held-out blocks; docs/method.md), or "
       f"auto (validated for focus simulation, and for prediction with fewer than "
       f"{ROWS_PER_TERM} rows per "
       "candidate term)", "criterion", choices=("auto", "criterion", "validated")),
    _s("max_terms", int, 0, "largest number of terms a model may have (0: no limit)",
       "criterion", low=0, high=100_000),
    _s("polish", bool, True, "after the GA, a local search (one term added, removed or "
       "swapped) from its best while that improves the criterion, then kicks of a few terms "
       "each followed by the same search, restarted when the kicks stop helping, within a "
       "fixed count of steps (off in the paper's study, which measures the GA alone)",
       "criterion"),
    _s("auto_certify_time_limit", float, 10.0, "seconds of certification after every GA "
       "with aic, aicc or bic whose structure is chosen by the criterion (focus prediction) "
       f"on spaces of at most {AUTO_CERTIFY_TERMS} usable terms: the answer then says "
       "certified optimal or "
       "gives the gap (0: off)", "criterion", low=0.0, high=86_400.0),
    _s("certify", bool, False, "after the GA, prove its result the best of all structures "
       "by branch and bound (aic, bic), or report the gap (docs/method.md)", "criterion"),
    _s("certify_time_limit", float, 60.0, "seconds the certification may take before it "
       "reports the best structure, a lower bound and the gap", "criterion", low=0.0,
       high=86_400.0),
    # -- validation ----------------------------------------------------------------------
    _s("horizon", int, 0, "also report k-step-ahead prediction for this k (0: only "
       "one-step and free-run)", "validation", low=0, high=1_000_000),
    _s("validation", str, "estimation", "validate on the estimation data, a held-out tail, "
       "or not at all", "validation", choices=("estimation", "holdout", "none")),
    _s("validation_split", float, 0.5, "estimation fraction for holdout validation",
       "validation", low=0.1, high=0.9, aliases=("--split",)),
    _s("correlation_lags", int, 20, "largest lag of the correlation tests", "validation",
       low=1, high=10_000, aliases=("--corr-lags",)),
    # -- the data's timeline ---------------------------------------------------------------
    _s("sample_period", float, 0.0, "sampling period, s, for finding gaps in stamps "
       "(0: estimated from the stamps)", "data", low=0.0, high=3600.0, cli=False),
    _s("gap_factor", float, 1.5, "a stamp difference above gap_factor periods is a gap",
       "data", low=1.01, high=1000.0, cli=False),
    _s("decimate", int, 1, "identify at a slower rate: blocks of this many samples become "
       "one (inputs averaged, outputs the block's first; for records sampled much faster "
       "than their dynamics, e.g. a 1 kHz joint; 1: the record's rate)", "data", low=1,
       high=10_000),
    _s("spikes", str, "warn", "output spikes, samples that jump and come back within "
       "5 (the data check finds them; docs/cli.md): warn, or gaps (no regression row uses "
       "them; the answer counts them)", "data", choices=("warn", "gaps")),
    # -- the node's own ---------------------------------------------------------------------
    _s("input_topic", str, "/robot_arm/torque", "input signal topic(s): one, or a comma "
       "list, one per input (inputs on one topic share its messages)", "node",
       read_only=True),
    _s("input_type", str, "geometry_msgs/msg/WrenchStamped", "input message type(s): one "
       "for all input topics, or a comma list, one per input", "node",
       cli=False, read_only=True),
    _s("input_field", str, "", "field path(s) of the inputs (e.g. effort[0],effort[1], or "
       "effort[shoulder],effort[elbow]: joints by name; empty: the type's default)", "node",
       read_only=True),
    _s("input_names", str, "", "names of the inputs in the model, a comma list (empty: u, "
       "or u1, u2, ... for several)", "node", read_only=True),
    _s("output_topic", str, "/robot_arm/acceleration", "output signal topic(s): one, or a "
       "comma list, one per output (several outputs: one coupled model of several joints)",
       "node", read_only=True),
    _s("output_type", str, "geometry_msgs/msg/AccelStamped", "output message type(s): one "
       "for all output topics, or a comma list, one per output", "node",
       cli=False, read_only=True),
    _s("output_field", str, "", "field path(s) of the outputs (e.g. "
       "velocity[0],velocity[1], or velocity[elbow]: a joint by name; empty: the type's "
       "default)", "node", read_only=True),
    _s("output_names", str, "", "names of the outputs in the model, a comma list (empty: y, "
       "or y1, y2, ... for several)", "node", read_only=True),
    _s("best_effort", bool, False, "subscribe best-effort, keep-last qos_depth (for "
       "best-effort sensors); default: reliable, keep-all", "node", cli=False,
       read_only=True),
    _s("qos_depth", int, 1000, "subscription queue depth (keep-last history only)", "node",
       low=1, high=100_000, cli=False, read_only=True),
    _s("buffer_capacity", int, 100_000, "most sample pairs kept (the oldest are dropped, "
       "counted)", "node", low=10, high=10_000_000, cli=False, read_only=True),
    _s("stamp_tolerance", float, 0.0005, "largest input/output stamp difference of a pair, s",
       "node", low=0.0, high=1.0, read_only=True),
    _s("resync_samples", int, 10, "in-order samples behind a stream's last stamp that "
       "start a new segment (a jump back in time)", "node", low=1, high=100_000, cli=False,
       read_only=True),
    _s("diagnostics_period", float, 1.0, "seconds between /diagnostics messages", "node",
       low=0.05, high=60.0, cli=False, read_only=True),
    _s("min_samples", int, 100, "fewest paired samples for an identification", "node",
       low=10, high=10_000_000, cli=False),
    _s("job_timeout", float, 600.0, "seconds an identification may run before it is "
       "stopped (0: no limit)", "node", low=0.0, high=1e6, cli=False),
    _s("model_path", str, "", "save each model's JSON document here and publish it again "
       "at start-up (empty: don't)", "node", cli=False),
    # -- the live dashboard (a read-only web page served by the node) --------------------
    _s("dashboard_port", int, 0, "serve the live dashboard (monitor state, measured against "
       "predicted, residuals, the model, progress, the last report) on this TCP port (0: "
       "off)", "node", low=0, high=65535, cli=False, read_only=True),
    _s("dashboard_host", str, "127.0.0.1", "address the dashboard binds (any other than a "
       "loopback address needs dashboard_token)", "node", cli=False, read_only=True),
    _s("dashboard_token", str, "", "token the dashboard asks for (?token=...; required when "
       "dashboard_host is not a loopback address)", "node", cli=False, read_only=True),
    _s("dashboard_seconds", float, 10.0, "seconds of measured and predicted samples the "
       "dashboard shows", "node", low=0.5, high=3600.0, cli=False, read_only=True),
    # -- online: prediction, validity monitor, tracking, re-identification ----------------
    _s("monitor", bool, True, "with a current model, predict each paired sample one step "
       "ahead (~/prediction) and monitor the model's validity (~/validity)", "online",
       cli=False),
    _s("monitor_window", int, 200, "samples of the monitor's residual RMS and whiteness "
       "window", "online", low=20, high=100_000, cli=False),
    _s("prediction_horizon", int, 1, "also predict k steps ahead on ~/prediction "
       "(predicted_k: y(t) from the samples up to t-k; 1: one-step only)", "online", low=1,
       high=1000, cli=False),
    _s("prediction_every", int, 1, "publish every n-th prediction on ~/prediction (all are "
       "monitored)", "online", low=1, high=100_000, cli=False),
    _s("tracking", bool, False, "track the coefficients by recursive least squares and "
       "publish them on ~/tracked_model (never replacing the identified model)", "online",
       cli=False),
    _s("forgetting", float, 0.99, "forgetting factor of the tracking (memory about "
       "1/(1-forgetting) samples)", "online", low=0.9, high=1.0, cli=False),
    _s("tracking_period", float, 1.0, "seconds between ~/tracked_model messages", "online",
       low=0.05, high=3600.0, cli=False, read_only=True),
    _s("reidentify", str, "never", "automatic re-identification: never, when_invalid (on the "
       "data since the detected change) or periodic (every reidentify_interval on recent "
       "data); a new model replaces the current one only when it predicts the held-out "
       "recent samples better", "online", choices=("never", "when_invalid", "periodic"),
       cli=False),
    _s("reidentify_interval", float, 60.0, "fewest seconds between automatic "
       "identifications (the period with reidentify periodic)", "online", low=1.0,
       high=1e7, cli=False),
    _s("reidentify_samples", int, 500, "fewest new samples (since the change, or the last "
       "model) for an automatic identification", "online", low=50, high=10_000_000,
       cli=False),
    _s("reidentify_holdout", float, 0.25, "share of those samples (the most recent) held "
       "out to compare the new model with the current one", "online", low=0.05, high=0.5,
       cli=False),
]

#: Every setting by name, in documentation order.
SETTINGS: dict[str, Setting] = {s.name: s for s in _LIST}

JOB_GROUPS = ("term_space", "ga", "criterion", "validation", "data")


def check(name: str, value: Any) -> Any:
    """Check one value against its setting; return it in the setting's type.

    Integers are accepted for float settings; booleans are not numbers here.

    Raises
    ------
    SettingsError
        Unknown setting, wrong type, out of range, or not one of the choices; the
        message names the setting.
    """
    try:
        s = SETTINGS[name]
    except KeyError:
        raise SettingsError(f"unknown setting {name!r}") from None
    value = _typed(s, value)
    if s.kind in (int, float) and ((s.low is not None and value < s.low)
                                   or (s.high is not None and value > s.high)):
        raise SettingsError(f"{name} must be {s.describe_range()}, got {value!r} ({s.help})")
    return value


def _number(name: str, value: Any) -> float:
    """A finite real number as a float (an integer is one; a boolean is not)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SettingsError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(float(value)):
        raise SettingsError(f"{name} must be a finite number, got {float(value)!r}")
    return float(value)


def _typed(s: Setting, value: Any) -> Any:
    """``value`` in the setting's type, or a SettingsError naming the setting."""
    name = s.name
    if s.kind is bool:
        if not isinstance(value, bool):
            raise SettingsError(f"{name} must be true or false, got {value!r}")
        return value
    if s.kind is int:
        if isinstance(value, bool):
            raise SettingsError(f"{name} must be an integer, got {value!r}")
        try:
            return operator.index(value)  # int and numpy integers; not 4.0 or "4"
        except TypeError:
            raise SettingsError(f"{name} must be an integer, got {value!r}") from None
    if s.kind is float:
        return _number(name, value)
    if s.kind is str:
        if not isinstance(value, str):
            raise SettingsError(f"{name} must be text, got {value!r}")
        if s.choices and value not in s.choices:
            raise SettingsError(f"{name} must be one of {', '.join(s.choices)}, got {value!r}")
    return value


def parse_text(setting: Setting | str, text: str) -> Any:
    """A value written as text (an action goal's override) in the setting's type.

    ``true``/``false`` for booleans, a number for numbers, the text itself for
    text settings. The result still goes through :func:`check`.

    Raises
    ------
    SettingsError
        Text that is not a value of the setting's type; the message names it.
    """
    s = SETTINGS[setting] if isinstance(setting, str) else setting
    word = text.strip()
    if s.kind is str:
        return text
    if s.kind is bool:
        if word.lower() in ("true", "false"):
            return word.lower() == "true"
        raise SettingsError(f"{s.name} must be true or false, got {text!r}")
    try:
        return int(word) if s.kind is int else float(word)
    except ValueError:
        kind = "an integer" if s.kind is int else "a number"
        raise SettingsError(f"{s.name} must be {kind}, got {text!r}") from None


def check_all(values: Mapping[str, Any], names: Iterable[str] | None = None) -> dict[str, Any]:
    """Check several values (all of ``values``, or only ``names``); a checked copy."""
    keys = list(values) if names is None else [n for n in names if n in values]
    return {k: check(k, values[k]) for k in keys}


def defaults(groups: Iterable[str] | None = None) -> dict[str, Any]:
    """Default values of the settings in ``groups`` (all when None)."""
    groups = None if groups is None else set(groups)
    return {s.name: s.default for s in _LIST if groups is None or s.group in groups}


def node_settings() -> list[Setting]:
    """The node's parameters, in documentation order."""
    return [s for s in _LIST if s.node]


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        import json

        import yaml

        # quoted when YAML would read it as something else ("off" is false in YAML 1.1)
        return value if value and yaml.safe_load(value) == value else json.dumps(value)
    return repr(value)


def node_yaml() -> str:
    """``config/sysid_node.yaml``: every node parameter, its default and what it is."""
    lines = ["# Parameters of sysid_node (node name spm_sysid), generated from the settings",
             "# schema (spm_sysid/core/settings.py) by `spm-sysid settings --yaml`. Load with",
             "#   ros2 run spm_sysid sysid_node --ros-args --params-file config/sysid_node.yaml",
             "# (or: sysid_node --ros-args --params-file config/sysid_node.yaml).",
             "# read-only: set at start only; the others may change at run time and are",
             "# checked when set (an invalid value is refused with the reason).",
             "spm_sysid:", "  ros__parameters:"]
    group = None
    for st in node_settings():
        if st.group != group:
            group = st.group
            lines.append(f"    # -- {group.replace('_', ' ')}")
        rng = st.describe_range()
        note = st.help + (f"; {rng}" if rng else "") + ("; read-only" if st.read_only else "")
        lines.append(f"    {st.name}: {_yaml_value(st.default)}  # {note}")
    return "\n".join(lines) + "\n"


def settings_table() -> str:
    """Every setting as a Markdown table: name, default, rule, where, help."""
    rows = ["| name | default | allowed | where | what |", "|---|---|---|---|---|"]
    for st in _LIST:
        where = ", ".join(w for w, on in (("command line", st.cli), ("node", st.node))
                          if on) or "Python"
        opt = f" (`{st.option}`" + "".join(f", `{a}`" for a in st.aliases) + ")" if st.cli \
            else ""
        rows.append(f"| `{st.name}`{opt} | `{_yaml_value(st.default)}` | "
                    f"{st.describe_range() or ('true/false' if st.kind is bool else '')} | "
                    f"{where}{', read-only' if st.read_only else ''} | {st.help} |")
    return "\n".join(rows) + "\n"

