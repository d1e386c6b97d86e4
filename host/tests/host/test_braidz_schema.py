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
import math
import re
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


# Braid's TrackingParams (braid-types, serde deny_unknown_fields): field -> (kind, required).
_TRACKING_PARAMS = {
    "motion_noise_scale": ("f64", True), "initial_position_std_meters": ("f64", True),
    "initial_vel_std_meters_per_sec": ("f64", True), "ekf_observation_covariance_pixels": ("f64", True),
    "accept_observation_min_likelihood": ("f64", True), "max_position_std_meters": ("f64", True),
    "hypothesis_test_params": ("hypothesis", False), "num_observations_to_visibility": ("u8", False),
    "mini_arena_config": ("mini_arena", False),
}
_FPS_LINE = re.compile(r"^(\S+) fps, \((.*)\)$")


def braidz_parser_basics(z: zipfile.ZipFile) -> dict:
    r"""What braidz-parser's `parse_basics` (strand-braid, braidz/braidz-parser/src/incremental_parser.rs)
    demands of an archive, rule by rule, raising AssertionError where Braid's tools return an error or
    panic: the metadata parses; a textlog message starting "MainBrain running at " matches its
    `^(\S+) fps, \((.*)\)$` (UnknownTextlogData otherwise) with a number or "unknown"; a message that
    parses as JSON is an object (it unwraps it), and its `tracking_params`, if any, deserialises as
    TrackingParams (unknown fields denied; `mini_arena_config` an internally tagged enum) and comes once;
    kalman_estimates needs tracking parameters (MissingTrackingParameters). Returns fps and params."""
    names = set(z.namelist())
    yaml.safe_load(z.read("braid_metadata.yml"))
    _, rows = read_csv_text(z, "textlog")
    fps, params = math.nan, None
    for r in rows:
        msg = r[3]
        if msg.startswith("MainBrain running at "):
            m = _FPS_LINE.match(msg.removeprefix("MainBrain running at "))
            assert m, f"textlog {msg!r}: braidz-parser's fps regex does not match (UnknownTextlogData)"
            if m.group(1) != "unknown":
                fps = float(m.group(1))  # Rust's f64 parse: plain decimal or exponent
            continue
        try:
            js = json.loads(msg)
        except ValueError:
            continue
        assert isinstance(js, dict), f"textlog {msg!r} is JSON but not an object: braidz-parser panics on it"
        if "tracking_params" in js:
            assert params is None, "tracking_params twice in the textlog (MultipleTrackingParameters)"
            params = js["tracking_params"]
            unknown = set(params) - set(_TRACKING_PARAMS)
            assert not unknown, f"TrackingParams has deny_unknown_fields; unknown: {sorted(unknown)}"
            for key, (kind, required) in _TRACKING_PARAMS.items():
                if key not in params:
                    assert not required, f"TrackingParams.{key} is missing"
                    continue
                v = params[key]
                if kind == "f64":
                    assert isinstance(v, float | int) and not isinstance(v, bool), key
                elif kind == "u8":
                    assert isinstance(v, int) and 0 <= v <= 255, key
                elif kind == "hypothesis":
                    assert v is None or (set(v) == {"minimum_number_of_cameras", "hypothesis_test_max_acceptable_error",
                                                    "minimum_pixel_abs_zscore"}
                                         and 0 <= v["minimum_number_of_cameras"] <= 255), key
                else:  # #[serde(tag = "type")] enum MiniArenaConfig { NoMiniArena, XYGrid(..) }
                    assert isinstance(v, dict) and v.get("type") in ("NoMiniArena", "XYGrid"), \
                        f"mini_arena_config {v!r} is not Braid's internally tagged enum"
    if "kalman_estimates.csv.gz" in names or "kalman_estimates.csv" in names:
        assert params is not None, "kalman_estimates without tracking parameters (MissingTrackingParameters)"
    read_csv_text(z, "cam_info")
    return {"fps": fps, "tracking_params": params}


def test_braidz_export_passes_braidz_parsers_rules(tracked_run, tmp_path):
    """Braid's own tools (braidz-cli, the viewer, braid-offline, the Rerun export) open archives through
    braidz-parser; pybraidz-chunked-iter reads only kalman_estimates, so it cannot tell."""
    _, _, summary = tracked_run
    out = tmp_path / "run.braidz"
    export_braidz(load_recording(summary["recording"]), out)
    with zipfile.ZipFile(out) as z:
        basics = braidz_parser_basics(z)
        assert basics["fps"] == FPS
        assert "experiment_info.csv.gz" in z.namelist()  # Braid writes it with every recording
        header, _ = read_csv_text(z, "experiment_info")
        assert header == ["uuid"]
        _, log_rows = read_csv_text(z, "textlog")
        assert [r[1] for r in log_rows[:2]] == ["mainbrain", "mainbrain"]


def test_the_braidz_parser_rules_refuse_what_braid_refuses(tmp_path):
    """The checker above must fail where Braid does: the fps line without its parenthesis, a string
    mini_arena_config, an unknown tracking field."""
    def archive(messages: list[str]) -> zipfile.ZipFile:
        path = tmp_path / f"a{len(list(tmp_path.iterdir()))}.zip"
        log = "mainbrain_timestamp,cam_id,host_timestamp,message\n" + "".join(
            f'1.0,mainbrain,1.0,"{m.replace(chr(34), chr(34) * 2)}"\n' for m in messages)
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("braid_metadata.yml", "schema: 3\n")
            z.writestr("textlog.csv.gz", gzip.compress(log.encode()))
            z.writestr("cam_info.csv.gz", gzip.compress(b"camn,cam_id\n0,cam1\n"))
        return zipfile.ZipFile(path)

    good = json.dumps({"tracking_params": braid_tracking_params(None)})
    assert braidz_parser_basics(archive(["MainBrain running at 100 fps, ()", good]))["fps"] == 100.0
    for bad in (["MainBrain running at 100 fps", good],
                ["MainBrain running at 100 fps, ()",
                 json.dumps({"tracking_params": {**braid_tracking_params(None), "mini_arena_config": "NoMiniArena"}})],
                ["MainBrain running at 100 fps, ()",
                 json.dumps({"tracking_params": {**braid_tracking_params(None), "extra": 1}})],
                ["MainBrain running at 100 fps, ()", "42"]):
        with pytest.raises(AssertionError):
            braidz_parser_basics(archive(bad))


def test_braid_tracking_params_from_flytrack_params():
    p = braid_tracking_params(TrackingParams(measurement_noise_px=3.0, confirm_min_frames=7).model_dump())
    assert p["ekf_observation_covariance_pixels"] == 9.0 and p["num_observations_to_visibility"] == 7
    assert braid_tracking_params(None)["ekf_observation_covariance_pixels"] == 1.0  # Braid's default
