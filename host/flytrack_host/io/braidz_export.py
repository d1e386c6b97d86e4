"""Write a FlyTrack recording as Braid's `.braidz`, part by part (the format is described in braidz.py,
its names are in braid_format.py).

A recording in parts is read one part at a time (recording.source) and regrouped by frame
(recording.stream), so each table comes out sorted by frame exactly as a whole read would sort it, in
memory bounded by about two parts. Each table is streamed into its own gzipped CSV in a temporary
folder beside the output, and the archive is put together from them at the end (written under a
temporary name, renamed when complete). A recording in memory (a Recording) is one part.
"""

from __future__ import annotations

import gzip
import io
import json
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flytrack_host import __version__
from flytrack_host.io.braid_format import (
    ASSOC_COLUMNS,
    BRAID_SCHEMA,
    CAM_INFO_COLUMNS,
    CLOCK_COLUMNS,
    DATA2D_COLUMNS,
    DVS_POINTS,
    DVS_POINTS_COLUMNS,
    KALMAN_COLUMNS,
    TEXTLOG_COLUMNS,
    BraidzError,
    _rust_f64,
    braid_tracking_params,
)
from flytrack_host.io.hdr import Histogram, hlog_text
from flytrack_host.io.reprojection import associated_reprojection
from flytrack_host.recording.schema import FLAG_DVS, FLAG_REJECTED
from flytrack_host.recording.source import RecordingSource
from flytrack_host.recording.stream import frame_blocks
from flytrack_host.util import hostclock

FRAME_TABLES = ["data2d_distorted", "kalman_estimates", "data_association", "dvs_point_covariance", "latency"]


class _CsvGz:
    """One table as a gzipped CSV, written a block of rows at a time (the header once)."""

    def __init__(self, path: Path, columns: list[str]):
        self.path, self.columns, self.rows = path, columns, 0
        self._raw = open(path, "wb")  # noqa: SIM115 (closed in close())
        self._gz = gzip.GzipFile(filename="", fileobj=self._raw, mode="wb", compresslevel=6, mtime=0)
        self._text = io.TextIOWrapper(self._gz, encoding="utf-8", newline="")
        self._header = True

    def write(self, df: pd.DataFrame) -> None:
        if not len(df) and not self._header:
            return
        df.to_csv(self._text, index=False, header=self._header, na_rep="", lineterminator="\n")
        self._header = False
        self.rows += len(df)

    def close(self) -> None:
        if self._header:
            pd.DataFrame(columns=self.columns).to_csv(self._text, index=False, lineterminator="\n")
        self._text.close()
        self._raw.close()


def _cam_names(src: RecordingSource) -> dict[int, str]:
    return {int(r["camera_index"]): r["calibration_id"].decode() or r["name"].decode() for r in src.table("cam_info")}


def _calibration_xml(src: RecordingSource) -> bytes | None:
    cal = src.calibration
    if cal is None:
        return None
    name, data = cal
    if name.endswith(".xml"):
        return data
    # Another format: convert with the calibration package (flydra XML is what Braid reads).
    from flytrack_host.geometry.formats import load_calibration, save_flydra_xml

    with tempfile.TemporaryDirectory() as d:
        src_path = Path(d) / name
        src_path.write_bytes(data)
        dst = Path(d) / "calibration.xml"
        save_flydra_xml(load_calibration(src_path), dst)
        return dst.read_bytes()


def _check_cameras(where: str, cams: np.ndarray) -> None:
    big = sorted({int(i) for i in cams if i > 255})
    if big:
        raise BraidzError(f"camera indices {big} do not fit Braid's camera numbers (0-255) (in {where})")


def _data2d_frame(d2: np.ndarray) -> pd.DataFrame:
    orient = d2["orientation"].astype(np.float64)
    with np.errstate(invalid="ignore"):
        slope = np.tan(orient)
    dev = d2["device_timestamp_ns"].astype("float64")
    df = pd.DataFrame({
        "camn": d2["camera_index"].astype(np.int64),
        "frame": d2["trigger_frame"],
        "timestamp": d2["timestamp"],
        "cam_received_timestamp": d2["cam_received_timestamp"],
        "device_timestamp": pd.array(np.where(dev > 0, d2["device_timestamp_ns"], 0), dtype="UInt64"),
        "block_id": pd.array(d2["camera_frame"], dtype="UInt64"),
        "x": d2["x_dist"].astype(np.float64),
        "y": d2["y_dist"].astype(np.float64),
        "area": d2["area"].astype(np.float64),
        "slope": slope,
        "eccentricity": d2["eccentricity"].astype(np.float64),
        "frame_pt_idx": np.minimum(d2["frame_pt_idx"], 255),
        "cur_val": np.minimum(d2["cur_val"], 255),
        "mean_val": d2["mean_val"].astype(np.float64),
        "sumsqf_val": d2["sumsq_val"].astype(np.float64),
    }, columns=DATA2D_COLUMNS)
    df.loc[dev <= 0, "device_timestamp"] = pd.NA
    df.loc[d2["camera_frame"] == 0, "block_id"] = pd.NA
    return df


def _kalman_frame(k: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({c: k["trigger_frame"] if c == "frame" else k[c] for c in KALMAN_COLUMNS},
                        columns=KALMAN_COLUMNS)


def _assoc_frame(a: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({"obj_id": a["obj_id"], "frame": a["trigger_frame"], "cam_num": a["camera_index"],
                         "pt_idx": np.minimum(a["pt_idx"], 255)}, columns=ASSOC_COLUMNS)


def _dvs_points(d2: np.ndarray, cov: np.ndarray) -> pd.DataFrame:
    """The exported rows that are DVS clusters, keyed as Braid's data2d is (frame, camn, frame_pt_idx), with
    the covariance the recording kept for each (NaN when it kept none)."""
    dvs = d2[((d2["flags"] & FLAG_DVS) != 0) & np.isfinite(d2["x_dist"])]
    pt = np.minimum(dvs["frame_pt_idx"], 255).astype(np.int64)
    out = pd.DataFrame({"frame": dvs["trigger_frame"], "camn": dvs["camera_index"].astype(np.int64),
                        "frame_pt_idx": pt, "var_x": np.nan, "var_y": np.nan, "cov_xy": np.nan},
                       columns=DVS_POINTS_COLUMNS)
    if len(cov) and len(dvs):
        c = pd.DataFrame({"frame": cov["trigger_frame"], "camn": cov["camera_index"].astype(np.int64),
                          "frame_pt_idx": np.minimum(cov["frame_pt_idx"], 255).astype(np.int64),
                          "var_x": cov["var_x"], "var_y": cov["var_y"], "cov_xy": cov["cov_xy"]})
        c = c.drop_duplicates(["frame", "camn", "frame_pt_idx"], keep="last")
        out = out[["frame", "camn", "frame_pt_idx"]].merge(c, how="left", on=["frame", "camn", "frame_pt_idx"])
    return out[DVS_POINTS_COLUMNS]


class _Hlogs:
    """Braid's two HdrHistogram logs, accumulated block by block."""

    def __init__(self, cams: dict | None) -> None:
        self.cams = cams
        self.latency = Histogram(1, 60_000_000, 3)
        self.reproj = Histogram(1, 1_000_000, 3)
        self.t_min, self.t_max = np.inf, -np.inf
        self.any_kal = self.any_assoc = False

    def add(self, kal: pd.DataFrame, assoc: pd.DataFrame, d2_rows: np.ndarray, lat: np.ndarray) -> None:
        if len(lat):
            self.latency.record((lat["estimate_time"] - lat["trigger_time"]) * 1e6)
        if len(kal):
            ts = kal["timestamp"].to_numpy(dtype=np.float64)
            self.t_min, self.t_max = min(self.t_min, np.min(ts)), max(self.t_max, np.max(ts))
        self.any_kal |= bool(len(kal))
        self.any_assoc |= bool(len(assoc))
        if self.cams is not None and len(kal) and len(assoc):
            d = associated_reprojection(kal[["obj_id", "frame", "x", "y", "z"]],
                                        assoc.rename(columns={"cam_num": "camn"}), d2_rows, self.cams)
            self.reproj.record(100.0 * d)

    def texts(self, t0: float) -> dict[str, str]:
        duration = float(self.t_max - self.t_min) if self.any_kal else 0.0
        duration = duration if np.isfinite(duration) else 0.0
        out = {}
        if self.latency.total:
            out["reconstruct_latency_usec.hlog"] = hlog_text(self.latency, t0, duration,
                                                             "trigger to 3D estimate, microseconds")
        if self.cams is not None and self.any_kal and self.any_assoc and self.reproj.total:
            out["reprojection_distance_100x_pixels.hlog"] = hlog_text(
                self.reproj, t0, duration,
                "distance of each associated 2D point to its estimate's projection, 1/100 px")
        return out


def _sorted(rows: np.ndarray) -> np.ndarray:
    return rows[np.argsort(rows["trigger_frame"], kind="stable")]


def export_source(src: RecordingSource, out: Path) -> dict[str, int]:
    """Write `src` as a .braidz at `out`; returns rows written per table (and what was left out)."""
    counts: dict[str, int] = {}
    names = _cam_names(src)
    _check_cameras("cam_info", np.array(list(names), dtype=np.int64))
    cal_xml = _calibration_xml(src)
    cams = None
    if cal_xml is not None:
        from flytrack_host.geometry.formats import load_flydra_xml

        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "calibration.xml"
            p.write_bytes(cal_xml)
            by_name = load_flydra_xml(p, [])
        cams = {int(i): by_name[n] for i, n in names.items() if n in by_name}
    skipped = {"data2d_distorted not exported: no trigger frame": 0,
               "data2d_distorted not exported: rejected live": 0,
               "kalman_estimates not exported: no trigger frame": 0,
               "data_association not exported: no trigger frame": 0}
    out_of_order = 0
    hl = _Hlogs(cams)
    t0 = float(src.meta.get("start_time", hostclock.wall()))  # a label: the export time if unknown
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as tmpdir:
        tmp = Path(tmpdir)
        kal_w = _CsvGz(tmp / "kalman_estimates.csv.gz", KALMAN_COLUMNS)
        d2_w = _CsvGz(tmp / "data2d_distorted.csv.gz", DATA2D_COLUMNS)
        as_w = _CsvGz(tmp / "data_association.csv.gz", ASSOC_COLUMNS)
        dvs_w = _CsvGz(tmp / f"{DVS_POINTS}.csv.gz", DVS_POINTS_COLUMNS)
        try:
            for block in frame_blocks(src.iter_tables(FRAME_TABLES)):
                out_of_order += block.n_late
                for rows_of in (block.tables, block.late):  # the late rows after the block, as they came
                    if not rows_of:
                        continue
                    def get(n: str, r: dict = rows_of, like: dict = block.tables) -> np.ndarray:
                        return r.get(n, like[n][:0])

                    d2 = get("data2d_distorted")
                    _check_cameras("data2d_distorted", d2["camera_index"])
                    no_frame = d2["trigger_frame"] < 0
                    rejected = ~no_frame & ((d2["flags"] & FLAG_REJECTED) != 0)
                    skipped["data2d_distorted not exported: no trigger frame"] += int(no_frame.sum())
                    skipped["data2d_distorted not exported: rejected live"] += int(rejected.sum())
                    d2x = _sorted(d2[~no_frame & ~rejected])
                    d2_w.write(_data2d_frame(d2x))
                    dvs_w.write(_dvs_points(d2x, get("dvs_point_covariance")))
                    k = get("kalman_estimates")
                    skipped["kalman_estimates not exported: no trigger frame"] += int((k["trigger_frame"] < 0).sum())
                    kal = _kalman_frame(_sorted(k[k["trigger_frame"] >= 0]))
                    kal_w.write(kal)
                    a = get("data_association")
                    _check_cameras("data_association", a["camera_index"])
                    skipped["data_association not exported: no trigger frame"] += int((a["trigger_frame"] < 0).sum())
                    assoc = _assoc_frame(_sorted(a[a["trigger_frame"] >= 0]))
                    as_w.write(assoc)
                    hl.add(kal, assoc, d2, get("latency"))
        finally:
            for w in (kal_w, d2_w, as_w, dvs_w):
                w.close()
        counts["data2d_distorted"], counts["kalman_estimates"] = d2_w.rows, kal_w.rows
        counts["data_association"] = as_w.rows
        if dvs_w.rows:
            counts[DVS_POINTS] = dvs_w.rows
        skipped_text = ", ".join(f"{k} {v}" for k, v in skipped.items() if v)
        order_note = (f"{out_of_order} rows came more than a part after their frame and are written after it, "
                      "out of frame order" if out_of_order else "")
        hlogs = hl.texts(t0)
        small = _small_tables(src, names, t0, skipped_text, order_note)
        images = {f"images/{n[len('background_'):]}": b for n, b in src.files.items() if n.startswith("background_")}
        part = out.with_name(out.name + ".tmp")
        with zipfile.ZipFile(part, "w", allowZip64=True) as z:
            z.writestr("README.md", _readme(src, skipped_text, order_note), compress_type=zipfile.ZIP_DEFLATED)
            z.writestr("braid_metadata.yml", _metadata(t0), compress_type=zipfile.ZIP_DEFLATED)
            if cal_xml is not None:
                z.writestr("calibration.xml", cal_xml, compress_type=zipfile.ZIP_DEFLATED)
            for name in ("kalman_estimates", "data2d_distorted", "data_association"):
                z.write(tmp / f"{name}.csv.gz", f"{name}.csv.gz", compress_type=zipfile.ZIP_STORED)
            for name, data in small.items():
                z.writestr(f"{name}.csv.gz", data, compress_type=zipfile.ZIP_STORED)
            if dvs_w.rows:
                z.write(tmp / f"{DVS_POINTS}.csv.gz", f"{DVS_POINTS}.csv.gz", compress_type=zipfile.ZIP_STORED)
            for name, text in hlogs.items():
                z.writestr(name, text, compress_type=zipfile.ZIP_DEFLATED)
            for name, data in images.items():
                z.writestr(name, data, compress_type=zipfile.ZIP_STORED)
        part.replace(out)
    counts.update(skipped)
    if out_of_order:
        counts["rows written out of frame order"] = out_of_order
    counts.update({name: 1 for name in hlogs})
    counts["images"] = len(images)
    return counts


def _gz(df: pd.DataFrame) -> bytes:
    return gzip.compress(df.to_csv(index=False, na_rep="").encode("utf-8"), compresslevel=6, mtime=0)


def _small_tables(src: RecordingSource, names: dict[int, str], t0: float, skipped_text: str,
                  order_note: str) -> dict[str, bytes]:
    """cam_info, trigger_clock_info, textlog and experiment_info, gzipped, in the archive's order."""
    cam_info = pd.DataFrame({"camn": list(names), "cam_id": list(names.values())}, columns=CAM_INFO_COLUMNS)
    c = src.table("trigger_clock_info")
    clock = pd.DataFrame({"start_timestamp": c["start_timestamp"], "framecount": c["framecount"],
                          "tcnt": np.clip(np.round(c["fraction"] * 255), 0, 255).astype(np.int64),
                          "stop_timestamp": c["stop_timestamp"]}, columns=CLOCK_COLUMNS)
    # Braid's first two textlog lines, which braidz-parser reads: the rate as `^(\S+) fps, \((.*)\)$`
    # (the number as Rust prints an f64, or "unknown") and the tracking parameters with the revision.
    fps = src.fps
    fps_text = _rust_f64(fps) if fps else "unknown"
    tz = time.strftime("%Z", time.localtime(t0)) or "UTC"
    saver = {"tracking_params": braid_tracking_params(src.meta.get("tracking_params")),
             "git_revision": f"flytrack-{__version__}"}
    log_rows: list[tuple[Any, ...]] = [
        (t0, "mainbrain", t0,
         f"MainBrain running at {fps_text} fps, (flytrack_version {__version__}, time_tzname0 {tz})"),
        (t0, "mainbrain", t0, json.dumps(saver))]
    for lines in src.iter_textlog():
        for r in lines:
            if str(r.get("message", "")).startswith("MainBrain running at"):
                continue
            t = float(r.get("host_time", t0))
            log_rows.append((t, str(r.get("source", "")), t, str(r.get("message", ""))))
    if skipped_text:
        log_rows.append((t0, "", t0, f"FlyTrack export: rows left out ({skipped_text})"))
    if order_note:
        log_rows.append((t0, "", t0, f"FlyTrack export: {order_note}"))
    # Braid's experiment_info: one row per SetExperimentUuid of the run.
    uuid = src.meta.get("experiment_uuid")
    experiment = pd.DataFrame({"uuid": [uuid] if uuid else []}, columns=["uuid"])
    return {"cam_info": _gz(cam_info), "trigger_clock_info": _gz(clock),
            "textlog": _gz(pd.DataFrame(log_rows, columns=TEXTLOG_COLUMNS)), "experiment_info": _gz(experiment)}


def _metadata(t0: float) -> str:
    rec_time = time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(t0))
    rec_time = rec_time[:-2] + ":" + rec_time[-2:]  # RFC 3339 offset, as chrono writes it
    return (f"schema: {BRAID_SCHEMA}\n"
            f"git_revision: flytrack-{__version__}\n"
            f"original_recording_time: {rec_time}\n"
            "save_empty_data2d: true\n"
            "saving_program_name: flytrack\n")


def _readme(src: RecordingSource, skipped_text: str, order_note: str) -> str:
    return (
        "# FlyTrack recording in Braid's .braidz format\n\n"
        "A zip of gzipped CSV tables (kalman_estimates, data2d_distorted, data_association, cam_info,\n"
        "trigger_clock_info, textlog, experiment_info), the calibration (flydra XML) and braid_metadata.yml.\n"
        "Read it with Braid's tools (braidz-parser, pybraidz-tools) or with pandas:\n\n"
        "    import zipfile, pandas as pd\n"
        "    z = zipfile.ZipFile('FILE.braidz')\n"
        "    df = pd.read_csv(z.open('kalman_estimates.csv.gz'), compression='gzip')\n\n"
        f"Written by FlyTrack {__version__} from the recording of rig {src.meta.get('rig_name', '?')!r}.\n"
        + (f"\nRows left out (Braid has no place for them): {skipped_text}.\n" if skipped_text else "")
        + (f"\nNote: {order_note}.\n" if order_note else "")
    )
