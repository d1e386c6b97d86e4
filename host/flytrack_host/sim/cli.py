"""`flytrack demo`: run the simulated rig end to end and print what it measured."""

from __future__ import annotations

import math
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from flytrack_host.live.launch import POSE_HELP, LiveOutputs, OutputsError
from flytrack_host.sim.goals import check_goals
from flytrack_host.sim.run import DemoConfig, DemoError, DemoReport, run_demo, write_json
from flytrack_host.util.placement import FRAMES_PER_HARDWARE_CPU
from flytrack_host.util.stopping import sigterm_as_ctrl_c, sigterm_received


def _f(x: float, fmt: str = ".2f") -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def summary_table(r: DemoReport) -> Table:
    """The summary, kept within 80 columns: figure, value, a short note (the manual's demo tutorial explains more)."""
    s = r.scores
    lat = r.latency
    t = Table(title="FlyTrack simulated rig: summary", show_header=True, header_style="bold")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_column("note", style="dim")
    c = r.config
    t.add_row("rig", f"{c['cameras']} cams, {c['animals']} animals",
              f"{c['fps']:g} fps, {c['seconds']:g} s, seed {c['seed']}")
    # A fallback from the firmware to the software trigger is said where the figures are read.
    fell_back = "fell back" in getattr(r, "trigger_note", "")
    t.add_row("trigger", f"[yellow]{r.trigger} (FELL BACK)[/yellow]" if fell_back else r.trigger,
              r.trigger_note if fell_back else "")
    if s is not None:  # None: the run was not scored against the ground truth (the soak)
        t.add_row("tracks found", str(s.tracks_found), f"{s.gt_objects} animals, {s.tracks_total} ids")
        t.add_row("3D RMSE", f"{_f(s.rmse_mm)} mm", f"matched within {s.match_threshold_m * 1000:.0f} mm")
        t.add_row("MOTA", _f(s.mota, ".4f"), f"{s.misses} misses, {s.false_positives} false pos.")
        t.add_row("IDF1", _f(s.idf1, ".4f"), f"recall {s.recall:.3f}, precision {s.precision:.3f}")
        t.add_row("ID switches", str(s.id_switches), f"{s.id_switches_free_flight} in free flight")
        t.add_row("merges", str(s.merges), f"{s.merge_frames} animal-frames")
    t.add_row("latency P50", f"{_f(lat['p50_ms'])} ms", "frames at the edges -> 3D")
    t.add_row("latency P99", f"{_f(lat['p99_ms'])} ms", "(simulated exposure and")
    t.add_row("latency max", f"{_f(lat['max_ms'])} ms", " transfer left out)")
    if r.latency_parts_p50_ms:
        names = {"edge_read": "edge read", "extraction": "extract", "udp_to_host": "udp", "sync_and_track": "host"}
        t.add_row("latency parts P50", "", ", ".join(f"{names.get(k, k)} {v:.2f}"
                                                     for k, v in r.latency_parts_p50_ms.items()))
    hl = r.latency_host
    if hl:
        nan = float("nan")
        t.add_row("host latency P50/P99", f"{_f(hl.get('p50_ms', nan))}/{_f(hl.get('p99_ms', nan))} ms",
                  "host's trigger time -> 3D")
    t.add_row("trigger time bias", f"{_f(r.trigger_time_bias_ms)} ms", "host clock model vs the pulses")
    t.add_row("packets lost / late", f"{r.packets_lost} / {r.packets_late}", "loopback UDP")
    t.add_row("camera frames received", f"{r.camera_frames_received}/{r.camera_frames_sent}",
              "by the host before it stopped")
    t.add_row("frames misnumbered", str(r.frames_misnumbered), "by the host synchroniser")
    t.add_row("frames in time", f"{r.frames_in_time}/{r.frames_triggered}",
              f"host kept up: {'yes' if r.host_kept_up else 'NO'}")
    el = r.exposure_lateness
    t.add_row("camera lateness P99/max", f"{_f(el['p99_ms'], '.1f')}/{_f(el['max_ms'], '.1f')} ms",
              "simulated cameras vs clock")
    if r.cpu_seconds:
        t.add_row("CPU seconds", f"{sum(r.cpu_seconds.values()):.1f} s", ", ".join(
            f"{k.replace('simulated ', 'sim ')} {v:.1f}" for k, v in r.cpu_seconds.items()))
    cp = r.cpu_placement
    t.add_row("CPUs", "split" if cp else "shared",
              f"host {_cpus(cp['host'])}, sim hardware {_cpus(cp['simulated_hardware'])}" if cp
              else "host and simulated hardware on the same CPUs")
    wake = (r.host_summary or {}).get("cpu_wake_latency")
    if wake:
        t.add_row("CPU wake-up latency", f"{wake['requested_us']} us" if wake["held"] else "not held",
                  "PM QoS while the closed loop ran" if wake["held"] else wake["note"])
    t.add_row("frames rendered/tracked", f"{r.frames_rendered}/{r.frames_tracked}",
              f"{r.live_frames} live frames sent")
    for d in r.dvs:
        t.add_row(f"DVS {d['name']} events", f"{d['events_received']}/{d['events_sent']}",
                  f"received/sent, {d['slices_received']} slices, {d['clusters_received']} clusters")
        t.add_row(f"DVS {d['name']} points used", f"{d['points_used']}/{d['points_observed']}",
                  f"by the 3D tracker / given, {d['frames_observed']} frames")
    cmp_ = r.dvs_comparison
    if cmp_.get("with_dvs") and cmp_.get("without_dvs"):
        w, wo = cmp_["with_dvs"], cmp_["without_dvs"]
        t.add_row("3D RMSE with / without DVS", f"{_f(w['rmse_mm'], '.2f')} / {_f(wo['rmse_mm'], '.2f')} mm",
                  f"the run's {cmp_['bundles']} bundles tracked again, {w['dvs_points_used']}/{w['dvs_points']} "
                  "DVS points used")
        t.add_row("MOTA with / without DVS", f"{_f(w['mota'], '.4f')} / {_f(wo['mota'], '.4f')}",
                  f"false pos. {w['false_positives']} / {wo['false_positives']}")
    if r.actuation:
        from flytrack_host.sim.closed_loop import closed_loop_line

        t.add_row("closed loop fired", *closed_loop_line(r.actuation))
    return t


def _cpus(cpus: list[int]) -> str:
    return ("CPU " if len(cpus) == 1 else "CPUs ") + ",".join(str(c) for c in cpus)


def demo_command(
    cameras: int = typer.Option(5, "--cameras", help="Number of simulated cameras."),
    animals: int = typer.Option(3, "--animals", help="Number of flying insects."),
    fps: float = typer.Option(100.0, "--fps", help="Trigger rate, frames per second."),
    seconds: float = typer.Option(10.0, "--seconds", help="Length of the run."),
    noise: float = typer.Option(2.0, "--noise", help="Sensor noise, grey levels (std)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the flight model, the rig and the rendering."),
    out: Path = typer.Option(Path("build") / "demo", "--out", help="Output folder (rig, calibration, "
                             "recording, figure); relative to the current folder."),
    json_path: Path | None = typer.Option(None, "--json", help="Write every figure of the summary here."),
    trigger: str = typer.Option("auto", "--trigger", help="auto | simavr | software"),
    no_progress: bool = typer.Option(False, "--no-progress", help="No progress bar."),
    cpus: str = typer.Option("auto", "--cpus", help="split: the host on the first half of the CPUs, the "
                             "simulated hardware (cameras, edges, trigger, lab devices) on the rest, as on a rig "
                             "where they are machines of their own; share: all on all; auto: split unless the "
                             "simulated cameras need more than the hardware's half (over "
                             f"{FRAMES_PER_HARDWARE_CPU:.0f} camera frames/s per hardware CPU)."),
    rules: Path | None = typer.Option(
        None, "--rules", help="Closed-loop rules file (e.g. examples/closed_loop.toml): its rules drive the "
        "firmware's high-speed camera line, a Modbus TCP server and a CAN bus on loopback, scored against the "
        "flight's ground truth (JSON `actuation`)."),
    serve: bool = typer.Option(False, "--serve", help="Serve Braid's event stream and the live page while it "
                               "runs (on --http, default 127.0.0.1:8397)."),
    http: str = typer.Option("127.0.0.1:8397", "--http", help="With --serve: HOST:PORT to serve on. Any "
                             "address other than loopback needs the token printed at start."),
    pose: str | None = typer.Option(None, "--pose", help=POSE_HELP),
    pose_rate: float = typer.Option(200.0, "--pose-rate", help="Pose datagrams per second."),
    pose_lead_ms: float = typer.Option(0.0, "--pose-lead-ms", help="Extrapolate the pose this far past now."),
    pose_lock: str = typer.Option("auto", "--pose-lock", help="auto (oldest live object), all, or an obj_id."),
    dvs: int = typer.Option(0, "--dvs", help="Add N simulated DVS (event) cameras beside the frame cameras: "
                            "events rendered from the flight model, streamed into their own flytrack-edge "
                            "(--source events), DVS_CLUSTERS to the host; the JSON `dvs` counts events "
                            "sent and received per DVS camera."),
    dvs_sensor: str = typer.Option("davis346", "--dvs-sensor", help="dvs128 (128x128) or davis346 (346x260)."),
) -> None:
    """Simulated rig end to end: flight model, firmware trigger in simavr, rendered cameras, real edge
    extractors, UDP on loopback, the real host; scores against ground truth."""
    console = Console()
    cfg = DemoConfig(cameras=cameras, animals=animals, fps=fps, seconds=seconds, noise=noise, seed=seed,
                     out=out, trigger=trigger, progress=not no_progress, cpus=cpus, rules=rules,
                     dvs=dvs, dvs_sensor=dvs_sensor)
    try:
        outputs = LiveOutputs.from_options(http=http if serve else None, pose=pose, pose_rate=pose_rate,
                                           pose_lead_ms=pose_lead_ms, pose_lock=pose_lock)
        outputs.http_required = True  # --serve asked for it: a busy port is an error
    except OutputsError as exc:
        Console(stderr=True).print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    cfg.attach.append(lambda pipe: outputs.attach(pipe, echo=lambda s: console.print(s, highlight=False,
                                                                                      soft_wrap=True)))
    try:
        # A SIGTERM (a service manager's, a supervisor's) stops the run as Ctrl-C does: the recording
        # is finalised, every process the demo started is stopped, exit code 130 (util.stopping).
        with sigterm_as_ctrl_c():
            report = run_demo(cfg, console)
    except DemoError as exc:
        Console(stderr=True).print(f"[red]demo cannot run:[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    except KeyboardInterrupt:
        rec = Path(cfg.out).resolve() / "recording.flytrack"
        why = "SIGTERM" if sigterm_received() else "Ctrl-C"
        Console(stderr=True).print(f"[yellow]stopped[/yellow] by {why} before the end of the run"
                                   + (f"; recording {rec}" if rec.exists() else ""), highlight=False, soft_wrap=True)
        raise typer.Exit(code=130) from None
    console.print(summary_table(report))
    goals = check_goals(report)
    met = sum(g.ok for g in goals)
    console.print(f"goals met: {met}/{len(goals)}  " + ", ".join(
        f"{g.name} {g.goal}: {'[green]yes[/green]' if g.ok else '[red]NO[/red]'}" for g in goals), highlight=False)
    for n in report.notes:
        console.print(f"[yellow]note[/yellow] {n}", highlight=False)
    console.print(f"rig file   {report.rig_file}", highlight=False)
    console.print(f"recording  {report.recording}", highlight=False)
    console.print(f"braidz     {report.braidz}", highlight=False)
    console.print(f"figure     {report.figure}", highlight=False)
    if json_path is not None:
        write_json(report, json_path)
        console.print(f"json       {json_path}", highlight=False)
