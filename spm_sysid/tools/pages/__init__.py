"""The pages' files: HTML templates, their stylesheet and scripts, shipped as package data.

The report (:mod:`spm_sysid.tools.html_report`) and the node's live dashboard
(:mod:`spm_sysid.tools.dashboard_page`) are HTML templates here, filled with
:class:`string.Template` (``$name`` placeholders; ``$$`` is a dollar sign). Both
share ``style.css``; each has its script (``report.js``, ``dashboard.js``), kept
as files so that they read, and lint, as what they are. A page inlines all it
uses: it works offline and can be sent as one file.
"""

from __future__ import annotations

from functools import cache
from importlib import resources
from string import Template

__all__ = ["read_page_file", "render_page"]


@cache
def read_page_file(name: str) -> str:
    """One of the pages' files (``style.css``, ``report.js`` ...), as text."""
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def render_page(template: str, **values: str) -> str:
    """The template ``template`` (a file name here) with its placeholders filled.

    Every placeholder must be given (a missing one is a KeyError, never a page
    with ``$name`` left in it); ``style`` is the shared stylesheet unless given.
    """
    values.setdefault("style", read_page_file("style.css"))
    return Template(read_page_file(template)).substitute(values)
