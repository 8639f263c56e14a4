"""The live dashboard: a read-only web page served by the node (``dashboard_port``).

``/`` is the page (:mod:`spm_sysid.tools.dashboard_page`), ``/state.json`` what it
shows, ``/report.html`` the last identification's report
(:mod:`spm_sysid.tools.html_report`, built on the first request after each
identification). Only GET is answered: nothing on the page changes the node or
the robot. The server binds ``dashboard_host`` (127.0.0.1 by default; an IPv6
address such as ``::1`` too); any other address than the loopback needs
``dashboard_token``, and every request must then carry it (``?token=...``). The
token is never logged nor published: the log gives the address without it.
Without a token, only requests whose ``Host`` names the loopback are answered
(a page elsewhere cannot reach the node through DNS rebinding). A port in use,
or a non-local address without a token, is one error line in the log and no
dashboard: the node runs on.

Clients cannot take the node's resources: at most :data:`MAX_CONNECTIONS`
connections are served at once (a connection past it is closed at once and
counted), and each must send its request within :data:`REQUEST_TIMEOUT`
seconds (idle or slow connections are closed and counted). A client that
resets its connection is counted, never a traceback in the log
(:attr:`Dashboard.counts`, also on ``/diagnostics``).

Cost on the node: each paired sample counts one, and every ``stride``-th
appends one tuple per output to a bounded deque (:meth:`Dashboard.feed`; the
stride keeps about :data:`MAX_POINTS` samples in a window, from the stamps'
rate); the server's thread builds ``/state.json`` from those, four times a
second per open page. The residual statistics are of the samples kept.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import json
import math
import socket
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import numpy as np

from ...core.files import json_float

__all__ = ["MAX_CONNECTIONS", "MAX_POINTS", "REQUEST_TIMEOUT", "Dashboard", "DashboardError",
           "describe_stamp", "host_name", "is_loopback"]

#: About this many points per output in one ``/state.json`` (the last seconds, thinned).
MAX_POINTS = 1000

#: Connections served at once; one more is closed at once (and counted).
MAX_CONNECTIONS = 32

#: Seconds a connection has to send its request, and for each read or write after.
REQUEST_TIMEOUT = 5.0

#: A stamp further than this from the node's clock is the data's own time (a bag's).
WALL_CLOCK_SPAN_NS = 86_400 * 10**9


class DashboardError(RuntimeError):
    """The dashboard cannot start (the message says why)."""


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (``localhost``, 127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_name(header: str) -> str:
    """The host of a ``Host`` header, without its port (``[::1]:80`` -> ``::1``)."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1:header.find("]")] if "]" in header else header[1:]
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


class _Server(ThreadingHTTPServer):
    """The HTTP server, bounded: a slot per connection, errors counted, IPv4 or IPv6."""

    daemon_threads = True
    request_queue_size = 64  # a burst waits in the kernel's queue (no descriptor of ours)

    def __init__(self, address, handler, board: Dashboard) -> None:
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        self.board = board
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        super().__init__(address, handler)

    def process_request(self, request, client_address) -> None:
        if not self.slots.acquire(blocking=False):  # full: refuse now, keep nothing open
            self.board.counts["refused"] += 1
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def handle_error(self, request, client_address) -> None:
        """A connection that failed (reset, timed out): counted, no traceback."""
        self.board.counts["connection_errors"] += 1




class Dashboard:
    """The node's live page and its data.

    Parameters
    ----------
    node
        The :class:`~spm_sysid.ros.sysid_node.SysidNode` (read, never changed).
    port, host, token
        Where to serve and the token to ask for (see the module doc).
    seconds
        Samples shown (by their stamps).

    Raises
    ------
    DashboardError
        A non-local host without a token, or an address that cannot be bound.
    """

    def __init__(self, node, port: int, host: str = "127.0.0.1", token: str = "",
                 seconds: float = 10.0) -> None:
        if not is_loopback(host) and not token:
            raise DashboardError(
                f"the dashboard is not served on {host}: an address other than the "
                "loopback (127.0.0.1) needs dashboard_token (anyone who reaches the port "
                "could read the robot's signals)")
        self.node, self.token, self.seconds = node, token, float(seconds)
        # the last samples per output: (stamp_ns, measured, predicted, residual), every
        # _stride-th sample kept so that a window holds about MAX_POINTS of them
        self.samples: dict[str, deque] = {}
        self._count, self._stride = 0, 1
        self._report: tuple[int, bytes] | None = None  # (id of the result, page)
        self._report_lock = threading.Lock()
        self.last_result = None
        self.last_message: str | None = None
        self.requests = 0
        #: what clients did that was not served: refused (over the cap), timed out or reset
        #: (connection errors), wrong token, a Host that is not the loopback's
        self.counts = {"refused": 0, "connection_errors": 0, "forbidden": 0, "bad_host": 0}
        handler = _handler(self)
        try:
            self.server = _Server((host, port), handler, self)
        except OSError as exc:
            why = exc.strerror or str(exc)
            hint = ("is another node or program using that port? Choose another "
                    "dashboard_port" if exc.errno == errno.EADDRINUSE else
                    "is it an address of this machine? (IPv4 such as 127.0.0.1, or IPv6 "
                    "such as ::1)")
            raise DashboardError(f"the dashboard cannot listen on {host}:{port} ({why}): "
                                 f"{hint}") from None
        self.port = self.server.server_address[1]
        self.host = host
        self.thread = threading.Thread(target=self.server.serve_forever, name="dashboard",
                                       daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        """The page's address, without the token (which is never logged)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def describe(self) -> str:
        """The log line's words: where, and how to open it (never the token itself)."""
        if self.token:
            return (f"live dashboard at {self.url} (read-only; open it with ?token= and the "
                    "value of the dashboard_token parameter)")
        return f"live dashboard at {self.url} (read-only)"

    # -- the executor thread's side: as cheap as it can be --------------------------------
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

    def _restride(self, rows: list) -> None:
        """Keep about :data:`MAX_POINTS` samples per window: the stride from the stamps."""
        if len(rows) < 20:
            return
        span = (rows[-1][0] - rows[0][0]) / 1e9
        if span <= 0:
            return
        rate = (len(rows) - 1) * self._stride / span  # samples per second arriving
        self._stride = max(1, math.ceil(rate * self.seconds / MAX_POINTS))

    def new_model(self) -> None:
        """A new model in use: the samples of the previous one are dropped."""
        self.samples = {}
        self._count = 0

    def new_result(self, result) -> None:
        """The last identification's result (its report is built when asked for)."""
        self.last_result = result
        self.last_message = time.strftime("%H:%M:%S ") + result.summary("line")

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    # -- the server thread's side ---------------------------------------------------------
    def state(self) -> dict:
        """What the page shows (``/state.json``)."""
        node = self.node
        online = node.online
        session = online.session
        monitor = {"state": "NO_MODEL", "reason": "no model", "samples": 0, "since": None}
        if session is not None:
            st = session.state
            monitor = {"state": st.state, "reason": st.reason, "samples": int(st.samples),
                       "since": None}
            if session.transitions:
                stamp = session.transitions[-1][0]
                monitor["since"] = describe_stamp(stamp)
                monitor["since_stamp_ns"] = str(stamp)
            else:
                monitor["since"] = "the model was set"
        per_output = {}
        states = {}
        for s in getattr(session, "sessions", [session] if session is not None else []):
            name = s.model.term_space.output
            states[name] = s.state
        for name, d in list(self.samples.items()):
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
            mst = states.get(name)
            stats = {"samples": int(len(resid)),
                     "mean": json_float(resid.mean()) if resid.size else None,
                     "rms": json_float(np.sqrt(np.mean(resid * resid))) if resid.size else None,
                     "rms_ratio": json_float(mst.rms_ratio) if mst is not None else None,
                     "whiteness_p": json_float(mst.whiteness_p) if mst is not None else None}
            t_end = rows[-1][0] if rows else 0
            per_output[name] = {
                "t": [(r[0] - t_end) / 1e9 for r in rows],
                "stamp_sec": [r[0] // 1_000_000_000 for r in rows],
                "stamp_nanosec": [r[0] % 1_000_000_000 for r in rows],
                "measured": [json_float(r[1]) for r in rows],
                "predicted": [json_float(r[2]) for r in rows],
                "stride": self._stride, "stats": stats}
        ident = node.identification
        progress = None
        if ident.started is not None:
            p = ident.progress
            progress = {"phase": p.phase if p else "checking data",
                        "step": int(p.step) if p else 0, "total": int(p.total) if p else 0,
                        "best": json_float(p.best) if p and p.best is not None else None,
                        "elapsed": time.monotonic() - ident.started}
        return {"node": node.get_fully_qualified_name(), "seconds": self.seconds,
                "monitor": monitor, "outputs": per_output, "progress": progress,
                "last_identification": self.last_message,
                "model": self._model(), "report": "report.html"
                if self.last_result is not None else None}

    def _model(self) -> dict | None:
        pub = self.node.publisher
        model, doc = pub.model, pub.doc
        if model is None or doc is None:
            return None
        from ...core.model.mimo import MimoModel

        models = model.models if isinstance(model, MimoModel) else [model]
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
                           + (f", restored from {pub.restored_from}" if pub.restored_from
                              else "")}

    def report_page(self) -> bytes | None:
        """The last identification's report (built once per result), or None."""
        result = self.last_result
        if result is None:
            return None
        with self._report_lock:
            if self._report is not None and self._report[0] == id(result):
                return self._report[1]
            from ...tools.html_report import OutputSection, ReportContent, build_report

            outputs = getattr(result, "outputs", None)
            if outputs is not None:  # several outputs
                sections = [OutputSection(n, r.model, r.report, None, r.search.history)
                            for n, r in zip(result.output_names, outputs)]
                cross = result.cross_tests
            else:
                sections = [OutputSection(result.model.term_space.output, result.model,
                                          result.report, None, result.search.history)]
                cross = []
            page = build_report(ReportContent(
                title="the last identification", command=self.node.get_fully_qualified_name(),
                data=f"{result.data.get('used_samples', '?')} samples from the node's buffer",
                summary=result.summary("lines"), cross_tests=cross), sections).encode()
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


def _handler(board: Dashboard):
    page = None

    class Handler(BaseHTTPRequestHandler):
        server_version = "spm_sysid-dashboard"
        timeout = REQUEST_TIMEOUT  # each read and write on the connection

        def setup(self):
            super().setup()
            # the whole request (line and headers) within REQUEST_TIMEOUT, however slowly
            # it trickles in: then the connection is closed
            self._deadline = threading.Timer(REQUEST_TIMEOUT, self._expire)
            self._deadline.daemon = True
            self._deadline.start()

        def _expire(self):
            board.counts["connection_errors"] += 1
            try:
                self.connection.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

        def parse_request(self):
            ok = super().parse_request()
            self._deadline.cancel()
            return ok

        def finish(self):
            self._deadline.cancel()
            try:
                super().finish()
            except OSError:  # the client went away while the answer was flushed
                board.counts["connection_errors"] += 1

        def log_message(self, format, *args):  # noqa: A002 - the base class's name
            pass  # requests are counted, not logged line by line

        def _allowed(self, url) -> bool:
            """The token when one is set; else a Host that names the loopback."""
            if board.token:
                given = parse_qs(url.query).get("token", [""])[0]
                if not hmac.compare_digest(given.encode(), board.token.encode()):
                    board.counts["forbidden"] += 1
                    self._send(403, b"this dashboard needs its token: ?token=... (the "
                               b"node's dashboard_token parameter)\n",
                               "text/plain; charset=utf-8")
                    return False
                return True
            host = self.headers.get("Host")
            if host is not None and not is_loopback(host_name(host)):
                board.counts["bad_host"] += 1
                self._send(421, b"this dashboard answers requests to the loopback only "
                           b"(Host: localhost or 127.0.0.1)\n", "text/plain; charset=utf-8")
                return False
            return True

        def _send(self, code: int, body: bytes, kind: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):  # noqa: N802 - http.server's name
            nonlocal page
            board.requests += 1
            url = urlsplit(self.path)
            if not self._allowed(url):
                return
            try:
                if url.path in ("/", "/index.html"):
                    if page is None:
                        from ...tools.dashboard_page import page as make_page

                        page = make_page().encode()
                    self._send(200, page, "text/html; charset=utf-8")
                elif url.path == "/state.json":
                    body = json.dumps(board.state(), allow_nan=False).encode()
                    self._send(200, body, "application/json")
                elif url.path == "/report.html":
                    report = board.report_page()
                    if report is None:
                        self._send(404, b"no identification yet\n", "text/plain; charset=utf-8")
                    else:
                        self._send(200, report, "text/html; charset=utf-8")
                else:
                    self._send(404, b"not found\n", "text/plain; charset=utf-8")
            except OSError:  # reset, broken pipe, timed out: the client went away
                board.counts["connection_errors"] += 1
            except Exception as exc:  # noqa: BLE001 - a failing page never stops the node
                self._send(500, f"dashboard error: {exc}\n".encode(),
                           "text/plain; charset=utf-8")

        def _read_only(self):
            self._send(405, b"the dashboard is read-only\n", "text/plain; charset=utf-8")

        do_POST = do_PUT = do_DELETE = do_PATCH = _read_only  # noqa: N815

    return Handler
