"""The house plan of the host package, held: its subsystems, what each may import, no import circle.

`ALLOWED` is the one table of the plan. Each subsystem is a package of `flytrack_host` whose docstring
ends with the same "May import:" list; `docs/architecture.md` draws the same boxes. Every import counts,
at module level or inside a function (a lazy import is still a dependency), and `cli.py` at the top may
import anything.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from flytrack_host.util.testing import strongly_connected

PKG = Path(__file__).resolve().parents[1] / "flytrack_host"

# subsystem -> the subsystems it may import, lowest first. Data flows one way: edges -> intake ->
# tracking -> recording / live / actuation; the offline and simulation layers sit on top.
ALLOWED: dict[str, set[str]] = {
    "util": set(),
    "protocol": {"util"},
    "geometry": {"util"},
    "tracking": {"util", "protocol", "geometry"},
    "rig": {"util", "protocol", "tracking"},
    "intake": {"util", "protocol", "rig", "tracking"},
    "trigger": {"util", "protocol", "rig"},
    "recording": {"util", "protocol", "geometry", "tracking", "intake"},
    "live": {"util", "protocol", "geometry", "tracking", "rig", "intake"},
    "actuation": {"util", "protocol", "tracking", "rig", "trigger", "recording"},
    "edges": {"util", "protocol", "geometry"},
    "dvs": {"util", "protocol", "geometry", "tracking", "intake"},
    "pipeline": {"util", "protocol", "geometry", "tracking", "rig", "intake", "trigger", "recording", "live",
                 "actuation", "dvs"},
    "calibration": {"util", "protocol", "geometry", "recording", "dvs"},
    "io": {"util", "protocol", "geometry", "tracking", "trigger", "recording"},
    "batch": {"util", "geometry", "recording", "io"},
    "fish": {"util", "geometry"},
    "sim": {"util", "protocol", "geometry", "tracking", "rig", "intake", "trigger", "recording", "live",
            "actuation", "edges", "dvs", "pipeline", "calibration", "io"},
}
TOP_LEVEL_FILES = {"__init__.py", "cli.py", "py.typed"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts}


def _imports(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """The flytrack_host modules `path` imports anywhere in it: `from a.b import c` is a.b.c when that
    is a module, else a.b (the package's __init__)."""
    out: set[str] = set()
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("flytrack_host"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: len(name.split(".")) - (node.level - 1) - (0 if is_pkg else 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("flytrack_host"):
                continue
            for a in node.names:
                out.add(f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod)
    out.discard(name)
    return out


def _subsystem(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_the_top_level_is_the_subsystems_and_the_command_line() -> None:
    entries = {p.name for p in PKG.iterdir() if p.name != "__pycache__"}
    packages = {p.name for p in PKG.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert packages == set(ALLOWED), (
        f"subsystems not in the plan: {sorted(packages - set(ALLOWED))}; "
        f"in the plan but missing: {sorted(set(ALLOWED) - packages)} (host/tests/test_layering.py ALLOWED)")
    loose = entries - packages - TOP_LEVEL_FILES
    assert not loose, f"a module at the top level of flytrack_host: {sorted(loose)}; give it a subsystem"


@pytest.mark.parametrize("subsystem", sorted(ALLOWED))
def test_each_subsystem_says_what_it_may_import(subsystem: str) -> None:
    doc = ast.get_docstring(ast.parse((PKG / subsystem / "__init__.py").read_text())) or ""
    assert "May import:" in doc, f"flytrack_host/{subsystem}/__init__.py: the docstring has no 'May import:' line"
    said = " ".join(doc.split("May import:")[-1].split()).rstrip(".")
    said_set = set() if said.startswith("nothing") else {s.strip() for s in said.split(",")}
    assert said_set == ALLOWED[subsystem], (
        f"{subsystem}: the docstring says {sorted(said_set)}, the plan {sorted(ALLOWED[subsystem])}")


def test_no_subsystem_imports_one_it_may_not() -> None:
    modules = _modules()
    bad = []
    for name, path in sorted(modules.items()):
        mine = _subsystem(name)
        if mine is None or mine == "cli":
            continue
        for target in sorted(_imports(path, name, modules)):
            theirs = _subsystem(target)
            if theirs is None or theirs == mine or theirs == "__version__":
                continue
            if theirs not in ALLOWED.get(mine, set()):
                bad.append(f"{name} imports {target}: {mine} may not import {theirs}")
    assert not bad, "\n".join(bad)


def test_no_import_circle_between_modules() -> None:
    modules = _modules()
    graph = {name: _imports(path, name, modules) for name, path in modules.items()}
    cycles = strongly_connected(graph)
    assert not cycles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_circle() -> None:
    """The check above is only as good as this: a circle of three and a self-contained chain."""
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_the_architecture_page_shows_the_same_boxes() -> None:
    """docs/architecture.md: its diagram has one box per subsystem and only allowed arrows; its table
    lists each subsystem with exactly what the plan lets it import."""
    import re

    page = (PKG.parents[1] / "docs" / "architecture.md").read_text()
    diagram = page.split("```mermaid", 1)[1].split("```", 1)[0]
    boxes: set[str] = set()
    for line in diagram.splitlines()[2:]:  # after "flowchart BT"
        src, _, dst = line.strip().partition("-->")
        src = src.strip()
        if not src:
            continue
        boxes.add(src)
        for target in (t.strip() for t in dst.split("&") if t.strip()):
            boxes.add(target)
            assert target in ALLOWED.get(src, set()), f"the diagram draws {src} --> {target}; the plan forbids it"
    assert boxes == set(ALLOWED), f"diagram boxes {sorted(boxes ^ set(ALLOWED))} differ from the subsystems"
    rows = dict(re.findall(r"^\| `([a-z]+)` \| [^|]+ \| ([^|]+) \|$", page, re.M))
    assert set(rows) == set(ALLOWED), f"table rows {sorted(set(rows) ^ set(ALLOWED))} differ from the subsystems"
    for name, said in rows.items():
        said_set = set() if said.strip() == "nothing" else {s.strip() for s in said.split(",")}
        assert said_set == ALLOWED[name], f"docs/architecture.md: {name} may import {sorted(said_set)}?"
