"""Live output: one LIVE_ESTIMATES datagram per tracked frame (split when more than 27 objects) to
every UDP subscriber, and `LiveClient`, which a stimulus program imports to receive them.

    from flytrack_host.live.udp import LiveClient
    with LiveClient(7100) as client:
        for frame in client.frames(timeout=1.0):      # stops after 1 s without data
            for obj in frame.objects: ...               # OBJECT_DTYPE: obj_id, x, y, z, vx, vy, vz, cov
"""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.protocol import OBJECT_DTYPE, LiveEstimates, ProtocolError, decode_datagram, encode
from flytrack_host.tracking.types import FrameResult
from flytrack_host.util import hostclock

LIVE_MAX_OBJECTS = 27
_COV_IDX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def estimates_to_objects(result: FrameResult) -> tuple[np.ndarray, int]:
    """FrameResult -> (OBJECT_DTYPE array, number of estimates dropped for non-finite values)."""
    objs = np.zeros(len(result.estimates), dtype=OBJECT_DTYPE)
    keep = np.ones(len(objs), dtype=bool)
    for i, e in enumerate(result.estimates):
        s = np.asarray(e.state, dtype=np.float64)
        c = np.asarray(e.covariance, dtype=np.float64)
        cov = [c[a, b] for a, b in _COV_IDX]
        vals = np.concatenate([s[:6], cov])
        # float32 overflow would turn a finite value into inf, which the protocol forbids.
        if not np.all(np.isfinite(vals)) or np.any(np.abs(vals) > 3e38):
            keep[i] = False
            continue
        objs[i]["obj_id"] = e.obj_id
        objs[i]["x"], objs[i]["y"], objs[i]["z"] = s[0], s[1], s[2]
        objs[i]["vx"], objs[i]["vy"], objs[i]["vz"] = s[3], s[4], s[5]
        objs[i]["cov"] = cov
    return objs[keep], int((~keep).sum())


def parse_host_port(value: str) -> tuple[str, int]:
    host, _, port = value.rpartition(":")
    return host, int(port)


@dataclass
class LiveSenderStats:
    frames: int = 0
    datagrams: int = 0
    send_errors: int = 0
    dropped_objects: int = 0


class LiveSender:
    def __init__(self, subscribers: Sequence[str]):
        self.subscribers = [parse_host_port(s) for s in subscribers]
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.seq = 0
        self.stats = LiveSenderStats()

    def close(self) -> None:
        self.sock.close()

    def send(self, result: FrameResult, trigger_time: float) -> int:
        """Send one frame's estimates to every subscriber; returns datagrams sent per subscriber."""
        if not self.subscribers:
            return 0
        objs, dropped = estimates_to_objects(result)
        self.stats.dropped_objects += dropped
        n_parts = max(1, -(-len(objs) // LIVE_MAX_OBJECTS))
        tt = trigger_time if np.isfinite(trigger_time) else hostclock.now()
        datagrams = []
        for part in range(n_parts):
            chunk = objs[part * LIVE_MAX_OBJECTS : (part + 1) * LIVE_MAX_OBJECTS]
            latency_ms = (hostclock.now() - tt) * 1e3
            msg = LiveEstimates(
                trigger_frame=max(int(result.trigger_frame), 0),
                trigger_time=float(tt),
                seq=self.seq & 0xFFFFFFFF,
                latency_ms=float(latency_ms),
                part_index=part,
                part_count=n_parts,
                flags=1 if n_parts > 1 else 0,
                objects=chunk,
            )
            self.seq += 1
            datagrams.append(encode(msg))
        for addr in self.subscribers:
            for d in datagrams:
                try:
                    self.sock.sendto(d, addr)
                    self.stats.datagrams += 1
                except OSError:  # nobody listening, buffer full: a stimulus program must not stall us
                    self.stats.send_errors += 1
        self.stats.frames += 1
        return len(datagrams)


@dataclass
class LiveFrame:
    trigger_frame: int
    trigger_time: float
    latency_ms: float  # host-side latency when the (first) datagram was built
    objects: np.ndarray  # OBJECT_DTYPE
    recv_time: float
    complete: bool = True


@dataclass
class LiveClientStats:
    datagrams: int = 0
    frames: int = 0
    malformed: int = 0
    incomplete: int = 0
    other: int = 0
    errors_by_name: dict[str, int] = field(default_factory=dict)


class LiveClient:
    """Receives LIVE_ESTIMATES on a UDP port. Use `recv(timeout)`, iterate `frames(timeout)`, or
    `run(callback, timeout)`."""

    def __init__(self, port: int = 7100, host: str = "127.0.0.1", rcvbuf_bytes: int = 1 << 20):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:  # room for a few seconds of frames if the program is busy drawing
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
        except OSError:
            pass
        self.sock.bind((host, port))
        self.sock.setblocking(False)
        self.stats = LiveClientStats()
        self._parts: dict[int, list[LiveEstimates]] = {}
        self._ready: list[LiveFrame] = []

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> LiveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def recv(self, timeout: float | None = 1.0) -> LiveFrame | None:
        """The next complete frame, or None after `timeout` seconds without one."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._ready:
            wait = None if deadline is None else deadline - time.monotonic()
            if wait is not None and wait <= 0:
                return None
            r, _, _ = select.select([self.sock], [], [], wait)
            if not r:
                return None
            while True:
                try:
                    data = self.sock.recv(2048)
                except (BlockingIOError, InterruptedError):
                    break
                self._handle(data)
        return self._ready.pop(0)

    def frames(self, timeout: float | None = 1.0) -> Iterator[LiveFrame]:
        """Yield frames until none arrives for `timeout` seconds."""
        while (f := self.recv(timeout)) is not None:
            yield f

    def run(self, callback: Callable[[LiveFrame], object], timeout: float | None = 1.0) -> int:
        n = 0
        for f in self.frames(timeout):
            callback(f)
            n += 1
        return n

    def _handle(self, data: bytes) -> None:
        self.stats.datagrams += 1
        now = hostclock.now()
        try:
            msg = decode_datagram(data)
        except ProtocolError as exc:
            self.stats.malformed += 1
            self.stats.errors_by_name[exc.name] = self.stats.errors_by_name.get(exc.name, 0) + 1
            return
        if not isinstance(msg, LiveEstimates):
            self.stats.other += 1
            return
        if msg.part_count == 1:
            self._emit([msg], now, True)
            return
        parts = self._parts.setdefault(msg.trigger_frame, [])
        parts.append(msg)
        if len({p.part_index for p in parts}) == msg.part_count:
            del self._parts[msg.trigger_frame]
            self._emit(sorted(parts, key=lambda p: p.part_index), now, True)
        # Older unfinished frames will never complete once a newer frame is under way.
        for tf in [k for k in self._parts if k < msg.trigger_frame - 2]:
            self.stats.incomplete += 1
            self._emit(sorted(self._parts.pop(tf), key=lambda p: p.part_index), now, False)

    def _emit(self, parts: list[LiveEstimates], now: float, complete: bool) -> None:
        objs = np.concatenate([np.asarray(p.objects) for p in parts])
        p0 = parts[0]
        self.stats.frames += 1
        self._ready.append(LiveFrame(p0.trigger_frame, p0.trigger_time, p0.latency_ms, objs, now, complete))
