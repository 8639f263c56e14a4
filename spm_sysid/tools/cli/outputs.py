"""What ``identify`` and ``validate`` write, written by one helper: document, figures, page.

A command gathers what it has (:class:`Written`: the model to save, a section
per output with its validation and the rows' times, the cross-correlation, the
page's title and summary) and :func:`write_outputs` writes what the user asked
for: ``--json`` (the model document), ``--plots`` (figures), ``--report`` (the
page). The destinations were checked before the work
(:func:`~spm_sysid.tools.cli.common.check_outputs`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Written", "command_line", "write_outputs"]


def command_line() -> str:
    """The command as typed (for a report's header)."""
    import shlex
    import sys

    return "spm-sysid " + " ".join(shlex.quote(a) for a in sys.argv[1:])


@dataclass
class Written:
    """What a command has to write (see the module doc).

    Attributes
    ----------
    model : NarxModel or MimoModel or None
        The document ``--json`` saves (None: nothing to save).
    sections : list of OutputSection
        One per output: its model, validation report, rows' times, search history.
    cross : list of CorrelationTest
        The residuals' cross-correlation between outputs (several outputs).
    title, data, summary : str
        The page's title, what the data were, what the command printed.
    notes : list of str
        What the user should know about the data.
    """

    model: object | None
    sections: list
    cross: list = field(default_factory=list)
    title: str = ""
    data: str = ""
    summary: str = ""
    notes: list[str] = field(default_factory=list)


def write_outputs(args, w: Written) -> None:
    """Write what ``args`` asks for (``plots``, ``json``, ``report``) and say where."""
    if getattr(args, "plots", None):
        _figures(args.plots, w)
    if getattr(args, "json", None) and w.model is not None:
        print(f"model written to {w.model.save(args.json)}")
    if getattr(args, "report", None):
        from ..html_report import ReportContent, write_model_report

        path = write_model_report(args.report, ReportContent(
            title=w.title, command=command_line(), data=w.data, summary=w.summary,
            cross_tests=w.cross, notes=w.notes), w.sections)
        print(f"report written to {path}")


def _figures(folder: str, w: Written) -> None:
    from ..plots import write_mimo_figures, write_model_figures

    times = w.sections[0].times
    if len(w.sections) > 1:
        paths = write_mimo_figures([s.report for s in w.sections],
                                   [s.model for s in w.sections],
                                   tuple(s.name for s in w.sections), w.cross, folder,
                                   times=times)
    else:
        s = w.sections[0]
        paths = write_model_figures(s.report, folder, model=s.model, times=times)
    print(f"figures written to {folder}: {', '.join(p.name for p in paths)}")
