"""`flytrack`: the command line of the FlyTrack host.

Each component adds its own command group (a typer app in its own module) to `_GROUPS` below, so this
file stays a table of contents.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import typer
from rich.console import Console

from flytrack_host import __version__
from flytrack_host.protocol import PROTOCOL_VERSION
from flytrack_host.rig import RigError, load_rig

app = typer.Typer(
    help="FlyTrack: real-time multi-camera 3D tracking of flying animals.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",  # docstrings wrap like prose instead of keeping their line breaks
)
console = Console()
err_console = Console(stderr=True)

# (module, attribute, command name, help): command groups that live in their components.
_GROUPS: list[tuple[str, str, str, str]] = [
    ("flytrack_host.recording.cli", "app", "recording", "Recordings: recover after a crash, summarise."),
    ("flytrack_host.tracking.bench", "app", "bench", "Benchmarks that print measured figures."),
    ("flytrack_host.trigger.cli", "app", "trigger", "Trigger box: info, start, stop, watch, pulse, flash."),
    ("flytrack_host.calibration.cli", "app", "calibrate",
     "Calibration: selfcal, dlt, align, intrinsics, collect, report, convert, dvs-points, dvs-sim."),
    ("flytrack_host.actuation.cli", "app", "rules", "Closed-loop rules: check, replay on a recording."),
    ("flytrack_host.batch.cli", "app", "batch", "Batches on Dask: re-track many recordings, sweep parameters, export."),
    ("flytrack_host.dvs.events.cli", "app", "events", "Event-camera files: info, convert (AEDAT 2/3/4, EVT 2/3, DAT)."),
    ("flytrack_host.fish.cli", "app", "fish", "Fish: offline 3D shape tracking of schooling fish (track, demo)."),
]
# (group module, function module, function, command name): commands added to a group from a higher
# subsystem, so the group's own package need not import it (calibrate dvs-sim runs the simulator).
_GROUP_COMMANDS: list[tuple[str, str, str, str]] = [
    ("flytrack_host.calibration.cli", "flytrack_host.sim.dvs_calibration", "dvs_sim_cmd", "dvs-sim"),
]
# (module, function, command name): top-level commands that live in their components.
_COMMANDS: list[tuple[str, str, str]] = [
    ("flytrack_host.pipeline", "run_command", "run"),
    ("flytrack_host.io.cli", "export_command", "export"),
    ("flytrack_host.io.cli", "retrack_command", "retrack"),
    ("flytrack_host.io.cli", "compare_command", "compare"),
    ("flytrack_host.sim.cli", "demo_command", "demo"),
    ("flytrack_host.dvs.wingbeat.cli", "wingbeat_command", "wingbeat"),
    ("flytrack_host.edges.oak.cli", "edge_oak_command", "edge-oak"),
]


@app.command()
def version() -> None:
    """Print the host version and the wire-protocol version it speaks."""
    typer.echo(f"flytrack host {__version__}")
    typer.echo(f"wire protocol version {PROTOCOL_VERSION}")


rig_app = typer.Typer(help="Rig files: the TOML that describes cameras, trigger, calibration, tracking.")
app.add_typer(rig_app, name="rig")


@rig_app.command("check")
def rig_check(
    path: Path = typer.Argument(..., help="The rig TOML file to validate."),
) -> None:
    """Validate a rig file and print every problem with the field and the fix."""
    try:
        rig = load_rig(path)
    except RigError as exc:
        for line in str(exc).splitlines():
            err_console.print(f"[red]error[/red] {line}", highlight=False)
        raise typer.Exit(code=2) from None
    console.print(f"[green]ok[/green] {path}: rig {rig.name!r}, {len(rig.cameras)} cameras, "
                  f"trigger {rig.trigger.kind} at {rig.trigger.fps:g} fps", highlight=False)
    for cam in rig.cameras:
        console.print(f"  camera {cam.index}: {cam.name} from {cam.edge}", highlight=False)
    from flytrack_host.pipeline import calibration_problems, load_cameras

    try:
        cameras = load_cameras(rig)
    except Exception as exc:  # a calibration that does not load is an error of the rig
        err_console.print(f"[red]error[/red] calibration {rig.calibration_path}: {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    for problem in calibration_problems(rig, cameras):
        err_console.print(f"[yellow]warning[/yellow] {problem}", highlight=False, soft_wrap=True)


def _register_groups() -> None:
    for module, attr, name, help_text in _GROUPS:
        sub = getattr(importlib.import_module(module), attr)
        app.add_typer(sub, name=name, help=help_text)
    for group_module, module, func, name in _GROUP_COMMANDS:
        group = importlib.import_module(group_module).app
        group.command(name)(getattr(importlib.import_module(module), func))
    for module, func, name in _COMMANDS:
        app.command(name)(getattr(importlib.import_module(module), func))


_register_groups()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
