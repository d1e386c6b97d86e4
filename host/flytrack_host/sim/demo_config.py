"""The simulated rig's settings (`flytrack demo`'s options), its errors, and the live parts a fault
injector is handed (flytrack_host.sim.faults)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.flight import FlightParams
from flytrack_host.sim.render import RenderParams

ROOT = Path(__file__).resolve().parents[3]
# Frames each camera sends before the trigger starts: the edges take their background from them.
PREROLL_FRAMES = 3


@dataclass
class DemoContext:
    """What a fault injector may touch in a running demo (flytrack_host.sim.faults)."""

    host: Any
    session: Any
    edges: Any
    feeder: Any
    trigger: Any
    cameras: list[Camera]
    port: int
    fps: float
    edge_bin: Path
    out: Path
    lab: Any = None  # the closed loop's lab devices (sim/closed_loop.py ClosedLoopLab), with --rules


class DemoError(RuntimeError):
    """The demo cannot run; the message says which part is missing and how to get it."""


@dataclass
class DemoConfig:
    cameras: int = 5
    animals: int = 3
    fps: float = 100.0
    seconds: float = 10.0
    noise: float = 2.0  # sensor noise, grey levels
    seed: int = 0
    out: Path = field(default_factory=lambda: ROOT / "build" / "demo")
    width: int = 640
    height: int = 480
    trigger: str = "auto"  # auto | simavr | software
    edge_bin: Path | None = None
    firmware: Path | None = None
    match_threshold_m: float = 0.02
    close_distance_m: float = 0.02
    progress: bool = True
    cpus: str = "auto"  # split | share | auto: host and simulated hardware on separate CPUs (sim/placement.py)
    flight: FlightParams = field(default_factory=FlightParams)
    render: RenderParams | None = None
    rules: Path | None = None  # closed-loop rules file (sim/closed_loop.py drives its lab devices)
    # Called with the host pipeline before it starts: live outputs join its sinks (`--serve`).
    attach: list[Callable[[Any], object]] = field(default_factory=list)
    # Fault injection (flytrack_host.sim.faults): an object with start(ctx: DemoContext) and stop(), started
    # once the trigger runs; and the host on a fixed-rate clock instead of the trigger's (--no-trigger).
    fault: Any = None
    host_fixed_clock: bool = False
    dvs: int = 0  # simulated DVS (event) cameras beside the frame cameras (sim/dvs.py)
    dvs_sensor: str = "davis346"  # dvs128 (128 x 128) or davis346 (346 x 260)
    # False for a long run (the soak, sim/soak.py): of each 3D result only the time it came is kept, in an
    # array sized for the run and filled up front, so the process's memory does not grow with the run;
    # no scores against the ground truth (`scores` is None), no tracks figure, no .braidz export.
    score: bool = True
    # Called with the running demo's parts once the trigger has started (the soak's sampler watches them).
    on_running: list[Callable[[DemoContext], object]] = field(default_factory=list)

    def check(self) -> None:
        if not 2 <= self.cameras <= 64:
            raise DemoError(f"--cameras must be 2..64 (3D needs two views), got {self.cameras}")
        if not 1 <= self.animals <= 100:
            raise DemoError(f"--animals must be 1..100, got {self.animals}")
        if not (math.isfinite(self.fps) and 1 <= self.fps <= 1000):
            raise DemoError(f"--fps must be 1..1000, got {self.fps}")
        if not (math.isfinite(self.seconds) and 0.1 <= self.seconds <= 3600):
            raise DemoError(f"--seconds must be 0.1..3600, got {self.seconds}")
        if not (math.isfinite(self.noise) and 0 <= self.noise <= 40):
            raise DemoError(f"--noise must be 0..40 grey levels, got {self.noise}")
        if not 0 <= self.dvs <= 16:
            raise DemoError(f"--dvs must be 0..16 event cameras, got {self.dvs}")
        from flytrack_host.sim.dvs import DVS_SIZES

        if self.dvs_sensor not in DVS_SIZES:
            raise DemoError(f"--dvs-sensor must be one of {', '.join(DVS_SIZES)}, got {self.dvs_sensor!r}")
        if self.cpus not in ("auto", "split", "share"):
            raise DemoError(f"--cpus must be auto, split or share, got {self.cpus!r}")
        if self.trigger not in ("auto", "simavr", "software"):
            raise DemoError(f"--trigger must be auto, simavr or software, got {self.trigger!r}")
