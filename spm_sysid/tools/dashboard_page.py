"""The live dashboard's page: one HTML file, its script inlined, no library, no network.

The node serves it (:mod:`spm_sysid.ros.node.dashboard`) at ``/`` and the data
at ``/state.json``; the page asks for the data four times a second and redraws
in place (no reload): the monitor's state with its reason and the time it
changed (``WAITING FOR SAMPLES`` while a model has predicted nothing yet),
measured against predicted for the last seconds with the residual beneath (one
pair of canvases per output, a time axis in seconds before the newest sample),
the residual statistics, the model in use with its coefficient table, an
identification's progress while it runs, and a link to the last
identification's report. It has no button that changes anything.

The page is ``pages/dashboard.html`` with ``pages/dashboard.js`` and the
stylesheet the report shares (:mod:`spm_sysid.tools.pages`). The plots are
drawn on ``<canvas>`` by the page's own few lines: a live view needs lines, not
a plotting library. ``window.spmDashboard`` holds the last state the page
received (``state``) and how many it has drawn (``updates``), for a reader or a
test to check what the page shows.
"""

from __future__ import annotations

from string import Template

from .pages import read_page_file, render_page

__all__ = ["POLL_MS", "page"]

#: Polling period of the page, milliseconds.
POLL_MS = 250


def page() -> str:
    """The page's HTML."""
    script = Template(read_page_file("dashboard.js")).substitute(poll_ms=POLL_MS)
    return render_page("dashboard.html", script=script)
