"""Braid's `.braidz` archive: export a FlyTrack recording, import 2D data for re-tracking.

A .braidz is a zip of gzipped CSV tables plus `calibration.xml` (flydra XML), `braid_metadata.yml`
and a README, with Braid's file and column names (braid_types / flydra_types, schema 3):

- kalman_estimates: obj_id, frame, timestamp, x, y, z, xvel, yvel, zvel, P00 P01 P02 P11 P12 P22 P33 P44 P55
- data2d_distorted: camn, frame, timestamp, cam_received_timestamp, device_timestamp, block_id, x, y,
  area, slope, eccentricity, frame_pt_idx, cur_val, mean_val, sumsqf_val (no detection: empty x)
- data_association: obj_id, frame, cam_num, pt_idx
- cam_info: camn, cam_id
- trigger_clock_info: start_timestamp, framecount, tcnt, stop_timestamp
- textlog: mainbrain_timestamp, cam_id, host_timestamp, message. Braid's reader (braidz-parser) takes
  the frame rate from a line "MainBrain running at F fps, (...)" (F as Rust prints an f64, or
  "unknown"; without the parenthesis it refuses the archive) and the tracking parameters from a JSON
  line {"tracking_params": {...}, "git_revision": ...}, which it requires when kalman_estimates is
  present (TrackingParams denies unknown fields);
- experiment_info: uuid (one row per experiment UUID set during the run).

Missing values (an unknown trigger timestamp, a NaN coordinate, a zero device timestamp or camera
frame number, which Braid keeps as NonZeroU64) are written as empty fields, which Braid reads as
None / NaN. Rows FlyTrack could not map to a trigger frame (-1) and 2D rows the live run rejected are
left out (Braid's frame numbers are unsigned), counted in the returned counts (`<table> not exported:
...`), the archive's textlog and its README. Optional parts: `reconstruct_latency_usec.hlog` (trigger
to estimate, from the recording's latency table) and `reprojection_distance_100x_pixels.hlog` (each
associated 2D point's distance to its estimate's projection, x100), HdrHistogram logs (io/hdr.py), and
`images/<camera>.png` from the recording's background_<camera>.png files. Reading accepts a `.braidz`
and Braid's uncompressed `.braid` folder (the same files, written while it records).
Braid's camera numbers are u8: a camera index above 255 is an error. FlyTrack's orientation (radians) is
Braid's slope = tan(orientation).
"""

from __future__ import annotations

import gzip
import io
import json
import re
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd

from flytrack_host import __version__
from flytrack_host.io.data2d import Data2D, empty_rows
from flytrack_host.io.reprojection import associated_reprojection
from flytrack_host.recording.reader import Recording
from flytrack_host.recording.schema import DVS_COVARIANCE, FLAG_DVS, FLAG_REJECTED
from flytrack_host.util import hostclock

BRAID_SCHEMA = 3
KALMAN_COLUMNS = ["obj_id", "frame", "timestamp", "x", "y", "z", "xvel", "yvel", "zvel",
                  "P00", "P01", "P02", "P11", "P12", "P22", "P33", "P44", "P55"]
DATA2D_COLUMNS = ["camn", "frame", "timestamp", "cam_received_timestamp", "device_timestamp", "block_id",
                  "x", "y", "area", "slope", "eccentricity", "frame_pt_idx", "cur_val", "mean_val", "sumsqf_val"]
ASSOC_COLUMNS = ["obj_id", "frame", "cam_num", "pt_idx"]
CAM_INFO_COLUMNS = ["camn", "cam_id"]
CLOCK_COLUMNS = ["start_timestamp", "framecount", "tcnt", "stop_timestamp"]
TEXTLOG_COLUMNS = ["mainbrain_timestamp", "cam_id", "host_timestamp", "message"]
# FlyTrack's own table beside Braid's: which data2d rows are event (DVS) cameras' clusters, with their
# covariance (px^2). Braid's data2d has no place for either; without it a re-track of the .braidz would
# take those points as frame cameras' (weighed at 1 px^2, able to start targets).
DVS_POINTS = "flytrack_dvs_points"
DVS_POINTS_COLUMNS = ["frame", "camn", "frame_pt_idx", "var_x", "var_y", "cov_xy"]


class BraidzError(Exception):
    pass


def _csv_gz(df: pd.DataFrame) -> bytes:
    text = df.to_csv(index=False, na_rep="")
    return gzip.compress(text.encode("utf-8"), compresslevel=6, mtime=0)


def _rust_f64(v: float) -> str:
    """A float as Rust's `{}` prints an f64 (and braidz-parser reads it back): 100.0 -> "100"."""
    text = repr(float(v))
    return text[:-2] if text.endswith(".0") else text


def braid_tracking_params(params: dict | None) -> dict:
    """FlyTrack TrackingParams -> Braid's TrackingParams (the JSON in textlog)."""
    p = params or {}
    return {
        "motion_noise_scale": p.get("motion_noise_scale", 0.1),
        "initial_position_std_meters": p.get("initial_position_std_m", 0.1),
        "initial_vel_std_meters_per_sec": p.get("initial_velocity_std_m_s", 1.0),
        "accept_observation_min_likelihood": 1e-8,
        # Braid's R is this value times I: a variance (px^2), where FlyTrack keeps a standard deviation.
        "ekf_observation_covariance_pixels": float(p.get("measurement_noise_px", 1.0)) ** 2,
        "max_position_std_meters": p.get("death_position_std_m", 0.01212),
        "hypothesis_test_params": {
            "minimum_number_of_cameras": p.get("birth_min_cameras", 2),
            "hypothesis_test_max_acceptable_error": p.get("birth_max_reproj_px", 5.0),
            "minimum_pixel_abs_zscore": 0.0,
        },
        "num_observations_to_visibility": int(min(max(p.get("confirm_min_frames", 3), 0), 255)),  # u8
        # No `mini_arena_config`: Braid leaves it out when there is none (an internally tagged enum, so a
        # plain string would not parse).
    }


def _cam_names(rec: Recording) -> dict[int, str]:
    ci = rec.table("cam_info")
    out = {}
    for r in ci:
        cid = r["calibration_id"].decode() or r["name"].decode()
        out[int(r["camera_index"])] = cid
    return out


def _calibration_xml(rec: Recording) -> bytes | None:
    cal = rec.calibration
    if cal is None:
        return None
    name, data = cal
    if name.endswith(".xml"):
        return data
    # Another format: convert with the calibration package (flydra XML is what Braid reads).
    from flytrack_host.geometry.formats import load_calibration, save_flydra_xml

    with tempfile.TemporaryDirectory() as d:
        src = Path(d) / name
        src.write_bytes(data)
        dst = Path(d) / "calibration.xml"
        save_flydra_xml(load_calibration(src), dst)
        return dst.read_bytes()


def export_braidz(rec: Recording, out: Path | str) -> dict[str, int]:
    """Write `rec` as a .braidz; returns rows written per table."""
    out = Path(out)
    counts: dict[str, int] = {}
    fps = rec.fps
    names = _cam_names(rec)

    big = sorted({int(i) for t in ("data2d_distorted", "data_association", "cam_info")
                  for i in rec.table(t)["camera_index"] if i > 255})
    if big:
        raise BraidzError(f"camera indices {big} do not fit Braid's camera numbers (0-255)")
    d2 = rec.table("data2d_distorted")
    no_frame = d2["trigger_frame"] < 0
    rejected = ~no_frame & ((d2["flags"] & FLAG_REJECTED) != 0)
    skipped = {"data2d_distorted not exported: no trigger frame": int(no_frame.sum()),
               "data2d_distorted not exported: rejected live": int(rejected.sum())}
    d2 = d2[~no_frame & ~rejected]
    d2 = d2[np.argsort(d2["trigger_frame"], kind="stable")]
    orient = d2["orientation"].astype(np.float64)
    with np.errstate(invalid="ignore"):
        slope = np.tan(orient)
    dev = d2["device_timestamp_ns"].astype("float64")
    data2d = pd.DataFrame({
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
    data2d.loc[dev <= 0, "device_timestamp"] = pd.NA
    data2d.loc[d2["camera_frame"] == 0, "block_id"] = pd.NA
    counts["data2d_distorted"] = len(data2d)
    dvs_points = _dvs_points(rec, d2)
    if dvs_points is not None:
        counts[DVS_POINTS] = len(dvs_points)

    k = rec.table("kalman_estimates")
    skipped["kalman_estimates not exported: no trigger frame"] = int((k["trigger_frame"] < 0).sum())
    k = k[k["trigger_frame"] >= 0]
    k = k[np.argsort(k["trigger_frame"], kind="stable")]
    kal = pd.DataFrame({
        "obj_id": k["obj_id"], "frame": k["trigger_frame"], "timestamp": k["timestamp"],
        "x": k["x"], "y": k["y"], "z": k["z"], "xvel": k["xvel"], "yvel": k["yvel"], "zvel": k["zvel"],
        "P00": k["P00"], "P01": k["P01"], "P02": k["P02"], "P11": k["P11"], "P12": k["P12"], "P22": k["P22"],
        "P33": k["P33"], "P44": k["P44"], "P55": k["P55"],
    }, columns=KALMAN_COLUMNS)
    counts["kalman_estimates"] = len(kal)

    a = rec.table("data_association")
    skipped["data_association not exported: no trigger frame"] = int((a["trigger_frame"] < 0).sum())
    a = a[a["trigger_frame"] >= 0]
    a = a[np.argsort(a["trigger_frame"], kind="stable")]
    assoc = pd.DataFrame({"obj_id": a["obj_id"], "frame": a["trigger_frame"], "cam_num": a["camera_index"],
                          "pt_idx": np.minimum(a["pt_idx"], 255)}, columns=ASSOC_COLUMNS)
    counts["data_association"] = len(assoc)

    cam_info = pd.DataFrame({"camn": list(names), "cam_id": list(names.values())}, columns=CAM_INFO_COLUMNS)

    c = rec.table("trigger_clock_info")
    clock = pd.DataFrame({"start_timestamp": c["start_timestamp"], "framecount": c["framecount"],
                          "tcnt": np.clip(np.round(c["fraction"] * 255), 0, 255).astype(np.int64),
                          "stop_timestamp": c["stop_timestamp"]}, columns=CLOCK_COLUMNS)

    t0 = float(rec.meta.get("start_time", hostclock.wall()))  # a label: the export time if unknown
    # Braid's first two textlog lines, which braidz-parser reads: the rate as `^(\S+) fps, \((.*)\)$`
    # (the number as Rust prints an f64, or "unknown") and the tracking parameters with the revision.
    fps_text = _rust_f64(fps) if fps else "unknown"
    tz = time.strftime("%Z", time.localtime(t0)) or "UTC"
    revision = f"flytrack-{__version__}"
    saver = {"tracking_params": braid_tracking_params(rec.meta.get("tracking_params")), "git_revision": revision}
    log_rows = [(t0, "mainbrain", t0,
                 f"MainBrain running at {fps_text} fps, (flytrack_version {__version__}, time_tzname0 {tz})"),
                (t0, "mainbrain", t0, json.dumps(saver))]
    for r in rec.textlog:
        if str(r.get("message", "")).startswith("MainBrain running at"):
            continue
        t = float(r.get("host_time", t0))
        log_rows.append((t, str(r.get("source", "")), t, str(r.get("message", ""))))
    skipped_text = ", ".join(f"{k} {v}" for k, v in skipped.items() if v)
    if skipped_text:
        log_rows.append((t0, "", t0, f"FlyTrack export: rows left out ({skipped_text})"))
    textlog = pd.DataFrame(log_rows, columns=TEXTLOG_COLUMNS)
    # Braid's experiment_info: one row per SetExperimentUuid of the run.
    uuid = rec.meta.get("experiment_uuid")
    experiment = pd.DataFrame({"uuid": [uuid] if uuid else []}, columns=["uuid"])

    rec_time = time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(t0))
    rec_time = rec_time[:-2] + ":" + rec_time[-2:]  # RFC 3339 offset, as chrono writes it
    metadata = (
        f"schema: {BRAID_SCHEMA}\n"
        f"git_revision: {revision}\n"
        f"original_recording_time: {rec_time}\n"
        "save_empty_data2d: true\n"
        "saving_program_name: flytrack\n"
    )
    readme = (
        "# FlyTrack recording in Braid's .braidz format\n\n"
        "A zip of gzipped CSV tables (kalman_estimates, data2d_distorted, data_association, cam_info,\n"
        "trigger_clock_info, textlog, experiment_info), the calibration (flydra XML) and braid_metadata.yml.\n"
        "Read it with Braid's tools (braidz-parser, pybraidz-tools) or with pandas:\n\n"
        "    import zipfile, pandas as pd\n"
        "    z = zipfile.ZipFile('FILE.braidz')\n"
        "    df = pd.read_csv(z.open('kalman_estimates.csv.gz'), compression='gzip')\n\n"
        f"Written by FlyTrack {__version__} from the recording of rig {rec.meta.get('rig_name', '?')!r}.\n"
        + (f"\nRows left out (Braid has no place for them): {skipped_text}.\n" if skipped_text else "")
    )
    cal_xml = _calibration_xml(rec)
    hlogs = _hlogs(rec, kal, assoc, data2d, cal_xml, t0)
    images = {f"images/{n[len('background_'):]}": b for n, b in rec.files.items() if n.startswith("background_")}
    tmp = out.with_name(out.name + ".tmp")
    with zipfile.ZipFile(tmp, "w") as z:
        z.writestr("README.md", readme, compress_type=zipfile.ZIP_DEFLATED)
        z.writestr("braid_metadata.yml", metadata, compress_type=zipfile.ZIP_DEFLATED)
        if cal_xml is not None:
            z.writestr("calibration.xml", cal_xml, compress_type=zipfile.ZIP_DEFLATED)
        for name, df in (("kalman_estimates", kal), ("data2d_distorted", data2d), ("data_association", assoc),
                         ("cam_info", cam_info), ("trigger_clock_info", clock), ("textlog", textlog),
                         ("experiment_info", experiment)):
            z.writestr(f"{name}.csv.gz", _csv_gz(df), compress_type=zipfile.ZIP_STORED)
        if dvs_points is not None:
            z.writestr(f"{DVS_POINTS}.csv.gz", _csv_gz(dvs_points), compress_type=zipfile.ZIP_STORED)
        for name, text in hlogs.items():
            z.writestr(name, text, compress_type=zipfile.ZIP_DEFLATED)
        for name, data in images.items():
            z.writestr(name, data, compress_type=zipfile.ZIP_STORED)
    tmp.replace(out)
    counts.update(skipped)
    counts.update({name: 1 for name in hlogs})
    counts["images"] = len(images)
    return counts


def _hlogs(rec: Recording, kal: pd.DataFrame, assoc: pd.DataFrame, data2d: pd.DataFrame, cal_xml: bytes | None,
           t0: float) -> dict[str, str]:
    """Braid's two HdrHistogram logs, where the recording has what they need."""
    from flytrack_host.io.hdr import Histogram, hlog_text

    out: dict[str, str] = {}
    lat = rec.table("latency")
    duration = float(kal["timestamp"].max() - kal["timestamp"].min()) if len(kal) else 0.0
    duration = duration if np.isfinite(duration) else 0.0
    if len(lat):
        h = Histogram(1, 60_000_000, 3)
        h.record((lat["estimate_time"] - lat["trigger_time"]) * 1e6)
        if h.total:
            out["reconstruct_latency_usec.hlog"] = hlog_text(h, t0, duration, "trigger to 3D estimate, microseconds")
    if cal_xml is not None and len(assoc) and len(kal):
        from flytrack_host.geometry.formats import load_flydra_xml

        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "calibration.xml"
            p.write_bytes(cal_xml)
            by_name = load_flydra_xml(p, [])
        names = _cam_names(rec)
        cams = {int(i): by_name[n] for i, n in names.items() if n in by_name}
        d = associated_reprojection(kal[["obj_id", "frame", "x", "y", "z"]],
                                    assoc.rename(columns={"cam_num": "camn"}), rec.table("data2d_distorted"), cams)
        h = Histogram(1, 1_000_000, 3)
        h.record(100.0 * d)
        if h.total:
            out["reprojection_distance_100x_pixels.hlog"] = hlog_text(
                h, t0, duration, "distance of each associated 2D point to its estimate's projection, 1/100 px")
    return out


# --- reading ----------------------------------------------------------------------------------


class _Folder:
    """Braid's uncompressed `.braid` folder, read like the zip it becomes."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def namelist(self) -> list[str]:
        return [p.relative_to(self.path).as_posix() for p in self.path.rglob("*") if p.is_file()]

    def read(self, name: str) -> bytes:
        return (self.path / name).read_bytes()

    def __enter__(self) -> _Folder:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def _dvs_points(rec: Recording, d2: np.ndarray) -> pd.DataFrame | None:
    """The exported rows that are DVS clusters, keyed as Braid's data2d is (frame, camn, frame_pt_idx), with
    the covariance the recording kept for each (NaN when it kept none)."""
    dvs = d2[((d2["flags"] & FLAG_DVS) != 0) & np.isfinite(d2["x_dist"])]
    if not len(dvs):
        return None
    pt = np.minimum(dvs["frame_pt_idx"], 255).astype(np.int64)
    out = pd.DataFrame({"frame": dvs["trigger_frame"], "camn": dvs["camera_index"].astype(np.int64),
                        "frame_pt_idx": pt, "var_x": np.nan, "var_y": np.nan, "cov_xy": np.nan},
                       columns=DVS_POINTS_COLUMNS)
    cov = rec.table("dvs_point_covariance")
    if len(cov):
        c = pd.DataFrame({"frame": cov["trigger_frame"], "camn": cov["camera_index"].astype(np.int64),
                          "frame_pt_idx": np.minimum(cov["frame_pt_idx"], 255).astype(np.int64),
                          "var_x": cov["var_x"], "var_y": cov["var_y"], "cov_xy": cov["cov_xy"]})
        c = c.drop_duplicates(["frame", "camn", "frame_pt_idx"], keep="last")
        out = out[["frame", "camn", "frame_pt_idx"]].merge(c, how="left", on=["frame", "camn", "frame_pt_idx"])
    return out[DVS_POINTS_COLUMNS]


def _apply_dvs_points(data: Data2D, dp: pd.DataFrame) -> None:
    """Flag the rows FlyTrack's DVS table names as event-camera points and attach their covariances, as a
    FlyTrack recording carries them (FLAG_DVS, dvs_point_covariance)."""
    if not all(c in dp.columns for c in DVS_POINTS_COLUMNS) or not len(dp):
        return
    rows = data.rows

    def key(frame: np.ndarray, camn: np.ndarray, pt: np.ndarray) -> np.ndarray:
        return (frame.astype(np.int64) << 24) | (camn.astype(np.int64) << 8) | np.minimum(pt, 255).astype(np.int64)

    num = {c: pd.to_numeric(dp[c], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
           for c in DVS_POINTS_COLUMNS}
    ok = np.isfinite(num["frame"]) & np.isfinite(num["camn"]) & np.isfinite(num["frame_pt_idx"])
    k = key(num["frame"][ok], num["camn"][ok], num["frame_pt_idx"][ok])
    rows["flags"][np.isin(key(rows["trigger_frame"], rows["camera_index"], rows["frame_pt_idx"]), k)] |= FLAG_DVS
    has = ok & np.isfinite(num["var_x"]) & np.isfinite(num["var_y"]) & np.isfinite(num["cov_xy"])
    if has.any():
        cov = np.zeros(int(has.sum()), dtype=DVS_COVARIANCE)
        cov["trigger_frame"] = num["frame"][has]
        cov["camera_index"] = num["camn"][has]
        cov["frame_pt_idx"] = num["frame_pt_idx"][has]
        for c in ("var_x", "var_y", "cov_xy"):
            cov[c] = num[c][has]
        data.dvs_cov = cov


def _read_table(z: zipfile.ZipFile | _Folder, name: str) -> pd.DataFrame | None:
    names = set(z.namelist())
    # Braid archives may hold a top-level folder; accept "x/name" too.
    for cand in (f"{name}.csv", f"{name}.csv.gz"):
        hits = [n for n in names if n == cand or n.endswith("/" + cand)]
        if hits:
            data = z.read(hits[0])
            if cand.endswith(".gz"):
                try:
                    data = gzip.decompress(data)
                except (OSError, EOFError):
                    # A braid still being written may end in a cut gzip stream: keep what inflates.
                    data = _partial_gunzip(data)
            return pd.read_csv(io.BytesIO(data), comment=None)
    return None


def _partial_gunzip(data: bytes) -> bytes:
    import zlib

    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    out = d.decompress(data)
    return out[: out.rfind(b"\n") + 1]


def read_braidz(path: Path | str) -> Data2D:
    path = Path(path)
    z: zipfile.ZipFile | _Folder
    if path.is_dir():
        z = _Folder(path)
    else:
        try:
            z = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError) as exc:
            raise BraidzError(f"{path}: not a .braidz (zip) file: {exc}") from None
    with z:
        d2 = _read_table(z, "data2d_distorted")
        if d2 is None:
            raise BraidzError(f"{path}: no data2d_distorted table; not a Braid archive")
        missing = [c for c in ("camn", "frame", "x", "y") if c not in d2.columns]
        if missing:
            raise BraidzError(f"{path}: data2d_distorted lacks columns {missing}")
        ci = _read_table(z, "cam_info")
        names = {int(r.camn): str(r.cam_id) for r in ci.itertuples()} if ci is not None else {}
        cal = None
        for n in z.namelist():
            if n == "calibration.xml" or n.endswith("/calibration.xml"):
                cal = ("calibration.xml", z.read(n))
        clock = _read_table(z, "trigger_clock_info")
        dvs_points = _read_table(z, DVS_POINTS)
        fps, params = None, None
        tl = _read_table(z, "textlog")
        if tl is not None and "message" in tl.columns:
            for msg in tl["message"].astype(str):
                m = re.match(r"MainBrain running at ([0-9.eE+-]+) ", msg + " ")
                if m:
                    try:
                        fps = float(m.group(1))
                    except ValueError:
                        pass
                elif msg.startswith("{") and "tracking_params" in msg:
                    try:
                        params = json.loads(msg)["tracking_params"]
                    except (json.JSONDecodeError, KeyError, TypeError):
                        pass
    data = Data2D(rows=_rows_from_braid_df(d2), cam_names=names, fps=fps, calibration=cal,
                  source=str(path), tracking_params=None, notes=[f"braid tracking_params: {params}"] if params else [])
    if dvs_points is not None:
        _apply_dvs_points(data, dvs_points)
    if clock is not None and len(clock) and all(c in clock.columns for c in CLOCK_COLUMNS):
        data.clock_samples = np.array(
            list(clock[CLOCK_COLUMNS].itertuples(index=False, name=None)),
            dtype=[("start_timestamp", "<f8"), ("framecount", "<f8"), ("tcnt", "<f8"), ("stop_timestamp", "<f8")])
    return data


def _rows_from_braid_df(d2: pd.DataFrame) -> np.ndarray:
    """Braid/flydra data2d_distorted columns -> DATA2D rows (x_undist filled later from the calibration)."""
    n = len(d2)
    rows = empty_rows(n)

    def col(name: str, default: float = np.nan) -> np.ndarray:
        if name in d2.columns:
            return pd.to_numeric(d2[name], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
        return np.full(n, default)

    frame = col("frame", -1)
    rows["trigger_frame"] = np.where(np.isfinite(frame), frame, -1).astype(np.int64)
    rows["camera_index"] = col("camn", 0).astype(np.int64)
    block = col("block_id", 0)
    rows["camera_frame"] = np.where(np.isfinite(block), block, 0).astype(np.uint64)
    rows["timestamp"] = col("timestamp")
    rows["cam_received_timestamp"] = col("cam_received_timestamp")
    dev = col("device_timestamp", 0)
    rows["device_timestamp_ns"] = np.where(np.isfinite(dev), dev, 0).astype(np.uint64)
    rows["x_dist"] = col("x")
    rows["y_dist"] = col("y")
    rows["area"] = col("area")
    with np.errstate(invalid="ignore"):
        rows["orientation"] = np.arctan(col("slope"))
    rows["eccentricity"] = col("eccentricity")
    pt = col("frame_pt_idx", 0)
    rows["frame_pt_idx"] = np.where(np.isfinite(pt), pt, 0).astype(np.uint16)
    cv = col("cur_val", 0)
    rows["cur_val"] = np.where(np.isfinite(cv), cv, 0).astype(np.uint16)
    rows["mean_val"] = col("mean_val")
    rows["sumsq_val"] = col("sumsqf_val")
    return rows
