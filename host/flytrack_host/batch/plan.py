"""What a batch does: parameter sets from --set/--sweep, and one task per (recording, parameter set).

Every task has a fixed output path derived from its inputs, so a batch run again skips what is done
(resumable) and two runs of the same task can never produce two outputs.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal


class BatchError(Exception):
    """A batch that cannot be planned or run (bad options, no inputs, no scheduler)."""


@dataclass(frozen=True)
class ParamSet:
    """Tracking-parameter overrides, as `--set KEY=VALUE` strings, and the name its outputs carry."""

    sets: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        if not self.sets:
            return "base"
        return "_".join(re.sub(r"[^A-Za-z0-9_.+-]+", "-", s.replace("=", "-")) for s in self.sets)

    @property
    def overrides(self) -> dict[str, str]:
        return dict(s.split("=", 1) for s in self.sets)


def _split(option: str, text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or not value.strip():
        raise BatchError(f"{option} {text!r}: write KEY=VALUE (e.g. {option} motion_noise_scale=0.2"
                         f"{',0.4' if option == '--sweep' else ''})")
    return key.strip(), value.strip()


def param_sets(sets: list[str] | None = None, sweeps: list[str] | None = None) -> list[ParamSet]:
    """Every combination of the --sweep values, each with the --set overrides.

    `--sweep motion_noise_scale=0.05,0.1 --sweep birth_max_reproj_px=3,5` gives 4 sets; a key given
    both ways, or twice, is an error rather than a silent choice."""
    fixed = [_split("--set", s) for s in sets or []]
    axes: list[tuple[str, list[str]]] = []
    for s in sweeps or []:
        key, values = _split("--sweep", s)
        vals = [v.strip() for v in values.split(",")]
        if any(not v for v in vals):
            raise BatchError(f"--sweep {s!r}: an empty value in the list")
        if len(set(vals)) != len(vals):
            raise BatchError(f"--sweep {s!r}: a value is repeated")
        axes.append((key, vals))
    keys = [k for k, _ in fixed] + [k for k, _ in axes]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise BatchError(f"parameter {', '.join(dup)} is given more than once in --set/--sweep")
    out = []
    for combo in itertools.product(*[[(k, v) for v in vals] for k, vals in axes]):
        items = [f"{k}={v}" for k, v in fixed] + [f"{k}={v}" for k, v in combo]
        out.append(ParamSet(tuple(items)))
    return out


@dataclass(frozen=True)
class Task:
    kind: Literal["retrack", "export"]
    source: Path
    out: Path  # the finished output; written under a temporary name and renamed at the end
    params: ParamSet = field(default_factory=ParamSet)
    calibration: Path | None = None
    fps: float | None = None
    formats: tuple[str, ...] = ()  # export: "braidz", "csv"

    @property
    def key(self) -> str:
        """A dask key unique to this task (its output path names it)."""
        return f"flytrack-{self.kind}-{self.out}"

    @property
    def label(self) -> str:
        return f"{self.source.name} [{self.params.name}]" if self.kind == "retrack" else self.source.name


def source_stem(source: Path) -> str:
    name = source.name
    if name == "recording.h5":
        name = source.parent.name
    for suffix in (".flytrack", ".braidz", ".braid", ".h5", ".hdf5"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def _unique_stems(sources: list[Path]) -> list[str]:
    stems = [source_stem(s) for s in sources]
    if len(set(stems)) != len(stems):  # same name in two folders: keep them apart by their parent
        stems = [f"{s.parent.name}-{st}" for s, st in zip(sources, stems, strict=True)]
    if len(set(stems)) != len(stems):
        raise BatchError("two inputs have the same name and parent folder name; give them distinct names")
    return stems


def plan_retracks(sources: list[Path], sets: list[ParamSet], out_dir: Path, calibration: Path | None = None,
                  fps: float | None = None) -> list[Task]:
    """One re-tracking task per recording and parameter set: OUT_DIR/<recording>/<set>.flytrack."""
    if not sources:
        raise BatchError("no recordings given")
    missing = [str(s) for s in sources if not s.exists()]
    if missing:
        raise BatchError(f"no such recording: {', '.join(missing)}")
    stems = _unique_stems(sources)
    return [Task("retrack", src, out_dir / stem / f"{ps.name}.flytrack", ps, calibration, fps)
            for src, stem in zip(sources, stems, strict=True) for ps in sets]


def plan_exports(recordings: list[Path], out_dir: Path, formats: tuple[str, ...]) -> list[Task]:
    """One export task per recording: OUT_DIR/<recording>.braidz and/or OUT_DIR/<recording>_csv/."""
    if not recordings:
        raise BatchError("no recordings given")
    bad = [f for f in formats if f not in ("braidz", "csv")]
    if bad or not formats:
        raise BatchError(f"export formats are braidz and csv (got {', '.join(formats) or 'none'})")
    missing = [str(s) for s in recordings if not s.exists()]
    if missing:
        raise BatchError(f"no such recording: {', '.join(missing)}")
    return [Task("export", src, out_dir / stem, formats=formats)
            for src, stem in zip(recordings, _unique_stems(recordings), strict=True)]
