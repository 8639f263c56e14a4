"""The live dashboard's content: what the page shows, from a snapshot of the node.

``/`` is the page (:mod:`spm_sysid.tools.dashboard_page`), ``/state.json`` what
it shows (:meth:`Dashboard.state`), ``/report.html`` the last identification's
report (:mod:`spm_sysid.tools.html_report`, built on the first request after each
identification); the server is :mod:`.dashboard_server`.

The server's threads never touch the node's parts: the node hands the dashboard a
read-only :class:`NodeStatus` (:func:`node_status`, on the executor thread, four
times a second) and the predictions it makes (:meth:`Dashboard.feed`); the
server's threads read those.

Cost on the node: each paired sample counts one, and every ``stride``-th
appends one tuple per output to a bounded deque (the stride keeps about
:data:`MAX_POINTS` samples in a window, from the stamps' rate); the server's
thread builds ``/state.json`` from those, four times a second per open page. The
residual statistics are of the samples kept.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ...core.files import json_float

__all__ = ["MAX_POINTS", "STATUS_PERIOD", "WALL_CLOCK_SPAN_NS", "Dashboard", "NodeStatus",
           "describe_stamp",
           "node_status"]

#: About this many points per output in one ``/state.json`` (the last seconds, thinned).
MAX_POINTS = 1000

#: A stamp further than this from the node's clock is the data's own time (a bag's).
WALL_CLOCK_SPAN_NS = 86_400 * 10**9

#: Seconds between the node's snapshots for the dashboard.
STATUS_PERIOD = 0.25


@dataclass(frozen=True)
class NodeStatus:
    """What the dashboard may know of the node: a snapshot made on the executor thread.

    Attributes
    ----------
    node : str
        The node's name.
    monitor : dict
        The monitor's state, reason, samples monitored, and since when.
    quality : dict
        Per output: the monitor's RMS ratio and whiteness p.
    progress : dict or None
        The running identification's phase, step, total, best and seconds.
    model : dict or None
        The model in use: equation, terms, coefficients, standard errors, summary.
    """

    node: str = ""
    monitor: dict = field(default_factory=lambda: {
        "state": "NO_MODEL", "reason": "no model", "samples": 0, "since": None})
    quality: dict = field(default_factory=dict)
    progress: dict | None = None
    model: dict | None = None


def node_status(name: str, session, running: tuple | None, model, doc,
                restored_from: str | None) -> NodeStatus:
    """The snapshot of the node's parts (called on the executor thread).

    ``session``: the online session (or None); ``running``: ``(progress, started)``
    of a running identification; ``model``, ``doc``: the model in use and its
    document; ``restored_from``: where it was read at start-up.
    """
    status = NodeStatus(node=name)
    monitor, quality = status.monitor, {}
    if session is not None:
        st = session.state
        monitor = {"state": st.state, "reason": st.reason, "samples": int(st.samples),
                   "since": "the model was set"}
        if session.transitions:
            stamp = session.transitions[-1][0]
            monitor.update(since=describe_stamp(stamp), since_stamp_ns=str(stamp))
        for s in getattr(session, "sessions", [session]):
            quality[s.model.term_space.output] = (s.state.rms_ratio, s.state.whiteness_p)
    progress = None
    if running is not None:
        p, started = running
        progress = {"phase": p.phase if p else "checking data",
                    "step": int(p.step) if p else 0, "total": int(p.total) if p else 0,
                    "best": json_float(p.best) if p and p.best is not None else None,
                    "elapsed": time.monotonic() - started}
    return NodeStatus(name, monitor, quality, progress, _model(model, doc, restored_from))


def _model(model, doc, restored_from) -> dict | None:
    if model is None or doc is None:
        return None
    models = getattr(model, "models", [model])  # several outputs, or one
    outputs = []
    for m in models:
        unc = getattr(m, "uncertainty", None)
        outputs.append({"output": m.term_space.output, "equation": m.equation(),
                        "terms": list(m.terms),
                        "coefficients": [float(c) for c in m.coefficients],
                        "standard_errors": [float(v) for v in unc.standard_errors]
                        if unc is not None else None})
    crit = models[0].criterion or ""
    return {"id": str(id(doc)), "outputs": outputs,
            "summary": f"{len(models)} output(s), {sum(len(m.terms) for m in models)} "
                       f"terms, criterion {crit.upper()}"
                       + (f", restored from {restored_from}" if restored_from else "")}


class Dashboard:
    """The live page's content (see the module doc); ``seconds`` of samples shown."""

    def __init__(self, seconds: float = 10.0) -> None:
        self.seconds = float(seconds)
        self.status = NodeStatus()
        # the last samples per output: (stamp_ns, measured, predicted, residual), every
        # _stride-th sample kept so that a window holds about MAX_POINTS of them
        self.samples: dict[str, deque] = {}
        self._count, self._stride = 0, 1
        self._report: tuple[int, bytes] | None = None  # (id of the result, page)
        self._report_lock = threading.Lock()
        self.last_result = None
        self.last_message: str | None = None

    # -- the executor thread's side: as cheap as it can be --------------------------------
    def update(self, status: NodeStatus) -> None:
        """The node's newest snapshot (replaced whole: the server reads it as it is)."""
        self.status = status

    def feed(self, names, samples) -> None:
        """Keep every ``stride``-th paired sample's prediction per output (the online part)."""
        self._count += 1
        if self._count % self._stride:
            return
        for name, s in zip(names, samples):
            if s is None:
                continue
            d = self.samples.get(name)
            if d is None:
                d = self.samples[name] = deque(maxlen=2 * MAX_POINTS)
            d.append((s.stamp_ns, s.measured, s.predicted, s.residual))

    def new_model(self) -> None:
        """A new model in use: the samples of the previous one are dropped."""
        self.samples = {}
        self._count = 0

    def new_result(self, result) -> None:
        """The last identification's result (its report is built when asked for)."""
        self.last_result = result
        self.last_message = time.strftime("%H:%M:%S ") + result.summary("line")

    # -- the server threads' side ---------------------------------------------------------
    def _restride(self, rows: list) -> None:
        """Keep about :data:`MAX_POINTS` samples per window: the stride from the stamps."""
        if len(rows) < 20:
            return
        span = (rows[-1][0] - rows[0][0]) / 1e9
        if span <= 0:
            return
        rate = (len(rows) - 1) * self._stride / span  # samples per second arriving
        self._stride = max(1, math.ceil(rate * self.seconds / MAX_POINTS))

    def _window(self, name: str, d: deque, quality: dict) -> dict:
        """One output's last seconds of samples and their residual statistics."""
        rows = list(d)
        if rows:  # the window: back from the newest while the stamps go back in order
            first = rows[-1][0] - int(self.seconds * 1e9)
            i = len(rows) - 1
            while i > 0 and first <= rows[i - 1][0] <= rows[i][0]:
                i -= 1
            rows = rows[i:]
            self._restride(rows)
        resid = np.array([r[3] for r in rows], dtype=float)
        resid = resid[np.isfinite(resid)]
        ratio, white = quality.get(name, (None, None))
        stats = {"samples": int(len(resid)),
                 "mean": json_float(resid.mean()) if resid.size else None,
                 "rms": json_float(np.sqrt(np.mean(resid * resid))) if resid.size else None,
                 "rms_ratio": json_float(ratio), "whiteness_p": json_float(white)}
        t_end = rows[-1][0] if rows else 0
        return {"t": [(r[0] - t_end) / 1e9 for r in rows],
                "stamp_sec": [r[0] // 1_000_000_000 for r in rows],
                "stamp_nanosec": [r[0] % 1_000_000_000 for r in rows],
                "measured": [json_float(r[1]) for r in rows],
                "predicted": [json_float(r[2]) for r in rows],
                "stride": self._stride, "stats": stats}

    def state(self) -> dict:
        """What the page shows (``/state.json``)."""
        status = self.status
        outputs = {name: self._window(name, d, status.quality)
                   for name, d in list(self.samples.items())}
        return {"node": status.node, "seconds": self.seconds, "monitor": status.monitor,
                "outputs": outputs, "progress": status.progress,
                "last_identification": self.last_message, "model": status.model,
                "report": "report.html" if self.last_result is not None else None}

    def report_page(self) -> bytes | None:
        """The last identification's report (built once per result), or None."""
        result = self.last_result
        if result is None:
            return None
        with self._report_lock:
            if self._report is not None and self._report[0] == id(result):
                return self._report[1]
            from ...tools.html_report import OutputSection, ReportContent, build_report

            sections = [OutputSection(o.name, o.model, o.report, None, o.history)
                        for o in result.per_output]
            page = build_report(ReportContent(
                title="the last identification", command=self.status.node,
                data=f"{result.data.get('used_samples', '?')} samples from the node's buffer",
                summary=result.summary("lines"), cross_tests=result.cross_tests),
                sections).encode()
            self._report = (id(result), page)
            return page


def describe_stamp(stamp_ns: int, now_ns: int | None = None) -> str:
    """A sample's stamp in words: the node's local time, or the data's own time.

    Stamps near the node's clock are a date and time (24 h); stamps far from it
    (a bag replayed with its recorded stamps, a simulator's clock from zero) are
    the data's time in seconds, said to be so.
    """
    now_ns = time.time_ns() if now_ns is None else now_ns
    if abs(now_ns - stamp_ns) < WALL_CLOCK_SPAN_NS:
        return (time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(stamp_ns / 1e9))
                + f".{int(stamp_ns % 1_000_000_000) // 1_000_000:03d}")
    return f"{stamp_ns / 1e9:.3f} s in the data's time (its stamps, e.g. a replayed bag's)"
