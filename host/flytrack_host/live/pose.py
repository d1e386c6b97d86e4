"""Pose stream for virtual reality: the animal's position extrapolated to "now + lead", at a fixed rate.

As flydra's ROS pose node does: lock on one object (or send every object), and at a fixed rate (200 Hz
by default), whether or not a new frame came in, send the last estimate's position moved on by its
velocity over (now - acquisition time + lead); `lead` hides the display's own latency. An object
whose newest estimate is older than `drop_after_s` (0.5 s) is dropped; a locked object that dies or
is dropped releases the lock and ("auto") the oldest live object is taken instead. With no object a NO_OBJECT datagram
still goes out at the rate, so a display knows the stream is alive and can blank the stimulus.

The datagram is owned by this module (not a wire-protocol message of protocol/SPEC.md): one UDP
datagram per object per tick, 104 bytes, little-endian:

    offset type  field
     0     4s    magic b"FTPS"
     4     u8    version (1)
     5     u8    flags: 1 LOCKED (the lock's object), 2 NO_OBJECT (nothing to send: NaN/0 fields)
     6     u16   count: datagrams in this tick (objects sent together)
     8     u32   seq: datagram counter of this sender (wraps)
    12     u32   obj_id
    16     i64   trigger_frame of the estimate (-1 with NO_OBJECT)
    24     f64   send_time: host clock (Unix epoch s) when the datagram was built
    32     f64   acquisition_time: trigger time of the estimate's frame (host clock)
    40     f64   age_s = send_time - acquisition_time
    48     f64   horizon_s = age_s + lead: how far the position was extrapolated
    56     3f64  x, y, z (m), extrapolated
    80     3f64  vx, vy, vz (m/s)

`PoseClient` receives them: `with PoseClient(7300) as c: msg = c.recv(1.0)`.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

from flytrack_host.tracking.types import FrameResult
from flytrack_host.util import hostclock

MAGIC = b"FTPS"
VERSION = 1
FLAG_LOCKED = 1
FLAG_NO_OBJECT = 2
_FMT = struct.Struct("<4sBBHIIqdddd3d3d")
POSE_SIZE = _FMT.size  # 104
assert POSE_SIZE == 104


class PoseError(ValueError):
    pass


@dataclass(slots=True)
class PoseMessage:
    flags: int
    count: int
    seq: int
    obj_id: int
    trigger_frame: int
    send_time: float
    acquisition_time: float
    age_s: float
    horizon_s: float
    position: tuple[float, float, float]
    velocity: tuple[float, float, float]
    recv_time: float = math.nan

    @property
    def no_object(self) -> bool:
        return bool(self.flags & FLAG_NO_OBJECT)

    @property
    def locked(self) -> bool:
        return bool(self.flags & FLAG_LOCKED)


def encode_pose(m: PoseMessage) -> bytes:
    return _FMT.pack(MAGIC, VERSION, m.flags, m.count, m.seq & 0xFFFFFFFF, m.obj_id & 0xFFFFFFFF,
                     m.trigger_frame, m.send_time, m.acquisition_time, m.age_s, m.horizon_s,
                     *m.position, *m.velocity)


def decode_pose(data: bytes) -> PoseMessage:
    if len(data) != POSE_SIZE:
        raise PoseError(f"pose datagram of {len(data)} bytes, expected {POSE_SIZE}")
    f = _FMT.unpack(data)
    if f[0] != MAGIC:
        raise PoseError(f"bad magic {f[0]!r}, expected {MAGIC!r}")
    if f[1] != VERSION:
        raise PoseError(f"pose datagram version {f[1]}, this client reads {VERSION}")
    if f[2] & ~(FLAG_LOCKED | FLAG_NO_OBJECT):
        raise PoseError(f"unknown flags 0x{f[2]:02x}")
    return PoseMessage(f[2], f[3], f[4], f[5], f[6], f[7], f[8], f[9], f[10], (f[11], f[12], f[13]),
                       (f[14], f[15], f[16]))


def parse_lock(value: str | int | None) -> str | int:
    """"auto" (lock on the oldest live object), "all" (every object) or an obj_id."""
    if value is None:
        return "auto"
    if isinstance(value, int):
        return value
    v = value.strip().lower()
    if v in ("auto", "all"):
        return v
    try:
        i = int(v)
    except ValueError:
        raise ValueError(f"pose lock must be auto, all or an object id, got {value!r}") from None
    if i < 0:
        raise ValueError(f"object id must be >= 0, got {i}")
    return i


def check_settings(rate_hz: float, lead_s: float, drop_after_s: float) -> None:
    """A clear ValueError for a setting out of range."""
    if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 2000.0):
        raise ValueError(f"pose rate must be 1..2000 Hz, got {rate_hz}")
    if not (math.isfinite(lead_s) and -1.0 <= lead_s <= 1.0):
        raise ValueError(f"pose lead must be -1..1 s, got {lead_s}")
    if not (math.isfinite(drop_after_s) and drop_after_s > 0):
        raise ValueError(f"drop_after_s must be > 0, got {drop_after_s}")


@dataclass
class PoseStats:
    frames: int = 0
    ticks: int = 0
    datagrams: int = 0
    no_object: int = 0
    send_errors: int = 0
    late_ticks: int = 0  # a tick more than one period late (the machine was busy)
    max_tick_late_s: float = 0.0
    drops: int = 0  # objects dropped after drop_after_s without data
    lock_changes: int = 0


@dataclass
class _Obj:
    frame: int
    t_acq: float
    state: tuple[float, ...]


class PoseStream:
    """A `ResultSink`: `on_frame` keeps a reference to the frame's estimates; the sender thread does
    the rest at `rate_hz`."""

    def __init__(self, destinations: Sequence[tuple[str, int]], rate_hz: float = 200.0, lead_s: float = 0.0,
                 lock: str | int | None = "auto", drop_after_s: float = 0.5, start: bool = True):
        check_settings(rate_hz, lead_s, drop_after_s)
        self.destinations = list(destinations)
        self.period = 1.0 / rate_hz
        self.lead_s = lead_s
        self.lock_mode = parse_lock(lock)
        self.drop_after_s = drop_after_s
        self.stats = PoseStats()
        self.locked_id: int | None = self.lock_mode if isinstance(self.lock_mode, int) else None
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self._latest: tuple[int, float, list, list[int]] | None = None
        self._objs: dict[int, _Obj] = {}
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="flytrack-pose", daemon=True)
        if start:  # start=False: ticks driven by the caller (tests, benchmarks)
            self._thread.start()

    # --- ResultSink: tracking thread -------------------------------------------------------------
    def on_frame(self, result: FrameResult, frame_time: float, estimate_time: float) -> None:
        # One reference assignment: the sender picks it up at its next tick. The Estimates hold
        # fresh arrays (the tracker copies them per frame), so nothing here is mutated later.
        self._latest = (result.trigger_frame, frame_time, result.estimates, result.died)
        self.stats.frames += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self.sock.close()

    # --- sender thread ----------------------------------------------------------------------------
    def _take_latest(self, now: float) -> None:
        latest, self._latest = self._latest, None
        if latest is None:
            return
        frame, t_acq, estimates, died = latest
        for e in estimates:
            s = e.state
            self._objs[int(e.obj_id)] = _Obj(int(frame), t_acq if math.isfinite(t_acq) else now,
                                             (float(s[0]), float(s[1]), float(s[2]),
                                              float(s[3]), float(s[4]), float(s[5])))
        for i in died:
            self._objs.pop(int(i), None)

    def _select(self, now: float) -> list[int]:
        # Dropped once its newest estimate is older than drop_after_s: no pose is ever sent older.
        for i in [i for i, o in self._objs.items() if now - o.t_acq > self.drop_after_s]:
            del self._objs[i]
            self.stats.drops += 1
        if self.lock_mode == "all":
            return sorted(self._objs)
        if isinstance(self.lock_mode, int):
            return [self.lock_mode] if self.lock_mode in self._objs else []
        if self.locked_id not in self._objs:
            new = min(self._objs) if self._objs else None  # the oldest live object
            if new != self.locked_id and new is not None:
                self.stats.lock_changes += 1
            self.locked_id = new
        return [self.locked_id] if self.locked_id is not None else []

    def tick(self, now: float | None = None) -> list[bytes]:
        """One tick's datagrams (also used by the tests without the thread)."""
        now = hostclock.now() if now is None else now  # the estimates' times are host times
        self._take_latest(now)
        ids = self._select(now)
        out = []
        flags = 0 if self.lock_mode == "all" else FLAG_LOCKED
        nan3 = (math.nan, math.nan, math.nan)
        if not ids:
            self.stats.no_object += 1
            out.append(encode_pose(PoseMessage(FLAG_NO_OBJECT, 1, self._seq, 0, -1, now, math.nan, math.nan,
                                               math.nan, nan3, nan3)))
            self._seq += 1
        for i in ids:
            o = self._objs[i]
            age = now - o.t_acq
            h = age + self.lead_s
            s = o.state
            pos = (s[0] + s[3] * h, s[1] + s[4] * h, s[2] + s[5] * h)
            out.append(encode_pose(PoseMessage(flags, len(ids), self._seq, i, o.frame, now, o.t_acq, age, h,
                                               pos, (s[3], s[4], s[5]))))
            self._seq += 1
        self.stats.ticks += 1
        return out

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            for d in self.tick():
                for addr in self.destinations:
                    try:
                        self.sock.sendto(d, addr)
                        self.stats.datagrams += 1
                    except OSError:  # nobody listening, buffer full: never stall
                        self.stats.send_errors += 1
            next_t += self.period
            now = time.monotonic()
            late = now - next_t
            if late > self.period:
                self.stats.late_ticks += 1
                self.stats.max_tick_late_s = max(self.stats.max_tick_late_s, late)
                next_t = now  # do not burst to catch up: a VR display wants the newest pose
            else:
                self._stop.wait(max(0.0, next_t - now))


@dataclass
class PoseClientStats:
    datagrams: int = 0
    malformed: int = 0
    errors: list[str] = field(default_factory=list)


class PoseClient:
    """Receives pose datagrams on a UDP port: `recv(timeout)` or iterate `messages(timeout)`."""

    def __init__(self, port: int = 7300, host: str = "127.0.0.1"):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.stats = PoseClientStats()

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def recv(self, timeout: float | None = 1.0) -> PoseMessage | None:
        """The next valid message, or None after `timeout` s without one (malformed ones are counted)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            r, _, _ = select.select([self.sock], [], [], wait)
            if not r:
                return None
            data = self.sock.recv(2048)
            self.stats.datagrams += 1
            try:
                m = decode_pose(data)
            except PoseError as exc:
                self.stats.malformed += 1
                if len(self.stats.errors) < 20:
                    self.stats.errors.append(str(exc))
                continue
            m.recv_time = time.time()  # noqa: TID251 - the stimulus program's own clock, a label
            return m

    def messages(self, timeout: float | None = 1.0) -> Iterator[PoseMessage]:
        while (m := self.recv(timeout)) is not None:
            yield m

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> PoseClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
