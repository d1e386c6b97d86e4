"""The real tracker end to end over UDP, and the .braidz export checked against Braid's own schema.

Braid's row types (strand-braid: flydra-types `KalmanEstimatesRow`, `Data2dDistortedRow`,
`CamInfoRow`, `TriggerClockInfoRow`, `TextlogRow`, flydra2 `DataAssocRow`, braidz-types
`BraidMetadata`) are written below as (column, kind) lists, in Braid's field order. Each CSV of the
archive is read as text and every field is checked against the kind Braid's serde would parse it
as: an unsigned field must be digits within range (a float "3.0" or a negative number fails), a
`NonZeroU64` option must be empty or > 0, a plain f64 must not be empty.
"""

from __future__ import annotations

import csv
import datetime
import gzip
import io
import json
import time
import zipfile

import numpy as np
import pytest
import yaml

from flytrack_host.io.braidz import braid_tracking_params, export_braidz
from flytrack_host.pipeline import HostPipeline
from flytrack_host.protocol import FeatureFrame, encode_features
from flytrack_host.recording import load_recording
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import make_scenario

FPS = 100.0

_F64 = [(n, "f64") for n in ("x", "y", "z", "xvel", "yvel", "zvel", "P00", "P01", "P02", "P11", "P12", "P22",
                             "P33", "P44", "P55")]
BRAID_SCHEMA: dict[str, list[tuple[str, str]]] = {
    "kalman_estimates": [("obj_id", "u32"), ("frame", "u64"), ("timestamp", "opt_f64")] + _F64,
    "data2d_distorted": [
        ("camn", "u8"), ("frame", "i64"), ("timestamp", "opt_f64"), ("cam_received_timestamp", "f64"),
        ("device_timestamp", "opt_nonzero_u64"), ("block_id", "opt_nonzero_u64"), ("x", "nan_f64"),
        ("y", "nan_f64"), ("area", "nan_f64"), ("slope", "nan_f64"), ("eccentricity", "nan_f64"),
        ("frame_pt_idx", "u8"), ("cur_val", "u8"), ("mean_val", "nan_f64"), ("sumsqf_val", "nan_f64"),
    ],
    "data_association": [("obj_id", "u32"), ("frame", "u64"), ("cam_num", "u8"), ("pt_idx", "u8")],
    "cam_info": [("camn", "u8"), ("cam_id", "str")],
    "trigger_clock_info": [("start_timestamp", "f64"), ("framecount", "i64"), ("tcnt", "u8"),
                           ("stop_timestamp", "f64")],
    "textlog": [("mainbrain_timestamp", "f64"), ("cam_id", "str"), ("host_timestamp", "f64"), ("message", "str")],
}
_UNSIGNED_MAX = {"u8": 255, "u32": 2**32 - 1, "u64": 2**64 - 1}


def check_field(kind: str, value: str) -> str | None:
    """None when `value` parses as Braid's type `kind`, else what is wrong."""
    if kind == "str":
        return None
    if kind in _UNSIGNED_MAX:
        if not value.isdigit() or int(value) > _UNSIGNED_MAX[kind]:
            return f"not a {kind}"
        return None
    if kind == "i64":
        return None if value.lstrip("-").isdigit() and abs(int(value)) < 2**63 else "not an i64"
    if kind == "opt_nonzero_u64":
        return None if value == "" or (value.isdigit() and 0 < int(value) < 2**64) else "not empty or > 0"
    if value == "":
        return None if kind in ("opt_f64", "nan_f64") else "empty"
    try:
        float(value)
    except ValueError:
        return "not a number"
    return None


def read_csv_text(z: zipfile.ZipFile, name: str) -> tuple[list[str], list[list[str]]]:
    text = gzip.decompress(z.read(f"{name}.csv.gz")).decode("utf-8")
    rows = list(csv.reader(io.StringIO(text)))
    return rows[0], rows[1:]


def _send(sock, dest, cam: int, frame: int, seq: int, pts: np.ndarray) -> int:
    ff = FeatureFrame(camera_index=cam, seq=seq, camera_frame=frame, trigger_frame=frame,
                      total_points=len(pts), points=pts, edge_recv_ns=1, edge_done_ns=2)
    out = encode_features(ff)
    for d in out:
        sock.sendto(d, dest)
    return len(out)


@pytest.fixture(scope="module")
def tracked_run(tmp_path_factory):
    """Four cameras of a synthetic scene sent over UDP to a HostPipeline with the real Tracker."""
    import socket

    from flytrack_host.rig import parse_rig

    sc = make_scenario(n_cameras=4, n_targets=2, duration_s=1.5, fps=FPS, close_pass_m=None, enter_exit=False,
                       false_positives_per_camera=0.0, seed=3)
    rig = parse_rig({
        "name": "braidrig", "trigger": {"kind": "software", "fps": FPS},
        "host": {"listen": "127.0.0.1:7000", "sync_deadline_fraction": 0.5},
        "recording": {"folder": "rec", "flush_interval_s": 0.2},
        "cameras": [{"name": f"cam{i}", "index": i, "edge": "127.0.0.1"} for i in sc.cameras],
        "tracking": {"measurement_noise_px": 2.0, "confirm_min_frames": 5},
    })
    d = tmp_path_factory.mktemp("braid")
    pipe = HostPipeline(rig, cameras=sc.cameras, recording_path=d / "run.flytrack", bind="127.0.0.1:0",
                        keep_results=True)  # default tracker factory: the real Tracker
    pipe.start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    seqs = dict.fromkeys(sc.cameras, 0)
    try:
        t0 = time.monotonic()
        for k, b in enumerate(sc.bundles):
            for cam in sc.cameras:
                pts = b.detections.get(cam, np.zeros(0, b.detections[next(iter(b.detections))].dtype))
                seqs[cam] += _send(sock, pipe.address, cam, k, seqs[cam], pts)
            if k % 50 == 0:
                t = time.time()
                pipe.record_clock_sample(t, k, 0.25, t + 0.0005)
            time.sleep(max(0.0, t0 + (k + 1) / FPS - time.monotonic()))
        time.sleep(0.1)
    finally:
        summary = pipe.stop()
        sock.close()
    return sc, pipe, summary


def test_real_tracker_end_to_end_over_udp(tracked_run):
    sc, pipe, summary = tracked_run
    n = len(sc.bundles)
    assert summary["loop_errors"] == 0 and summary["tracker_errors"] == 0
    assert summary["frames_tracked"] == n
    assert [r.trigger_frame for r in pipe.results] == list(range(n))
    errs, ids = [], set()
    for r in pipe.results:
        for e in r.estimates:
            ids.add(e.obj_id)
            errs.append(min(np.linalg.norm(np.asarray(e.state[:3]) - t) for t in sc.truth[r.trigger_frame].values()))
    assert len(errs) > n  # both targets, most of the time
    assert float(np.median(errs)) < 0.01, np.median(errs)
    rec = load_recording(summary["recording"])
    assert len(rec.table("kalman_estimates")) == len(errs)
    assert len(rec.table("data_association")) > 0


def test_braidz_export_matches_braid_schema(tracked_run, tmp_path):
    _, _, summary = tracked_run
    out = tmp_path / "run.braidz"
    export_braidz(load_recording(summary["recording"]), out)
    with zipfile.ZipFile(out) as z:
        for table, schema in BRAID_SCHEMA.items():
            header, rows = read_csv_text(z, table)
            assert header == [c for c, _ in schema], table  # names and order
            assert rows, f"{table} is empty"
            bad = [(i, c, r[j], why) for i, r in enumerate(rows) for j, (c, kind) in enumerate(schema)
                   if (why := check_field(kind, r[j] if j < len(r) else "<missing>")) is not None]
            assert not bad, f"{table}: {bad[:5]}"
            assert all(len(r) == len(schema) for r in rows), table
            cols = {c: [r[j] for r in rows] for j, (c, _) in enumerate(schema)}
            if "frame" in cols:
                frames = [int(f) for f in cols["frame"]]
                assert min(frames) >= 0, table
                if table in ("kalman_estimates", "data2d_distorted"):  # Braid readers rely on order
                    assert frames == sorted(frames), table
            if "obj_id" in cols:
                assert all(v != "" for v in cols["obj_id"])
        # Camera frame 0 (a NonZeroU64 in Braid) is an empty block_id, never "0".
        header, rows = read_csv_text(z, "data2d_distorted")
        blocks = [r[header.index("block_id")] for r in rows if r[header.index("frame")] == "0"]
        assert "" in blocks and "0" not in blocks
        meta = yaml.safe_load(z.read("braid_metadata.yml"))
        assert meta["schema"] == 3 and isinstance(meta["git_revision"], str)
        assert meta["save_empty_data2d"] is True and meta["saving_program_name"] == "flytrack"
        t = meta["original_recording_time"]
        assert isinstance(t, datetime.datetime | str)
        if isinstance(t, str):
            datetime.datetime.fromisoformat(t)
        _, log_rows = read_csv_text(z, "textlog")
        params = next(json.loads(r[3])["tracking_params"] for r in log_rows if r[3].startswith('{"tracking_params"'))
    # Braid's R is ekf_observation_covariance_pixels * I, a variance: the rig's 2 px std is 4 px^2.
    assert params["ekf_observation_covariance_pixels"] == 4.0
    assert params["num_observations_to_visibility"] == 5
    for key in ("motion_noise_scale", "initial_position_std_meters", "initial_vel_std_meters_per_sec",
                "accept_observation_min_likelihood", "max_position_std_meters"):
        assert isinstance(params[key], float), key
    h = params["hypothesis_test_params"]
    assert 0 <= h["minimum_number_of_cameras"] <= 255 and isinstance(h["hypothesis_test_max_acceptable_error"], float)


def test_braid_tracking_params_from_flytrack_params():
    p = braid_tracking_params(TrackingParams(measurement_noise_px=3.0, confirm_min_frames=7).model_dump())
    assert p["ekf_observation_covariance_pixels"] == 9.0 and p["num_observations_to_visibility"] == 7
    assert braid_tracking_params(None)["ekf_observation_covariance_pixels"] == 1.0  # Braid's default
