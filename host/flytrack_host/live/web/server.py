"""The host's live HTTP server: Braid's event stream at `/events` and the live page.

    server = LiveServer("127.0.0.1", 8397)
    server.attach(pipe)          # before pipe.start(): joins pipe.sinks, starts serving
    print(server.banner())       # the URL (with the token when one is needed)

Routes: `/` the page and `/static/*` its assets (package data, no CDN); `/events` Braid's server-sent
events (message version 3, see `flytrack_host.live.braid`); `/ui/events` the page's state as
server-sent events (`event: state`, ~20 Hz); `/api/state` one state snapshot; `/api/stats` the
server's own counts.

Threads: the tracking thread only appends to a bounded deque in `on_frame`. Connection threads
(stdlib `ThreadingHTTPServer`) answer requests; a streaming request's socket is handed, after the
headers, to the one publisher thread, which turns frames into Braid events and page states and writes
every stream with non-blocking sockets, each client with a bounded backlog (`web.clients`). A client
that stops reading is dropped when its backlog is full, and counted.

Bound to a loopback address no token is asked. Bound to any other address, every request needs the
token (printed at start, as Braid does) as `?token=` or the `flytrack_token` cookie that a page
loaded with `?token=` receives; a wrong or missing token gets 401.
"""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import json
import logging
import math
import re
import secrets
import socket
import tempfile
import threading
import time
from collections import deque
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from flytrack_host.live import braid
from flytrack_host.live.web.clients import ClientSet
from flytrack_host.live.web.state import LiveState
from flytrack_host.live.web.thumbs import Requester, ThumbnailAssembler
from flytrack_host.tracking.types import FrameResult

log = logging.getLogger("flytrack.web")

DEFAULT_PORT = 8397  # Braid's model server port
MAX_REQUEST_LINE = 8192
MAX_HEADER_BYTES = 16384
MAX_CONNECTIONS = 128
POLL_S = 0.005  # the publisher looks for new frames this often while clients are connected
COOKIE = "flytrack_token"
_STATIC_NAME = re.compile(r"^[A-Za-z0-9_-]+\.(html|js|css|png|svg|ico)$")
_TYPES = {"html": "text/html; charset=utf-8", "js": "text/javascript; charset=utf-8",
          "css": "text/css; charset=utf-8", "png": "image/png", "svg": "image/svg+xml", "ico": "image/x-icon"}


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and "localhost"; "" and 0.0.0.0 (every interface) are not."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_bind(value: str, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """"HOST:PORT", "HOST" or ":PORT" -> (host, port); a clear ValueError otherwise."""
    host, sep, port_s = value.rpartition(":") if ":" in value else (value, "", "")
    if not sep:
        host, port_s = value, ""
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_s) if port_s else default_port
    except ValueError:
        raise ValueError(f"bad port in {value!r}: expected HOST:PORT, e.g. 127.0.0.1:{default_port}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"port {port} out of range 0-65535")
    return host, port


def _clean(x: Any) -> Any:
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    return x


def to_json(x: Any) -> bytes:
    try:
        return json.dumps(x, allow_nan=False, separators=(",", ":")).encode()
    except ValueError:  # a NaN somewhere: JSON has none, the page's JSON.parse would fail
        return json.dumps(_clean(x), allow_nan=False, separators=(",", ":"), default=str).encode()


class _HttpServer(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 64
    live: LiveServer

    def process_request(self, request: Any, client_address: Any) -> None:
        if self.live._connections >= MAX_CONNECTIONS:
            self.live.counts["refused_connections"] += 1
            with contextlib.suppress(OSError):
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Length: 0\r\n\r\n")
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def handle_error(self, request: Any, client_address: Any) -> None:
        # A client that went away mid-answer is ordinary; anything else is a bug worth a traceback.
        import sys

        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):
            self.live.counts["connection_errors"] += 1
            log.debug("client %s went away: %r", client_address, exc)
        else:
            self.live.counts["handler_errors"] += 1
            log.exception("live server: request from %s failed", client_address)

    def shutdown_request(self, request: Any) -> None:
        # A streaming client's socket now belongs to the publisher thread: leave it open.
        if request in self.live._handed:
            self.live._handed.discard(request)
            return
        super().shutdown_request(request)


class _HttpServer6(_HttpServer):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    server: _HttpServer
    timeout = 10.0  # seconds: reading a request, and each write (a stuck client is let go)
    server_version = "FlyTrack"

    # --- request checks ---------------------------------------------------------------------------
    def setup(self) -> None:
        super().setup()
        with self.server.live._lock:
            self.server.live._connections += 1

    def finish(self) -> None:
        with contextlib.suppress(OSError):
            super().finish()
        with self.server.live._lock:
            self.server.live._connections -= 1

    def parse_request(self) -> bool:
        if len(self.raw_requestline) > MAX_REQUEST_LINE:
            self.requestline = ""
            self.request_version = "HTTP/1.0"
            self.command = ""
            self.send_error(HTTPStatus.REQUEST_URI_TOO_LONG, f"request line over {MAX_REQUEST_LINE} bytes")
            return False
        if not super().parse_request():
            return False
        size = sum(len(k) + len(v) + 4 for k, v in self.headers.items())
        if size > MAX_HEADER_BYTES:
            self.send_error(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE, f"headers over {MAX_HEADER_BYTES} bytes")
            return False
        return True

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        self.server.live._count_error(int(code))
        if getattr(self, "request_version", "HTTP/0.9") == "HTTP/0.9":
            self.request_version = "HTTP/1.0"  # HTTP/0.9 is not served: every error gets a status line
        super().send_error(code, message, explain)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s %s", self.address_string(), format % args)

    def _authorised(self, query: dict[str, list[str]]) -> tuple[bool, bool]:
        """(allowed, token came in the query: set the cookie)."""
        token = self.server.live.token
        if token is None:
            return True, False
        given = query.get("token", [None])[0]
        if given is not None:
            return hmac.compare_digest(given.encode(), token.encode()), True
        for part in (self.headers.get("Cookie") or "").split(";"):
            k, _, v = part.strip().partition("=")
            if k == COOKIE:
                return hmac.compare_digest(v.encode(), token.encode()), False
        return False, False

    # --- methods ----------------------------------------------------------------------------------
    def _not_allowed(self) -> None:
        self.send_error(HTTPStatus.METHOD_NOT_ALLOWED, "only GET is served")

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _not_allowed

    def do_HEAD(self) -> None:
        self._not_allowed()

    def do_GET(self) -> None:
        live = self.server.live
        url = urlsplit(self.path)
        query = parse_qs(url.query, max_num_fields=20)
        ok, set_cookie = self._authorised(query)
        if not ok:
            live.counts["unauthorised"] += 1
            self.send_error(HTTPStatus.UNAUTHORIZED, "wrong or missing token: open the URL printed at start "
                                                     "(.../?token=...)")
            return
        self._cookie = f"{COOKIE}={live.token}; Path=/; HttpOnly; SameSite=Strict" if set_cookie else None
        path = url.path
        if path == "/events":
            # As Braid: its event stream only for a client that asks for one.
            accept = ",".join(self.headers.get_all("Accept") or [])
            if "text/event-stream" not in [a.split(";")[0].strip() for a in accept.split(",")]:
                live.counts["not_event_stream"] += 1
                self.send_error(HTTPStatus.BAD_REQUEST, 'It is required that you have an HTTP header '
                                                        '"Accept: text/event-stream"')
                return
            self._stream("braid", live._calibration_event())
        elif path == "/ui/events":
            self._stream("ui", live._last_ui_event)
        elif path == "/api/state":
            self._send(200, "application/json", live._last_state_json or to_json(live.state.snapshot()))
        elif path == "/api/stats":
            self._send(200, "application/json", to_json(live.stats()))
        elif path in ("/", "/index.html"):
            self._static("index.html")
        elif path.startswith("/thumb/") and path.endswith(".png"):
            try:
                t = live.thumbs.latest.get(int(path[len("/thumb/"):-len(".png")]))
            except ValueError:
                t = None
            if t is None:
                self.send_error(HTTPStatus.NOT_FOUND, "no image from this camera yet")
            else:
                self._send(200, "image/png", t.png)
        elif path == "/favicon.ico":
            self._headers(204, "image/x-icon", 0)
        elif path.startswith("/static/"):
            self._static(path[len("/static/"):])
        else:
            self.send_error(HTTPStatus.NOT_FOUND, "no such page: /, /events, /ui/events, /api/state, /api/stats")

    def _headers(self, code: int, ctype: str, length: int | None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        if length is not None:
            self.send_header("Content-Length", str(length))
        self.send_header("Cache-Control", "no-cache")
        self.send_header("X-Content-Type-Options", "nosniff")
        if self._cookie:
            self.send_header("Set-Cookie", self._cookie)
        self.end_headers()

    def _send(self, code: int, ctype: str, body: bytes) -> None:
        self._headers(code, ctype, len(body))
        self.wfile.write(body)

    def _static(self, name: str) -> None:
        if not _STATIC_NAME.match(name):
            self.send_error(HTTPStatus.NOT_FOUND, "no such asset")
            return
        try:
            body = resources.files("flytrack_host.live.web").joinpath("static", name).read_bytes()
        except (FileNotFoundError, IsADirectoryError, OSError):
            self.send_error(HTTPStatus.NOT_FOUND, "no such asset")
            return
        self._send(200, _TYPES[name.rsplit(".", 1)[1]], body)

    def _stream(self, kind: str, first: bytes | None) -> None:
        live = self.server.live
        if live._closed or not live.clients.reserve():
            self.send_error(HTTPStatus.SERVICE_UNAVAILABLE, f"too many streaming clients ({live.clients.max_clients})")
            return
        chunked = self.request_version == "HTTP/1.1"
        try:
            if chunked:  # one chunk per event, as Braid sends them (see web/clients.py)
                self.protocol_version = "HTTP/1.1"
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-cache")
                self.send_header("Transfer-Encoding", "chunked")
                self.send_header("Connection", "close")
                if self._cookie:
                    self.send_header("Set-Cookie", self._cookie)
                self.end_headers()
            else:
                self._headers(200, "text/event-stream", None)
            self.wfile.flush()
        except OSError:
            live.clients.unreserve()
            return
        # From here the publisher thread writes to this socket (non-blocking), this thread is done.
        self.close_connection = True
        live._handed.add(self.connection)
        live.clients.hand_over(kind, self.connection, self.address_string(), first, chunked)
        live._signal()


class LiveServer:
    """HTTP server for Braid's event stream and the live page; a `ResultSink` of the pipeline."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, token: str | None = None,
                 calibration_xml: str | None = None, ui_hz: float = 20.0, max_clients: int = 64,
                 client_backlog_bytes: int = 2 << 20, frame_backlog: int = 2000, thumbnails_every_s: float = 0.0,
                 poll_s: float = POLL_S):
        self.host = host
        self.port = port
        # Any address other than loopback needs the token (generated unless given).
        self.token = None if is_loopback(host) and token is None else (token or secrets.token_urlsafe(16))
        self.calibration_xml = calibration_xml
        self.ui_period = 1.0 / ui_hz
        self.poll_s = poll_s
        self.clients = ClientSet(max_clients=max_clients, limit_bytes=client_backlog_bytes)
        self.state = LiveState()
        # Camera thumbnails from the edges' IMAGE messages; with thumbnails_every_s > 0 the server
        # asks each edge for a frame that often (CONTROL SEND_FULL_IMAGE on the rig's control port).
        self.thumbs = ThumbnailAssembler()
        self.state.thumbs = self.thumbs
        self.thumbnails_every_s = thumbnails_every_s
        self._requester: Requester | None = None
        self.counts: dict[str, int] = {"frames_in": 0, "frames_dropped": 0, "frames_published": 0,
                                       "unauthorised": 0, "bad_requests": 0, "refused_connections": 0,
                                       "publish_errors": 0, "ui_snapshots": 0, "connection_errors": 0,
                                       "handler_errors": 0, "deaths_added": 0, "not_event_stream": 0}
        self._frames: deque[tuple[FrameResult, float, float]] = deque()
        self._live_ids: set[int] = set()
        self._frame_backlog = frame_backlog
        # The publisher polls for frames every POLL_S while clients are connected: on_frame is then only
        # an append. Waking it per frame (Event.set: a futex call and a thread switch on the tracking
        # thread) measured 20-30 us a frame here; the poll adds 2.5 ms of delay on average. Each wake
        # takes the GIL, and on an overloaded machine the kernel can deschedule a thread holding it
        # while the tracking thread waits, so the publisher wakes as rarely as the delay allows.
        self._wake = threading.Event()  # new clients and close() wake it
        self._handed: set[socket.socket] = set()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._connections = 0
        self._httpd: _HttpServer | None = None
        self._threads: list[threading.Thread] = []
        self._last_state_json: bytes | None = None
        self._last_ui_event: bytes | None = None
        self._closed = False

    # --- life -------------------------------------------------------------------------------------
    def attach(self, pipe: Any) -> LiveServer:
        """Feed on `pipe`'s frames (joins its sinks), read its state for the page, and start serving."""
        self.state.pipe = pipe
        if self.thumbnails_every_s > 0 and self._requester is None:
            port = pipe.rig.host.control_port
            self._requester = Requester({c.index: (c.edge, port) for c in pipe.rig.cameras}, self.thumbnails_every_s)
        if self.calibration_xml is None:
            self.calibration_xml = calibration_xml_of(pipe)
        if self._httpd is None:
            self.start()  # first: a port that cannot be bound leaves the pipeline untouched
        pipe.sinks.append(self)
        return self

    def start(self) -> None:
        cls = _HttpServer6 if ":" in self.host else _HttpServer
        httpd = cls((self.host, self.port), _Handler)
        httpd.live = self
        self._httpd = httpd
        self.port = httpd.server_address[1]
        for name, target in (("flytrack-web-http", httpd.serve_forever), ("flytrack-web-publish", self._publish)):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def banner(self) -> str:
        tok = f"?token={self.token}" if self.token else ""
        return (f"live view: {self.url}{tok}   Braid events: {self.url}events{tok}"
                + ("   (token required: this address is not loopback)" if self.token else ""))

    def close(self) -> None:
        """Publish what is pending and a final page state, let the clients have it (up to 2 s), end
        every stream, stop serving."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._signal()
        for t in self._threads:
            if t.name == "flytrack-web-publish":
                t.join(10.0)
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
        if self._requester is not None:
            self._requester.close()

    # --- ResultSink (tracking thread: append and return) ------------------------------------------
    def on_frame(self, result: FrameResult, frame_time: float, estimate_time: float) -> None:
        q = self._frames
        if len(q) >= self._frame_backlog:  # the publisher is far behind: lose the oldest, count it
            q.popleft()
            self.counts["frames_dropped"] += 1
        q.append((result, frame_time, estimate_time))
        self.counts["frames_in"] += 1

    def _signal(self) -> None:
        self._wake.set()

    def add_rule_firing(self, text: str) -> None:
        """Hook for the actuation rules: one line shown in the page's rule panel."""
        self.state.add_rule_firing(text)

    # --- publisher thread -------------------------------------------------------------------------
    def _publish(self) -> None:
        sel = self.clients.selector
        next_ui = next_keep = next_check = time.monotonic()
        while True:
            try:
                # Every POLL_S with clients (frames, slow clients' backlogs, clients that left), else at
                # the next page tick; a new client or close() wakes it at once.
                wait = max(0.0, next_ui - time.monotonic())
                self._wake.wait(min(wait, self.poll_s) if self.clients.clients else min(wait, 0.05))
                self._wake.clear()  # before draining: a frame appended from now on wakes us again
                stopping = self._stop.is_set()
                now = time.monotonic()
                # Sockets are polled (a system call) when a backlog waits, else every 0.1 s to notice
                # clients that left.
                if self.clients.clients and (self.clients.pending_bytes() or now >= next_check):
                    next_check = now + 0.1
                    for key, mask in sel.select(0):
                        self.clients.on_ready(key.data, mask)
                self.clients.admit()
                self._drain()
                self._images()
                now = time.monotonic()
                if now >= next_ui or stopping:
                    self._ui_tick(final=stopping)
                    period = self.ui_period if self.clients.count("ui") else 0.5
                    next_ui = max(next_ui + period, now + 0.2 * period)
                if now >= next_keep:
                    self.clients.keepalive()
                    next_keep = now + 1.0
            except Exception as exc:  # a bug here must not end the live outputs for good
                self.counts["publish_errors"] += 1
                if self.counts["publish_errors"] <= 10:
                    log.exception("live server publisher: %r", exc)
                time.sleep(0.01)
                stopping = self._stop.is_set()
            if stopping and not self._frames:
                break
        # The last frames and the final page state are queued: give the clients 2 s to take them.
        self.clients.end_streams()
        end = time.monotonic() + 2.0
        while self.clients.pending_bytes() and time.monotonic() < end:
            for key, mask in sel.select(0.05):
                self.clients.on_ready(key.data, mask)
        self.clients.close_all()

    def _images(self) -> None:
        pipe = self.state.pipe
        rx = getattr(pipe, "receiver", None) if pipe is not None else None
        if rx is not None and getattr(rx, "on_image", False) is None:
            rx.on_image = self.thumbs.add  # the receiver exists once the pipeline started
        if self.thumbs.chunks:
            self.thumbs.assemble()
        if self._requester is not None:
            self._requester.tick(time.monotonic())

    def _drain(self) -> None:
        q = self._frames
        while q:
            result, frame_time, estimate_time = q.popleft()
            if result.trigger_frame < 0:
                continue
            # An object gone without a Death (the tracker restarted after an error or a clock jump,
            # or frames lost here) gets one, so a Braid client never keeps a stale object.
            ids = {int(e.obj_id) for e in result.estimates}
            vanished = self._live_ids - ids - {int(i) for i in result.died}
            self._live_ids = ids
            self.counts["deaths_added"] += len(vanished)
            if self.clients.count("braid"):
                events = braid.frame_events(result, frame_time)
                if vanished:
                    f = int(result.trigger_frame)
                    events[-1:-1] = [braid.sse_event(braid.envelope({"Death": i}, f, frame_time))
                                     for i in sorted(vanished)]
                self.clients.broadcast("braid", events)
            self.state.add_frame(result, frame_time, estimate_time)
            self.counts["frames_published"] += 1
            # Let the GIL go between frames: a tracking thread waiting for it gets it now, not after
            # the interpreter's 5 ms switch interval.
            time.sleep(0)

    def _ui_tick(self, final: bool = False) -> None:
        snap = self.state.snapshot(self.stats(), final=final)
        time.sleep(0)  # as in _drain: the tracking thread first
        body = to_json(snap)
        self._last_state_json = body
        self._last_ui_event = b"event: state\ndata: " + body + b"\n\n"
        self.counts["ui_snapshots"] += 1
        self.clients.broadcast("ui", [self._last_ui_event])

    def _calibration_event(self) -> bytes | None:
        return braid.calibration_event(self.calibration_xml) if self.calibration_xml else None

    def _count_error(self, code: int) -> None:
        if 400 <= code < 500 and code != 401:
            self.counts["bad_requests"] += 1

    def stats(self) -> dict[str, Any]:
        s = self.clients.stats
        th = self.thumbs
        return {**self.counts, "thumbnails": th.images, "thumbnails_incomplete": th.dropped_incomplete,
                "thumbnail_requests": self._requester.sent if self._requester else 0,
                "clients": s.connected, "clients_by_kind": dict(s.by_kind),
                "clients_total": s.total, "clients_dropped_slow": s.dropped_slow,
                "clients_disconnected": s.disconnected, "clients_refused_busy": s.refused_busy,
                "bytes_sent": s.bytes_sent, "backlog_frames": len(self._frames)}


def calibration_xml_of(pipe: Any) -> str | None:
    """The pipeline's calibration as flydra XML text (Braid sends its reconstructor so), or None."""
    path = getattr(pipe, "calibration_path", None)
    if path is not None and Path(path).suffix.lower() == ".xml" and Path(path).is_file():
        return Path(path).read_text(encoding="utf-8", errors="replace")
    cams = getattr(pipe, "cameras", None)
    if not cams:
        return None
    try:
        from flytrack_host.geometry.formats import save_flydra_xml

        with tempfile.TemporaryDirectory() as d:
            out = Path(d) / "calibration.xml"
            save_flydra_xml({c.name: c for c in cams.values()}, out)
            return out.read_text(encoding="utf-8")
    except Exception as exc:  # the stream works without it; say why it is missing
        log.warning("no calibration for the event stream: %r", exc)
        return None


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])
