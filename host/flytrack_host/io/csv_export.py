"""Export a recording as plain CSV files for spreadsheets: one file per table, a header row each."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from flytrack_host.recording.reader import Recording


def table_frame(rows: np.ndarray) -> pd.DataFrame:
    cols = {}
    for name in rows.dtype.names:
        v = rows[name]
        if v.dtype.kind == "S":
            v = np.char.decode(v, "utf-8", errors="replace")
        cols[name] = v
    return pd.DataFrame(cols)


def export_csv(rec: Recording, out_dir: Path | str) -> dict[str, Path]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, rows in rec.tables.items():
        p = out_dir / f"{name}.csv"
        table_frame(rows).to_csv(p, index=False, na_rep="")
        written[name] = p
    p = out_dir / "textlog.csv"
    pd.DataFrame(rec.textlog, columns=["host_time", "source", "message"]).to_csv(p, index=False)
    written["textlog"] = p
    return written
