"""Export a recording as plain CSV files for spreadsheets: one file per table, a header row each.

Written part by part (a recording in parts is read one part at a time: memory bounded by one part),
each table's rows in the order a whole read gives them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from flytrack_host.recording.reader import Recording
from flytrack_host.recording.source import RecordingSource, open_source


def table_frame(rows: np.ndarray) -> pd.DataFrame:
    cols = {}
    for name in rows.dtype.names:
        v = rows[name]
        if v.dtype.kind == "S":
            v = np.char.decode(v, "utf-8", errors="replace")
        cols[name] = v
    return pd.DataFrame(cols, columns=list(rows.dtype.names))


def export_csv(rec: Recording | RecordingSource | Path | str, out_dir: Path | str) -> dict[str, Path]:
    """`rec`: a recording's path (read part by part), a RecordingSource or a Recording."""
    src = open_source(rec)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = src.table_names
    written = {name: out_dir / f"{name}.csv" for name in names}
    files = {name: open(p, "w", newline="") for name, p in written.items()}  # noqa: SIM115 (closed below)
    try:
        for i, tables in enumerate(src.iter_tables(names)):
            for name, rows in tables.items():
                if i == 0 or len(rows):
                    table_frame(rows).to_csv(files[name], index=False, header=i == 0, na_rep="")
        p = out_dir / "textlog.csv"
        with open(p, "w", newline="") as f:
            for i, lines in enumerate(src.iter_textlog()):
                pd.DataFrame(lines, columns=["host_time", "source", "message"]).to_csv(f, index=False, header=i == 0)
        written["textlog"] = p
    finally:
        for f in files.values():
            f.close()
    return written
