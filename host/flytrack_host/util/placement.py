"""Which CPUs, and at which priority, the simulated rig's parts run.

On a rig the cameras, the edge computers, the trigger box and the lab devices (a PLC, a CAN node) are
machines of their own: the host PC's cores are its own. Simulated on one machine, at each trigger
pulse five edge processes, the camera process, simavr and the Modbus server all wake at once and take
the cores the host needs for that very frame: the host's part of the latency (last datagram -> 3D
estimate) measured 0.68-0.69 ms P50, and a closed-loop rule's acknowledgement 2.35-2.85 ms, against
0.50-0.59 ms and 1.69-2.03 ms with the CPUs split (two 30 s runs each, 6 animals, seeds 1-2, idle
2-core machine, alternated).

So the demo splits the CPUs it may use: the host process (every thread, and what it starts later)
on the first half, every simulated hardware process on the rest (on 2 CPUs: host on one, hardware on
the other). The hardware needs far less than a core (10 s of the default demo: cameras 2.0, edges
0.65, trigger 0.1 CPU seconds); when the cameras need more than their half (`choose_split`), or with
one CPU, all share the CPUs as before (`flytrack demo --cpus share` asks for that).
A process's threads each carry their own affinity on Linux, so every thread of a process is placed,
and new threads inherit their creator's.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

_HARDWARE: frozenset[int] | None = None  # set while a demo runs split (a forked child sees it too)


@dataclass(frozen=True)
class CpuSplit:
    host: frozenset[int]
    hardware: frozenset[int]


def split_cpus(cpus: set[int] | frozenset[int]) -> CpuSplit | None:
    """The host gets the first half (at least one CPU), the simulated hardware the rest; None with
    fewer than two CPUs."""
    s = sorted(cpus)
    if len(s) < 2:
        return None
    k = max(1, len(s) // 2)
    return CpuSplit(frozenset(s[:k]), frozenset(s[k:]))


# Camera frames a second one CPU of simulated hardware keeps up with, with room to spare: a frame costs
# the cameras' process 0.2-0.4 ms to render and its edge 0.1 ms (5 cameras x 100 fps used 0.28 of a CPU;
# 11 x 200 needed more than one, and the cameras fell 0.56 s behind on a CPU of their own).
FRAMES_PER_HARDWARE_CPU = 1000.0


def choose_split(mode: str, camera_frames_per_s: float, cpus: set[int] | None = None) -> tuple[bool, str]:
    """Whether to split ("split", "share", or "auto": when the simulated cameras fit their CPUs), and a
    note when auto decided to share."""
    if mode != "auto":
        return mode == "split", ""
    s = split_cpus(set(os.sched_getaffinity(0)) if cpus is None else cpus)
    if s is None:
        return False, ""
    if camera_frames_per_s > FRAMES_PER_HARDWARE_CPU * len(s.hardware):
        return False, (f"CPUs shared by the host and the simulated hardware: {camera_frames_per_s:.0f} camera "
                       f"frames/s need more than the {len(s.hardware)} CPU(s) a split would give the cameras")
    return True, ""


def threads_of(pid: int) -> list[int]:
    """The thread ids of process `pid` (0: this one); just [pid] when /proc cannot tell."""
    try:
        return [int(t) for t in os.listdir(Path("/proc") / (str(pid) if pid else "self") / "task")]
    except (FileNotFoundError, ProcessLookupError, PermissionError, ValueError):
        return [pid]


def pin(pid: int, cpus: frozenset[int] | set[int]) -> bool:
    """Every thread of process `pid` (0: this one) on `cpus`; False if none could be (gone, or not
    allowed)."""
    done = False
    for tid in threads_of(pid):
        try:
            os.sched_setaffinity(tid, cpus)
            done = True
        except (ProcessLookupError, PermissionError, OSError):
            continue
    return done


def to_hardware(pid: int = 0) -> bool:
    """A simulated hardware process onto the hardware's CPUs, if the running demo split them."""
    return _HARDWARE is not None and pin(pid, _HARDWARE)


class Placement:
    """For the life of a demo run (`with Placement(split=True) as p:`): this process on the host's CPUs,
    `to_hardware(pid)` for each simulated part; on exit this process gets back the CPUs it had."""

    def __init__(self, split: bool = True):
        self.original = frozenset(os.sched_getaffinity(0))
        self.split = split_cpus(self.original) if split else None

    def apply(self) -> Placement:
        """This process onto the host's CPUs; from now on `to_hardware` places the simulated parts."""
        global _HARDWARE
        if self.split is not None and pin(0, self.split.host):
            _HARDWARE = self.split.hardware
        else:
            self.split = None
        return self

    def restore(self) -> None:
        """This process back on the CPUs it had; nothing is placed any more."""
        global _HARDWARE
        _HARDWARE = None
        if self.split is not None:
            pin(0, self.original)

    def __enter__(self) -> Placement:
        return self.apply()

    def __exit__(self, *exc: object) -> None:
        self.restore()

    def describe(self) -> dict[str, list[int]] | None:
        """For the report: which CPUs each side had (None: shared, as when not split)."""
        if self.split is None:
            return None
        return {"host": sorted(self.split.host), "simulated_hardware": sorted(self.split.hardware)}


SIM_NICE = -5


def run_as_hardware(pid: int = 0) -> bool:
    """Run a simulated hardware process (cameras, trigger, an edge, a lab device; 0: this one) ahead
    of, and when the demo splits the CPUs apart from, the software under test.

    Real cameras and trigger boxes are silicon: a busy host PC never delays an exposure. Here they are
    processes sharing the machine with the host, so each of their threads gets a somewhat higher
    priority (nice -5, when allowed) and a loaded machine delays the software under test, not the
    simulated clock; and the hardware's CPUs (`to_hardware`), so they do not take the host's. Returns
    whether the priority was raised."""
    to_hardware(pid)
    raised = False
    for tid in threads_of(pid):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, SIM_NICE)
            raised = True
        except (PermissionError, OSError):
            continue
    return raised
