"""The manual's reference pages against the code, both ways: every command, option, rig-file field
and rules-file field has an entry, and no entry names something the code no longer has. The pages are
generated (scripts/gen_reference.py, at every `make docs`); these tests walk the code on their own and
read the pages as a reader gets them. Also: the example files are valid, each field's example is
accepted by the validator, and every `flytrack ...` line in the manual and the README names a command
and options that exist."""

from __future__ import annotations

import copy
import re
import shlex
import subprocess
import sys
import tomllib
import typing
from pathlib import Path

import pytest
import typer
from pydantic import BaseModel

from flytrack_host.actuation.rules import RulesError, RuleSet, parse_rules
from flytrack_host.cli import app
from flytrack_host.rig import RigConfig, RigError, parse_rig

REPO = Path(__file__).resolve().parents[2]
FLYTRACK = [sys.executable, "-m", "flytrack_host.cli"]


sys.path.insert(0, str(REPO / "scripts"))  # the generator's package, scripts/reference/
from reference import cli as ref_cli  # noqa: E402
from reference import models as ref_models  # noqa: E402
from reference import recording as ref_recording  # noqa: E402
from reference import rig_rules as ref_rig_rules  # noqa: E402

# ------------------------------------------------------------------------------------------------
# The command line


def _cli_params() -> dict[tuple[str, ...], set[str]]:
    """command path -> every spelling of its visible options and its arguments (upper case)."""
    root = typer.main.get_command(app)
    ctx_cls = type(root).context_class
    out: dict[tuple[str, ...], set[str]] = {}

    def visit(cmd, path: tuple[str, ...]) -> None:
        ctx = ctx_cls(cmd)
        names = set()
        for p in cmd.params:
            if p.hidden or p.name == "help":
                continue
            if type(p).__name__.endswith("Option"):
                names.update(p.opts, getattr(p, "secondary_opts", []))
            else:
                names.add(p.name.upper())
        out[path] = names
        if hasattr(cmd, "list_commands"):
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                if not sub.hidden:
                    visit(sub, (*path, name))

    visit(root, ())
    return out


def _cli_entries(page: str) -> dict[tuple[str, ...], set[str]]:
    """command path -> the names its section of the page lists."""
    out: dict[tuple[str, ...], set[str]] = {(): set()}
    current: tuple[str, ...] | None = None
    for line in page.splitlines():
        m = re.match(r"#{2,4} `flytrack ([^`]+)` \{#[\w-]+\}$", line)
        if m:
            current = tuple(m.group(1).split())
            out[current] = set()
        elif current is not None and line.startswith("| `"):
            first = line.split(" | ")[0].lstrip("| ")
            out[current].update(re.findall(r"`([^`]+)`", first))
    return out


def test_every_command_and_option_has_an_entry_and_every_entry_exists():
    code, page = _cli_params(), _cli_entries(ref_cli.cli_page())
    assert set(code) == set(page), (
        f"commands without a section: {sorted(set(code) - set(page))}; "
        f"sections of commands that do not exist: {sorted(set(page) - set(code))}")
    problems = []
    for path, names in code.items():
        if names - page[path]:
            problems.append(f"flytrack {' '.join(path)}: no entry for {sorted(names - page[path])}")
        if page[path] - names:
            problems.append(f"flytrack {' '.join(path)}: entries for {sorted(page[path] - names)}, which do not exist")
    assert not problems, "\n".join(problems)


def test_every_option_has_help_text():
    """An entry without a description tells the reader nothing: the option's help= is missing."""
    bare = [f"flytrack {' '.join(c.path)} {p.name}" for c in ref_cli.walk_cli() for p in c.params if not p.help]
    assert not bare, f"options and arguments without help text: {bare}"


# ------------------------------------------------------------------------------------------------
# The rig file and the rules file


def _fields(root: type) -> set[tuple[str, str]]:
    """(model class, key as written) of every field reachable from `root`."""
    out: set[tuple[str, str]] = set()
    seen: set[type] = set()

    def models_in(ann) -> list[type]:
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            return [ann]
        return [m for a in typing.get_args(ann) for m in models_in(a)]

    def visit(model: type) -> None:
        if model in seen:
            return
        seen.add(model)
        for name, fi in model.model_fields.items():
            if fi.exclude:
                continue
            out.add((model.__name__, fi.alias or name))
            for sub in models_in(fi.annotation):
                visit(sub)

    visit(root)
    return out


def _resolve(root: type, key: str, shared: dict[str, str]) -> type | None:
    """The model a section key of the page names, walked from the root by field names."""
    by_key = {v: k for k, v in shared.items()}
    model, parts = root, key.split(".") if key else []
    for i in range(len(parts), 0, -1):           # the longest shared prefix ("region.box") first
        if ".".join(parts[:i]) in by_key:
            name = by_key[".".join(parts[:i])]
            model = next((m for m in _all_models(root) if m.__name__ == name), None)
            parts = parts[i:]
            break
    for part in parts:
        if model is None:
            return None
        fi = next((f for n, f in model.model_fields.items() if (f.alias or n) == part), None)
        if fi is None:
            return None
        subs = [a for a in _flatten(fi.annotation) if isinstance(a, type) and issubclass(a, BaseModel)]
        model = subs[0] if subs else None
    return model


def _flatten(ann) -> list:
    return [ann, *[x for a in typing.get_args(ann) for x in _flatten(a)]]


def _all_models(root: type) -> list[type]:
    out, todo = [], [root]
    while todo:
        m = todo.pop()
        if m in out:
            continue
        out.append(m)
        for fi in m.model_fields.values():
            todo += [a for a in _flatten(fi.annotation) if isinstance(a, type) and issubclass(a, BaseModel)]
    return out


def _model_entries(page: str, root: type, shared: dict[str, str]) -> tuple[set[tuple[str, str]], list[str]]:
    """(model class, key) of every entry on the page, and the entries that name nothing in the code."""
    entries, stale = set(), []
    section_model: type | None = None
    for line in page.splitlines():
        sec = re.match(r"## (.+) \{#([\w-]+)\}$", line)
        field = re.match(r"### `([\w]+)` \{#([\w-]+)\}$", line)
        if sec:
            title = sec.group(1)
            key = "" if title == "Top level" else title.strip("[]")
            if not (title == "Top level" or title.startswith("[") or key in shared.values()):
                section_model = None  # a section of prose or tables (output kinds), not of fields
                continue
            section_model = _resolve(root, key, shared)
            if section_model is None:
                stale.append(f"section {title}")
                continue
            if key and key not in shared.values():   # a table that is a field of its parent
                parent_key, _, name = key.rpartition(".")
                parent = _resolve(root, parent_key, shared)
                entries.add((parent.__name__ if parent else "?", name))
        elif field:
            names = {(fi.alias or n) for n, fi in section_model.model_fields.items()} if section_model else set()
            if field.group(1) not in names:
                stale.append(f"{section_model.__name__ if section_model else '?'}.{field.group(1)}")
            else:
                entries.add((section_model.__name__, field.group(1)))
    return entries, stale


@pytest.mark.parametrize("which", ["rig", "rules"])
def test_every_field_has_an_entry_and_every_entry_exists(which):
    root, page, shared = ((RigConfig, ref_rig_rules.rig_page(), {}) if which == "rig" else
                          (RuleSet, ref_rig_rules.rules_page(), ref_rig_rules.RULES_SHARED))
    entries, stale = _model_entries(page, root, shared)
    missing = _fields(root) - entries
    assert not missing, f"{which} fields without an entry: {sorted(missing)}"
    assert not stale, f"{which} page entries that name no field: {stale}"


@pytest.mark.parametrize("which", ["rig", "rules"])
def test_every_field_is_described_typed_and_has_an_example(which):
    docs = ref_rig_rules.rig_docs() if which == "rig" else ref_rig_rules.rules_docs()
    problems = []
    for sec in docs.sections:
        for f in [sec.table_field] * (sec.table_field is not None) + sec.fields:
            where = f"{sec.key or '(top)'}.{f.name}"
            if not f.description:
                problems.append(f"{where}: no description (Field(description=...) in the model)")
            if not f.type:
                problems.append(f"{where}: no type")
            if f is not sec.table_field and not f.example and "](#" not in f.type:
                problems.append(f"{where}: no example")
            suffix = next((u for s, u in ref_models._UNIT_SUFFIXES if f.name.endswith(s)), "")
            if suffix and f.unit != suffix:
                problems.append(f"{where}: its name says {suffix}, the page says {f.unit!r}")
    assert not problems, "\n".join(problems)


def _place(doc: dict, example: str) -> dict:
    """Put an example (a `[table]` or `[[table]]` header, then `key = value`) into a whole document:
    the key's value is replaced in that table, or in the first item of a list of tables."""
    lines = example.strip().splitlines()
    header = lines[0].strip("[]") if lines[0].startswith("[") else ""
    key, value = next(iter(tomllib.loads(lines[-1]).items()))
    node = doc
    for part in header.split(".") if header else []:
        node = node.setdefault(part, {})
        if isinstance(node, list):
            node = node[0]
    node[key] = value
    return doc


@pytest.mark.parametrize("which", ["rig", "rules"])
def test_every_example_is_accepted_by_the_validator(which):
    """Each field's example, put into the example file, still validates: no example shows a value
    the file would refuse."""
    docs = ref_rig_rules.rig_docs() if which == "rig" else ref_rig_rules.rules_docs()
    path = REPO / "examples" / ("rig.toml" if which == "rig" else "closed_loop.toml")
    base = tomllib.loads(path.read_text())
    problems = []
    for sec in docs.sections:
        for f in sec.fields:
            if not f.example:
                continue
            doc = _place(copy.deepcopy(base), f.example)
            try:
                parse_rig(doc, path) if which == "rig" else parse_rules(doc, path)
            except (RigError, RulesError) as exc:
                problems.append(f"{sec.key}.{f.name}: example\n{f.example}\nrefused: {exc}")
    assert not problems, "\n".join(problems)


# ------------------------------------------------------------------------------------------------
# The example files


def test_the_example_rig_file_passes_rig_check():
    r = subprocess.run([*FLYTRACK, "rig", "check", "examples/rig.toml"], cwd=REPO, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ok examples/rig.toml" in r.stdout
    assert "error" not in r.stderr


def test_the_example_rig_file_shows_every_table_and_its_rules_line_works_as_written(tmp_path):
    """examples/rig.toml shows every table of the rig file, and uncommenting its `rules = ...` line,
    where it is, gives a rig with its rules (it once said to add it below the [[cameras]] tables,
    where TOML makes it a key of the last camera: `cameras[3].rules: Extra inputs are not permitted`)."""
    text = (REPO / "examples" / "rig.toml").read_text()
    data = tomllib.loads(text)
    tables = {n for n, fi in RigConfig.model_fields.items() if not fi.exclude and ref_models._models_in(fi.annotation)}
    assert tables <= set(data), f"examples/rig.toml has no {sorted(tables - set(data))}"
    assert text.count('# rules = "closed_loop.toml"') == 1
    (tmp_path / "rig.toml").write_text(text.replace('# rules = "closed_loop.toml"', 'rules = "closed_loop.toml"'))
    (tmp_path / "closed_loop.toml").write_text((REPO / "examples" / "closed_loop.toml").read_text())
    r = subprocess.run([*FLYTRACK, "rig", "check", str(tmp_path / "rig.toml")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert tomllib.loads((tmp_path / "rig.toml").read_text()).get("rules") == "closed_loop.toml"


def test_the_example_rules_file_binds_to_the_example_rig():
    r = subprocess.run([*FLYTRACK, "rules", "check", "examples/closed_loop.toml", "--rig", "examples/rig.toml"],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


# ------------------------------------------------------------------------------------------------
# Commands written in the manual and the README


def _doc_files() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def _command_lines(text: str) -> list[str]:
    """`flytrack ...` lines of the code blocks, continuation lines joined, prompts and comments cut."""
    out, in_block, pending = [], False, ""
    for raw in text.splitlines():
        if raw.lstrip().startswith("```"):
            in_block = not in_block
            continue
        if not in_block:
            continue
        line = pending + raw.strip()
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        pending = ""
        line = re.sub(r"^\$ ", "", line)
        m = re.search(r"(?:^|[;&|(]\s*|\bthen\s+)(?:\S*/)?flytrack ([^;&|#]*)", line)
        if m and not line.startswith("#"):
            out.append("flytrack " + m.group(1).strip())
    return out


def test_every_flytrack_command_in_the_docs_exists_with_its_options():
    code = _cli_params()
    groups = {p for p in code if any(q[: len(p)] == p and len(q) > len(p) for q in code)}
    problems = []
    for path in _doc_files():
        for line in _command_lines(path.read_text()):
            try:
                words = shlex.split(line)[1:]
            except ValueError:
                problems.append(f"{path.relative_to(REPO)}: cannot parse {line!r}")
                continue
            cmd: tuple[str, ...] = ()
            while words and (*cmd, words[0]) in code:
                cmd = (*cmd, words.pop(0))
            if cmd in groups and not (words and words[0] in ("--help",)):
                problems.append(f"{path.relative_to(REPO)}: {line!r}: `flytrack {' '.join(cmd)}` needs a command")
                continue
            for w in words:
                opt = w.split("=", 1)[0]
                if opt.startswith("--") and opt != "--help" and opt not in code[cmd]:
                    problems.append(f"{path.relative_to(REPO)}: {line!r}: flytrack {' '.join(cmd)} has no {opt}")
    assert not problems, "\n".join(problems)


# ------------------------------------------------------------------------------------------------
# The recording's tables


def test_every_recording_table_and_column_has_an_entry_and_every_note_names_a_column():
    from flytrack_host.recording.schema import TABLES

    page = ref_recording.recording_page()
    problems = []
    for name, dt in TABLES.items():
        if name not in ref_recording.TABLE_NOTES or not ref_recording.TABLE_NOTES[name][0]:
            problems.append(f"table {name}: no description in TABLE_NOTES")
        if f"## `{name}`" not in page:
            problems.append(f"table {name}: no section")
        problems += [f"{name}.{c}: no row" for c in dt.names if f"| `{c}` |" not in page]
    for name, (_, notes) in ref_recording.TABLE_NOTES.items():
        if name not in TABLES:
            problems.append(f"TABLE_NOTES names a table that does not exist: {name}")
            continue
        problems += [f"TABLE_NOTES {name}.{c}: no such column" for c in notes if c not in TABLES[name].names]
    assert not problems, "\n".join(problems)


def test_every_output_kind_has_a_row_with_its_keys_address_and_acknowledgement():
    from flytrack_host.actuation.rules import KIND_FIELDS
    from flytrack_host.rig import ActuatorKind

    rows = {k: (keys, addr, ack) for k, keys, addr, ack in ref_rig_rules.output_kinds()}
    assert set(rows) == set(typing.get_args(ActuatorKind)) == set(KIND_FIELDS)
    for kind, (keys, addr, ack) in rows.items():
        assert keys and addr and ack and ack != "?", (kind, keys, addr, ack)


# ------------------------------------------------------------------------------------------------
# Make targets


def _make_targets() -> set[str]:
    """Every target `make help` names, the per-part ones included."""
    out = subprocess.run(["make", "--no-print-directory", "help"], cwd=REPO, capture_output=True, text=True,
                         timeout=60).stdout
    names = set(re.findall(r"^\s+make ([a-z][a-z0-9-]*)", out, re.M))
    part = re.search(r"per part:\s*(.*)", out)
    return names | set(part.group(1).split() if part else [])


def test_every_make_target_has_an_entry_and_every_make_command_in_the_docs_exists():
    targets = _make_targets()
    page = (REPO / "docs" / "reference" / "make.md").read_text()
    documented = set(re.findall(r"`(?:make )?([a-z][a-z0-9-]*)(?: [A-Z_]+=[^`]*)?`", page))
    assert targets - {"help"} <= documented, f"make targets without an entry: {sorted(targets - documented)}"
    known = targets | {"help", "clean", "format", "docs", "docs-serve", "test-python", "test-c", "cbuild",
                       "setup", "firmware-avr"}
    problems = []
    for path in _doc_files():
        text = path.read_text()
        blocks = re.findall(r"```.*?```", text, re.S)
        code = blocks + re.findall(r"`[^`\n]+`", re.sub(r"```.*?```", "", text, flags=re.S))
        for m in re.finditer(r"(?:^|[\s`(])make ([a-z][a-z0-9-]*)", "\n".join(code)):
            if m.group(1) not in known:
                problems.append(f"{path.relative_to(REPO)}: make {m.group(1)}")
    assert not problems, "make targets that do not exist: " + ", ".join(sorted(set(problems)))


# ------------------------------------------------------------------------------------------------
# The README


def test_the_readme_is_short_and_its_links_lead_somewhere():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 200, "the README is the front page: at most 200 lines; the rest goes in docs/"
    missing = [t for t in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text)
               if not t.startswith(("http://", "https://")) and not (REPO / t).exists()]
    assert not missing, f"README links to files that do not exist: {missing}"
