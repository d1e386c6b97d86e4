"""The clock model against a crystal that is off: a paced simavr run whose MCU clock runs at
f_cpu (1 + (ppm + drift t) 1e-6), queried over the real pty, scored against the harness's truth.

`record_crystal_run` runs the firmware (SimulatedTrigger with ppm/drift), queries its clock as the
host does and returns every query with the true host time of its device sample and of every
trigger edge (simulator.host_time_of_cycle). `score_fit` feeds a ClockModel those queries and
compares it with the truth: the fitted gain against the crystal's true rate at the middle of the
fit's span (for a linearly drifting rate a straight line's slope is the rate there), the host time
it gives each trigger edge within that span against the edge's true time. Used by the firmware
test and by `make bench-trigger-clock`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .clock_model import ClockModel
from .common import TriggerError
from .device import TriggerDevice
from .simulator import SimulatedTrigger, host_time_of_cycle, read_pacing, rising


@dataclass
class CrystalRun:
    ppm: float
    drift_ppm_per_s: float
    anchor: float  # host time at which cycle 0 was due
    frame_period_s: float  # nominal (device) seconds a frame
    host_t0: np.ndarray  # per running query: host time the request was written
    host_t1: np.ndarray  # host time its reply was read
    device_s: np.ndarray  # device time of the sample (s since frame 0 began)
    frame: np.ndarray  # frame count of the reply (frame under way, 1-based)
    true_sample: np.ndarray  # true host time of the device's sample
    edge_true: np.ndarray  # true host time of every trigger rising edge (frame n begins at edge n)
    priority_raised: bool = False  # the harness ran at nice -5
    timeouts: int = 0  # queries whose reply came too late (lost)

    @property
    def sim_behind_s(self) -> np.ndarray:
        """Per query, how far the simulated device was behind the wall clock when it answered, as far
        as it shows: its sample's due time came before the request was even written (> 0). A real
        crystal never lags; a starved simulator does, and its truth is then not the device's time."""
        return self.host_t0 - self.true_sample

    def true_gain(self, host_t: float) -> float:
        """The crystal's host seconds per device second at host time host_t."""
        return 1.0 / (1.0 + (self.ppm + self.drift_ppm_per_s * (host_t - self.anchor)) * 1e-6)


def record_crystal_run(seconds: float, ppm: float = 37.0, drift_ppm_per_s: float = 0.5, fps: float = 100.0,
                       query_period_s: float = 0.01, elf: object = None, harness: object = None) -> CrystalRun:
    """Runs the firmware paced with the given crystal error for `seconds`, querying its clock every
    query_period_s (plus the round trip) over the pty, as TriggerDevice does."""
    from flytrack_host.util.placement import run_as_hardware

    with SimulatedTrigger(elf=elf, harness=harness, realtime=True, ppm=ppm, drift_ppm_per_s=drift_ppm_per_s) as sim:
        # The harness stands for silicon, whose crystal a busy host never delays: it runs ahead of the
        # software under test (nice -5, when allowed), as in the simulated rig (sim/trigger_source.py).
        # Starved (nice 10 at load 8), it fell up to 140 ms behind the wall clock, and the truth with it.
        priority_raised = run_as_hardware(sim.proc.pid)
        # The device's own model is not scored here (score_fit refits): a small window keeps it cheap.
        dev = TriggerDevice(sim.pty, reset_wait_s=0, timeout_s=2.0, model=ClockModel(window=20, max_rtt_s=0.05))
        try:
            dev.set_rate(fps)
            assert dev.rate is not None
            divisor, period = dev.rate.divisor, dev.rate.period_s
            dev.start()
            readings = []
            timeouts = 0
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                try:
                    readings.append(dev.query_clock())
                except TriggerError:
                    # A reply later than the timeout (a starved host): lost, as the clock thread loses it.
                    timeouts += 1
                time.sleep(query_period_s)
            dev.stop()
        finally:
            dev.close()
    f_cpu, edges = sim.edges()
    pacing = read_pacing(sim.edge_log)
    if pacing is None:
        raise RuntimeError("the harness wrote no pacing line: was it run with --realtime?")
    if not np.allclose(pacing[1:], (ppm, drift_ppm_per_s)):
        raise RuntimeError(f"the harness paced {pacing[1:]} (ppm, ppm/s), not the {ppm, drift_ppm_per_s} asked for")
    rises = np.array(rising(edges, "trigger"), dtype=np.float64)
    run = [q for q in readings if q.running and 0 < q.frame_count <= len(rises)]
    cycles = np.array([rises[q.frame_count - 1] + q.ticks * divisor for q in run])
    return CrystalRun(
        ppm=ppm, drift_ppm_per_s=drift_ppm_per_s, anchor=pacing[0], frame_period_s=period,
        host_t0=np.array([q.host_t0 for q in run]), host_t1=np.array([q.host_t1 for q in run]),
        device_s=np.array([q.device_time_s for q in run]), frame=np.array([q.frame_count for q in run]),
        true_sample=np.asarray(host_time_of_cycle(cycles, f_cpu, pacing)),
        edge_true=np.asarray(host_time_of_cycle(rises, f_cpu, pacing)), priority_raised=priority_raised,
        timeouts=timeouts)


def score_fit(run: CrystalRun, model: ClockModel, start: int = 0, stop: int | None = None) -> dict[str, float]:
    """Feeds `model` the run's queries [start, stop) and scores its last fit against the truth."""
    stop = len(run.host_t0) if stop is None else stop
    for i in range(start, stop):
        model.add_sample(float(run.host_t0[i]), float(run.host_t1[i]), float(run.device_s[i]))
    if not model.fitted:
        raise RuntimeError("the clock model has no fit (too few usable queries)")
    model.frame_period_s = run.frame_period_s
    t_lo, t_hi = float(run.host_t0[start]), float(run.host_t1[stop - 1])
    true_gain = run.true_gain(0.5 * (t_lo + t_hi))
    # Trigger edges of the frames the queries covered: frame n (0-based) began at rising edge n.
    frames = np.arange(int(run.frame[start]), int(run.frame[stop - 1]))
    frames = frames[frames < len(run.edge_true)]
    err = model.gain * frames * run.frame_period_s + model.offset - run.edge_true[frames]
    rtt = run.host_t1[start:stop] - run.host_t0[start:stop]
    return {
        "queries": float(stop - start),
        "used": float(model.n_samples),
        "span_s": float(model.span_s),
        "rtt_median_ms": float(np.median(rtt) * 1e3),
        "rtt_p90_ms": float(np.percentile(rtt, 90) * 1e3),
        "gain_err_ppm": (model.gain - true_gain) * 1e6,
        "gain_se_ppm": model.gain_se * 1e6,
        "edges": float(len(frames)),
        "edge_mean_us": float(err.mean() * 1e6),
        "edge_sd_us": float(err.std() * 1e6),
        "edge_max_us": float(np.abs(err).max() * 1e6),
        "sim_behind_max_ms": float(max(0.0, run.sim_behind_s[start:stop].max()) * 1e3),
    }


def score_windows(run: CrystalRun, make_model: Callable[[], ClockModel], window_s: float,
                  step_s: float | None = None) -> list[dict[str, float]]:
    """score_fit over consecutive (or overlapping, step_s) windows of window_s seconds of queries."""
    step_s = step_s or window_s
    out = []
    t = float(run.host_t0[0])
    while True:
        lo = int(np.searchsorted(run.host_t0, t))
        hi = int(np.searchsorted(run.host_t0, t + window_s))
        if t + window_s > run.host_t1[-1] or hi - lo < 10:
            break
        out.append(score_fit(run, make_model(), lo, hi))
        t += step_s
    return out
