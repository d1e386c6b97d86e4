"""Streaming clients of the live server, written by ONE thread with non-blocking sockets.

A connection thread of the HTTP server answers the request, writes the headers and hands the socket
over; from then on the publisher thread alone writes to it (no thread per client: in one Python
process, ten writer threads waking per frame would take the GIL from the tracking thread). Each client
has a bounded backlog: what the kernel does not take at once waits there, and a client whose backlog
would pass `limit_bytes` (it stopped reading, or reads slower than the stream) is dropped: backlog
freed, socket closed, drop counted. Memory per client is at most `limit_bytes` plus the kernel's
socket buffers, and nothing ever blocks.

An HTTP/1.1 client gets the stream with chunked transfer encoding, one chunk per event, as Braid's
server sends it: Braid's own Python clients read `iter_content(chunk_size=None)` and expect each
piece to be exactly one event. An HTTP/1.0 client gets the events as a plain body until close.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field


@dataclass
class ClientStats:
    connected: int = 0  # now
    total: int = 0  # ever accepted
    dropped_slow: int = 0  # backlog full: stopped reading or too slow
    disconnected: int = 0  # went away (closed, reset, send error)
    refused_busy: int = 0  # too many streaming clients at once
    bytes_sent: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)  # connected now, per stream


def chunk(data: bytes) -> bytes:
    """One HTTP/1.1 chunk."""
    return b"%x\r\n" % len(data) + data + b"\r\n"


END_CHUNKS = b"0\r\n\r\n"


class StreamClient:
    def __init__(self, kind: str, sock: socket.socket, limit_bytes: int, address: str = "", chunked: bool = False):
        self.kind = kind
        self.chunked = chunked
        self.sock = sock
        self.limit_bytes = limit_bytes
        self.address = address
        self.pending: deque[memoryview] = deque()
        self.backlog_bytes = 0
        self.sent_bytes = 0
        self.closed = False
        self.dropped = False
        self.last_write = time.monotonic()

    def queue(self, data: bytes) -> bool:
        """Send what the kernel takes now, keep the rest; False when the client must go."""
        if self.closed:
            return False
        if self.pending:
            if self.backlog_bytes + len(data) > self.limit_bytes:
                self.dropped = True
                return False
            self.pending.append(memoryview(data))
            self.backlog_bytes += len(data)
            return self.flush()
        try:
            n = self.sock.send(data)
        except BlockingIOError:
            n = 0
        except OSError:
            return False
        self.sent_bytes += n
        self.last_write = time.monotonic()
        if n < len(data):
            rest = memoryview(data)[n:]
            if len(rest) > self.limit_bytes:
                self.dropped = True
                return False
            self.pending.append(rest)
            self.backlog_bytes += len(rest)
        return True

    def flush(self) -> bool:
        """Write as much of the backlog as the kernel takes; False on a send error."""
        while self.pending:
            head = self.pending[0]
            try:
                n = self.sock.send(head)
            except BlockingIOError:
                return True
            except OSError:
                return False
            self.sent_bytes += n
            self.backlog_bytes -= n
            self.last_write = time.monotonic()
            if n < len(head):
                self.pending[0] = head[n:]
                return True
            self.pending.popleft()
        return True

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.pending.clear()
        self.backlog_bytes = 0
        with contextlib.suppress(OSError):
            self.sock.close()


class ClientSet:
    """The streaming clients by kind ("braid", "ui"); used by the publisher thread only, except `add`
    (connection threads), which hands new clients over through a queue."""

    def __init__(self, max_clients: int = 64, limit_bytes: int = 2 << 20):
        self.max_clients = max_clients
        self.limit_bytes = limit_bytes
        self.stats = ClientStats()
        self.clients: list[StreamClient] = []
        self.incoming: deque[StreamClient] = deque()  # appended by connection threads
        self.selector = selectors.DefaultSelector()
        self._reserved = 0
        self._lock = threading.Lock()

    # --- connection threads ------------------------------------------------------------------------
    def reserve(self) -> bool:
        """A slot for a new streaming client, or False when full (counted)."""
        with self._lock:
            if self._reserved >= self.max_clients:
                self.stats.refused_busy += 1
                return False
            self._reserved += 1
            return True

    def hand_over(self, kind: str, sock: socket.socket, address: str, first: bytes | None,
                  chunked: bool = False) -> None:
        sock.setblocking(False)
        c = StreamClient(kind, sock, self.limit_bytes, address, chunked)
        if first:
            data = chunk(first) if chunked else first
            c.pending.append(memoryview(data))
            c.backlog_bytes = len(data)
        self.incoming.append(c)

    def unreserve(self) -> None:
        with self._lock:
            self._reserved -= 1

    # --- publisher thread ----------------------------------------------------------------------------
    def admit(self) -> None:
        while self.incoming:
            c = self.incoming.popleft()
            self.clients.append(c)
            self.selector.register(c.sock, selectors.EVENT_READ, c)
            self.stats.total += 1
            if not c.flush():
                self.remove(c)
        self._count()

    def broadcast(self, kind: str, events: list[bytes]) -> int:
        """Queue `events` for every client of `kind` (one write each); clients that must go are
        removed. Returns the clients reached."""
        n = 0
        plain = chunked = b""
        for c in [c for c in self.clients if c.kind == kind]:
            if c.chunked:
                data = chunked = chunked or b"".join(chunk(e) for e in events)
            else:
                data = plain = plain or b"".join(events)
            if c.queue(data):
                n += 1
                self._want_write(c)
            else:
                self.remove(c)
        return n

    def on_ready(self, c: StreamClient, mask: int) -> None:
        if mask & selectors.EVENT_READ:
            # A streaming client sends nothing after its request: data or EOF both mean it is done
            # with us (EOF: it closed; anything else is ignored but read so it cannot pile up).
            try:
                got = c.sock.recv(4096)
            except BlockingIOError:
                got = None
            except OSError:
                got = b""
            if got == b"":
                self.remove(c)
                return
        if mask & selectors.EVENT_WRITE:
            if not c.flush():
                self.remove(c)
                return
            self._want_write(c)

    def keepalive(self, idle_s: float = 5.0) -> None:
        """A comment line to the page's stream when it has been idle: proxies and browsers keep it open.
        Never on Braid's stream: Braid sends none, and its clients (braid_retransmit_udp.py) take every
        block for an event of two lines."""
        now = time.monotonic()
        for c in [c for c in self.clients if c.kind != "braid"]:
            ka = b": keep-alive\n\n"
            if not c.pending and now - c.last_write > idle_s and not c.queue(chunk(ka) if c.chunked else ka):
                self.remove(c)

    def end_streams(self) -> None:
        """The last chunk for chunked clients: their HTTP response ends cleanly."""
        for c in list(self.clients):
            if c.chunked and not c.queue(END_CHUNKS):
                self.remove(c)

    def _want_write(self, c: StreamClient) -> None:
        if c.closed:
            return
        ev = selectors.EVENT_READ | (selectors.EVENT_WRITE if c.pending else 0)
        with contextlib.suppress(KeyError, ValueError):
            if self.selector.get_key(c.sock).events != ev:
                self.selector.modify(c.sock, ev, c)

    def remove(self, c: StreamClient) -> None:
        if c in self.clients:
            self.clients.remove(c)
            with contextlib.suppress(KeyError, ValueError):
                self.selector.unregister(c.sock)
            if c.dropped:
                self.stats.dropped_slow += 1
            else:
                self.stats.disconnected += 1
            self.stats.bytes_sent += c.sent_bytes
            self.unreserve()
        c.close()
        self._count()

    def pending_bytes(self) -> int:
        return sum(c.backlog_bytes for c in self.clients)

    def count(self, kind: str | None = None) -> int:
        return sum(1 for c in self.clients if kind is None or c.kind == kind)

    def close_all(self) -> None:
        for c in list(self.clients):
            self.remove(c)
        for c in list(self.incoming):
            c.close()
            self.unreserve()
        self.incoming.clear()
        self.selector.close()

    def _count(self) -> None:
        self.stats.connected = len(self.clients)
        kinds: dict[str, int] = {}
        for c in self.clients:
            kinds[c.kind] = kinds.get(c.kind, 0) + 1
        self.stats.by_kind = kinds
