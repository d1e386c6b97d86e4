"""`flytrack rules check|replay`, and the rules part of `flytrack run` (`--rules`, or `rules =` in the rig)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from flytrack_host.actuation.rules import RulesError, RuleSet, bind_rules, load_rules, load_rules_skipping
from flytrack_host.rig import RigConfig, RigError, load_rig

app = typer.Typer(help="Closed-loop rules: check a rules file, replay it on a recording.", no_args_is_help=True)
err = Console(stderr=True)


def _fail(exc: Exception) -> typer.Exit:
    for line in str(exc).splitlines():
        err.print(f"[red]error[/red] {escape(line)}", highlight=False, soft_wrap=True)
    return typer.Exit(code=2)


@app.command("check")
def check_command(
    rules: Path = typer.Argument(..., help="The rules TOML file."),
    rig: Path | None = typer.Option(None, "--rig", help="Rig file whose [[actuators]] the actions name."),
) -> None:
    """Validate a rules file (and, with --rig, that every action names an actuator of the rig and only
    uses fields its kind takes); every problem names the file, the rule and the field."""
    try:
        rs = load_rules(rules)
        if rig is not None:
            bind_rules(rs, load_rig(rig).actuators, rules)
    except (RulesError, RigError) as exc:
        raise _fail(exc) from None
    console = Console()
    for r in rs.rules:
        acts = ", ".join(a.output for a in r.actions) or "nothing"
        console.print(f"[green]ok[/green] rule {r.name!r}: drives {acts}{' (dry run)' if r.dry_run else ''}",
                      highlight=False)


@app.command("replay")
def replay_command(
    recording: Path = typer.Argument(..., help="A recording folder (or its recording.h5)."),
    rules: Path = typer.Option(..., "--rules", help="The rules TOML file to try."),
    plot: Path | None = typer.Option(None, "--plot", help="Figure of the tracks and firing points "
                                     "(default: replay.png beside the recording)."),
    json_path: Path | None = typer.Option(None, "--json", help="Write the firings as JSON here."),
    no_prediction: bool = typer.Option(False, "--no-prediction", help="Judge every rule on the frame's own "
                                       "estimate (as with predict = false)."),
    lead_ms: float | None = typer.Option(None, "--lead-ms", help="Time the actions need before their frame "
                                         "(default: by output kind from the recording's rig file)."),
) -> None:
    """When the rules would have fired on a past recording, with a plot of the tracks and the firing
    points: design rules on old data. The same evaluator as the live engine, fed the recorded tracks and
    each frame's measured trigger-to-estimate latency."""
    from rich.progress import Progress

    from flytrack_host.actuation.replay import fires_as_dicts, plot_replay, replay
    from flytrack_host.recording import load_recording
    from flytrack_host.recording.finalize import RecordingError

    try:
        rs = load_rules(rules)
        rec = load_recording(recording)
    except (RulesError, RecordingError) as exc:
        raise _fail(exc) from None
    if not len(rec.table("kalman_estimates")):
        raise _fail(RecordingError(f"{recording}: no 3D tracks (kalman_estimates) to replay the rules on"))
    console = Console()
    with Progress(console=console, transient=True) as prog:
        prog.add_task("replaying", total=None)
        try:
            res = replay(rec, rs, prediction=False if no_prediction else None,
                         lead_s=None if lead_ms is None else lead_ms / 1e3)
        except ValueError as exc:
            raise _fail(exc) from None
        out_plot = plot or (Path(recording) if Path(recording).is_dir() else Path(recording).parent) / "replay.png"
        plot_replay(rec, rs, res, out_plot)
    t = Table(title=f"{len(res.fires)} firings over {res.frames} frames ({res.fps:g} fps)")
    for c in ("rule", "obj", "frame", "time s", "x", "y", "z"):
        t.add_column(c, justify="right")
    for d in fires_as_dicts(res):
        t.add_row(d["rule"], str(d["obj_id"]), str(d["frame"]), f"{d['time_s']:.3f}", f"{d['x']:.3f}",
                  f"{d['y']:.3f}", f"{d['z']:.3f}")
    console.print(t)
    for name, sup in res.suppressed.items():
        if sup:
            console.print(f"{name}: suppressed {sup}", highlight=False)
    if len(res.recorded):
        console.print(f"the recording's own firings: {len(res.recorded)} action rows "
                      f"(actuation_firings)", highlight=False)
    console.print(f"plot: {out_plot}", highlight=False)
    if json_path is not None:
        json_path.write_text(json.dumps({"fps": res.fps, "frames": res.frames, "firings": fires_as_dicts(res),
                                         "suppressed": res.suppressed}, indent=1))
        console.print(f"json: {json_path}", highlight=False)


class RunRules:
    """The rules of a `flytrack run`, validated before anything starts."""

    def __init__(self, rig: RigConfig, path: Path, rules: RuleSet):
        self.rig, self.path, self.rules = rig, path, rules
        self.problems: list[str] = []  # rules left out (--skip-bad-rules)

    def engine(self, fps: float, session: Any) -> Any:
        from flytrack_host.actuation.engine import ActuationEngine

        ctx = {"base_dir": self.rig.base_dir,
               "trigger": (lambda: session.device) if session is not None else None,
               "clock": session.clock if session is not None else None}
        eng = ActuationEngine(self.rules, self.rig.actuators, fps, ctx, self.path)
        eng.rule_problems = list(self.problems)
        return eng


def rules_for_run(rig: RigConfig, rules: Path | None, skip_bad: bool = False) -> RunRules | None:
    """--rules, else the rig's `rules`; a bad file (or an action naming an unknown actuator) exits 2
    with every problem listed, unless `skip_bad`: then the run goes on with the good rules, and each
    problem is printed, logged in the recording and counted (`RunRules.problems`). None when there are
    no rules (actuators then drive nothing: said once)."""
    path = rules or rig.rules_path
    if path is None:
        if rig.actuators:
            names = ", ".join(f"{a.name} ({a.kind})" for a in rig.actuators)
            err.print(f"[yellow]note[/yellow] no rules file (rig `rules = ...` or --rules): the actuators "
                      f"{names} are not driven", highlight=False, soft_wrap=True)
        return None
    if skip_bad:
        rs, problems = load_rules_skipping(path, rig.actuators)
        for p in problems:
            err.print(f"[yellow]rule left out[/yellow] {escape(p)}", highlight=False, soft_wrap=True)
        if rs is None:
            err.print(f"[yellow]note[/yellow] no usable rule in {path}: tracking and recording without rules",
                      highlight=False, soft_wrap=True)
            return None
        out = RunRules(rig, Path(path), rs)
        out.problems = problems
        return out
    try:
        rs = load_rules(path)
        bind_rules(rs, rig.actuators, path)
    except RulesError as exc:
        err.print("(or run with --skip-bad-rules to track and record with the good rules only)", highlight=False)
        raise _fail(exc) from None
    return RunRules(rig, Path(path), rs)
