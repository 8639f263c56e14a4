"""What the commands share: options from the settings schema, data, destinations, errors.

Every option of a job setting comes from the schema (:mod:`spm_sysid.core.settings`):
its name (``--population-size`` for ``population_size``, older spellings as
aliases), type, default and allowed values. Every failure a user can cause is a
:class:`UserError` (or one of the core's ``ValueError`` subclasses) and ends as
one ``error: ...`` line with exit status 2 (:func:`spm_sysid.tools.cli.run`).
"""

from __future__ import annotations

import argparse

from ...core.errors import SettingsError
from ...core.files import check_writable_dir
from ...core.settings import BAG_OPTIONS, SETTINGS, check

__all__ = ["JOB_TITLES", "PER_INPUT", "Parser", "UserError", "add_data_options",
           "add_schema_options", "announce_compile", "check_correlation_lags_option",
           "check_outputs", "check_report_name", "data_spec", "job_settings", "load",
           "positive_int", "read_yaml", "record_settings", "schema_type", "seed_type",
           "usable_segments"]


class UserError(Exception):
    """A problem the user can fix; printed without a traceback."""


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``spm-sysid identify: error: ...``), exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# -- option types -------------------------------------------------------------------------

PER_INPUT = ("nu", "delay")  # one value for all inputs, or a comma list: one per input


def schema_type(name: str):
    """An argparse type that checks a value against the settings schema."""
    setting = SETTINGS[name]

    def convert(text: str):
        if name in PER_INPUT and "," in text:
            return tuple(convert(part) for part in text.split(","))
        try:
            value = setting.kind(text) if setting.kind is not bool else text
        except ValueError:
            kind = {int: "an integer", float: "a number"}.get(setting.kind, "text")
            raise argparse.ArgumentTypeError(f"must be {kind}, got {text!r}") from None
        try:
            return check(name, value)
        except SettingsError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = setting.kind.__name__
    return convert


def positive_int(text: str) -> int:
    """An integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def seed_type(text: str) -> int:
    """A seed: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value


def comma_list(text: str) -> list[str]:
    """``a,b`` -> ``["a", "b"]`` (empty items dropped)."""
    return [c for c in text.split(",") if c]


# -- options ---------------------------------------------------------------------------------

JOB_TITLES = {
    "term_space": "term space (default: the paper's)",
    "ga": "genetic algorithm (default: the paper's settings)",
    "criterion": "criterion and seed",
    "validation": "validation",
    "data": "the data's rate",
}

#: The bag options (settings names) every data-reading command offers.


class _JoinWords(argparse.Action):
    """Several words of one option as one text, separated by ``;``."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, "; ".join(values))


def add_schema_options(p: argparse.ArgumentParser, groups: tuple[str, ...],
                       titles: dict[str, str] = JOB_TITLES, exclude: tuple[str, ...] = ()
                       ) -> None:
    """Options for every command-line setting of ``groups``, from the schema.

    The option is ``--`` + the setting's name with dashes; older spellings are
    aliases; the default and the allowed values come from the schema. Settings
    in ``exclude`` are left to the command.
    """
    for group in groups:
        g = p.add_argument_group(titles.get(group, group))
        for s in SETTINGS.values():
            if s.group != group or not s.cli or s.name in exclude:
                continue
            names = [s.option, *s.aliases]
            rng = s.describe_range()
            text = f"{s.help} (default {s.default!r}{'; ' + rng if rng else ''})"
            # default None: "not given" (the schema's default applies in JobSettings)
            if s.kind is bool and s.default:  # on by default: --no-NAME turns it off
                g.add_argument(*names, dest=s.name, action=argparse.BooleanOptionalAction,
                               default=None, help=f"{s.help} (default: on)")
            elif s.kind is bool:
                g.add_argument(*names, dest=s.name, action="store_true", default=None,
                               help=f"{s.help}")
            elif s.choices:
                g.add_argument(*names, dest=s.name, choices=s.choices, help=text)
            elif s.many:  # several words, kept as one ';'-separated text
                g.add_argument(*names, dest=s.name, nargs="+", action=_JoinWords,
                               metavar="TEXT", help=text)
            else:
                g.add_argument(*names, dest=s.name, type=schema_type(s.name),
                               metavar=s.kind.__name__.upper(), help=text)


def add_data_options(p: argparse.ArgumentParser, bag: bool = True,
                     title: str = "data (default: the robot-arm data)") -> None:
    """``--data`` (repeatable), and with ``bag`` also ``--bag``, columns, topics and fields."""
    g = p.add_argument_group(title)
    g.add_argument("--data", metavar="PATH", action="append",
                   help="two-column, CSV or MATLAB (.mat) file of u, y; give it several times for "
                        "several records (no regression row crosses from one to the next)")
    if bag:
        g.add_argument("--bag", metavar="PATH", help="rosbag2 bag (MCAP) to read u, y from")
        add_column_options(g)
        for name in BAG_OPTIONS:
            s = SETTINGS[name]
            g.add_argument(s.option, dest=name, default=s.default or None,
                           help=f"{s.help} (default {s.default!r})")


def add_column_options(g) -> None:
    """``--inputs`` and ``--output``: the columns of data files."""
    g.add_argument("--inputs", metavar="NAMES", type=comma_list,
                   help="input columns of --data files, by header name or 0-based index "
                        "(comma-separated; several inputs make a MISO model)")
    g.add_argument("--output", dest="output_column", metavar="NAME",
                   help="output column of --data files (default: 'y', else the last); a comma "
                        "list for several outputs (identify, validate: one coupled model)")


# -- settings, data, destinations --------------------------------------------------------


def job_settings(args):
    """The job's settings from the options, checked once (names come with the data)."""
    from ...core.jobs import JobSettings

    try:
        return JobSettings.from_values(vars(args))
    except (TypeError, ValueError) as exc:
        raise UserError(str(exc)) from None


def record_settings(settings, record):
    """The settings naming the record's signals, its regressors expanded on the record.

    For commands that run no job (``certify``, ``check-data``): presets take
    their scales from the whole record, as a job takes them from its
    estimation samples.
    """
    from ...core.errors import SettingsError

    try:
        return settings.for_signals(record.input_names, record.output_name).with_regressors(
            record.y, record.u)
    except SettingsError as exc:
        raise UserError(as_option(exc)) from None


def data_spec(args):
    """Where the command's data come from (:class:`~spm_sysid.core.record.DataSpec`)."""
    from ...core.record import DataSpec

    values = {k: getattr(args, k, None) for k in BAG_OPTIONS}
    values["inputs"] = getattr(args, "inputs", None)
    values["output"] = getattr(args, "output_column", None)
    data = getattr(args, "data", None)
    return DataSpec.from_values(values, data=data, bag=getattr(args, "bag", None))


def load(args, several: bool = False, decimate: bool = False):
    """The command's data as a :class:`~spm_sysid.core.record.Record`; its notes printed.

    ``several``: the command takes several outputs (else one clear error).
    ``decimate``: decimated here by ``--decimate`` (commands that run no job;
    a job decimates its record itself, :func:`~spm_sysid.core.jobs.run_job`).
    """
    from ...core.record import load_record

    record = load_record(data_spec(args))
    if not several:
        record.require_one_output(f"spm-sysid {getattr(args, 'command', '')}".strip())
    if decimate and (getattr(args, "decimate", None) or 1) > 1:
        record = record.decimated(args.decimate)
    for note in record.notes:
        print(f"note: {note}")
    return record


def read_yaml(path: str, option: str):
    """A YAML file's content, or one ``error:`` line naming the option, line and problem."""
    import yaml

    from ...core.files import read_bytes

    raw = read_bytes(path, f"{option} file", error=UserError)
    try:
        return yaml.safe_load(raw.decode("utf-8-sig"))
    except UnicodeDecodeError:
        raise UserError(f"{option} {path} is not a text file") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        raise UserError(f"{option} {path} is not valid YAML{where}: {problem}") from None


def usable_segments(record, max_lag: int) -> list[tuple[int, int]]:
    """The record's segments longer than ``max_lag`` (one error line when there are none)."""
    from ...core.model.segments import usable_segments as usable

    info = record.segment_info()
    bounds, _, _ = usable(info.bounds, max_lag)
    if not bounds:
        raise UserError(f"{record.source}: no contiguous segment is longer than the largest "
                        f"lag ({max_lag}); {len(record)} samples in {len(info.bounds)} "
                        "segment(s)")
    return bounds


def read_around(record, setting: str, space, rows=None, means: str = "the record's"):
    """The samples a command reads: the record's, or their deviations from its means.

    As ``identify`` reads them (:mod:`~spm_sysid.core.model.operating_point`),
    decided on ``rows`` (default: every sample) with ``space``'s regressors.
    Returns u, y and what was done, '' when the record is read as it is.
    """
    from ...core.model.operating_point import choose_operating_point, point_clause

    pick = slice(None) if rows is None else rows
    point, kept = choose_operating_point(setting, record.u[pick], record.y[pick], space)
    if point is None:
        return record.u, record.y, f"as recorded: {kept}" if kept else ""
    u, y = point.centred(record.u, record.y)
    return u, y, f"around {means} means ({point_clause(point.to_dict(space))})"


def check_outputs(args) -> None:
    """Check every destination before any work (a search must not be lost, nor an input).

    ``--json`` and ``--report`` go through one check
    (:func:`~spm_sysid.core.files.check_destinations`): not an input (``--data``,
    the model validated), not each other, not a link, a regular file or absent,
    writable. ``--report`` must also name an HTML page; ``--plots`` a directory
    that can be written.
    """
    from ...core.errors import FileCheckError
    from ...core.files import check_destinations

    data = getattr(args, "data", None) or []
    inputs = ([data] if isinstance(data, str) else list(data)) + [
        getattr(args, "model", None), getattr(args, "bag", None)]
    report = getattr(args, "report", None)
    if report is not None:
        check_report_name(report)
    try:
        check_destinations({"--json": getattr(args, "json", None), "--report": report},
                           inputs)
    except FileCheckError as exc:
        raise UserError(str(exc)) from None
    if getattr(args, "plots", None):
        check_writable_dir(args.plots, "--plots directory")


def check_report_name(path) -> None:
    """A report is an HTML page: a file name ending in .html (or .htm)."""
    from pathlib import Path

    p = Path(path)
    if p.name.lower() in (".html", ".htm") or not p.name:
        raise UserError(f"--report {path} has no file name: give one such as report.html")
    if p.suffix.lower() not in (".html", ".htm"):
        raise UserError(f"--report writes an HTML page: give a file name ending in .html (or "
                        f".htm), got {path}")
    if p.is_dir():
        raise UserError(f"--report {path} is a folder; give a file name ending in .html")


def check_correlation_lags_option(corr_lags: int, rows: int) -> None:
    """The validation rule, named as the option (before any work)."""
    from ...core.validate.validation import check_correlation_lags

    try:
        check_correlation_lags(corr_lags, rows)
    except SettingsError as exc:
        raise UserError(as_option(exc)) from None


def as_option(exc: Exception) -> str:
    """A settings message with the setting named as its option."""
    return str(exc).replace("correlation_lags", "--correlation-lags")


def announce_compile() -> None:
    """Say so when this command will compile numba's kernels (their first use here)."""
    from ...core.jobs.warmup import kernels_are_cached

    if not kernels_are_cached():
        print("note: compiling the numeric kernels (first use on this machine, about 30 s; "
              "cached after; `spm-sysid compile` does it ahead, `make setup` runs it) ...",
              flush=True)
