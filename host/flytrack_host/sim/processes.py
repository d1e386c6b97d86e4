"""The simulated rig's processes: finding and starting one `flytrack-edge` per camera and stopping
them, the CPU each part of the rig uses, and the live subscriber that counts published frames."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.demo_config import DemoError
from flytrack_host.util import children, native


def find_edge_binary(explicit: Path | None = None) -> Path:
    """util.native.find_edge_binary, its error as the demo's (DemoError)."""
    try:
        return native.find_edge_binary(explicit)
    except native.NativeLibraryError as exc:
        raise DemoError(str(exc)) from None


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def edge_command(edge_bin: Path, cam_index: int, cam: Camera, port: int) -> list[str]:
    """The command line of one edge extractor reading raw 8-bit frames from stdin, with the camera's
    calibration for its undistorted coordinates (the same numbers as the calibration file)."""
    K = cam.Kd  # the distortion's K (flydra: intrinsic_linear): undistorted pixels are then P's
    return [
        str(edge_bin),
        "--source", "raw", "--input", "-",
        "--width", str(cam.width), "--height", str(cam.height), "--pixel-format", "mono8",
        "--camera-index", str(cam_index), "--camera-name", cam.name,
        "--host", "127.0.0.1", "--port", str(port), "--control-port", "0",
        "--intrinsics", ",".join(repr(float(x)) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1])),
        "--distortion", ",".join(repr(float(x)) for x in cam.dist),
    ]

class EdgeFleet:
    """One `flytrack-edge` process per camera, frames (or events) on stdin, logs in the output folder; each
    ends with this process, whatever ends it (util.children)."""

    def __init__(self, edge_bin: Path, cameras: list[Camera], port: int, log_dir: Path, first_index: int = 0,
                 command: Callable[[Path, int, Camera, int], list[str]] = edge_command):
        self.procs: list[subprocess.Popen] = []
        self.logs: list[Path] = []
        for i, cam in enumerate(cameras, start=first_index):
            cmd = command(edge_bin, i, cam, port)
            log = log_dir / f"edge_{cam.name}.log"
            self.logs.append(log)
            with open(log, "wb") as lf:
                # Through util.children: an edge ends with the demo, however the demo ends.
                p = children.popen(cmd, stdin=subprocess.PIPE, stdout=lf, stderr=subprocess.STDOUT, close_fds=True)
            self.procs.append(p)

    @property
    def stdin_fds(self) -> list[int]:
        return [p.stdin.fileno() for p in self.procs]  # type: ignore[union-attr]

    def close_stdins(self) -> None:
        """Our copies of the pipes' write ends: the frame feeder holds its own."""
        for p in self.procs:
            if p.stdin is not None:
                with contextlib.suppress(OSError):
                    p.stdin.close()

    def check_started(self) -> None:
        time.sleep(0.2)
        for p, log in zip(self.procs, self.logs, strict=True):
            if p.poll() is not None:
                text = log.read_text(errors="replace")[-2000:]
                raise DemoError(f"flytrack-edge exited at start with code {p.returncode}:\n{text}")

    def wait(self, timeout: float) -> list[int | None]:
        end = time.monotonic() + timeout
        for p in self.procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(0.0, end - time.monotonic()))
        return [p.poll() for p in self.procs]

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(2.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(2.0)

def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a process, from /proc (None when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class CpuSampler:
    """Keeps the last CPU time seen of each part of the simulated rig, so the summary can say where the
    machine's cores went (on a real rig the cameras, trigger and edges have their own hardware)."""

    def __init__(self) -> None:
        self.pids: dict[str, list[int]] = {}
        self.last: dict[int, float] = {}
        self.base: dict[int, float] = {}

    def mark_start(self) -> None:
        """CPU used from now on counts (not the set-up before the trigger starts)."""
        self.sample()
        self.base = dict(self.last)

    def add(self, part: str, pid: int | None) -> None:
        if pid is not None:
            self.pids.setdefault(part, []).append(pid)

    def sample(self) -> None:
        for pids in self.pids.values():
            for pid in pids:
                t = _cpu_seconds(pid)
                if t is not None:
                    self.last[pid] = t

    def totals(self) -> dict[str, float]:
        return {part: round(sum(self.last.get(p, 0.0) - self.base.get(p, 0.0) for p in pids), 2)
                for part, pids in self.pids.items()}


class _LiveCounter:
    """Counts LIVE_ESTIMATES frames published to the rig's live subscriber (a stimulus program)."""

    def __init__(self, port: int, counter: list[int]):
        from flytrack_host.live.udp import LiveClient

        self.client = LiveClient(port=port)
        self.counter = counter
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="sim-live")
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.client.recv(timeout=0.1) is not None:
                self.counter[0] += 1

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(1.0)
        self.client.close()
