"""Streaming clients of the live server, each with its own bounded backlog.

The publisher thread `offer`s bytes to every client; each client's connection thread `take`s them and
writes to its socket. A client whose backlog would pass `limit_bytes` (it stopped reading, or reads
slower than the stream) is dropped: its backlog is freed, its socket shut down (which also frees a
connection thread blocked in a write) and the drop is counted. Nothing here ever blocks the publisher,
and memory per client is at most `limit_bytes` plus the kernel's socket buffers.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections import deque
from dataclasses import dataclass, field


@dataclass
class ClientStats:
    connected: int = 0  # now
    total: int = 0  # ever accepted
    dropped_slow: int = 0  # backlog full: stopped reading or too slow
    disconnected: int = 0  # went away (closed, reset, write timeout)
    refused_busy: int = 0  # too many streaming clients at once
    bytes_sent: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)  # connected now, per stream


class StreamClient:
    def __init__(self, kind: str, limit_bytes: int, sock: socket.socket | None = None, address: str = ""):
        self.kind = kind
        self.limit_bytes = limit_bytes
        self.sock = sock
        self.address = address
        self._q: deque[bytes] = deque()
        self._bytes = 0
        self._cv = threading.Condition()
        self.closed = False
        self.finishing = False  # the server stops: send what is queued, then end the stream
        self.dropped = False
        self.sent_bytes = 0

    @property
    def backlog_bytes(self) -> int:
        return self._bytes

    def offer(self, data: bytes) -> bool:
        """Queue `data` (publisher thread); False when the client is closed or was just dropped."""
        with self._cv:
            if self.closed:
                return False
            if self._bytes + len(data) > self.limit_bytes:
                self.dropped = True
                self._close_locked()
                return False
            self._q.append(data)
            self._bytes += len(data)
            self._cv.notify()
        return True

    def take(self, timeout: float) -> bytes | None:
        """Everything queued, as one write (connection thread); b"" after `timeout` with nothing,
        None once the client is closed."""
        with self._cv:
            if not self._q and not self.closed and not self.finishing:
                self._cv.wait(timeout)
            if self.closed:
                return None
            if not self._q:
                return None if self.finishing else b""
            out = b"".join(self._q)
            self._q.clear()
            self._bytes = 0
            return out

    def close(self) -> None:
        with self._cv:
            self._close_locked()

    def finish(self) -> None:
        with self._cv:
            self.finishing = True
            self._cv.notify_all()

    def _close_locked(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._q.clear()
        self._bytes = 0
        self._cv.notify_all()
        if self.sock is not None:
            # Unblocks a connection thread stuck writing to a client that does not read.
            with contextlib.suppress(OSError):
                self.sock.shutdown(socket.SHUT_RDWR)


class ClientSet:
    """The streaming clients of one server, by stream kind ("braid", "ui"), with the counts."""

    def __init__(self, max_clients: int = 64, limit_bytes: int = 2 << 20):
        self.max_clients = max_clients
        self.limit_bytes = limit_bytes
        self.stats = ClientStats()
        self._lock = threading.Lock()
        self._clients: list[StreamClient] = []

    def add(self, kind: str, sock: socket.socket | None = None, address: str = "") -> StreamClient | None:
        with self._lock:
            if len(self._clients) >= self.max_clients:
                self.stats.refused_busy += 1
                return None
            c = StreamClient(kind, self.limit_bytes, sock, address)
            self._clients.append(c)
            self.stats.total += 1
            self._count()
            return c

    def remove(self, c: StreamClient) -> None:
        c.close()
        with self._lock:
            if c in self._clients:
                self._clients.remove(c)
                if c.dropped:
                    self.stats.dropped_slow += 1
                else:
                    self.stats.disconnected += 1
                self.stats.bytes_sent += c.sent_bytes
                self._count()

    def broadcast(self, kind: str, data: bytes) -> int:
        """Offer `data` to every client of `kind`; dropped ones leave the set. Returns clients reached."""
        with self._lock:
            targets = [c for c in self._clients if c.kind == kind]
        n = 0
        gone = []
        for c in targets:
            if c.offer(data):
                n += 1
            elif c.dropped:
                gone.append(c)
        for c in gone:
            self.remove(c)
        return n

    def count(self, kind: str | None = None) -> int:
        with self._lock:
            return sum(1 for c in self._clients if kind is None or c.kind == kind)

    def close_all(self, graceful: bool = True) -> None:
        """End every stream: gracefully, each gets what is already queued first."""
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            if graceful:
                c.finish()
            else:
                c.close()

    def _count(self) -> None:
        self.stats.connected = len(self._clients)
        kinds: dict[str, int] = {}
        for c in self._clients:
            kinds[c.kind] = kinds.get(c.kind, 0) + 1
        self.stats.by_kind = kinds
