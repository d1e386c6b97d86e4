"""A recording in parts: one folder the user names, a whole recording per part inside it.

    NAME.flytrack/
        parts.json          what this is: the layout, the part settings, the start time
        part-0001/          a complete recording of its own (meta.json, *.bin, textlog.jsonl, rig.toml,
        part-0002/          calibration.*, and recording.h5 once finalised)
        ...

The writer (writer.py) rolls to a new part every `seconds` or `bytes` (whichever comes first), between
two queued items (a frame's rows are queued as one item, so a frame is never split), without dropping
or repeating a row, and has the part it closed finalised by a background process (finalizer.py): at
stop only the last part is left to finalise, however long the recording ran. A crash damages at most
the part being written; `flytrack recording recover` finalises every part that has no HDF5 file yet.

Each part carries the rig, the calibration and the header tables' rows (schema.HEADER_TABLES:
cam_info), so a part can be copied and read alone; its meta.json says how many header rows it
repeats (`carried_rows`), and a reader of the whole recording (source.py, reader.py) keeps them once.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from flytrack_host.recording.schema import META_NAME, PART_PREFIX, PARTS_NAME

PARTS_FORMAT_VERSION = 1
PART_KEYS = ("part", "part_start_time", "part_start_wall_time", "carried_rows")  # per-part keys of meta.json


@dataclass(frozen=True)
class PartPolicy:
    """When the writer starts a new part. Both None: only when asked (`Recorder.new_part`)."""

    seconds: float | None = None
    bytes: int | None = None
    finalize: str = "process"  # closed parts: "process" (a background process finalises them) or "none"

    def __post_init__(self) -> None:
        if self.finalize not in ("process", "none"):
            raise ValueError(f"finalize must be 'process' or 'none', not {self.finalize!r}")
        if self.seconds is not None and self.seconds <= 0:
            raise ValueError("part seconds must be > 0 (None: no time limit)")
        if self.bytes is not None and self.bytes <= 0:
            raise ValueError("part bytes must be > 0 (None: no size limit)")

    @classmethod
    def from_rig(cls, minutes: float, gb: float) -> PartPolicy | None:
        """The rig file's `recording.part_minutes` and `recording.part_gb` (0: no limit of that kind; both 0:
        None, an unparted recording)."""
        if minutes <= 0 and gb <= 0:
            return None
        return cls(seconds=minutes * 60.0 if minutes > 0 else None, bytes=int(gb * 1e9) if gb > 0 else None)

    def describe(self) -> str:
        limits = []
        if self.seconds:
            limits.append(f"{self.seconds / 60:g} min")
        if self.bytes:
            limits.append(f"{self.bytes / 1e9:g} GB")
        if not limits:
            return "a new part on request"
        return "a new part every " + " or ".join(limits) + (", whichever first" if len(limits) > 1 else "")


def part_name(index: int) -> str:
    return f"{PART_PREFIX}{index:04d}"


def is_parted(folder: Path) -> bool:
    """A recording folder in parts (parts.json, or part folders left by a crash before it was written)."""
    folder = Path(folder)
    return folder.is_dir() and ((folder / PARTS_NAME).exists() or bool(part_dirs(folder)))


def part_dirs(folder: Path) -> list[Path]:
    """The part folders of a recording in parts, in order (those with a meta.json: a part whose folder was
    made but not its meta.json holds nothing)."""
    out = []
    for p in Path(folder).glob(PART_PREFIX + "*"):
        tail = p.name[len(PART_PREFIX):]
        if p.is_dir() and tail.isdigit() and (p / META_NAME).exists():
            out.append((int(tail), p))
    return [p for _, p in sorted(out)]


def read_parts_json(folder: Path) -> dict:
    p = Path(folder) / PARTS_NAME
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def whole_meta(part_meta: dict, n_parts: int) -> dict:
    """The meta of a whole recording in parts: its first part's, without the per-part keys."""
    meta = {k: v for k, v in part_meta.items() if k not in PART_KEYS}
    meta["parts"] = n_parts
    return meta


def recording_started(folder: Path) -> bool:
    """The recorder has made the folder's first files (either layout)."""
    folder = Path(folder)
    return (folder / META_NAME).exists() or bool(part_dirs(folder))
