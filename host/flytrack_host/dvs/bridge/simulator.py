"""Runs the DVS bridge firmware in simavr through its harness (firmware/dvs_usb/harness/dvs_sim.c).

The harness plays an AER event stream on the firmware's pins with the four-phase handshake, pulses the
sync input, serves the USB seam (bulk packets out, vendor requests in) and logs what happened; this
module writes its inputs, runs it and parses its log into a `BridgeRun`: the bulk words as the host
would receive them, the truth (the cycle each /REQ was asserted, each sync pulse's edge), the
firmware's Timer3 restarts (the epoch of its timestamps) and every vendor request's reply.
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flytrack_host.util import children

REPO_ROOT = Path(__file__).resolve().parents[4]
MCU = "atmega32u4"
F_CPU = 16_000_000
TIMER_DIV = 8  # Timer3 prescaler: 2 ticks per microsecond
USB_FS_PACKET_CYCLES = 842  # 16 MHz / (19 bulk packets per 1 ms frame): full-speed bulk's ceiling

# Vendor requests (firmware/dvs_usb/src/dvs_bridge.h); the DVS128's, plus FlyTrack's status request.
VR_START, VR_STOP, VR_BIASES, VR_RESET_TS, VR_RESET_ARRAY, VR_TS_MASTER, VR_FT_STATUS = (
    0xB3, 0xB4, 0xB8, 0xBB, 0xBD, 0xBE, 0xC8)  # fmt: skip
STATUS_SIZE = 20
VENDOR_OUT, VENDOR_IN = 0x40, 0xC0  # bmRequestType: vendor, device, host-to-device / device-to-host


def build_dir() -> Path:
    return Path(os.environ.get("FLYTRACK_BUILD_DIR", REPO_ROOT / "build"))


def harness_path() -> Path:
    return build_dir() / "bin" / "flytrack_dvs_sim"


def firmware_path() -> Path:
    return build_dir() / "firmware" / MCU / "flytrack_dvs_sim.elf"


def tools_available() -> bool:
    return all(shutil.which(t) for t in ("avr-gcc", "cmake")) and (
        Path("/usr/include/simavr/sim_avr.h").exists() or harness_path().exists()
    )


def build() -> tuple[Path, Path]:
    """Builds the firmware (make) and the harness (cmake); returns (harness, elf)."""
    subprocess.run(["make", "-s", "-C", str(REPO_ROOT / "firmware" / "dvs_usb"), f"OUT={build_dir() / 'firmware'}",
                    str(firmware_path())], check=True, stdout=subprocess.DEVNULL)  # fmt: skip
    b = build_dir()
    if not harness_path().exists():  # (re)configure: the harness's directory may be new to this build tree
        subprocess.run(["cmake", "-S", str(REPO_ROOT), "-B", str(b)], check=True, stdout=subprocess.DEVNULL)
    subprocess.run(["cmake", "--build", str(b), "--target", "flytrack_dvs_sim", "-j", "2"], check=True,
                   stdout=subprocess.DEVNULL)  # fmt: skip
    return harness_path(), firmware_path()


def control_request(cycle: int, request_type: int, request: int, value: int = 0, index: int = 0,
                    length: int = 0, data: bytes = b"") -> tuple[int, bytes]:  # fmt: skip
    """One vendor request for the harness: (cycle, 8 setup bytes + OUT data)."""
    if data and length != len(data):
        raise ValueError("wLength must be the OUT data's length")
    return cycle, struct.pack("<BBHHH", request_type, request, value, index, length) + data


@dataclass
class BridgeStatus:
    overflow: int
    sync_events: int
    sync_missed: int
    clamped: int
    fifo_max: int
    running: bool
    master: bool

    @classmethod
    def parse(cls, b: bytes) -> BridgeStatus:
        if len(b) != STATUS_SIZE:
            raise ValueError(f"status reply of {len(b)} bytes, expected {STATUS_SIZE}")
        o, s, m, c, fmax, run, mas = struct.unpack("<IIIIHBB", b)
        return cls(o, s, m, c, fmax, bool(run), bool(mas))


@dataclass
class Reply:
    cycle: int
    request: int
    ok: bool
    data: bytes


@dataclass
class BridgeRun:
    f_cpu: int
    req_cycles: np.ndarray  # /REQ assertion cycle of each played event, by index
    packets: list[tuple[int, bytes]]  # (cycle handed over, bytes)
    replies: list[Reply]
    sync_cycles: np.ndarray
    timers: list[tuple[int, int, int]]  # (cycle, TCCR3B written, TCNT3 then)
    biases: list[bytes]
    array_resets: list[int]
    violations: list[str]
    end: dict[str, int] = field(default_factory=dict)
    stderr: str = ""

    @property
    def stream(self) -> bytes:
        return b"".join(p for _, p in self.packets)

    def epoch_starts(self) -> np.ndarray:
        """(cycle, tcnt) of every Timer3 start (TCCR3B written with a clock): the timestamp epochs."""
        return np.array([(c, n) for c, v, n in self.timers if v & 7], dtype=np.int64).reshape(-1, 2)

    def truth_us(self, cycles: np.ndarray) -> np.ndarray:
        """Timestamp the firmware's counter held at each cycle, in us, as a real number (its epoch: the
        last Timer3 start at or before the cycle; ticks = tcnt written + elapsed / 8)."""
        ep = self.epoch_starts()
        cycles = np.asarray(cycles, np.int64)
        k = np.searchsorted(ep[:, 0], cycles, side="right") - 1
        if np.any(k < 0):
            raise ValueError("a cycle before the firmware started its timer")
        ticks = ep[k, 1] + (cycles - ep[k, 0]) / TIMER_DIV
        return ticks / 2.0

    def status(self) -> BridgeStatus:
        st = [r for r in self.replies if r.request == VR_FT_STATUS and r.ok]
        if not st:
            raise ValueError("the run has no status reply")
        return BridgeStatus.parse(st[-1].data)


def parse_log(text: str) -> BridgeRun:
    f_cpu = F_CPU
    reqs: dict[int, int] = {}
    run = BridgeRun(f_cpu, np.zeros(0), [], [], np.zeros(0), [], [], [], [])
    syncs: list[int] = []
    for line in text.splitlines():
        if not line:
            continue
        if line.startswith("#"):
            if "f_cpu=" in line:
                run.f_cpu = int(line.split("f_cpu=")[1].split()[0])
            continue
        kind, *rest = line.split()
        if kind == "req":
            reqs[int(rest[0])] = int(rest[1])
        elif kind == "bulk":
            run.packets.append((int(rest[0]), bytes.fromhex(rest[1]) if len(rest) > 1 else b""))
        elif kind == "ctrl":
            run.replies.append(Reply(int(rest[0]), int(rest[1], 16), rest[2] == "ok",
                                     bytes.fromhex(rest[3]) if len(rest) > 3 else b""))  # fmt: skip
        elif kind == "sync":
            syncs.append(int(rest[0]))
        elif kind == "timer":
            run.timers.append((int(rest[0]), int(rest[1]), int(rest[2])))
        elif kind == "bias":
            run.biases.append(bytes.fromhex(rest[0]) if rest else b"")
        elif kind == "array_reset":
            run.array_resets.append(int(rest[0]))
        elif kind == "violation":
            run.violations.append(" ".join(rest))
        elif kind == "end":
            run.end = {"cycle": int(rest[0])} | {k: int(v) for k, v in (r.split("=") for r in rest[1:])}
    run.req_cycles = np.array([reqs[i] for i in range(len(reqs))], dtype=np.int64)
    run.sync_cycles = np.array(syncs, dtype=np.int64)
    return run


def run_bridge(
    events: np.ndarray | None = None,
    controls: list[tuple[int, bytes]] = (),
    *,
    sync: tuple[int, int, int, int] | None = None,
    usb_packet_cycles: int = USB_FS_PACKET_CYCLES,
    req_delay: int = 2,
    next_delay: int = 2,
    banks: int = 2,
    drain_cycles: int = 160_000,
    max_cycles: int = 400_000_000,
    built: tuple[Path, Path] | None = None,
    timeout_s: float = 300.0,
) -> BridgeRun:
    """Plays `events` (structured array with `cycle` = earliest /REQ cycle and `addr` = the word's address
    bytes as u16) and the vendor requests; sync = (period, phase, high, count) in cycles."""
    harness, elf = built or build()
    with tempfile.TemporaryDirectory(prefix="dvs_sim_") as d:
        dd = Path(d)
        cmd = [str(harness), "--elf", str(elf), "--out", str(dd / "out.txt"),
               "--usb-packet-cycles", str(usb_packet_cycles), "--req-delay", str(req_delay),
               "--next-delay", str(next_delay), "--banks", str(banks), "--drain-cycles", str(drain_cycles),
               "--max-cycles", str(max_cycles)]  # fmt: skip
        if events is not None:
            rec = np.empty(len(events), np.dtype([("cycle", "<u4"), ("addr", "<u2")]))
            rec["cycle"] = events["cycle"]
            rec["addr"] = events["addr"]
            (dd / "ev.bin").write_bytes(rec.tobytes())
            cmd += ["--events", str(dd / "ev.bin")]
        if controls:
            (dd / "ctl.txt").write_text("".join(f"{c} {b.hex()}\n" for c, b in controls))
            cmd += ["--control", str(dd / "ctl.txt")]
        if sync:
            period, phase, high, count = sync
            cmd += ["--sync-period", str(period), "--sync-phase", str(phase), "--sync-high", str(high),
                    "--sync-count", str(count)]  # fmt: skip
        p = children.run(cmd, capture_output=True, text=True, timeout=timeout_s)  # ends with this process
        if p.returncode != 0:
            raise RuntimeError(f"flytrack_dvs_sim failed ({p.returncode}): {p.stderr.strip()[-2000:]}")
        run = parse_log((dd / "out.txt").read_text())
        run.stderr = p.stderr
        return run


def aer_events(x: np.ndarray, y: np.ndarray, polarity: np.ndarray, cycle: np.ndarray) -> np.ndarray:
    """The structured array run_bridge plays: address = x << 1 | polarity | y << 8 (SPEC §2's word)."""
    ev = np.empty(len(x), np.dtype([("cycle", "<u4"), ("addr", "<u2")]))
    ev["cycle"] = cycle
    ev["addr"] = (np.asarray(x, np.uint16) << 1) | np.asarray(polarity, np.uint16) | (np.asarray(y, np.uint16) << 8)
    return ev
