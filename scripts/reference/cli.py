"""The command line's reference page: every command and option of `flytrack` (the typer app in
flytrack_host.cli, walked as click sees it), hidden ones left out as `--help` leaves them out."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from .common import GENERATED_NOTE, _cell, _num


@dataclass
class CliParam:
    name: str               # --option (the first long name) or ARGUMENT
    names: list[str]        # every spelling: --port, -p, --no-progress ...
    kind: str               # "option" | "argument"
    type: str
    default: str            # "" when none
    required: bool
    help: str


@dataclass
class CliCommand:
    path: list[str]         # ["calibrate", "selfcal"]
    help: str
    params: list[CliParam] = field(default_factory=list)
    group: bool = False

    @property
    def line(self) -> str:
        return " ".join(["flytrack", *self.path])

    @property
    def anchor(self) -> str:
        return "-".join(["flytrack", *self.path])


def _root_command():
    import typer

    from flytrack_host.cli import app

    return typer.main.get_command(app)


def walk_cli() -> list[CliCommand]:
    """Every command and group of `flytrack`, depth first in the order `--help` lists them; hidden
    commands and options are left out, as `--help` leaves them out."""
    root = _root_command()
    ctx_cls = type(root).context_class
    out: list[CliCommand] = []

    def visit(cmd, path: list[str], parent_ctx) -> None:
        ctx = ctx_cls(cmd, info_name=path[-1] if path else "flytrack", parent=parent_ctx)
        is_group = hasattr(cmd, "list_commands")
        entry = CliCommand(path=path, help=(cmd.help or "").strip(), group=is_group)
        for p in cmd.params:
            if getattr(p, "hidden", False) or p.name == "help":
                continue
            entry.params.append(_param(p, ctx))
        out.append(entry)
        if is_group:
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                if sub is not None and not sub.hidden:
                    visit(sub, [*path, name], ctx)

    visit(root, [], None)
    return out


def _param(p, ctx) -> CliParam:
    is_option = type(p).__name__.endswith("Option")
    try:
        shown = p.display_type(ctx) or ""
    except Exception:  # a type typer cannot name: fall back on the annotation
        shown = ""
    shown = shown.strip("<>")
    m = re.fullmatch(r"list\[(.*)\]", shown)
    shown = m.group(1) if m else shown
    bounds = []
    if shown.endswith(" range"):  # typer's IntRange / FloatRange: the bounds are on the parameter
        shown = shown.removesuffix(" range")
        lo, hi = getattr(p, "min", None), getattr(p, "max", None)
        bounds = ([f"≥ {_num(lo)}"] if lo is not None else []) + ([f"≤ {_num(hi)}"] if hi is not None else [])
    shown = {"str": "text", "float": "number", "int": "integer", "bool": "true|false", "Path": "path"}.get(shown, shown)
    shown = ", ".join([shown, *bounds])
    if is_option and getattr(p, "is_flag", False):
        shown = "flag"
    default = ""
    if not p.required and p.default is not None and not callable(p.default):
        d = p.default
        if isinstance(d, bool):
            default = "on" if d else "off"
        elif isinstance(d, list | tuple):
            default = ", ".join(map(str, d)) if d else ""
        else:
            default = str(d)
    names = [*p.opts, *getattr(p, "secondary_opts", [])]
    name = next((n for n in p.opts if n.startswith("--")), p.opts[0]) if is_option else p.name.upper()
    if getattr(p, "multiple", False) or getattr(p, "nargs", 1) == -1:
        shown = f"{shown}, repeatable" if is_option else f"{shown} ..."
    return CliParam(name=name, names=names if is_option else [name], kind="option" if is_option else "argument",
                    type=shown, default=default, required=bool(p.required), help=(p.help or "").strip())


def cli_page(commands: list[CliCommand] | None = None) -> str:
    commands = commands if commands is not None else walk_cli()
    lines = [
        GENERATED_NOTE,
        "# Command line: `flytrack`",
        "",
        "Every command and option of `flytrack`, generated from the program itself. `flytrack COMMAND "
        "--help` prints the same in a terminal. Run it as `.venv/bin/flytrack` from the repository, or "
        "as `flytrack` once `source .venv/bin/activate` has put `.venv/bin` on your `PATH`.",
        "",
        "A flag is on when given (`--no-...` spellings turn one off). An option or argument the "
        "command cannot use (an unknown option, a value of the wrong type) is one line naming it, "
        "and exit code 2.",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    for c in commands:
        if c.path and not c.group:
            lines.append(f"| [`{c.line}`](#{c.anchor}) | {_cell(_first_sentence(c.help))} |")
    lines.append("")
    for c in commands:
        if not c.path:
            continue
        level = "#" * min(2 + len(c.path) - 1, 4)
        lines += [f"{level} `{c.line}` {{#{c.anchor}}}", ""]
        if c.help:
            lines += [c.help, ""]
        if c.group:
            subs = [d for d in commands if d.path[:-1] == c.path and len(d.path) == len(c.path) + 1]
            lines += ["Commands: " + ", ".join(f"[`{d.path[-1]}`](#{d.anchor})" for d in subs) + ".", ""]
            continue
        args = [p for p in c.params if p.kind == "argument"]
        usage = " ".join([c.line, "[OPTIONS]" if any(p.kind == "option" for p in c.params) else "",
                          *[p.name if p.required else f"[{p.name}]" for p in args]])
        lines += ["```text", " ".join(usage.split()), "```", ""]
        if c.params:
            lines += ["| argument or option | type | default | what it sets |", "|---|---|---|---|"]
            for p in c.params:
                spelled = ", ".join(f"`{n}`" for n in p.names)
                default = f"`{p.default}`" if p.default else ("required" if p.required else "")
                lines.append(f"| {spelled} | {_cell(p.type)} | {_cell(default)} | {_cell(p.help)} |")
            lines.append("")
    return "\n".join(lines)


def _first_sentence(text: str) -> str:
    text = " ".join(text.split())
    m = re.match(r"(.+?[.:])(\s|$)", text)
    return m.group(1).rstrip(":") + ("." if m and m.group(1).endswith(":") else "") if m else text
