"""Runs the trigger firmware in simavr through the C harness (firmware/avr_trigger/harness).

    with SimulatedTrigger(realtime=True) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        ...
    edges = read_edges(sim.edge_log)

The harness writes one line per output edge, `<cycle> <signal> <level>` (signals: trigger, pulse0,
out1..out3, event_in; '#' lines are comments; time = cycle / f_cpu). The edge log path may be a
FIFO (the harness writes it line-buffered), so a simulated rig can follow the real trigger edges
live.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flytrack_host.util import children

from .common import TriggerError

REPO_ROOT = Path(__file__).resolve().parents[3]
MCU_DEFAULT = "atmega328p"


def build_dir() -> Path:
    return Path(os.environ.get("FLYTRACK_BUILD_DIR", REPO_ROOT / "build"))


def harness_path() -> Path:
    return build_dir() / "bin" / "flytrack_trigger_sim"


def firmware_path(mcu: str = MCU_DEFAULT) -> Path:
    return build_dir() / "firmware" / mcu / "flytrack_trigger.elf"


def tools_available() -> bool:
    """avr-gcc and the simavr development files are installed (else use SoftwareTrigger)."""
    return shutil.which("avr-gcc") is not None and shutil.which("pkg-config") is not None and (
        subprocess.run(["pkg-config", "--exists", "simavr", "simavrparts"], check=False).returncode == 0
    )


def strawlab_box_path() -> Path:
    """The strawlab triggerbox stand-in for simavr (firmware/strawlab_box: what the strawlab firmware,
    version 14, does on the wire). FLYTRACK_STRAWLAB_ELF names another ELF to run in its place, for
    example the original firmware built with the Arduino core (docs/compatibility.md)."""
    other = os.environ.get("FLYTRACK_STRAWLAB_ELF")
    return Path(other) if other else build_dir() / "firmware" / "atmega328p" / "strawlab_box.elf"


def build_strawlab_box() -> tuple[Path, Path]:
    """Builds the strawlab box stand-in (make) and the harness (cmake) if missing; returns (harness, elf)."""
    elf = strawlab_box_path()
    if not elf.exists() and "FLYTRACK_STRAWLAB_ELF" not in os.environ:
        subprocess.run(
            ["make", "-s", "-C", str(REPO_ROOT / "firmware" / "strawlab_box"), f"OUT={build_dir() / 'firmware'}"],
            check=True,
        )
    return _build_harness(), elf


def build(mcu: str = MCU_DEFAULT) -> tuple[Path, Path]:
    """Builds the firmware (make) and the harness (cmake) if missing; returns (harness, elf)."""
    elf = firmware_path(mcu)
    if not elf.exists():
        subprocess.run(
            ["make", "-s", "-C", str(REPO_ROOT / "firmware" / "avr_trigger"), f"OUT={build_dir() / 'firmware'}"],
            check=True,
        )
    return _build_harness(), elf


def _build_harness() -> Path:
    harness = harness_path()
    if not harness.exists():
        b = build_dir()
        subprocess.run(["cmake", "-S", str(REPO_ROOT), "-B", str(b), "-Wno-dev"], check=True, capture_output=True)
        subprocess.run(["cmake", "--build", str(b), "--target", "flytrack_trigger_sim", "-j", "2"], check=True)
    return harness


@dataclass(frozen=True)
class Edge:
    cycle: int
    signal: str
    level: int


def read_edges(path: str | Path) -> tuple[int, list[Edge]]:
    """Parses an edge log -> (f_cpu, edges)."""
    f_cpu = 16_000_000
    edges: list[Edge] = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("#"):
            for tok in line.split():
                if tok.startswith("f_cpu="):
                    f_cpu = int(tok[6:])
            continue
        parts = line.split()
        if len(parts) == 3:
            edges.append(Edge(int(parts[0]), parts[1], int(parts[2])))
    return f_cpu, edges


def read_pacing(path: str | Path) -> tuple[float, float, float] | None:
    """(anchor, ppm, drift_ppm_per_s) of a paced run (see read_pacing_anchor and host_time_of_cycle),
    None when the run was not paced."""
    for line in Path(path).read_text().splitlines():
        if line.startswith("# paced"):
            kv = dict(tok.split("=", 1) for tok in line.split()[2:] if "=" in tok)
            return float(kv["t0_realtime"]), float(kv.get("ppm", 0.0)), float(kv.get("drift_ppm_per_s", 0.0))
        elif line and not line.startswith("#"):
            break
    return None


def host_time_of_cycle(cycle: float | np.ndarray, f_cpu: float, pacing: tuple[float, float, float]):  # noqa: ANN201
    """The host time (time.time()) at which a paced run's cycle was due: the harness's crystal runs at
    f_cpu (1 + (ppm + drift t) 1e-6), t the seconds since the anchor (trigger_sim.c, --ppm)."""
    anchor, ppm, drift = pacing
    a, b = 0.5e-6 * drift, 1.0 + 1e-6 * ppm
    x = np.asarray(cycle, dtype=np.float64) / f_cpu
    t = x / b if a == 0 else 2.0 * x / (b + np.sqrt(b * b + 4.0 * a * x))
    return anchor + t


def read_pacing_anchor(path: str | Path) -> float | None:
    """The host time (time.time()) at which a paced run's cycle 0 was due, or None when the run was
    not paced: cycle c of that run happened at anchor + c / f_cpu on the host's clock, to within
    the pacing's slack."""
    for line in Path(path).read_text().splitlines():
        if line.startswith("# paced"):
            for tok in line.split():
                if tok.startswith("t0_realtime="):
                    return float(tok[len("t0_realtime="):])
        elif line and not line.startswith("#"):
            break
    return None


class SimulatedTrigger:
    """The simavr harness running the real firmware; `pty` is its serial port, `edge_log` its edges."""

    def __init__(
        self,
        elf: str | Path | None = None,
        mcu: str = MCU_DEFAULT,
        realtime: bool = False,
        edge_log: str | Path | None = None,
        max_seconds: float | None = None,
        event_period_cycles: int = 0,
        event_phase_cycles: int = 0,
        event_high_cycles: int = 0,
        harness: str | Path | None = None,
        ppm: float = 0.0,
        drift_ppm_per_s: float = 0.0,
    ) -> None:
        if harness is None or elf is None:
            h, e = build(mcu)
            harness = harness or h
            elf = elf or e
        self._tmp = tempfile.TemporaryDirectory(prefix="flytrack-sim-")
        self.edge_log = Path(edge_log) if edge_log else Path(self._tmp.name) / "edges.log"
        cmd = [str(harness), "--elf", str(elf), "--mcu", mcu, "--edges", str(self.edge_log)]
        if realtime:
            cmd.append("--realtime")
            if ppm or drift_ppm_per_s:  # a crystal off its nominal frequency (paced runs only)
                cmd += ["--ppm", repr(float(ppm)), "--drift-ppm-per-s", repr(float(drift_ppm_per_s))]
        if max_seconds:
            cmd += ["--max-seconds", str(max_seconds)]
        if event_period_cycles:
            cmd += ["--event-period", str(event_period_cycles), "--event-phase", str(event_phase_cycles),
                    "--event-high", str(event_high_cycles)]
        self._stderr_path = Path(self._tmp.name) / "stderr.log"
        self._stderr = open(self._stderr_path, "w")  # noqa: SIM115 - lives as long as the process
        # Through util.children: the harness ends with this process, however it ends.
        self.proc = children.popen(cmd, stdout=subprocess.PIPE, stderr=self._stderr, text=True)
        self.pty = self._wait_pty()

    def _wait_pty(self, timeout_s: float = 10.0) -> str:
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if line.startswith("PTY "):
                return line.split(None, 1)[1].strip()
            if not line and self.proc.poll() is not None:
                break
        self.stop()
        raise TriggerError(f"simulator did not start: {self.stderr_text()}")

    def stderr_text(self) -> str:
        if not self._stderr.closed:
            self._stderr.flush()
        return self._stderr_path.read_text() if self._stderr_path.exists() else ""

    def stop(self, timeout_s: float = 5.0) -> int:
        """Stops the harness (SIGTERM, then SIGKILL) and returns its exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout:
            self.proc.stdout.close()
        self._stderr.close()
        return self.proc.returncode

    def edges(self) -> tuple[int, list[Edge]]:
        return read_edges(self.edge_log)

    def close(self) -> None:
        self.stop()
        self._tmp.cleanup()

    def __enter__(self) -> SimulatedTrigger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def rising(edges: Iterable[Edge], signal_name: str) -> list[int]:
    return [e.cycle for e in edges if e.signal == signal_name and e.level == 1]
