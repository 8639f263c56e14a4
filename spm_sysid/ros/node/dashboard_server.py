"""The live dashboard's server: read-only HTTP, bounded, for the node's page.

Serves ``/`` (the page, :mod:`spm_sysid.tools.dashboard_page`), ``/state.json``
and ``/report.html`` from a content object (:class:`~.dashboard.Dashboard`).
Only GET is answered: nothing on the page changes the node or the robot. It binds
``dashboard_host`` (127.0.0.1 by default; an IPv6 address such as ``::1`` too);
any other address than the loopback needs ``dashboard_token``, and every request
must then carry it (``?token=...``). The token is never logged nor published: the
log gives the address without it. Without a token, only requests whose ``Host``
names the loopback are answered (a page elsewhere cannot reach the node through
DNS rebinding). A port in use, or a non-local address without a token, is one
error line in the log and no dashboard: the node runs on.

Clients cannot take the node's resources: at most :data:`MAX_CONNECTIONS`
connections are served at once (a connection past it is closed at once and
counted), and each must send its request within :data:`REQUEST_TIMEOUT`
seconds (idle or slow connections are closed and counted). A client that
resets its connection is counted, never a traceback in the log
(:attr:`DashboardServer.counts`, also on ``/diagnostics``).
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

__all__ = ["MAX_CONNECTIONS", "REQUEST_TIMEOUT", "DashboardError", "DashboardServer",
           "host_name", "is_loopback"]

#: Connections served at once; one more is closed at once (and counted).
MAX_CONNECTIONS = 32

#: Seconds a connection has to send its request, and for each read or write after.
REQUEST_TIMEOUT = 5.0


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

    def __init__(self, address, handler, board: DashboardServer) -> None:
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




class DashboardServer:
    """The HTTP server of a dashboard's ``content`` (``state()``, ``report_page()``).

    Raises
    ------
    DashboardError
        A non-local host without a token, or an address that cannot be bound.
    """

    def __init__(self, content, port: int, host: str = "127.0.0.1", token: str = "") -> None:
        if not is_loopback(host) and not token:
            raise DashboardError(
                f"the dashboard is not served on {host}: an address other than the "
                "loopback (127.0.0.1) needs dashboard_token (anyone who reaches the port "
                "could read the robot's signals)")
        self.content, self.token, self.host = content, token, host
        self.requests = 0
        #: what clients did that was not served: refused (over the cap), timed out or reset
        #: (connection errors), wrong token, a Host that is not the loopback's
        self.counts = {"refused": 0, "connection_errors": 0, "forbidden": 0, "bad_host": 0}
        try:
            self.server = _Server((host, port), _handler(self), self)
        except OSError as exc:
            why = exc.strerror or str(exc)
            hint = ("is another node or program using that port? Choose another "
                    "dashboard_port" if exc.errno == errno.EADDRINUSE else
                    "is it an address of this machine? (IPv4 such as 127.0.0.1, or IPv6 "
                    "such as ::1)")
            raise DashboardError(f"the dashboard cannot listen on {host}:{port} ({why}): "
                                 f"{hint}") from None
        self.port = self.server.server_address[1]
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

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _handler(board: DashboardServer) -> type[BaseHTTPRequestHandler]:
    """The request handler class of one dashboard (its page built once, on first use)."""
    return type("Handler", (_Handler,), {"board": board, "page": None})


_TEXT = "text/plain; charset=utf-8"


class _Handler(BaseHTTPRequestHandler):
    """GET of the page, its state and the report; a whole request within REQUEST_TIMEOUT."""

    server_version = "spm_sysid-dashboard"
    timeout = REQUEST_TIMEOUT  # each read and write on the connection
    board: DashboardServer
    page: bytes | None

    def setup(self):
        super().setup()
        # the whole request (line and headers) within REQUEST_TIMEOUT, however slowly
        # it trickles in: then the connection is closed
        self._deadline = threading.Timer(REQUEST_TIMEOUT, self._expire)
        self._deadline.daemon = True
        self._deadline.start()

    def _expire(self):
        self.board.counts["connection_errors"] += 1
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
            self.board.counts["connection_errors"] += 1

    def log_message(self, format, *args):  # noqa: A002 - the base class's name
        pass  # requests are counted, not logged line by line

    def _allowed(self, url) -> bool:
        """The token when one is set; else a Host that names the loopback."""
        board = self.board
        if board.token:
            given = parse_qs(url.query).get("token", [""])[0]
            if not hmac.compare_digest(given.encode(), board.token.encode()):
                board.counts["forbidden"] += 1
                self._send(403, b"this dashboard needs its token: ?token=... (the "
                           b"node's dashboard_token parameter)\n", _TEXT)
                return False
            return True
        host = self.headers.get("Host")
        if host is not None and not is_loopback(host_name(host)):
            board.counts["bad_host"] += 1
            self._send(421, b"this dashboard answers requests to the loopback only "
                       b"(Host: localhost or 127.0.0.1)\n", _TEXT)
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
        self.board.requests += 1
        url = urlsplit(self.path)
        if not self._allowed(url):
            return
        try:
            self._answer(url.path)
        except OSError:  # reset, broken pipe, timed out: the client went away
            self.board.counts["connection_errors"] += 1
        except Exception as exc:  # noqa: BLE001 - a failing page never stops the node
            self._send(500, f"dashboard error: {exc}\n".encode(), _TEXT)

    def _answer(self, path: str) -> None:
        """The page, its state, the report, or 404."""
        if path in ("/", "/index.html"):
            if type(self).page is None:
                from ...tools.dashboard_page import page as make_page

                type(self).page = make_page().encode()
            self._send(200, type(self).page, "text/html; charset=utf-8")
        elif path == "/state.json":
            body = json.dumps(self.board.content.state(), allow_nan=False).encode()
            self._send(200, body, "application/json")
        elif path == "/report.html":
            report = self.board.content.report_page()
            if report is None:
                self._send(404, b"no identification yet\n", _TEXT)
            else:
                self._send(200, report, "text/html; charset=utf-8")
        else:
            self._send(404, b"not found\n", _TEXT)

    def _read_only(self):
        self._send(405, b"the dashboard is read-only\n", _TEXT)

    do_POST = do_PUT = do_DELETE = do_PATCH = _read_only  # noqa: N815
