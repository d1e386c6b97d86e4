"""Receive FEATURES and STATUS datagrams from the edges over UDP.

One non-blocking socket; `receive(timeout)` waits (select) for the first datagram, then drains what
is queued, decodes with the NumPy codec (points stay a view on the datagram bytes) and returns
`CameraFrame`s and `StatusReport`s. The caller (the pipeline's tracking thread) owns the loop, so a
frame goes from the socket to the synchroniser without a thread hand-off.

Checks: the sender's address and camera index must be in the rig file (else rejected and counted);
per camera, sequence numbers give lost (gaps), duplicated and reordered datagrams; undecodable
datagrams are counted by SPEC error name; SPLIT frames are joined (parts grouped by camera, camera
frame and part count, so parts that disagree on the count never mix), and a frame whose parts do not
all arrive within `split_timeout_s` is passed on incomplete (flagged, counted). No datagram can raise
out of `receive`: an unexpected error while handling one is logged and counted (`internal_errors`).

One sender per camera: the first (address, port) a camera's datagrams come from owns the camera
index. Datagrams for that index from another port while the owner is sending (heard within
`sender_switch_s`) are a second edge with the same index, or a replay: rejected, counted
(`second_sender`), logged. When the owner has been silent that long, the new port is the edge
restarted (a new process, a new socket): counted as a restart, its sequence numbers start afresh (no
loss, no reordering counted), and its first frame is flagged `restarted` for the synchroniser.
A forward sequence gap larger than the edge could have sent in the time since its last datagram is
a jump of the sender's numbering, not loss (`seq_jumps`). Repeated warnings are rate-limited per kind,
with counts (`ratelog.RateLimitedLog`).
"""

from __future__ import annotations

import ipaddress
import select
import socket
import struct
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.intake.sync import CameraFrame
from flytrack_host.protocol import (
    DvsClusters,
    EdgeStatus,
    FeatureFrame,
    ImageChunk,
    ProtocolError,
    decode_datagram,
    join_feature_parts,
)
from flytrack_host.rig import RigConfig
from flytrack_host.util import hostclock
from flytrack_host.util.ratelog import RateLimitedLog

SEQ_MOD = 1 << 32
_HALF = 1 << 31
SEQ_WINDOW = 512  # recent sequence numbers remembered per camera (duplicates, reordering)
RESTART_GAP = 10_000  # a sequence number this far behind means the edge restarted
FORWARD_RESTART_GAP = 1_000_000  # ... and this far ahead
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux
SWITCH_CONFIRM = 3  # datagrams in a row from a new port, the old one silent: the edge restarted
MAX_DATAGRAM_RATE = 20_000  # per camera and second: a larger gap in the time elapsed is no loss


@dataclass
class CameraRecvStats:
    packets: int = 0
    features: int = 0
    status: int = 0
    frames: int = 0
    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    malformed: int = 0
    split_incomplete: int = 0
    restarts: int = 0
    second_sender: int = 0  # datagrams from another port while the camera's edge was sending
    seq_jumps: int = 0  # sequence jumps too large to be loss in the time elapsed
    other: int = 0
    dvs_slices: int = 0  # DVS_CLUSTERS datagrams (event cameras)
    dvs_clusters: int = 0
    # The edge's own counts from its last STATUS (for an event camera: events read, events lost)
    status_frames_seen: int = 0
    status_frames_dropped: int = 0


@dataclass
class ReceiverStats:
    datagrams: int = 0
    bytes: int = 0
    rejected_address: int = 0
    rejected_camera: int = 0
    malformed_unattributed: int = 0
    internal_errors: int = 0  # datagrams whose handling raised (a bug): counted, logged, dropped
    errors_by_name: dict[str, int] = field(default_factory=dict)
    cameras: dict[int, CameraRecvStats] = field(default_factory=dict)


@dataclass(slots=True)
class StatusReport:
    camera_index: int
    status: EdgeStatus
    recv_time: float


@dataclass(slots=True)
class DvsSlice:
    """One DVS_CLUSTERS datagram of an event camera, as received."""

    camera_index: int
    msg: DvsClusters
    recv_time: float


@dataclass
class _SeqState:
    expected: int | None = None
    recent: deque = field(default_factory=lambda: deque(maxlen=SEQ_WINDOW))
    recent_set: set = field(default_factory=set)
    missing: OrderedDict = field(default_factory=OrderedDict)
    last_time: float = 0.0  # host time of the last datagram
    before_jump: int | None = None  # what was expected before the last sequence jump


def parse_host_port(value: str) -> tuple[str, int]:
    host, _, port = value.rpartition(":")
    return host, int(port)


class Receiver:
    def __init__(self, rig: RigConfig, bind: str | None = None, split_timeout_s: float = 0.05,
                 rcvbuf_bytes: int = 4 << 20, log=None, sender_switch_s: float = 0.5):
        self.rig = rig
        self.split_timeout_s = split_timeout_s
        self.log = log or (lambda msg: None)
        self.allowed: dict[int, str] = {c.index: str(ipaddress.ip_address(c.edge)) for c in rig.cameras}
        self.allowed_ips = set(self.allowed.values())
        self.stats = ReceiverStats(cameras={i: CameraRecvStats() for i in self.allowed})
        # IMAGE chunks go here when set (the live page's thumbnails); it runs on the tracking thread,
        # so it must only hand the chunk on.
        self.on_image: Callable[[ImageChunk], object] | None = None
        self._seq = {i: _SeqState() for i in self.allowed}
        # (camera, camera_frame, part_count) -> (monotonic time of the first part, part_index -> part)
        self._parts: dict[tuple[int, int, int], tuple[float, dict[int, FeatureFrame]]] = {}
        host, port = parse_host_port(bind or rig.host.listen)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
        except OSError:
            pass
        try:  # each datagram's arrival as the kernel saw it: a stalled host still knows when frames came
            self.sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            pass
        self.sock.bind((host, port))
        self.sock.setblocking(False)
        self.warn = RateLimitedLog(self.log)
        self.sender_switch_s = sender_switch_s
        self._senders: dict[int, list] = {}  # camera -> [port, arrival (host time) last heard]
        self._restarted: set[int] = set()  # cameras whose next frame is the first after a restart
        self._candidates: dict[int, list] = {}  # camera -> [port, held datagrams] of a would-be new sender

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def close(self) -> None:
        self.sock.close()

    # --- receiving ----------------------------------------------------------------------------
    def receive(self, timeout: float, max_batch: int = 256) -> list[CameraFrame | StatusReport | DvsSlice]:
        """Wait up to `timeout` s for datagrams; return what they carried (possibly nothing)."""
        out: list[CameraFrame | StatusReport | DvsSlice] = []
        r, _, _ = select.select([self.sock], [], [], max(0.0, timeout))
        if r:
            now = hostclock.now()
            # Kernel receive stamps are on the real wall clock: mapped to host time by the offset
            # measured now (a wall step between the two reads is caught by the bound below).
            wall_to_host = now - time.time()  # noqa: TID251 - the kernel stamps on the real wall clock
            for _ in range(max_batch):
                try:
                    data, anc, _flags, addr = self.sock.recvmsg(2048, 64)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as exc:  # e.g. ICMP errors surfacing on Linux; keep going
                    self._warn_once(f"socket error: {exc}", key="socket_error")
                    break
                # Read now, not at the batch's start: a batch can take tens of ms on a loaded host
                # (this thread descheduled or waiting for the GIL) and datagrams keep coming in
                # meanwhile. Bounding their kernel stamps by the batch's start, and falling back to
                # it, dated them before they arrived (a frame seemingly 1-6 periods before its
                # trigger pulse); the read time is never earlier than the arrival.
                t = t_read = hostclock.now()
                for level, kind, cdata in anc:
                    if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(cdata) >= 16:
                        sec, nsec = struct.unpack_from("qq", cdata)
                        k = sec + nsec * 1e-9 + wall_to_host
                        if now - 60.0 < k <= t_read:
                            t = k  # when it reached this host, however long it then waited for us
                try:
                    self.handle(data, addr, t, out)
                except Exception as exc:  # a bug on one datagram must not lose the batch
                    self.stats.internal_errors += 1
                    self._warn_once(f"datagram from {addr[0]} could not be handled: {exc!r}",
                                    key=f"internal:{type(exc).__name__}")
        self.expire(time.monotonic(), out)
        return out

    def handle(self, data: bytes, addr: tuple[str, int], now: float,
               out: list[CameraFrame | StatusReport]) -> None:
        """Check and decode one datagram (public so tests and replays can feed bytes directly)."""
        st = self.stats
        st.datagrams += 1
        st.bytes += len(data)
        ip = addr[0]
        if ip not in self.allowed_ips:
            st.rejected_address += 1
            self._warn_once(f"datagram from {ip}, which is no camera's edge in the rig file: rejected",
                            key=f"unknown_address:{ip}")
            return
        try:
            msg = decode_datagram(data)
        except ProtocolError as exc:
            st.errors_by_name[exc.name] = st.errors_by_name.get(exc.name, 0) + 1
            cam = self._cam_for_datagram(data, ip)
            if cam is not None:
                st.cameras[cam].malformed += 1
            else:
                st.malformed_unattributed += 1
            self._warn_once(f"malformed datagram from {ip}: {exc}", key=f"bad:{ip}:{exc.name}")
            return
        cam = getattr(msg, "camera_index", None)
        if cam is None or cam not in self.allowed:
            st.rejected_camera += 1
            self._warn_once(f"datagram for camera index {cam} from {ip}: not in the rig file, rejected",
                            key=f"unknown_camera:{ip}")
            return
        if self.allowed[cam] != ip:
            st.rejected_address += 1
            self._warn_once(f"camera {cam} datagram from {ip}, but the rig file says {self.allowed[cam]}: rejected",
                            key=f"wrong_address:{cam}")
            return
        cs = st.cameras[cam]
        if not self._check_sender(cam, ip, addr[1], data, now, out):
            return
        cs.packets += 1
        if not self._check_seq(cam, msg.seq if hasattr(msg, "seq") else None, now):
            return
        if isinstance(msg, FeatureFrame):
            cs.features += 1
            if msg.part_count > 1:
                self._add_part(msg, now, out)
            else:
                cs.frames += 1
                out.append(self._to_frame(msg, msg.points, now, incomplete=False))
            if cam in self._restarted and out and isinstance(out[-1], CameraFrame) and out[-1].camera_index == cam:
                out[-1].restarted = True
                self._restarted.discard(cam)
        elif isinstance(msg, EdgeStatus):
            cs.status += 1
            cs.status_frames_seen, cs.status_frames_dropped = int(msg.frames_seen), int(msg.frames_dropped)
            out.append(StatusReport(cam, msg, now))
        elif isinstance(msg, DvsClusters):
            cs.dvs_slices += 1
            cs.dvs_clusters += len(msg.clusters)
            out.append(DvsSlice(cam, msg, now))
        else:
            cs.other += 1
            if self.on_image is not None and isinstance(msg, ImageChunk):
                self.on_image(msg)

    def _cam_for_datagram(self, data: bytes, ip: str) -> int | None:
        """Which camera a bad datagram is counted against: the camera_index field (the first
        payload field of FEATURES and STATUS) when it names a camera of this address, else the
        address's only camera."""
        if len(data) >= 10:
            idx = int.from_bytes(data[8:10], "little")
            if self.allowed.get(idx) == ip:
                return idx
        cams = [i for i, a in self.allowed.items() if a == ip]
        return cams[0] if len(cams) == 1 else None

    def _check_sender(self, cam: int, ip: str, port: int, data: bytes = b"", now: float = 0.0,
                      out: list | None = None) -> bool:
        """One sender per camera (see the module doc); False when the datagram is rejected or held.
        Silence is judged on the datagrams' arrival times (`now`, the kernel's stamp), not on when
        this thread got to them: a host stalled for a while takes in the old edge's last datagrams
        and the restarted edge's first ones in one batch, and by the time it handled them the old
        edge had seemed silent for no time at all (at load 15 a restart 0.6 s after the kill was
        rejected as a second sender for 41 frames, then lost)."""
        owner = self._senders.get(cam)
        if owner is None:
            self._senders[cam] = [port, now]
            return True
        if owner[0] == port:
            owner[1] = max(owner[1], now)
            self._candidates.pop(cam, None)
            return True
        silent = now - owner[1]
        if silent >= self.sender_switch_s:
            # The owner went quiet. A new sender takes over once it sent SWITCH_CONFIRM datagrams in a
            # row (a restarted edge does; one stray datagram of a flood does not); they are held until then.
            cand = self._candidates.get(cam)
            if cand is None or cand[0] != port:
                cand = self._candidates[cam] = [port, []]
            cand[1].append((data, (ip, port), now))
            if len(cand[1]) < SWITCH_CONFIRM:
                return False
            del self._candidates[cam]
            self._switch(cam, ip, port, now, silent)
            st = self.stats
            for d, a, t in cand[1][:-1]:  # the held ones, in order, then this one (counted once)
                st.datagrams -= 1  # counted when it came; handled (and counted) now
                st.bytes -= len(d)
                self.handle(d, a, t, out if out is not None else [])
            return True
        self.stats.cameras[cam].second_sender += 1
        self.warn(f"second_sender:{cam}",
                  f"camera {cam}: datagrams from a second sender {ip}:{port} while {ip}:{owner[0]} is sending "
                  f"(two edges with camera index {cam}, or a replay): rejected")
        return False

    def _switch(self, cam: int, ip: str, port: int, now: float, silent: float) -> None:
        owner = self._senders[cam]
        cs = self.stats.cameras[cam]
        cs.restarts += 1
        self._seq[cam] = _SeqState()
        self._restarted.add(cam)
        self.log(f"camera {cam}: edge restarted (new sender {ip}:{port} after {silent:.2f} s without datagrams "
                 f"from port {owner[0]}); mapped again by arrival")
        self._senders[cam] = [port, now]

    def _check_seq(self, cam: int, seq: int | None, now: float) -> bool:
        """Update loss/duplicate/reorder counters; False for a duplicate (dropped). `now` is the
        datagram's host time (a replay passes the recorded one)."""
        if seq is None:
            return True
        s = self._seq[cam]
        cs = self.stats.cameras[cam]
        elapsed, s.last_time = now - s.last_time, now
        if s.expected is None:
            s.expected = (seq + 1) % SEQ_MOD
            self._remember(s, seq)
            return True
        d = (seq - s.expected) % SEQ_MOD
        if d < _HALF:
            if d > 64 + MAX_DATAGRAM_RATE * max(elapsed, 0.0) and d <= FORWARD_RESTART_GAP:
                # More datagrams than the edge could have sent since its last one: the sender's
                # numbering jumped (a misbehaving or replaying edge), nothing was lost.
                cs.seq_jumps += 1
                s.missing.clear()
                s.before_jump = s.expected
                self.warn(f"seq_jump:{cam}", f"camera {cam}: sequence number jumped ahead by {d} in "
                          f"{elapsed * 1e3:.0f} ms (to {seq}): not counted as loss")
            elif d > FORWARD_RESTART_GAP:
                # No link loses a million datagrams in a row: the edge restarted with other numbers.
                cs.restarts += 1
                s.missing.clear()
                self.warn(f"seq_restart:{cam}", f"camera {cam}: sequence number jumped ahead by {d} (to {seq}); "
                          "counted as an edge restart, not as loss")
            else:
                cs.lost += d
                # Remember the newest gaps: a late datagram comes from just before this one.
                for k in range(max(0, d - SEQ_WINDOW), d):
                    s.missing[(s.expected + k) % SEQ_MOD] = None
                while len(s.missing) > SEQ_WINDOW:
                    s.missing.popitem(last=False)
            s.expected = (seq + 1) % SEQ_MOD
            self._remember(s, seq)
            return True
        behind = SEQ_MOD - d
        if seq in s.recent_set:
            cs.duplicated += 1
            return False
        if seq in s.missing:
            del s.missing[seq]
            cs.lost -= 1
            cs.reordered += 1
            self._remember(s, seq)
            return True
        if behind > RESTART_GAP and s.before_jump is not None and 0 <= (seq - s.before_jump) % SEQ_MOD < 1000:
            # Back to the numbering from before the last jump: two streams interleave (a misbehaving
            # or replaying sender on the edge's port), not a restart.
            cs.seq_jumps += 1
            s.before_jump, s.expected = s.expected, (seq + 1) % SEQ_MOD
            self._remember(s, seq)
            return True
        if behind > RESTART_GAP:
            cs.restarts += 1
            self.warn(f"seq_restart:{cam}", f"camera {cam}: sequence numbers restarted ({seq}); edge restarted?")
            s.expected = (seq + 1) % SEQ_MOD
            s.missing.clear()
            self._remember(s, seq)
            return True
        cs.reordered += 1
        self._remember(s, seq)
        return True

    @staticmethod
    def _remember(s: _SeqState, seq: int) -> None:
        if len(s.recent) == s.recent.maxlen:
            s.recent_set.discard(s.recent[0])
        s.recent.append(seq)
        s.recent_set.add(seq)

    # --- split frames -------------------------------------------------------------------------
    def _add_part(self, msg: FeatureFrame, now: float, out: list) -> None:
        key = (msg.camera_index, msg.camera_frame, msg.part_count)
        entry = self._parts.get(key)
        if entry is None:
            entry = self._parts[key] = (time.monotonic(), {})
        parts = entry[1]
        parts[msg.part_index] = msg  # the decoder checked part_index < part_count
        if len(parts) == msg.part_count:
            del self._parts[key]
            try:
                joined = join_feature_parts(list(parts.values()))
            except ProtocolError as exc:
                self._count_malformed(msg.camera_index, exc)
                return
            self.stats.cameras[msg.camera_index].frames += 1
            out.append(self._to_frame(joined, joined.points, now, incomplete=False))

    def _count_malformed(self, cam: int, exc: ProtocolError) -> None:
        st = self.stats
        st.errors_by_name[exc.name] = st.errors_by_name.get(exc.name, 0) + 1
        st.cameras[cam].malformed += 1
        self._warn_once(f"camera {cam}: bad split frame: {exc}", key=f"split:{cam}:{exc.name}")

    def expire(self, mono_now: float, out: list, force: bool = False) -> None:
        """Pass on split frames whose missing parts did not come in time."""
        for key in [k for k, (t0, _) in self._parts.items() if force or mono_now - t0 > self.split_timeout_s]:
            _, parts = self._parts.pop(key)
            ordered = [parts[i] for i in sorted(parts)]
            cs = self.stats.cameras[key[0]]
            cs.split_incomplete += 1
            cs.frames += 1
            pts = np.concatenate([p.points for p in ordered])
            out.append(self._to_frame(ordered[0], pts, hostclock.now(), incomplete=True,
                                      truncated=any(p.truncated for p in ordered)))

    @staticmethod
    def _to_frame(msg: FeatureFrame, points: np.ndarray, now: float, incomplete: bool,
                  truncated: bool | None = None) -> CameraFrame:
        return CameraFrame(
            camera_index=msg.camera_index,
            camera_frame=msg.camera_frame,
            trigger_frame=msg.trigger_frame,
            points=points,
            recv_time=now,
            device_timestamp_ns=msg.device_timestamp_ns,
            edge_recv_ns=msg.edge_recv_ns,
            edge_done_ns=msg.edge_done_ns,
            total_points=msg.total_points,
            truncated=msg.truncated if truncated is None else truncated,
            incomplete=incomplete,
        )

    def _warn_once(self, msg: str, key: str | None = None) -> None:
        """Rate-limited per kind (`key`, else the message), with counts; never stops logging."""
        self.warn(key or msg, msg)
