"""`flytrack demo`: the simulated rig, end to end, through every real part.

    flight model -> trigger (firmware in simavr, or the software trigger) -> rendered camera frames
    -> one real `flytrack-edge` process per camera (frames on its stdin) -> UDP feature datagrams on
    loopback -> the real host pipeline (receive, synchronise, track, record, publish live)
    -> scores against ground truth, latency, a figure, a summary table.

The pieces are started in an order that matters: edge processes first, then the frame feeder (a
forked child, so before any thread exists here) following the trigger's edge FIFO, then the trigger
box (simavr opens that FIFO), the rig file, the host's TriggerSession (stop-and-reset, exact rate)
and HostPipeline, a few pre-roll frames (the edges take their background; the host sees the cameras
go quiet), and last the session's start: frame-0 tie armed, START; the first pulse is trigger frame 0
and every camera's next frame.
"""

from __future__ import annotations

import collections
import contextlib
import json
import math
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.camera import Camera
from flytrack_host.evaluation import FrameTracks, TrackingScores, score_tracks
from flytrack_host.sim.flight import Arena, FlightParams, GroundTruth, simulate_flight
from flytrack_host.sim.frames import FrameFeeder, raise_priority
from flytrack_host.sim.goals import check_goals
from flytrack_host.sim.metrics import latency_percentiles_ms
from flytrack_host.sim.render import RenderParams
from flytrack_host.sim.rig import make_cameras, rig_config, write_rig
from flytrack_host.sim.trigger_source import DemoTrigger

ROOT = Path(__file__).resolve().parents[3]
# Frames each camera sends before the trigger starts: the edges take their background from them.
PREROLL_FRAMES = 3


@dataclass
class DemoContext:
    """What a fault injector may touch in a running demo (flytrack_host.faults)."""

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
    flight: FlightParams = field(default_factory=FlightParams)
    render: RenderParams | None = None
    rules: Path | None = None  # closed-loop rules file (sim/closed_loop.py drives its lab devices)
    # Called with the host pipeline before it starts: live outputs join its sinks (`--serve`).
    attach: list[Callable[[Any], object]] = field(default_factory=list)
    # Fault injection (flytrack_host.faults): an object with start(ctx: DemoContext) and stop(), started
    # once the trigger runs; and the host on a fixed-rate clock instead of the trigger's (--no-trigger).
    fault: Any = None
    host_fixed_clock: bool = False
    dvs: int = 0  # simulated DVS (event) cameras beside the frame cameras (sim/dvs.py)
    dvs_sensor: str = "davis346"  # dvs128 (128 x 128) or davis346 (346 x 260)

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
        if self.trigger not in ("auto", "simavr", "software"):
            raise DemoError(f"--trigger must be auto, simavr or software, got {self.trigger!r}")


@dataclass
class HostResult:
    frame: int
    t_result: float
    ids: np.ndarray
    pos: np.ndarray


@dataclass
class DemoReport:
    config: dict[str, Any]
    trigger: str
    trigger_note: str
    scores: TrackingScores
    latency: dict[str, float]  # hand-over to 3D estimate (exposure and transfer are simulated)
    latency_parts_p50_ms: dict[str, float]
    trigger_time_bias_ms: float  # host's trigger time (clock model) minus when the pulse happened
    latency_host: dict[str, float]  # the host's own figure: trigger time (clock model) -> estimate
    frames_triggered: int
    frames_rendered: int
    frames_tracked: int
    frames_in_time: int
    packets_lost: int
    packets_late: int
    frames_misnumbered: int  # camera frames the host's synchroniser gave a wrong trigger frame
    camera_frames_sent: int  # frames handed to the edges (pre-roll excluded)
    camera_frames_received: int  # FEATURES frames the host's receiver took in before it stopped
    exposure_lateness: dict[str, float]  # hand-over vs an ideal clock: how faithful the simulated timing was
    clock_model: dict[str, Any]  # the host's trigger session summary (rate, clock model fit, samples)
    sim_priority_raised: bool
    world: dict[str, Any]  # what the flight model did: saccades, landings, close passes
    live_frames: int
    render_realtime_factor: float
    host_kept_up: bool
    recording: str | None
    braidz: str | None
    figure: str | None
    rig_file: str
    calibration: str | None
    wall_s: float
    notes: list[str] = field(default_factory=list)
    host_summary: dict[str, Any] = field(default_factory=dict)
    cpu_seconds: dict[str, float] = field(default_factory=dict)  # per part of the simulated rig
    actuation: dict[str, Any] = field(default_factory=dict)  # closed loop vs ground truth (with --rules)
    dvs: list[dict[str, Any]] = field(default_factory=list)  # per DVS camera: events sent and received
    # the same bundles tracked with and without the DVS cameras' points (eventcam.comparison)
    dvs_comparison: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["scores"] = self.scores.as_dict()
        return d


# --- parts ---------------------------------------------------------------------------------------
def find_edge_binary(explicit: Path | None = None) -> Path:
    cands = [explicit] if explicit else []
    env = os.environ.get("FLYTRACK_BUILD_DIR")
    if env:
        cands.append(Path(env) / "edge" / "feature_extractor" / "flytrack-edge")
    cands.append(ROOT / "build" / "edge" / "feature_extractor" / "flytrack-edge")
    which = shutil.which("flytrack-edge")
    if which:
        cands.append(Path(which))
    for c in cands:
        if c is not None and c.is_file() and os.access(c, os.X_OK):
            return c
    raise DemoError(
        "the edge extractor `flytrack-edge` is not built (looked in "
        + ", ".join(str(c) for c in cands if c)
        + "); run `make build`"
    )


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


# DVS slice length in the demo: 2 slices per 100 fps frame keeps the host's datagram load low (1 ms
# slices are 1000 datagrams/s per DVS camera for the Python receiver).
DVS_SLICE_US = 5000


def dvs_edge_command(edge_bin: Path, cam_index: int, cam: Camera, port: int,
                     slice_us: int = DVS_SLICE_US) -> list[str]:
    """The command line of one edge reading a DVS camera's event stream (EVT 2.0) from stdin."""
    return [
        str(edge_bin), "--source", "events", "--input", "-",
        "--camera-index", str(cam_index), "--camera-name", cam.name,
        "--host", "127.0.0.1", "--port", str(port), "--control-port", "0", "--slice-us", str(slice_us),
        "--realtime", "0",  # the events come as they happen: no pacing by their times on top
    ] + dvs_support_options(cam.width, cam.height)


def dvs_support_options(width: int, height: int) -> list[str]:
    """The edge's noise-filter window and cluster support for a sensor smaller than a DAVIS346 (the
    library defaults' class): an animal crosses s = 346 / side times fewer pixels, so it gives s times
    fewer events (support / s) and each pixel's neighbours fire sparser and later (window x s^2; the
    simulated background activity, 0.05 Hz per pixel, lets 8 x 0.05 Hz x 14.6 ms = 0.6 % of the noise
    through at 128 px). With the defaults a 128 x 128 sensor found 6 clusters in 2 s."""
    side = max(int(width), int(height))
    if side <= 0 or side >= 346:
        return []
    s = 346.0 / side
    return ["--ba-window-us", str(round(2000 * s * s)), "--cluster-min-mass", f"{5.0 / s:.3f}"]


class EdgeFleet:
    """One `flytrack-edge` process per camera, frames (or events) on stdin, logs in the output folder."""

    def __init__(self, edge_bin: Path, cameras: list[Camera], port: int, log_dir: Path, first_index: int = 0,
                 command: Callable[[Path, int, Camera, int], list[str]] = edge_command):
        self.procs: list[subprocess.Popen] = []
        self.logs: list[Path] = []
        for i, cam in enumerate(cameras, start=first_index):
            cmd = command(edge_bin, i, cam, port)
            log = log_dir / f"edge_{cam.name}.log"
            self.logs.append(log)
            with open(log, "wb") as lf:
                p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=lf, stderr=subprocess.STDOUT,
                                     close_fds=True)
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


# --- the run -------------------------------------------------------------------------------------
def run_demo(cfg: DemoConfig, console: Any = None) -> DemoReport:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    cfg.check()
    console = console or Console()
    wall0 = time.monotonic()
    out = Path(cfg.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    notes: list[str] = []
    for old in ("recording.flytrack", "recording.braidz"):  # this demo's own previous output
        p = out / old
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()

    # 1. World: flight, cameras, calibration, rig file.
    arena = Arena()
    gt = simulate_flight(cfg.animals, cfg.seconds, cfg.fps, seed=cfg.seed, arena=arena, params=cfg.flight)
    cams = make_cameras(cfg.cameras, arena, seed=cfg.seed, width=cfg.width, height=cfg.height)
    dvs_cams: list[Camera] = []
    if cfg.dvs:
        from flytrack_host.sim.dvs import make_dvs_cameras

        dvs_cams = make_dvs_cameras(cfg.dvs, arena, cfg.seed, cfg.dvs_sensor)
    calib_path = _write_calibration(cams + dvs_cams, out / "calibration.xml", notes)
    edge_bin = find_edge_binary(cfg.edge_bin)
    port = _free_udp_port()
    live_port = _free_udp_port()
    render_params = cfg.render or RenderParams(noise_sigma=cfg.noise)
    # The edges take their background from pre-roll frames sent before the trigger starts, so the
    # animals are in the picture from trigger frame 0.
    preroll = PREROLL_FRAMES
    warmup = 0
    trig = DemoTrigger(cfg.trigger, cfg.fps, out, firmware=cfg.firmware)
    notes.append(trig.note)

    cpu = CpuSampler()
    cpu.add("host", os.getpid())
    edges = dvs_edges = feeder = host = live = session = lab = engine = None
    trigger_summary: dict[str, Any] = {}
    results: list[HostResult] = []
    live_frames = [0]
    rig_path = out / "rig.toml"
    try:
        # 2. Edge extractors, then the frame feeder (it forks: no thread may exist yet), which then
        #    follows the trigger's edge FIFO.
        edges = EdgeFleet(edge_bin, cams, port, out)
        dvs_links: list[tuple[Any, int]] = []  # (width, height, chunks), edge stdin
        if dvs_cams:
            from flytrack_host.sim.dvs import DvsRenderer, render_stream

            dvs_edges = EdgeFleet(edge_bin, dvs_cams, port, out, first_index=len(cams), command=dvs_edge_command)
            # Each sensor's clock has its own epoch (as a real DVS's): only the sync events tie it to frames.
            # Rendered ahead, the whole run (the flight is known): a pulse then costs a write.
            dvs_links = [((c.width, c.height, render_stream(
                DvsRenderer(c, seed=cfg.seed * 1000 + 500 + i, t0_us=1_000_000 * (i + 1) + 12_345), gt, warmup)), fd)
                for i, (c, fd) in enumerate(zip(dvs_cams, dvs_edges.stdin_fds, strict=True))]
        feeder = FrameFeeder(gt, cams, edges.stdin_fds, render_params, cfg.seed, warmup_frames=warmup, dvs=dvs_links)
        edges.close_stdins()
        edges.check_started()
        if dvs_edges is not None:
            dvs_edges.close_stdins()
            dvs_edges.check_started()
            for p in dvs_edges.procs:
                cpu.add("edges", p.pid)
                raise_priority(p.pid)
        for p in edges.procs:
            cpu.add("edges", p.pid)
            # On a rig each edge has its own computer: here they run at the simulated hardware's
            # priority, so only the host competes with the rest of this machine.
            raise_priority(p.pid)
        cpu.add("simulated cameras", feeder.pid)
        feeder.set_source(str(trig.fifo))

        # 3. Trigger box, rig file, then the host as `flytrack run` does it: trigger session open
        #    (stop-and-reset, exact rate), pipeline, session start (quiet cameras, frame-0 tie, START).
        trig.launch()
        cpu.add("simulated trigger", trig.sim.proc.pid if trig.sim is not None else None)
        rig = rig_config(
            cams, cfg.fps, dvs_cameras=dvs_cams, listen=f"127.0.0.1:{port}", trigger_kind=trig.kind,
            trigger_port=trig.port,
            calibration=calib_path.name if calib_path else None, recording_folder="recordings",
            live_subscribers=[f"127.0.0.1:{live_port}"], name="simulated-rig",
        )
        if cfg.rules is not None:  # the closed loop: lab devices on loopback, the rules in the rig file
            from flytrack_host.actuation.rules import RulesError
            from flytrack_host.sim.closed_loop import ClosedLoopLab

            try:
                lab = ClosedLoopLab(cfg.rules, out)
            except RulesError as exc:
                raise DemoError(str(exc)) from None
            rig = lab.rig(rig)
        write_rig(rig, rig_path)
        from flytrack_host.pipeline import HostPipeline
        from flytrack_host.rig import load_rig
        from flytrack_host.trigger.common import TriggerError
        from flytrack_host.trigger_session import TriggerSession

        rig = load_rig(rig_path)  # exactly what a user's host would read
        cameras_for_host = _host_cameras(rig, cams, calib_path)
        session = TriggerSession(rig.trigger)
        try:
            fps = session.open()
        except TriggerError as exc:
            session = None
            raise DemoError(f"the trigger ({trig.kind_label}) did not open: {exc}") from None

        def on_result(r: Any) -> None:
            ids = np.fromiter((e.obj_id for e in r.estimates), dtype=np.int64, count=len(r.estimates))
            pos = np.array([e.state[:3] for e in r.estimates], dtype=np.float64).reshape(-1, 3)
            # compared with the simulated cameras' stamps (sim/frames.py), made in other processes
            results.append(HostResult(int(r.trigger_frame), time.time(), ids, pos))  # noqa: TID251

        host = HostPipeline(rig, cameras_for_host, clock=None if cfg.host_fixed_clock else session.clock, fps=fps,
                            hold_until_synchronized=True,
                            on_result=on_result, rig_text=rig_path.read_text(),
                            recording_path=out / "recording.flytrack")
        if dvs_cams:  # every bundle, for the side-by-side with and without the DVS cameras
            host.dvs_bundles = collections.deque(maxlen=gt.n_frames + 16)
        if lab is not None:
            try:
                engine = lab.engine(rig, fps, session)
            except RulesError as exc:
                raise DemoError(str(exc)) from None
        for fn in cfg.attach:
            try:
                fn(host)
            except OSError as exc:
                raise DemoError(f"a live output could not start: {exc}") from None
        host.start()
        if engine is not None:  # after start: its messages go into the recording's log too
            engine.attach(host)
            engine.start()
        session.attach(host)
        live = _LiveCounter(live_port, live_frames)
        trig.follow_software(session.software)
        feeder.preroll(preroll)
        t_wait = time.monotonic() + 5.0
        while host.last_frame_recv == 0.0 and time.monotonic() < t_wait:
            time.sleep(0.01)
        cpu.mark_start()
        session.start(host)  # waits until the cameras are quiet, arms the frame-0 tie, STARTs
        if cfg.fault is not None:
            cfg.fault.start(DemoContext(host, session, edges, feeder, trig, cams, port, fps, edge_bin, out))

        # 4. Run until every frame was rendered, with a progress bar.
        budget = cfg.seconds * 4 + 30
        t_end = time.monotonic() + budget
        with Progress(TextColumn("[bold]simulated rig[/bold]"), BarColumn(), TextColumn("{task.description}"),
                      TimeRemainingColumn(), console=console, disable=not cfg.progress, transient=True) as prog:
            task = prog.add_task("", total=gt.n_frames)
            while not feeder.done and feeder.alive() and time.monotonic() < t_end:
                time.sleep(0.1)
                cpu.sample()
                prog.update(task, completed=feeder.frames_rendered,
                            description=f"frames {feeder.frames_rendered}/{gt.n_frames}  tracked {len(results)}")
            prog.update(task, completed=feeder.frames_rendered)
        if not feeder.done:
            notes.append(f"the run did not finish within {budget:.0f} s; stopped early")
        cpu.sample()
        session.stop()  # the trigger stops (the cameras with it); the host then tracks what is pending
        trigger_summary = session.summary()
        session = None
        feeder.finish()
        t_wait = time.monotonic() + 5.0
        all_procs = edges.procs + (dvs_edges.procs if dvs_edges is not None else [])
        while time.monotonic() < t_wait and any(p.poll() is None for p in all_procs):
            cpu.sample()  # the feeder closed their stdin: they finish their frames and exit
            time.sleep(0.02)
        time.sleep(max(0.2, 3.0 / cfg.fps))  # the last datagrams
        cpu.sample()
    finally:
        if cfg.fault is not None:
            cfg.fault.stop()
        if session is not None:
            session.stop()
            trigger_summary = session.summary()
        host_summary = host.stop() if host is not None else {}
        if live is not None:
            live.stop()
        if edges is not None:
            edges.stop()
        if dvs_edges is not None:
            dvs_edges.stop()
        if feeder is not None:
            feeder.stop()
        trig.close()
        if lab is not None and engine is None:
            lab.close()

    fs = feeder.stats()
    report = _report(cfg, gt, rig_path, calib_path, trig, fs, results, host_summary, live_frames[0], out,
                     notes, wall0, cams, warmup, trigger_summary, preroll)
    report.cpu_seconds = cpu.totals()
    report.dvs = _dvs_counts(dvs_cams, len(cams), fs, host_summary, cfg.dvs_sensor)
    if any(d["events_lost"] for d in report.dvs):
        report.notes.append("DVS events lost between the simulated sensors and the host: "
                            + ", ".join(f"{d['name']} {d['events_lost']}" for d in report.dvs))
    if dvs_cams and host is not None and host.dvs_bundles:
        report.dvs_comparison = _dvs_comparison(cfg, gt, cams, warmup, host,
                                                range(len(cams), len(cams) + len(dvs_cams)))
    if lab is not None and engine is not None:
        try:
            report.actuation = lab.report(engine, gt, fs.pulse_frames if trig.mode == "simavr" else None)
        finally:
            lab.close()
    return report


def _dvs_comparison(cfg: DemoConfig, gt: GroundTruth, cams: list[Camera], warmup: int, host: Any,
                    dvs_indices: range) -> dict[str, Any]:
    """The run's bundles tracked again, with and without the DVS cameras' points, scored alike."""
    from flytrack_host.eventcam.comparison import with_and_without

    runs = with_and_without(list(host.dvs_bundles), host.cameras, host.params, 1.0 / cfg.fps, dvs_indices)
    scored = _scored_mask(gt, cams)
    scored[:warmup] = False
    out: dict[str, Any] = {"bundles": len(host.dvs_bundles)}
    for name, run in runs.items():
        hyps = [FrameTracks(f, ids, pos) for f, ids, pos in run.frames if 0 <= f < gt.n_frames]
        sc = score_tracks(gt.pos, hyps, scored=scored, close=gt.close_frames(cfg.close_distance_m),
                          match_threshold_m=cfg.match_threshold_m, close_window=int(round(0.1 * cfg.fps)))
        out[name] = {"rmse_mm": sc.rmse_mm, "mota": sc.mota, "idf1": sc.idf1, "id_switches": sc.id_switches,
                     "false_positives": sc.false_positives, "misses": sc.misses,
                     "dvs_points": int(run.stats.get("own_cov_points", 0)),
                     "dvs_points_used": int(run.stats.get("own_cov_used", 0)),
                     "dvs_points_gated_out": int(run.stats.get("own_cov_gated_out", 0))}
    return out


def _dvs_counts(dvs_cams: list[Camera], first: int, fs: Any, host_summary: dict[str, Any],
                sensor: str) -> list[dict[str, Any]]:
    """Per DVS camera: events (and sync events) the simulated sensor wrote into its edge, and what the
    host heard back: the events the edge read (its last STATUS), its slices and clusters."""
    recv = host_summary.get("receiver", {}).get("cameras", {})
    out = []
    for i, c in enumerate(dvs_cams):
        r = recv.get(first + i, recv.get(str(first + i), {}))
        obs = host_summary.get("dvs", {})
        o = obs.get(first + i, obs.get(str(first + i), {}))
        sent = int(fs.dvs_events_sent[i]) if i < len(fs.dvs_events_sent) else 0
        got = int(r.get("status_frames_seen", 0))
        out.append({
            "name": c.name, "camera_index": first + i, "sensor": sensor, "width": c.width, "height": c.height,
            "events_sent": sent, "sync_events_sent": int(fs.dvs_syncs_sent[i]) if i < len(fs.dvs_syncs_sent) else 0,
            "events_received": got, "events_lost": sent - got,
            "edge_events_dropped": int(r.get("status_frames_dropped", 0)),
            "slices_received": int(r.get("dvs_slices", 0)), "clusters_received": int(r.get("dvs_clusters", 0)),
            "datagrams_lost": int(r.get("lost", 0)),
            # What the 3D tracker got from this camera: trigger frames with its clusters, and points
            "frames_observed": int(o.get("frames_given", 0)), "points_observed": int(o.get("points_given", 0)),
            "points_used": int(o.get("points_used", 0)),
            "sensor_t0_us_estimated": o.get("t0_us"),
        })
    return out


def _write_calibration(cams: list[Camera], path: Path, notes: list[str]) -> Path | None:
    try:
        from flytrack_host.calibration.formats import save_flydra_xml
    except ImportError:
        notes.append("calibration writer missing: the host got the cameras directly")
        return None
    save_flydra_xml({c.name: c for c in cams}, path)
    return path


def _host_cameras(rig: Any, cams: list[Camera], calib_path: Path | None) -> dict[int, Camera]:
    """Cameras for the host, read back from the calibration file when there is one (as a user's)."""
    by_name = {c.name: c for c in cams}
    if calib_path is not None:
        from flytrack_host.calibration.formats import load_calibration

        by_name = load_calibration(calib_path)
    return {c.index: by_name[c.calib_name] for c in rig.cameras}


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
        from flytrack_host.live import LiveClient

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


# --- results -------------------------------------------------------------------------------------
def _scored_mask(gt: GroundTruth, cams: list[Camera]) -> np.ndarray:
    """An animal counts in a frame when at least two cameras see it (else nobody can place it)."""
    seen = np.zeros(gt.landed.shape, dtype=np.int32)
    flat = gt.pos.reshape(-1, 3)
    for c in cams:
        seen += c.in_view(flat, margin=2.0).reshape(gt.landed.shape)
    return seen >= 2


def _report(cfg: DemoConfig, gt: GroundTruth, rig_path: Path, calib_path: Path | None, trig: Any, fs: Any,
            results: list[HostResult], host_summary: dict[str, Any], live_frames: int, out: Path,
            notes: list[str], wall0: float, cams: list[Camera], warmup: int,
            trigger_summary: dict[str, Any], preroll: int) -> DemoReport:
    from flytrack_host.sim.plot import plot_tracks

    hyps = [FrameTracks(r.frame, r.ids, r.pos) for r in results if 0 <= r.frame < gt.n_frames]
    scored = _scored_mask(gt, cams)
    scored[:warmup] = False  # animals not drawn yet: the edges were taking their background
    scores = score_tracks(gt.pos, hyps, scored=scored, close=gt.close_frames(cfg.close_distance_m),
                          match_threshold_m=cfg.match_threshold_m, close_window=int(round(0.1 * cfg.fps)))
    recording = host_summary.get("recording")
    # The clock model's bias is judged against when each pulse happened (paced simavr states it);
    # with the software trigger, against when the cameras read it.
    truth_edges = fs.edge_true_time if np.any(np.isfinite(fs.edge_true_time)) else fs.edge_time
    numbering = _frame_numbering(recording, fs.written_time, preroll, truth_edges)
    if numbering["misnumbered"]:
        notes.append(f"the host's synchroniser gave {numbering['misnumbered']} of {numbering['camera_frames']} "
                     "camera frames a wrong trigger frame number (scores use the host's numbers)")
    if host_summary.get("behind_skipped"):  # the bounded backlog of an overloaded host (issue 16)
        notes.append(f"the host fell more than 1 s behind real time: {host_summary['behind_skipped']} frames were "
                     "recorded but not tracked, so that it caught up")
    # Latency from the hand-over of the frames a bundle was made of to its estimate: independent of
    # the numbering, so a misnumbered frame still gets its true processing time.
    lat = []
    for r in results:
        t0 = numbering["bundle_handoff"].get(r.frame, math.nan)
        if math.isfinite(t0):
            lat.append(r.t_result - t0)
    lat_a = np.asarray(lat)
    res_t = np.full(gt.n_frames, np.nan)
    for r in results:
        if 0 <= r.frame < gt.n_frames:
            res_t[r.frame] = r.t_result
    # Per-frame timing and the ground truth, for whoever wants to look closer than the summary.
    np.savez(out / "frame_timing.npz", trigger_edge=fs.edge_time, handoff=fs.handoff_time, estimate=res_t)
    np.savez(out / "ground_truth.npz", t=gt.t, pos=gt.pos, vel=gt.vel, axis=gt.axis, landed=gt.landed,
             fps=gt.fps, warmup_frames=warmup)
    period = 1.0 / cfg.fps
    in_time = int(np.sum(lat_a < period)) if lat_a.size else 0
    recv = host_summary.get("receiver", {}).get("cameras", {})
    sync = host_summary.get("sync", {})
    lost = sum(int(c.get("lost", 0)) for c in recv.values())
    late = sum(int(s.get("late", 0)) for s in sync.values()) if isinstance(sync, dict) else 0
    hl = host_summary.get("latency", {})
    latency_host = {k.removeprefix("total_"): v for k, v in hl.items() if k.startswith("total_")}
    rendered_s = fs.frames_rendered / cfg.fps
    busy = fs.render_s + fs.write_s
    rt = rendered_s / busy if busy > 0 else float("inf")
    braidz = _export_braidz(recording, out, notes)
    title = (f"{cfg.cameras} cameras, {cfg.animals} animals\n{cfg.fps:g} fps, {cfg.seconds:g} s, seed {cfg.seed}\n\n"
             f"RMSE {scores.rmse_mm:.2f} mm\nMOTA {scores.mota:.3f}\nIDF1 {scores.idf1:.3f}\n"
             f"ID switches {scores.id_switches}\ntracks {scores.tracks_found}")
    dvs_obs = host_summary.get("dvs", {})
    if dvs_obs:  # which observations came from event cameras
        title += "\n\nDVS points used\n" + "\n".join(
            f"cam {i}: {v.get('points_used', 0)} in {v.get('frames_given', 0)} fr." for i, v in dvs_obs.items())
    fig = plot_tracks(gt, hyps, out / "tracks.png", title=title, latencies_ms=lat_a * 1e3)
    frames_triggered = max(fs.edges, fs.frames_rendered)
    return DemoReport(
        config={f.name: (str(v) if isinstance(v, Path) else v) for f in fields(cfg)
                if f.name not in ("flight", "render", "attach", "fault") for v in [getattr(cfg, f.name)]},
        trigger=trig.kind_label,
        trigger_note=trig.note,
        scores=scores,
        latency=latency_percentiles_ms(lat_a),
        latency_parts_p50_ms=numbering["parts_p50_ms"],
        trigger_time_bias_ms=numbering["trigger_time_bias_ms"],
        latency_host=latency_host,
        frames_triggered=min(frames_triggered, gt.n_frames),
        frames_rendered=fs.frames_rendered,
        frames_tracked=len(hyps),
        frames_in_time=in_time,
        packets_lost=lost,
        packets_late=late,
        frames_misnumbered=numbering["misnumbered"],
        camera_frames_sent=int(np.isfinite(fs.written_time).sum()),
        camera_frames_received=max(0, sum(int(c.get("frames", 0)) for c in recv.values()) - preroll * cfg.cameras),
        exposure_lateness=_lateness(fs.handoff_time, float(trigger_summary.get("fps", cfg.fps))),
        clock_model=_jsonable(trigger_summary),
        sim_priority_raised=bool(fs.priority_raised),
        world=_world(gt, cfg.close_distance_m),
        live_frames=live_frames,
        render_realtime_factor=float(rt),
        host_kept_up=bool(in_time >= 0.99 * min(frames_triggered, gt.n_frames)),
        recording=recording,
        braidz=braidz,
        figure=str(fig),
        rig_file=str(rig_path),
        calibration=str(calib_path) if calib_path else None,
        wall_s=time.monotonic() - wall0,
        notes=[n for n in notes if n],
        host_summary=_jsonable(host_summary),
    )


def _world(gt: GroundTruth, close_m: float) -> dict[str, Any]:
    hs = gt.horizontal_speed()[~gt.landed]
    d = gt.pair_distances() if gt.n_animals > 1 else None
    return {
        **{k: v for k, v in gt.meta.items() if k != "step_s"},
        "horizontal_speed_mean_m_s": float(hs.mean()) if hs.size else float("nan"),
        "horizontal_speed_std_m_s": float(hs.std()) if hs.size else float("nan"),
        "landed_fraction": float(gt.landed.mean()),
        "closest_pass_m": float(d.min()) if d is not None else float("nan"),
        "animal_frames_in_close_pass": int(gt.close_frames(close_m).sum()),
    }


def _lateness(handoff: np.ndarray, fps: float) -> dict[str, float]:
    """How late each frame reached the edges compared with a perfect clock at the trigger's rate,
    anchored on the earliest frame: a real camera's is ~0; ours grows when the machine is busy."""
    n = np.arange(handoff.size)
    ok = np.isfinite(handoff)
    if not np.any(ok):
        return latency_percentiles_ms([])
    lag = handoff[ok] - n[ok] / fps
    return latency_percentiles_ms(lag - lag.min())


def _frame_numbering(recording: str | None, written: np.ndarray, preroll: int = 0,
                     edge_time: np.ndarray | None = None) -> dict[str, Any]:
    """Check the host's frame numbering against the truth, from the recording's 2D rows.

    Every edge got `preroll` frames before the trigger started, then every pulse's frame in order from
    the first, so camera frame c is trigger frame c - preroll. `written` (frames, cameras) is when each
    frame was completely in its edge's input: where the measured latency starts (what came before, the
    exposure and the image transfer, is simulated).
    Returns the count of camera frames numbered otherwise, and per host trigger frame the hand-over
    time of the latest camera frame it was built from."""
    out: dict[str, Any] = {"misnumbered": 0, "camera_frames": 0, "bundle_handoff": {}, "parts_p50_ms": {},
                           "trigger_time_bias_ms": math.nan}
    if not recording or not Path(recording).exists():
        return out
    import h5py

    from flytrack_host.recording.schema import FLAG_TRACKED

    with h5py.File(recording, "r") as f:
        if "data2d_distorted" not in f:
            return out
        d = f["data2d_distorted"][:]
        lat = f["latency"][:] if "latency" in f else None
    from flytrack_host.recording.schema import FLAG_DVS

    d = d[(d["camera_frame"] >= preroll) & ((d["flags"] & FLAG_DVS) == 0)]  # frame cameras' rows
    if len(d) == 0:
        return out
    d["camera_frame"] -= preroll
    key = d["camera_index"].astype(np.int64) * (1 << 40) + d["camera_frame"].astype(np.int64)
    _, first = np.unique(key, return_index=True)
    u = d[first]  # one row per camera frame
    out["camera_frames"] = int(len(u))
    out["misnumbered"] = int(np.sum(u["trigger_frame"] != u["camera_frame"]))
    written = np.asarray(written, dtype=np.float64).reshape(written.shape[0], -1)

    def written_at(rows: np.ndarray) -> np.ndarray:
        cf = rows["camera_frame"].astype(np.int64)
        cam = rows["camera_index"].astype(np.int64)
        ok = (cf >= 0) & (cf < written.shape[0]) & (cam >= 0) & (cam < written.shape[1])
        t = np.full(len(rows), np.nan)
        t[ok] = written[cf[ok], cam[ok]]
        return t

    tracked = u[(u["flags"] & FLAG_TRACKED) != 0]
    tf = tracked["trigger_frame"].astype(np.int64)
    t = written_at(tracked)
    bh: dict[int, float] = {}
    for a, b in zip(tf.tolist(), t.tolist(), strict=True):
        if math.isfinite(b) and b > bh.get(a, -math.inf):
            bh[a] = b
    out["bundle_handoff"] = bh
    # Where the time goes (medians, ms): frame to the edge's read, extraction, UDP to the host's
    # receiver, then synchronisation and tracking in the host.
    parts = {
        "edge_read": u["edge_recv_ns"] / 1e9 - written_at(u),
        "extraction": (u["edge_done_ns"].astype(np.int64) - u["edge_recv_ns"].astype(np.int64)) / 1e9,
        "udp_to_host": u["cam_received_timestamp"] - u["edge_done_ns"] / 1e9,
    }
    if lat is not None and len(lat):
        parts["sync_and_track"] = lat["estimate_time"] - lat["last_arrival"]
    if edge_time is not None and edge_time.size:
        # The host's trigger time of each frame (from its clock model) against the moment the
        # simulated cameras saw that pulse in the trigger's edge stream (itself ~0.1 ms after it).
        cf = u["camera_frame"].astype(np.int64)
        ok = (cf >= 0) & (cf < edge_time.size) & (u["trigger_frame"] == u["camera_frame"])
        bias = u["timestamp"][ok] - edge_time[cf[ok]]
        bias = bias[np.isfinite(bias)]
        if bias.size:
            out["trigger_time_bias_ms"] = float(np.median(bias) * 1e3)
    for k, v in parts.items():
        v = np.asarray(v, dtype=float)
        v = v[np.isfinite(v)]
        if v.size:
            out["parts_p50_ms"][k] = float(np.median(v) * 1e3)
    return out


def _export_braidz(recording: str | None, out: Path, notes: list[str]) -> str | None:
    if not recording or not Path(recording).exists():
        notes.append("no HDF5 recording to export")
        return None
    from flytrack_host.io.braidz import export_braidz
    from flytrack_host.recording import load_recording

    dest = out / "recording.braidz"
    export_braidz(load_recording(recording), dest)
    return str(dest)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(report: DemoReport, path: Path) -> None:
    data = report.as_dict()
    data["goals"] = [asdict(g) for g in check_goals(report)]
    Path(path).write_text(json.dumps(_jsonable(data), indent=1))
