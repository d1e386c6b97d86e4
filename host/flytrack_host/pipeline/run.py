"""`flytrack run`: the host live from the command line."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from flytrack_host.live.launch import HTTP_HELP, POSE_HELP, THUMBS_HELP, LiveOutputs, OutputsError
from flytrack_host.pipeline.cameras import calibration_problems, load_cameras
from flytrack_host.pipeline.host import RECORDING_INCOMPLETE_EXIT, HostPipeline
from flytrack_host.util.stopping import shielded, sigterm_as_ctrl_c


# A SIGTERM (a service manager's, a supervisor's) stops the run as Ctrl-C does (util.stopping): the
# trigger stops, pending frames are tracked, the recording is finalised, the same exit code.
@sigterm_as_ctrl_c()
def run_command(
    rig_path: Path = typer.Argument(..., help="The rig TOML file."),
    seconds: float | None = typer.Option(None, "--seconds", help="Stop after this many seconds (default: Ctrl-C)."),
    bind: str | None = typer.Option(None, help="Listen on HOST:PORT instead of the rig's host.listen."),
    recording: Path | None = typer.Option(None, help="Recording folder (default: in the rig's recording folder)."),
    no_record: bool = typer.Option(False, "--no-record", help="Do not record."),
    dead_timeout_s: float = typer.Option(0.5, help="A camera silent this long is marked dead."),
    no_trigger: bool = typer.Option(
        False, "--no-trigger",
        help="Do not open the trigger: fixed-rate clock anchored at the first frame (no trigger latency).",
    ),
    trigger_port: str | None = typer.Option(None, help="Serial port of the trigger instead of the rig's trigger.port."),
    trigger_reset_wait: float | None = typer.Option(
        None, help="Seconds to wait after opening the trigger port (default 2 for a board, 0 for a pty)."),
    http: str = typer.Option("127.0.0.1:8397", "--http", help=HTTP_HELP),
    pose: str | None = typer.Option(None, "--pose", help=POSE_HELP),
    pose_rate: float = typer.Option(200.0, "--pose-rate", help="Pose datagrams per second."),
    pose_lead_ms: float = typer.Option(0.0, "--pose-lead-ms", help="Extrapolate the pose this far past now."),
    pose_lock: str = typer.Option("auto", "--pose-lock", help="auto (oldest live object), all, or an obj_id."),
    thumbnails: float = typer.Option(0.0, "--thumbnails", help=THUMBS_HELP),
    rules: Path | None = typer.Option(
        None, "--rules", help="Closed-loop rules file (default: the rig's `rules`); its actions drive the rig's "
        "[[actuators]]."),
    skip_bad_rules: bool = typer.Option(
        False, "--skip-bad-rules", help="Run with the rules that are valid; each bad one is reported, logged in "
        "the recording and counted (default: a bad rules file stops the run before it starts)."),
) -> None:
    """Run the host live: open the trigger, receive, synchronise, track, serve live estimates and record
    until Ctrl-C (a SIGTERM, as a service manager sends, stops it the same way).

    Without a trigger board, pass --no-trigger (frames are timed by a fixed-rate clock anchored at the
    first frame), or use a rig file with [trigger] kind = "software"."""
    from rich.console import Console
    from rich.live import Live

    from flytrack_host.rig import RigError, load_rig

    console = Console()
    try:
        outputs = LiveOutputs.from_options(http=http, pose=pose, pose_rate=pose_rate, pose_lead_ms=pose_lead_ms,
                                           pose_lock=pose_lock, thumbnails_every_s=thumbnails)
    except OutputsError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    try:
        rig = load_rig(rig_path)
    except RigError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    try:
        cameras = load_cameras(rig)
    except Exception as exc:
        console.print(f"[red]error[/red] calibration {rig.calibration_path}: {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    for problem in calibration_problems(rig, cameras):
        Console(stderr=True).print(f"[yellow]warning[/yellow] {problem}", highlight=False, soft_wrap=True)
    from flytrack_host.actuation.cli import rules_for_run

    run_rules = rules_for_run(rig, rules, skip_bad_rules)  # a bad rules file exits 2 here unless skipped
    session = None
    if not no_trigger:
        from flytrack_host.trigger.common import TriggerError
        from flytrack_host.trigger.session import TriggerSession

        session = TriggerSession(rig.trigger, port=trigger_port, reset_wait_s=trigger_reset_wait)
        try:
            session.open()  # before anything is recorded: a trigger problem leaves no empty recording
        except TriggerError as exc:
            err = Console(stderr=True)
            err.print(f"[red]error[/red] trigger ({rig.trigger.kind}): {exc}", highlight=False, soft_wrap=True)
            err.print(f"no trigger board? run without one: flytrack run {rig_path} --no-trigger", highlight=False,
                      soft_wrap=True)
            raise typer.Exit(code=2) from None
    pipe = HostPipeline(rig, cameras, bind=bind, record=not no_record, recording_path=recording,
                        rig_text=Path(rig_path).read_text(encoding="utf-8"), dead_timeout_s=dead_timeout_s,
                        clock=session.clock if session else None, fps=session.fps if session else None,
                        hold_until_synchronized=session is not None)
    engine = run_rules.engine(pipe.fps, session) if run_rules is not None else None
    try:
        outputs.attach(pipe, echo=lambda s: None)  # printed after the first line below
        pipe.start()
    except OSError as exc:
        if session is not None:
            session.close()
        for sink in pipe.sinks:
            sink.close()
        where = f"{bind or rig.host.listen} (features) or {http} (live outputs)"
        console.print(f"[red]error[/red] cannot listen on {where}: {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    end = None if seconds is None else time.monotonic() + seconds
    trigger_failed: Exception | None = None
    # From here on the pipeline runs and records: Ctrl-C (or SIGTERM) at any point, also while the
    # trigger starts, ends in the finally below (trigger stopped, recording finalised).
    try:
        if engine is not None:  # after start: its messages go into the recording's log too
            engine.attach(pipe)
            engine.start()
        if session is not None:
            session.attach(pipe)
            try:
                session.start(pipe)
            except (TriggerError, OSError) as exc:
                trigger_failed = exc
        if trigger_failed is None:
            host, port = pipe.address
            # Plain first line, so scripts (and tests) can find the port and the recording.
            print(f"listening on {host}:{port}; recording to {pipe.recording_path if pipe.record else '-'}",
                  flush=True)
            for line in outputs.started:
                print(line, flush=True)
            if console.is_terminal:
                with Live(pipe.status_line(), console=console, refresh_per_second=4, transient=False) as live:
                    while (end is None or time.monotonic() < end) and pipe.running:
                        time.sleep(0.25)
                        live.update(pipe.status_line())
            else:
                last = 0.0
                while (end is None or time.monotonic() < end) and pipe.running:
                    time.sleep(0.25)
                    if time.monotonic() - last > 5:
                        print(pipe.status_line(), flush=True)
                        last = time.monotonic()
    except KeyboardInterrupt:
        pass
    finally:
        with shielded():  # a SIGTERM now waits for the recording to be finalised
            if session is not None and trigger_failed is not None:
                session.close()
            elif session is not None:
                session.stop()  # the cameras stop with the trigger; pending frames are tracked by pipe.stop()
            summary = pipe.stop()
    if trigger_failed is not None:
        Console(stderr=True).print(f"[red]error[/red] trigger did not start: {trigger_failed}", highlight=False,
                                   soft_wrap=True)
        raise typer.Exit(code=2)
    console.print(pipe.status_line(), highlight=False)
    console.print(summary["latency_text"], highlight=False)
    for w in summary.get("why_nothing") or []:
        Console(stderr=True).print(f"[yellow]warning[/yellow] no estimates: {w}", highlight=False, soft_wrap=True)
    if session is not None:
        t = session.summary()
        m = t["clock_model"]
        resid = f"{m['residual_us']:.1f} us over {m['n_samples']:.0f} samples" if m else "no fit"
        console.print(f"trigger: {t['fps']:.6f} fps; clock residual {resid}; {t['clock_samples']} clock samples, "
                      f"{t['clock_errors']} errors, lost {t['lost']}, device restarts {t['device_restarts']}",
                      highlight=False)
    if summary["recording"]:
        console.print(f"recording: {summary['recording']}", highlight=False)
        if summary.get("recording_stop"):
            console.print(f"  {summary['recording_stop']}", highlight=False, soft_wrap=True)
    rs = summary.get("recorder") or {}
    lost = sum(rs.get("dropped_rows", {}).values())
    if rs.get("write_errors") or lost or summary.get("recording_error"):
        console.print(f"[red]recording incomplete[/red]: {rs.get('write_errors', 0)} write errors, {lost} rows lost"
                      + (f"; not finalised ({summary['recording_error']}): run `flytrack recording recover`"
                         " (its --out writes the file on another disk)"
                         if summary.get("recording_error") else ""), highlight=False)
        raise typer.Exit(code=RECORDING_INCOMPLETE_EXIT)  # scripts must not take this run for a good one
