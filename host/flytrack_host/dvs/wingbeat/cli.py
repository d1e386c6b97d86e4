"""`flytrack wingbeat FILE`: wing-beat frequency and amplitude of a tethered fly from an event file."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from flytrack_host.dvs.wingbeat.files import load_events, save_events

console = Console()
err = Console(stderr=True)


def wingbeat_command(
    file: Path | None = typer.Argument(None, help="Event file of a tethered fly (AEDAT 2/3.1/4, EVT 2/3, DAT, or "
                                       ".npy). With --live: the file a flytrack-edge started here plays."),
    method: str = typer.Option("both", "--method", help="ekf, wra, or both (side by side)."),
    harmonics: int = typer.Option(2, "--harmonics", min=1, max=6, help="EKF: Fourier harmonics (1 = the seed's "
                                  "sinusoid)."),
    per_update: int = typer.Option(4, "--events-per-update", min=1, help="EKF: events averaged per update."),
    start_freq: float | None = typer.Option(None, "--start-freq", help="Starting frequency in Hz (default: found "
                                            "from the first 0.1 s)."),
    width: int = typer.Option(128, help="Sensor width (when the file does not say)."),
    height: int = typer.Option(128, help="Sensor height."),
    plot: Path | None = typer.Option(None, "--plot", help="Write the figure here (PNG)."),
    json_path: Path | None = typer.Option(None, "--json", help="Write the per-beat series here."),
    csv_path: Path | None = typer.Option(None, "--csv", help="Write the series here (file: per beat and wing; live: "
                                         "per datagram and record)."),
    live: bool = typer.Option(False, "--live", help="Take DVS_WINGBEAT from a DVS edge (flytrack-edge --wingbeat 1) "
                              "instead of reading FILE; with FILE, start that edge on it here."),
    port: int | None = typer.Option(None, "--port", min=0, max=65535, help="--live: UDP port to listen on (default "
                                    "7700, the edge's default; with FILE a free one)."),
    seconds: float | None = typer.Option(None, "--seconds", min=0.1, help="--live: stop after this many seconds "
                                         "(default: Ctrl-C, or the edge started here finishing)."),
    timeout: float = typer.Option(10.0, "--timeout", min=0.1, help="--live: give up when no datagram came for this "
                                  "many seconds."),
    edge_bin: Path | None = typer.Option(None, "--edge-bin", help="--live with FILE: the flytrack-edge binary "
                                         "(default: the build's)."),
    simulate: float | None = typer.Option(None, "--simulate", help="First write FILE with this many seconds of a "
                                          "simulated 200 Hz fly (a 10 % frequency rise, 20 % noise events)."),
    min_quality: float = typer.Option(0.5, "--min-quality", min=0.0, max=1.0, help="Refuse to report beats whose "
                                      "fit quality is below this (the share of the events' angle spread a wing stroke "
                                      "at the reported beats explains: a tethered fly about 0.98, noise about 0); 0 "
                                      "reports them anyway, with a warning."),
) -> None:
    """Wing-beat frequency and amplitude of a tethered fly from an event file (seed 002, part II).

    The fly is found in the first 0.1 s (2-means on the events, body between the wings, heading across
    them), then each wing's leading (OFF) and trailing (ON) edges are tracked by an EKF on a Fourier series
    and/or the weighted running average. Prints frequency and amplitude per wing over time and the fit
    quality (how much of the events' angle spread a wing stroke at the reported beats explains); below
    --min-quality nothing is reported (the events are not a beating wing); `--plot` draws the seed's figures.

    Live: `--live` listens for the edge's DVS_WINGBEAT (the same tracker in C at the edge, one datagram every
    5 ms of event time) and shows both wings on a status line; on exit it prints the table and writes
    --csv/--plot. `--simulate S --live FILE.aedat4` simulates the fly, starts flytrack-edge on the file
    and takes its datagrams over UDP: the whole live path, scored against the simulation."""
    if live:
        from flytrack_host.dvs.wingbeat.live_cli import run_live

        if method not in ("both", "ekf"):
            err.print("[red]error[/red] --live: the edge runs the EKF (--method is for event files)")
            raise typer.Exit(code=2)
        rc = run_live(console, err, file=file, simulate=simulate, port=port, seconds=seconds, timeout=timeout,
                      csv_path=csv_path, plot=plot, edge_bin=edge_bin, harmonics=harmonics, per_update=per_update,
                      start_freq=start_freq)
        if rc:
            raise typer.Exit(code=rc)
        return
    if file is None:
        err.print("[red]error[/red] give an event FILE, or --live to take wing beats from a DVS edge")
        raise typer.Exit(code=2)
    from flytrack_host.dvs.wingbeat.analysis import score_wings, track_wings
    from flytrack_host.dvs.wingbeat.ekf import EkfParams
    from flytrack_host.dvs.wingbeat.geometry import WingbeatError
    from flytrack_host.dvs.wingbeat.plot import plot_wingbeats

    methods = ["ekf", "wra"] if method == "both" else [method]
    if any(m not in ("ekf", "wra") for m in methods):
        err.print(f"[red]error[/red] --method is ekf, wra or both, not {method!r}")
        raise typer.Exit(code=2)
    truth = None
    try:
        if simulate is not None:
            from flytrack_host.dvs.wingbeat.simulate import FlySimParams, simulate_tethered_fly

            events, truth = simulate_tethered_fly(FlySimParams(duration_s=simulate))
            save_events(file, events, 128, 128)
            console.print(f"wrote {len(events)} simulated events to {file}", highlight=False, soft_wrap=True)
        events = load_events(file)
        results = [track_wings(events, m, width=width, height=height, start_freq_hz=start_freq,
                               ekf=EkfParams(harmonics=harmonics, events_per_update=per_update)) for m in methods]
    except (OSError, ValueError, WingbeatError) as exc:
        msg = str(exc)
        # The event readers' messages already start with the path: name it once.
        msg = msg if msg.startswith(f"{file}:") else f"{file}: {msg}"
        err.print(f"[red]error[/red] {msg}", highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None
    from flytrack_host.dvs.wingbeat.analysis import MIN_QUALITY

    low = [r for r in results if r.quality < max(min_quality, MIN_QUALITY)]
    figures = ", ".join(f"{r.method.upper()} {r.quality:.2f} (wings {r.wings[0].quality:.2f} / "
                        f"{r.wings[1].quality:.2f})" for r in low)
    if min_quality > 0 and any(r.quality < min_quality for r in results):
        err.print(f"[red]error[/red] {file}: the events do not follow a wing beat: fit quality {figures} is below "
                  f"--min-quality {min_quality:g} (the share of the events' angle spread that a wing stroke at the "
                  f"reported beats explains; a tethered fly gives about 0.98). Nothing reported; --min-quality 0 "
                  f"shows the estimates anyway.", highlight=False, soft_wrap=True)
        raise typer.Exit(code=2)
    g = results[0].geometry
    console.print(f"{len(events)} events, {results[0].events_in_roi} near the fly; body at ({g.body[0]:.1f}, "
                  f"{g.body[1]:.1f}) px, heading {np.degrees(g.heading_rad):.1f} deg, size {g.size_px:.1f} px; "
                  f"start frequency {results[0].start_freq_hz[0]:.1f} / {results[0].start_freq_hz[1]:.1f} Hz",
                  highlight=False, soft_wrap=True)
    t0, t1 = events["t"][0], events["t"][-1]
    edges = np.arange(t0, t1 + 1, 100_000)
    table = Table(title="per wing, mean over 0.1 s (frequency Hz / amplitude deg)")
    table.add_column("time (s)")
    for r in results:
        for w in (0, 1):
            table.add_column(f"{r.method.upper()} wing {w}")
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        row = [f"{(a - t0) * 1e-6:.1f}-{(b - t0) * 1e-6:.1f}"]
        for r in results:
            for wt in r.wings:
                sel = (wt.beats.t_us >= a) & (wt.beats.t_us < b)
                row.append(f"{wt.beats.freq_hz[sel].mean():.1f} / {np.degrees(wt.beats.amplitude[sel].mean()):.1f}"
                           if sel.any() else "-")
        table.add_row(*row)
    console.print(table)
    for r in results:
        console.print(f"{r.method.upper()}: {sum(len(w.beats.t_us) for w in r.wings)} beats, fit quality "
                      f"{r.quality:.2f} (wing 0 {r.wings[0].quality:.2f}, wing 1 {r.wings[1].quality:.2f}), "
                      f"{r.seconds:.2f} s CPU ({r.events_in_roi / max(r.seconds, 1e-9) / 1e6:.2f} M events/s)",
                      highlight=False, soft_wrap=True)
        if truth is not None:
            for s in score_wings(r, truth.freq_at, truth.amplitude_at):
                console.print(f"  wing {s.wing} against the simulation: frequency error {s.freq_err_pct_mean:.2f} % "
                              f"(jitter {s.freq_jitter_pct:.2f} %), amplitude error {s.amp_err_pct_mean:.2f} %",
                              highlight=False, soft_wrap=True)
    if low:
        err.print(f"[yellow]warning[/yellow] fit quality {figures} is below {MIN_QUALITY:g}: these are not the "
                  "wing beats of a tethered fly", highlight=False, soft_wrap=True)
    if plot is not None:
        plot_wingbeats(results, plot, truth=truth)
        console.print(f"wrote {plot}", highlight=False, soft_wrap=True)
    if json_path is not None:
        out = {r.method: {"geometry": asdict(r.geometry), "quality": r.quality, "wings": [
            {"wing": w.wing, "quality": w.quality, "t_us": w.beats.t_us.tolist(), "freq_hz": w.beats.freq_hz.tolist(),
             "amplitude_rad": w.beats.amplitude.tolist()} for w in r.wings]} for r in results}
        json_path.write_text(json.dumps(out))
    if csv_path is not None:
        csv_path.parent.mkdir(parents=True, exist_ok=True)
        with open(csv_path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["method", "wing", "t_us", "frequency_hz", "amplitude_rad"])
            for r in results:
                for wt in r.wings:
                    for t, f, a in zip(wt.beats.t_us, wt.beats.freq_hz, wt.beats.amplitude, strict=True):
                        w.writerow([r.method, wt.wing, f"{t:.0f}", f"{f:.4f}", f"{a:.6f}"])
        console.print(f"wrote {csv_path}", highlight=False, soft_wrap=True)
