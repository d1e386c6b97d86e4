"""`flytrack wingbeat --live`: the live path of the wing-beat command (cli.py parses the options).

Listens for DVS_WINGBEAT on a UDP port and shows both wings' frequency and amplitude on a status line;
on exit (Ctrl-C, --seconds, the edge silent for --timeout, or the edge started here ending) prints the
per-0.1 s table, writes --csv and --plot. With FILE (or --simulate S FILE) it first starts flytrack-edge
on that event file, played at its recorded pace, in wing-beat mode, sending to this process.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from flytrack_host.dvs.wingbeat.live import (
    DEFAULT_PORT,
    NoEdgeError,
    WingbeatReceiver,
    plot_live,
    score_live,
    start_edge,
)


class LiveError(RuntimeError):
    """The live run cannot go on; one line for the user."""


def _status_line(rx: WingbeatReceiver, t0_mono: float) -> Text:
    c = rx.counts
    now = time.monotonic()
    parts = [f"{now - t0_mono:.1f} s"]
    last = rx.last
    if last is None:
        parts.append(f"waiting for an edge on UDP port {rx.port}")
    elif last.n_edges == 0:
        why = rx.last_status.last_error if rx.last_status and rx.last_status.last_error else "window filling"
        parts.append(f"edge at {last.t_us / 1e6:.2f} s, looking for the fly ({why})")
    else:
        parts.append(f"event time {last.t_us / 1e6:.2f} s")
        for r in last.edges[:2]:
            parts.append(f"wing {int(r['edge_id'])} {float(r['frequency']):5.1f} Hz "
                         f"{np.degrees(float(r['amplitude'])):4.1f}°")
    parts.append(f"{c.wingbeat} received, {c.malformed} malformed, {c.lost} lost")
    if c.other:
        parts.append(f"{c.other} of other types ({', '.join(c.other_types)}): is the edge in --wingbeat 1 mode?")
    if rx.last_status is not None:
        parts.append(f"edge {rx.last_status.fps / 1e3:.0f} k ev/s")
    if rx.last_mono is not None and now - rx.last_mono > 1.0:
        parts.append(f"[edge silent for {now - rx.last_mono:.0f} s]")
    return Text(" | ".join(parts))


def _table(rx: WingbeatReceiver) -> Table:
    s = rx.series()
    table = Table(title="live, per wing, mean over 0.1 s (frequency Hz / amplitude deg)")
    table.add_column("time (s)")
    for w in (0, 1):
        table.add_column(f"wing {w}")
    t_all = np.concatenate([s[0][:, 0], s[1][:, 0]])
    if len(t_all) == 0:
        return table
    t0, t1 = t_all.min(), t_all.max()
    edges = np.arange(t0, t1 + 100_000, 100_000)
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        row = [f"{a * 1e-6:.1f}-{b * 1e-6:.1f}"]
        for w in (0, 1):
            d = s[w]
            sel = (d[:, 0] >= a) & (d[:, 0] < b)
            row.append(f"{d[sel, 3].mean():.1f} / {np.degrees(d[sel, 2].mean()):.1f}" if sel.any() else "-")
        table.add_row(*row)
    return table


def run_live(console: Console, err: Console, *, file: Path | None, simulate: float | None, port: int | None,
             seconds: float | None, timeout: float, csv_path: Path | None, plot: Path | None,
             edge_bin: Path | None, harmonics: int, per_update: int, start_freq: float | None = None) -> int:
    """The live run; returns the exit code (errors: one line on `err`, 2)."""
    from flytrack_host.dvs.wingbeat.files import save_events
    from flytrack_host.dvs.wingbeat.native import MAX_HARMONICS

    if file is not None and harmonics > MAX_HARMONICS:
        err.print(f"[red]error[/red] --harmonics {harmonics}: the edge's tracker has at most {MAX_HARMONICS}")
        return 2

    truth = None
    proc = None
    if simulate is not None or file is not None:
        if file is None:
            err.print("[red]error[/red] --simulate with --live needs FILE (the event file the edge plays)")
            return 2
        if file.suffix == ".npy":
            err.print(f"[red]error[/red] {file}: the edge reads event files (.aedat4, .raw, ...), not .npy")
            return 2
        if simulate is not None:
            from flytrack_host.dvs.wingbeat.simulate import FlySimParams, simulate_tethered_fly

            events, truth = simulate_tethered_fly(FlySimParams(duration_s=simulate))
            save_events(file, events, 128, 128)
            console.print(f"wrote {len(events)} simulated events to {file}", highlight=False, soft_wrap=True)
        elif not file.is_file():
            err.print(f"[red]error[/red] {file}: no such event file", highlight=False, soft_wrap=True)
            return 2
        from flytrack_host.util.native import NativeLibraryError, find_edge_binary

        try:
            binary = find_edge_binary(edge_bin)
        except NativeLibraryError as exc:
            err.print(f"[red]error[/red] {exc}", highlight=False, soft_wrap=True)
            return 2
    try:
        rx = WingbeatReceiver(port if port is not None else (0 if file is not None else DEFAULT_PORT),
                              bind="127.0.0.1" if file is not None else "0.0.0.0", csv_path=csv_path)
    except OSError as exc:
        err.print(f"[red]error[/red] {exc}", highlight=False, soft_wrap=True)
        return 2
    if file is not None:
        extra = ("--wingbeat-harmonics", str(harmonics), "--wingbeat-events-per-update", str(per_update),
                 "--wingbeat-start-freq", str(start_freq or 0))
        proc = start_edge(binary, file, rx.port, extra=extra)
        console.print(f"started {binary.name} on {file} (played at its recorded pace) -> UDP port {rx.port}",
                      highlight=False, soft_wrap=True)
    else:
        console.print(f"listening for DVS_WINGBEAT on UDP port {rx.port} (Ctrl-C to stop)", highlight=False)
    t0 = time.monotonic()
    why = "stopped"
    edge_rc = None
    try:
        with Live(_status_line(rx, t0), console=console, refresh_per_second=4, transient=False) as live:
            while True:
                rx.poll(0.1)
                now = time.monotonic()
                live.update(_status_line(rx, t0))
                if seconds is not None and now - t0 >= seconds:
                    why = f"--seconds {seconds:g} reached"
                    break
                if proc is not None and proc.poll() is not None:
                    rx.poll(0.3)  # the last datagrams
                    live.update(_status_line(rx, t0))
                    edge_rc = proc.returncode
                    why = "the edge finished the file"
                    break
                if rx.last_mono is None and now - t0 > timeout:
                    raise NoEdgeError(f"no datagram from an edge on UDP port {rx.port} in {timeout:g} s: start "
                                      f"flytrack-edge --source events|dvs128 --wingbeat 1 --host <this host> --port "
                                      f"{rx.port}")
                if rx.last_mono is not None and now - rx.last_mono > timeout:
                    why = f"the edge was silent for {timeout:g} s"
                    break
    except KeyboardInterrupt:
        why = "interrupted"
    except NoEdgeError as exc:
        err.print(f"[red]error[/red] {exc}", highlight=False, soft_wrap=True)
        return 2
    finally:
        if not console.is_terminal:
            console.line()  # the status line's last render has no newline of its own
        stderr = ""
        if proc is not None:
            if proc.poll() is None:
                proc.terminate()  # SIGTERM: the daemon sends its last STATUS and exits
            try:
                _, stderr = proc.communicate(timeout=10)
            except Exception:  # noqa: BLE001 - a stuck daemon must not keep the host from writing
                proc.kill()
                _, stderr = proc.communicate()
        rx.close()
    c = rx.counts
    console.print(f"{why}: {c.wingbeat} DVS_WINGBEAT ({c.with_fly} with the fly), {c.status} STATUS, "
                  f"{c.malformed} malformed{' ' + str(c.errors) if c.errors else ''}, {c.other} of other types, "
                  f"{c.lost} lost", highlight=False, soft_wrap=True)
    if rx.first_error:
        err.print(f"first malformed datagram: {rx.first_error}", highlight=False, soft_wrap=True)
    if edge_rc not in (None, 0):
        err.print(f"[red]error[/red] flytrack-edge exited with {edge_rc}: {stderr.strip()[-600:]}",
                  highlight=False, soft_wrap=True)
        return 2
    if proc is not None:
        for line in stderr.splitlines():
            if "wing-beat" in line:
                console.print(f"  edge: {line.removeprefix('flytrack-edge: ')}", highlight=False, soft_wrap=True)
    if csv_path is not None:
        console.print(f"wrote {csv_path} (every record of every datagram)", highlight=False, soft_wrap=True)
    if c.datagrams == 0:
        err.print(f"[red]error[/red] no datagram from an edge on UDP port {rx.port}: start flytrack-edge --source "
                  f"events|dvs128 --wingbeat 1 --host <this host> --port {rx.port}", highlight=False, soft_wrap=True)
        return 2
    if c.with_fly == 0:
        why_not = rx.last_status.last_error if rx.last_status and rx.last_status.last_error else "no reason given"
        err.print(f"[red]error[/red] the edge never found the fly ({why_not})", highlight=False, soft_wrap=True)
        return 2
    console.print(_table(rx))
    if truth is not None and file is not None:
        # Side by side: the live path (the edge's C tracker, sampled every report) and the file path (the
        # host's Python EKF per beat) on the same event file, both against the simulation.
        from flytrack_host.dvs.wingbeat.analysis import score_wings, track_wings
        from flytrack_host.dvs.wingbeat.ekf import EkfParams
        from flytrack_host.dvs.wingbeat.files import load_events

        offline = track_wings(load_events(file), "ekf", start_freq_hz=start_freq,
                              ekf=EkfParams(harmonics=harmonics, events_per_update=per_update))
        for label, scores in (("live, edge C EKF", score_live(rx, truth)),
                              ("file, host Python EKF", score_wings(offline, truth.freq_at, truth.amplitude_at))):
            for s in scores:
                console.print(f"  {label}: wing {s.wing} against the simulation ({s.beats} estimates): frequency "
                              f"error {s.freq_err_pct_mean:.2f} % (max {s.freq_err_pct_max:.2f} %, jitter "
                              f"{s.freq_jitter_pct:.2f} %), amplitude error {s.amp_err_pct_mean:.2f} % "
                              f"(max {s.amp_err_pct_max:.2f} %)", highlight=False, soft_wrap=True)
    if plot is not None:
        plot_live(rx, plot, truth=truth)
        console.print(f"wrote {plot}", highlight=False, soft_wrap=True)
    return 0
