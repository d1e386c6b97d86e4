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

import collections
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.demo_config import (
    PREROLL_FRAMES,
    ROOT,
    DemoConfig,
    DemoContext,
    DemoError,
)
from flytrack_host.sim.dvs_run import DVS_SLICE_US, _dvs_comparison, _dvs_counts, dvs_edge_command, dvs_support_options
from flytrack_host.sim.flight import Arena, simulate_flight
from flytrack_host.sim.frames import FrameFeeder
from flytrack_host.sim.processes import (
    CpuSampler,
    EdgeFleet,
    _cpu_seconds,
    _free_udp_port,
    _LiveCounter,
    edge_command,
    find_edge_binary,
)
from flytrack_host.sim.render import RenderParams
from flytrack_host.sim.report import (
    DemoReport,
    HostResult,
    _export_braidz,
    _frame_numbering,
    _jsonable,
    _lateness,
    _report,
    _scored_mask,
    _world,
    write_json,
)
from flytrack_host.sim.rig import _host_cameras, _write_calibration, make_cameras, rig_config, write_rig
from flytrack_host.sim.trigger_source import DemoTrigger
from flytrack_host.util.placement import Placement, choose_split, run_as_hardware
from flytrack_host.util.stopping import shielded

# The names other code (and tests) import from here, where they lived before the split.
__all__ = [
    "DVS_SLICE_US", "PREROLL_FRAMES", "ROOT", "CpuSampler", "DemoConfig", "DemoContext", "DemoError",
    "DemoReport", "EdgeFleet", "HostResult", "dvs_edge_command", "dvs_support_options", "edge_command",
    "find_edge_binary", "run_demo", "write_json",
    "_LiveCounter", "_cpu_seconds", "_dvs_comparison", "_dvs_counts", "_export_braidz", "_frame_numbering",
    "_free_udp_port", "_host_cameras", "_jsonable", "_lateness", "_report", "_scored_mask", "_world",
    "_write_calibration",
]


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
    # The host on its own CPUs, the simulated hardware on the others, as on a rig (sim/placement.py).
    split, why = choose_split(cfg.cpus, cfg.cameras * cfg.fps + cfg.dvs * cfg.fps)
    placement = Placement(split=split).apply()
    if why:
        notes.append(why)
    edges = dvs_edges = feeder = host = live = session = lab = engine = None
    trigger_summary: dict[str, Any] = {}
    results: list[HostResult] = []
    result_times: np.ndarray | None = None  # cfg.score False: each frame's result time only
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
                run_as_hardware(p.pid)
        for p in edges.procs:
            cpu.add("edges", p.pid)
            # On a rig each edge has its own computer: here they run at the simulated hardware's
            # priority, so only the host competes with the rest of this machine.
            run_as_hardware(p.pid)
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
        from flytrack_host.trigger.session import TriggerSession

        rig = load_rig(rig_path)  # exactly what a user's host would read
        cameras_for_host = _host_cameras(rig, cams, calib_path)
        session = TriggerSession(rig.trigger)
        try:
            fps = session.open()
        except TriggerError as exc:
            session = None
            raise DemoError(f"the trigger ({trig.kind_label}) did not open: {exc}") from None

        if not cfg.score:  # filled now: every page is touched up front, none later
            result_times = np.full(gt.n_frames, np.nan)

        def on_result(r: Any) -> None:
            if result_times is not None:
                f = int(r.trigger_frame)
                if 0 <= f < result_times.size:
                    result_times[f] = time.time()  # noqa: TID251 - as HostResult.t_result below
                return
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
                engine = lab.engine(rig, fps, session, score=cfg.score)
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
        if cfg.fault is not None or cfg.on_running:
            ctx = DemoContext(host, session, edges, feeder, trig, cams, port, fps, edge_bin, out, lab=lab)
            if cfg.fault is not None:
                cfg.fault.start(ctx)
            for fn in cfg.on_running:
                fn(ctx)

        # 4. Run until every frame was rendered, with a progress bar.
        budget = cfg.seconds * 4 + 30
        t_end = time.monotonic() + budget
        # Drawn by this loop twice a second, not by rich's refresh thread at 10 Hz: each redraw holds the
        # host's GIL for about a millisecond, which the tracking and device threads then wait for.
        with Progress(TextColumn("[bold]simulated rig[/bold]"), BarColumn(), TextColumn("{task.description}"),
                      TimeRemainingColumn(), console=console, disable=not cfg.progress, transient=True,
                      auto_refresh=False) as prog:
            task = prog.add_task("", total=gt.n_frames)
            turn = 0
            while not feeder.done and feeder.alive() and time.monotonic() < t_end:
                time.sleep(0.1)
                cpu.sample()
                turn += 1
                prog.update(task, completed=feeder.frames_rendered, refresh=turn % 5 == 0,
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
        # Also after Ctrl-C, or a SIGTERM (`flytrack demo` takes it as Ctrl-C: util.stopping), which
        # then waits for the end of this block: the recording is finalised, every process stopped.
        with shielded():
            placement.restore()
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
                     notes, wall0, cams, warmup, trigger_summary, preroll, result_times=result_times)
    report.cpu_seconds = cpu.totals()
    report.cpu_placement = placement.describe()
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
