"""No C module calls back into a module that calls it: calls between object files flow one way.

For every target CMake built under build/ (libraries, daemons, tests), its object files and those of the
targets it links (read from CMake's DependInfo.cmake, so stale objects of removed sources and targets are
left out) are read with `nm`: an object that leaves a symbol undefined depends on the object that defines
it. Any cycle in that graph (ev_reader.c calling ev_aedat.c calling ev_reader.c, say) fails the test, named with
the symbols along it. A cycle means the two files are one module in two pieces: neither can be read,
tested or replaced alone. Needs `make cbuild` first. The components are found by the same
`strongly_connected` as the Python layering test's (flytrack_host.util.testing).
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
import subprocess
from collections import defaultdict
from pathlib import Path

import pytest

from flytrack_host.util.testing import strongly_connected

REPO = Path(__file__).resolve().parents[2]
BUILD = Path(os.environ.get("FLYTRACK_BUILD_DIR", REPO / "build"))
NM = shutil.which("nm")

# nm -P types of a symbol an object defines for others: uppercase except U (undefined), plus "i"
# (GNU indirect function: what GCC target_clones makes, global though shown lowercase) and "u".
DEFINED = set("ABCDGRSTVW") | {"i", "u"}


def symbols(objects: list[Path]) -> dict[Path, tuple[set[str], set[str]]]:
    """Per object: (global symbols it defines, symbols it leaves undefined)."""
    out: dict[Path, tuple[set[str], set[str]]] = {o: (set(), set()) for o in objects}
    for i in range(0, len(objects), 200):  # a few nm calls, not one per object
        chunk = objects[i:i + 200]
        res = subprocess.run([NM, "-P", "-A", *map(str, chunk)], capture_output=True, text=True, check=True)
        for line in res.stdout.splitlines():
            # "path.o: name type [value size]"
            head, _, rest = line.partition(": ")
            parts = rest.split()
            if len(parts) < 2:
                continue
            name, kind = parts[0], parts[1]
            defined, undefined = out[Path(head)]
            if kind == "U":
                undefined.add(name)
            elif kind in DEFINED:
                defined.add(name)
    return out


def graph(objects: list[Path]) -> dict[Path, dict[Path, set[str]]]:
    """object -> {object defining a symbol it uses: those symbols}."""
    syms = symbols(objects)
    definers: dict[str, list[Path]] = defaultdict(list)
    for o, (defined, _) in syms.items():
        for s in defined:
            definers[s].append(o)
    g: dict[Path, dict[Path, set[str]]] = {o: defaultdict(set) for o in objects}
    for o, (_, undefined) in syms.items():
        for s in undefined:
            for d in definers.get(s, ()):
                if d != o:
                    g[o][d].add(s)
    return g


def cycles(g: dict[Path, dict[Path, set[str]]]) -> list[tuple[list[Path], list[Path]]]:
    """Per strongly connected component of more than one object (objects that all reach each other):
    one cycle through it (a closed path of objects) and all its objects."""
    sccs = strongly_connected({v: set(ws) for v, ws in g.items()})
    out = []
    for comp in sccs:  # the shortest way round from the first object back to it, inside the component
        members, start = set(comp), min(comp)
        prev: dict[Path, Path] = {}
        frontier = [start]
        end = None
        while frontier and end is None:
            nxt = []
            for u in frontier:
                for w in sorted(g[u]):
                    if w == start:
                        end = u
                        break
                    if w in members and w not in prev:
                        prev[w] = u
                        nxt.append(w)
                if end is not None:
                    break
            frontier = nxt
        path = [end]
        while path[-1] != start:
            path.append(prev[path[-1]])
        out.append(([*reversed(path), start], sorted(comp)))
    return out


def describe(cycle: list[Path], g: dict[Path, dict[Path, set[str]]], names: dict[Path, str]) -> str:
    steps = [names.get(cycle[0], cycle[0].name)]
    for a, b in itertools.pairwise(cycle):
        steps.append(f"--({', '.join(sorted(g[a][b])[:3])})--> {names.get(b, b.name)}")
    return " ".join(steps)


# ---- CMake's targets ------------------------------------------------------------------------------

QUOTED = re.compile(r'"([^"]*)"')


def _cmake_list(text: str, var: str) -> list[str]:
    m = re.search(r"set\(" + var + r"\s*(.*?)\n\s*\)", text, re.S)
    return QUOTED.findall(m.group(1)) if m else []


def target_objects(depend_info: Path, seen: set[Path] | None = None) -> dict[Path, str]:
    """The objects of a target and of the targets it links, each with its source file."""
    seen = set() if seen is None else seen
    if depend_info in seen or not depend_info.is_file():
        return {}
    seen.add(depend_info)
    text = depend_info.read_text()
    objs: dict[Path, str] = {}
    deps = _cmake_list(text, "CMAKE_DEPENDS_DEPENDENCY_FILES")
    for src, obj in zip(deps[0::4], deps[1::4], strict=True):
        o = BUILD / obj
        if o.suffix == ".o" and o.is_file():
            objs[o] = os.path.relpath(src, REPO) if src.startswith(str(REPO)) else src
    for linked in _cmake_list(text, "CMAKE_TARGET_LINKED_INFO_FILES"):
        objs.update(target_objects(Path(linked), seen))
    return objs


def targets() -> dict[str, dict[Path, str]]:
    # The targets of the current configuration (CMake leaves the folder of a target that moved or was
    # removed behind, with its old objects).
    listing = BUILD / "CMakeFiles" / "TargetDirectories.txt"
    if listing.is_file():
        infos = [Path(d) / "DependInfo.cmake" for d in listing.read_text().split()]
    else:
        infos = list(BUILD.glob("**/CMakeFiles/*.dir/DependInfo.cmake"))
    out = {}
    for info in sorted(infos):
        objs = target_objects(info)
        if len(objs) > 1:
            out[info.parent.name.removesuffix(".dir")] = objs
    return out


@pytest.fixture(scope="module")
def built_targets() -> dict[str, dict[Path, str]]:
    if NM is None:
        pytest.fail("nm (binutils) is not installed")
    found = targets()
    if not found:
        pytest.fail(f"no CMake targets with objects under {BUILD}: run `make cbuild` first")
    return found


def test_no_object_level_cycles(built_targets) -> None:
    # One report per knot of sources, from the smallest target that shows it (the library, not every
    # daemon and test that links it).
    found: dict[frozenset[str], tuple[int, str]] = {}
    for target, objs in built_targets.items():
        g = graph(sorted(objs))
        for cyc, comp in cycles(g):
            key = frozenset(objs[o] for o in comp)
            text = f"{target}: {describe(cyc, g, objs)}"
            if len(comp) > len(cyc) - 1:
                text += f" (the same knot holds {', '.join(sorted(objs[o] for o in comp if o not in cyc))})"
            if key not in found or len(objs) < found[key][0]:
                found[key] = (len(objs), text)
    if found:
        pytest.fail("calls between C files go round in a circle:\n  "
                    + "\n  ".join(sorted(t for _, t in found.values())), pytrace=False)


def test_the_graph_sees_the_libraries(built_targets) -> None:
    """The check reads real dependencies: the extractor's API calls its scan, the event readers'
    dispatcher its decoders, the daemon its event side. An empty graph would pass the test above."""
    expected = {
        "flytrack_features": ("edge/feature_extractor/src/features.c", "edge/feature_extractor/src/scan.c"),
        "flytrack_events": ("edge/events/src/ev_reader.c", "edge/events/src/ev_prophesee.c"),
        "flytrack-edge": ("edge/feature_extractor/daemon/edge_main.c", "edge/dvs_daemon/edge_dvs.c"),
    }
    for target, (user, used) in expected.items():
        objs = built_targets.get(target)
        assert objs, f"target {target} not found under {BUILD}"
        g = graph(sorted(objs))
        by_src = {src: o for o, src in objs.items()}
        assert by_src[used] in g[by_src[user]], f"{target}: {user} -> {used} not seen"


def test_a_cycle_is_found(tmp_path) -> None:
    """Two objects that call each other, compiled here: the cycle is reported with its symbols."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None or NM is None:
        pytest.fail("needs a C compiler and nm")
    (tmp_path / "a.c").write_text("int b(int);\nint a(int x) { return x ? b(x - 1) : 0; }\n")
    (tmp_path / "b.c").write_text("int a(int);\nint b(int x) { return a(x); }\n")
    (tmp_path / "c.c").write_text("int a(int);\nint c(void) { return a(3); }\n")
    objs = []
    for n in "abc":
        subprocess.run([cc, "-c", str(tmp_path / f"{n}.c"), "-o", str(tmp_path / f"{n}.o")], check=True)
        objs.append(tmp_path / f"{n}.o")
    g = graph(objs)
    found = cycles(g)
    assert len(found) == 1 and found[0][1] == [tmp_path / "a.o", tmp_path / "b.o"], found
    text = describe(found[0][0], g, {o: o.name for o in objs})
    assert text == "a.o --(b)--> b.o --(a)--> a.o", text
