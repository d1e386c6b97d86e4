"""The live HTTP server under good and bad clients: real sockets, real threads, no pipeline needed."""

from __future__ import annotations

import socket
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from flytrack_host.live.braid import iter_sse, open_event_stream
from flytrack_host.live.web.server import LiveServer, is_loopback, parse_bind

sys.path.insert(0, str(Path(__file__).parent))
from frames import make_result  # noqa: E402


@pytest.fixture
def server():
    s = LiveServer("127.0.0.1", 0, calibration_xml="<multi_camera_reconstructor/>", client_backlog_bytes=256 << 10)
    s.start()
    yield s
    s.close()


def _feed(s: LiveServer, frames: range, n: int = 10) -> list[float]:
    """Frames into the sink as the tracking thread would; returns each on_frame's duration (s)."""
    took = []
    for f in frames:
        r = make_result(f, n, born=list(range(1, n + 1)) if f == frames[0] else [])
        t0 = time.perf_counter()
        s.on_frame(r, time.time() - 0.002, time.time())
        took.append(time.perf_counter() - t0)
    return took


def _wait(cond, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return False


def _raw(s: LiveServer, data: bytes, read: bool = True) -> bytes:
    with socket.create_connection(("127.0.0.1", s.port), timeout=10) as c:
        c.sendall(data)
        if not read:
            return b""
        out = b""
        while chunk := c.recv(65536):
            out += chunk
        return out


class Reader:
    """A Braid client on its own thread, counting EndOfFrame events."""

    def __init__(self, s: LiveServer, stop_after: int | None = None):
        self.resp = open_event_stream(s.url + "events", timeout=30)
        self.events: list = []
        self.stop_after = stop_after
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        try:
            for ev in iter_sse(self.resp):
                self.events.append(ev)
                if self.stop_after is not None and len(self.events) >= self.stop_after:
                    self.resp.close()  # leave mid-stream
                    return
        except (OSError, ValueError):
            pass

    @property
    def frames(self) -> int:
        return sum(1 for e in self.events if '"EndOfFrame"' in e.data)


class RawReader:
    """A fast client: raw socket, keeps every byte (parsing is not what is tested here)."""

    def __init__(self, s: LiveServer):
        self.sock = socket.create_connection(("127.0.0.1", s.port))
        self.sock.sendall(b"GET /events HTTP/1.0\r\nAccept: text/event-stream\r\n\r\n")
        self.buf = bytearray()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        while chunk := self.sock.recv(1 << 20):
            self.buf += chunk

    @property
    def frames(self) -> int:
        return bytes(self.buf).count(b'"EndOfFrame"')


def test_many_clients_get_the_same_stream():
    server = LiveServer("127.0.0.1", 0, calibration_xml="<multi_camera_reconstructor/>")  # 2 MB backlogs
    server.start()
    try:
        _many_clients(server)
    finally:
        server.close()


def _many_clients(server: LiveServer) -> None:
    readers = [Reader(server) for _ in range(20)]
    assert _wait(lambda: server.clients.count("braid") == 20)
    for i in range(20):  # 1000 frames/s in bursts of 10, as a fast rig would
        _feed(server, range(i * 10, i * 10 + 10), n=5)
        time.sleep(0.01)
    assert _wait(lambda: all(r.frames == 200 for r in readers)), [r.frames for r in readers]
    first = [e.data for e in readers[0].events]
    assert first[0].startswith('{"v":3,"msg":{"CalibrationFlydraXml"')
    assert all([e.data for e in r.events] == first for r in readers)
    assert server.stats()["clients_dropped_slow"] == 0


def test_client_that_never_reads_is_dropped_and_tracking_is_not_held():
    # 1 MB backlogs: the reading client may be starved ~0.25 s by a loaded machine and stay.
    server = LiveServer("127.0.0.1", 0, client_backlog_bytes=1 << 20)
    server.start()
    try:
        _never_reads(server)
    finally:
        server.close()


def _never_reads(server: LiveServer) -> None:
    good = RawReader(server)
    # A client that sends its request and then never reads a byte.
    lazy = socket.create_connection(("127.0.0.1", server.port))
    lazy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    lazy.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\nAccept: text/event-stream\r\n\r\n")
    assert _wait(lambda: server.clients.count("braid") == 2)
    took = []
    # 1000 frames a second of 10 targets, ~9 MB: far beyond the 1 MB backlog plus what the kernel
    # buffers for the lazy client (~3 MB on loopback).
    for chunk in range(200):
        took += _feed(server, range(chunk * 10, chunk * 10 + 10), n=10)
        time.sleep(0.01)
    assert _wait(lambda: server.stats()["clients_dropped_slow"] == 1), str(server.stats())
    assert _wait(lambda: good.frames == 2000, 30), good.frames
    # The tracking thread's side stayed an append: no call waited for the stuck client.
    took.sort()
    # (the max also holds whatever the kernel took from this thread on a loaded machine)
    assert took[len(took) // 2] < 1e-3 and took[-1] < 0.5, (took[len(took) // 2], took[-1])
    # Memory bounded: no backlog beyond the limit anywhere, the lazy client is gone.
    assert server.clients.count("braid") == 1
    assert all(c.backlog_bytes <= c.limit_bytes for c in list(server.clients.clients))
    lazy.close()


def test_clients_leaving_mid_stream_are_counted_and_the_rest_go_on(server):
    leavers = [Reader(server, stop_after=k) for k in (2, 10, 50)]
    stayer = Reader(server)
    assert _wait(lambda: server.clients.count("braid") == 4)
    for i in range(5):
        _feed(server, range(i * 60, i * 60 + 60), n=3)
        time.sleep(0.05)
    assert _wait(lambda: stayer.frames == 300)
    assert _wait(lambda: server.stats()["clients_disconnected"] >= 3 and server.clients.count("braid") == 1)
    assert all(not r.t.is_alive() for r in leavers)
    # A client that resets the connection at once.
    c = socket.create_connection(("127.0.0.1", server.port))
    c.sendall(b"GET /events HTTP/1.0\r\nAccept: text/event-stream\r\n\r\n")
    c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    c.close()
    _feed(server, range(300, 400), n=3)
    assert _wait(lambda: stayer.frames == 400)
    assert _wait(lambda: server.clients.count("braid") == 1)


def test_oversized_and_malformed_requests_get_clear_errors(server):
    assert _raw(server, b"GET /" + b"a" * 10000 + b" HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.0 414 request line over")
    big = b"".join(b"X-%d: %s\r\n" % (i, b"v" * 1000) for i in range(40))
    assert _raw(server, b"GET / HTTP/1.0\r\n" + big + b"\r\n").startswith(b"HTTP/1.0 431 headers over")
    assert _raw(server, b"garbage\r\n\r\n").startswith(b"HTTP/1.0 400")
    assert _raw(server, b"GET / HTTP/x.y\r\n\r\n").startswith(b"HTTP/1.0 400")
    assert _raw(server, b"\x00\xff\xfe binary\r\n\r\n").split(b" ")[1] == b"400"
    assert _raw(server, b"POST /events HTTP/1.0\r\nContent-Length: 5\r\n\r\nhello").split(b" ")[1] == b"405"
    assert _raw(server, b"BREW / HTTP/1.0\r\n\r\n").split(b" ")[1] == b"501"
    assert _raw(server, b"GET /nothing HTTP/1.0\r\n\r\n").split(b" ")[1] == b"404"
    assert _raw(server, b"GET /static/../server.py HTTP/1.0\r\n\r\n").split(b" ")[1] == b"404"
    assert _raw(server, b"GET /static/app.js HTTP/1.0\r\n\r\n").split(b" ")[1] == b"200"
    # A client that connects and sends half a request line is let go after the read timeout;
    # meanwhile the server answers others.
    half = socket.create_connection(("127.0.0.1", server.port))
    half.sendall(b"GET /ev")
    assert b"200 OK" in _raw(server, b"GET /api/stats HTTP/1.0\r\n\r\n")
    half.close()
    assert server.stats()["bad_requests"] >= 7
    # Still serving events after all that.
    r = Reader(server)
    assert _wait(lambda: server.clients.count("braid") == 1)
    _feed(server, range(10), n=2)
    assert _wait(lambda: r.frames == 10)


def test_token_needed_off_loopback_and_checked():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("") and not is_loopback("192.168.1.5")
    assert parse_bind("0.0.0.0:9000") == ("0.0.0.0", 9000) and parse_bind(":0") == ("127.0.0.1", 0)
    assert parse_bind("[::1]:8397") == ("::1", 8397)
    # Every interface: a token is generated, printed by banner(), and asked for.
    every = LiveServer("0.0.0.0", 0)
    every.start()
    try:
        assert every.token and f"?token={every.token}" in every.banner()
        local = f"http://127.0.0.1:{every.port}/"
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(local + "api/stats", timeout=10)
        assert e.value.code == 401
        assert urllib.request.urlopen(local + f"api/stats?token={every.token}", timeout=10).status == 200
    finally:
        every.close()
    with pytest.raises(ValueError, match="bad port"):
        parse_bind("host:http")
    s = LiveServer("127.0.0.1", 0, token="s3cret-token")
    s.start()
    try:
        assert "?token=s3cret-token" in s.banner()
        for url in (s.url, s.url + "events", s.url + "events?token=wrong", s.url + "api/state?token="):
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(url, timeout=10)
            assert e.value.code == 401
        r = urllib.request.urlopen(s.url + "?token=s3cret-token", timeout=10)
        cookie = r.headers["Set-Cookie"]
        assert r.status == 200 and cookie.startswith("flytrack_token=s3cret-token") and "HttpOnly" in cookie
        req = urllib.request.Request(s.url + "api/stats", headers={"Cookie": "flytrack_token=s3cret-token"})
        assert urllib.request.urlopen(req, timeout=10).status == 200
        bad = urllib.request.Request(s.url + "api/stats", headers={"Cookie": "flytrack_token=nope"})
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(bad, timeout=10)
        assert e.value.code == 401
        assert s.stats()["unauthorised"] == 5
    finally:
        s.close()


def test_too_many_streaming_clients_are_refused_with_503():
    s = LiveServer("127.0.0.1", 0, max_clients=3)
    s.start()
    try:
        readers = [Reader(s) for _ in range(3)]
        assert _wait(lambda: s.clients.count() == 3)
        with pytest.raises(urllib.error.HTTPError) as e:
            open_event_stream(s.url + "events", timeout=10)
        assert e.value.code == 503
        assert s.stats()["clients_refused_busy"] == 1
        _feed(s, range(5), n=1)
        assert _wait(lambda: all(r.frames == 5 for r in readers))
    finally:
        s.close()


def test_close_ends_every_stream_and_frees_the_port(server):
    readers = [Reader(server) for _ in range(3)]
    assert _wait(lambda: server.clients.count() == 3)
    _feed(server, range(20), n=2)
    server.close()
    for r in readers:
        r.t.join(5)
        assert not r.t.is_alive() and r.frames == 20
    with socket.socket() as probe:
        assert probe.connect_ex(("127.0.0.1", server.port)) != 0


def test_a_braid_client_reading_with_requests_gets_one_event_per_chunk():
    """Braid's Python clients (its UDP re-send script) open the page with a requests session (the
    token cookie is kept), then read /events with iter_content(chunk_size=None) and expect every
    piece to be exactly one event: `event: braid` and one `data:` line, v 2 or 3."""
    import json

    import requests

    s = LiveServer("127.0.0.1", 0, token="t0k", calibration_xml="<multi_camera_reconstructor/>")
    s.start()
    try:
        session = requests.session()
        session.get(s.url + "?token=t0k", timeout=10).raise_for_status()  # the cookie for what follows
        r = session.get(s.url + "events", stream=True, headers={"Accept": "text/event-stream"}, timeout=10)
        r.raise_for_status()
        assert r.headers["Transfer-Encoding"] == "chunked"
        assert _wait(lambda: s.clients.count("braid") == 1)
        for i in range(10):
            _feed(s, range(i * 10, i * 10 + 10), n=3)
            time.sleep(0.01)
        kinds: dict[str, int] = {}
        for piece in r.iter_content(chunk_size=None, decode_unicode=True):
            lines = piece.strip().split("\n")
            assert len(lines) == 2 and lines[0] == "event: braid" and lines[1].startswith("data: "), piece[:200]
            data = json.loads(lines[1][len("data: "):])
            assert data.get("v", 1) in (2, 3)
            k = next(iter(data["msg"]))
            kinds[k] = kinds.get(k, 0) + 1
            if k == "Update":
                assert {"x", "y", "z"} <= set(data["msg"]["Update"])
            if kinds.get("EndOfFrame") == 100:
                break
        assert kinds == {"CalibrationFlydraXml": 1, "Birth": 30, "Update": 300, "EndOfFrame": 100}  # _feed: 10 x 3 born
        r.close()
    finally:
        s.close()


def test_objects_gone_without_a_death_get_one(server):
    """A tracker restart drops every object without Death messages; Braid clients must hear of it."""
    r = Reader(server)
    assert _wait(lambda: server.clients.count("braid") == 1)
    _feed(server, range(0, 3), n=3)  # objects 1, 2, 3
    restarted = make_result(3, 1, first_id=10, born=[10])  # a fresh tracker: 1-3 gone, 10 born
    server.on_frame(restarted, time.time(), time.time())
    assert _wait(lambda: r.frames == 4)
    last = [e.json()["msg"] for e in r.events if e.json()["synced_frame"] == 3]
    assert [next(iter(m)) for m in last] == ["Birth", "Update", "Death", "Death", "Death", "EndOfFrame"]
    assert [m["Death"] for m in last if "Death" in m] == [1, 2, 3]
    assert server.stats()["deaths_added"] == 3


def test_braids_stream_needs_accept_event_stream_as_braid_does(server):
    """Braid answers 400 to a GET /events without `Accept: text/event-stream`; so does FlyTrack."""
    reply = _raw(server, b"GET /events HTTP/1.0\r\n\r\n")
    assert reply.split(b" ")[1] == b"400" and b"text/event-stream" in reply
    reply = _raw(server, b"GET /events HTTP/1.0\r\nAccept: text/html\r\n\r\n")
    assert reply.split(b" ")[1] == b"400"
    assert server.counts["not_event_stream"] == 2
    ok = socket.create_connection(("127.0.0.1", server.port))
    ok.sendall(b"GET /events HTTP/1.0\r\nAccept: text/event-stream\r\n\r\n")
    assert ok.recv(64).startswith(b"HTTP/1.0 200")
    ok.close()


def test_a_quiet_braid_stream_gets_no_keep_alive_comments():
    """Braid sends nothing on an idle stream, and its documented client braid_retransmit_udp.py takes every
    block for a two-line event (it asserts so); only the page's stream gets keep-alive comments."""
    from flytrack_host.live.web.clients import ClientSet

    clients = ClientSet()
    pairs = {kind: socket.socketpair() for kind in ("braid", "ui")}
    for kind, (ours, _) in pairs.items():
        assert clients.reserve()
        clients.hand_over(kind, ours, kind, None)
    clients.admit()
    clients.keepalive(idle_s=0.0)  # every client idle for longer than the threshold
    for kind, (_, theirs) in pairs.items():
        theirs.setblocking(False)
        try:
            got = theirs.recv(100)
        except BlockingIOError:
            got = b""
        assert got == (b": keep-alive\n\n" if kind == "ui" else b""), kind
        for s in pairs[kind]:
            s.close()
