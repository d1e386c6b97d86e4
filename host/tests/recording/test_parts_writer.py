"""The writer of a recording in parts: it rolls by size and by time between two queued items, so every
row is in exactly one part, in order, and a frame's item is never split; each part carries the rig and
the header rows; a new part that cannot be made costs nothing; and stop finalises one part whatever the
recording's length (judged by the bytes stop finalised, not by seconds)."""

from __future__ import annotations

import errno
import json
import time

import numpy as np
import pytest

from flytrack_host.recording import Recorder, load_recording
from flytrack_host.recording import rolling as rolling_mod
from flytrack_host.recording.finalize import read_raw_table
from flytrack_host.recording.parts import PartPolicy, part_dirs
from flytrack_host.recording.schema import CAM_INFO, DATA2D, H5_NAME, KALMAN, LATENCY
from flytrack_host.recording.stream import frame_blocks


def frame_item(f: int, n2d: int = 3) -> list[tuple[str, np.ndarray]]:
    """Frame f's rows as the pipeline queues them: its 2D rows, one estimate and its latency row."""
    d = np.zeros(n2d, DATA2D)
    d["trigger_frame"], d["frame_pt_idx"], d["camera_index"] = f, np.arange(n2d), np.arange(n2d) % 2
    d["x_dist"] = f * 0.5 + np.arange(n2d)
    k = np.zeros(1, KALMAN)
    k["trigger_frame"], k["obj_id"], k["x"] = f, 1, f * 0.01
    lat = np.zeros(1, LATENCY)
    lat["trigger_frame"] = f
    return [("data2d_distorted", d), ("kalman_estimates", k), ("latency", lat)]


ITEM_BYTES = sum(r.nbytes for _, r in frame_item(0))


def parts_rows(folder, table: str, dtype) -> list[np.ndarray]:  # noqa: ANN001
    return [read_raw_table(p, table, dtype)[0] for p in part_dirs(folder)]


def check_whole_frames(folder, n_frames: int) -> None:  # noqa: ANN001
    """Every frame's rows exactly once, in order, and all of a frame's rows in one part."""
    where: dict[str, dict[int, set[int]]] = {}
    for table, dt in (("data2d_distorted", DATA2D), ("kalman_estimates", KALMAN), ("latency", LATENCY)):
        chunks = parts_rows(folder, table, dt)
        tf = np.concatenate([c["trigger_frame"] for c in chunks])
        per = 3 if table == "data2d_distorted" else 1
        assert np.array_equal(tf, np.repeat(np.arange(n_frames), per)), table  # once each, in order
        where[table] = {}
        for i, c in enumerate(chunks):
            for f in np.unique(c["trigger_frame"]).tolist():
                where[table].setdefault(f, set()).add(i)
    for f in range(n_frames):
        homes = {frozenset(where[t][f]) for t in where}
        assert len(homes) == 1 and len(next(iter(homes))) == 1, f"frame {f} split across parts: {homes}"


def test_rolls_by_size_between_items(tmp_path) -> None:
    limit = 40 * ITEM_BYTES + 100
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05, on_full="block",
                   parts=PartPolicy(bytes=limit, finalize="none"))
    rec.start()
    n = 1000
    for f in range(n):
        rec.append_many(frame_item(f))
        if f % 97 == 0:  # (the writer takes what is queued in its own turns, a few items or many at once)
            time.sleep(0.01)
    rec.stop(finalize=False)
    check_whole_frames(tmp_path / "r", n)
    parts = part_dirs(tmp_path / "r")
    sizes = [sum(f.stat().st_size for f in p.iterdir() if f.suffix in (".bin", ".jsonl")) for p in parts]
    assert len(parts) == rec.stats.parts >= n * ITEM_BYTES // limit
    # Each part holds what fits under the limit: it is closed before the item that would take it past.
    assert all(limit - ITEM_BYTES < s <= limit for s in sizes[:-1]), (limit, sizes)
    assert rec.stats.rows["data2d_distorted"] == 3 * n and not rec.stats.dropped_rows and not rec.stats.write_errors
    print(f"{n} frames of {ITEM_BYTES} bytes, parts of at most {limit} bytes: {len(parts)} parts, sizes {sizes}")


def test_rolls_by_time_between_items(tmp_path) -> None:
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05, parts=PartPolicy(seconds=0.25, finalize="none"))
    rec.start()
    f = 0
    while rec.part_index < 4:  # until the writer has started its 4th part (a condition; the pace is the feed's)
        rec.append_many(frame_item(f))
        f += 1
        time.sleep(0.002)
    rec.stop(finalize=False)
    check_whole_frames(tmp_path / "r", f)
    starts = [json.loads((p / "meta.json").read_text())["part_start_time"] for p in part_dirs(tmp_path / "r")]
    assert len(starts) >= 4 and all(b - a >= 0.25 for a, b in zip(starts, starts[1:], strict=False)), starts
    print(f"{f} frames in {len(starts)} parts, started {np.round(np.diff(starts), 3).tolist()} s apart")


def test_every_part_carries_the_rig_and_the_cameras(tmp_path) -> None:
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05, on_full="block",
                   parts=PartPolicy(bytes=10 * ITEM_BYTES, finalize="none"), meta={"fps": 100.0, "rig_name": "x"})
    rec.start()
    ci = np.zeros(3, CAM_INFO)
    ci["camera_index"], ci["name"] = [0, 1, 2], [b"a", b"b", b"c"]
    rec.append("cam_info", ci)
    rec.attach("rig.toml", b'name = "x"\n')
    rec.attach("calibration.xml", b"<multi_camera_reconstructor/>")
    for f in range(60):
        rec.append_many(frame_item(f))
    rec.stop(finalize=True)
    parts = part_dirs(tmp_path / "r")
    assert len(parts) >= 5
    for i, p in enumerate(parts):
        part = load_recording(p)  # alone
        assert part.table("cam_info").tobytes() == ci.tobytes()
        assert part.files == {"rig.toml": b'name = "x"\n', "calibration.xml": b"<multi_camera_reconstructor/>"}
        assert part.meta["part"] == i + 1 and part.meta["carried_rows"] == ({} if i == 0 else {"cam_info": 3})
        assert part.fps == 100.0
    whole = load_recording(tmp_path / "r")
    assert whole.table("cam_info").tobytes() == ci.tobytes() and whole.meta["parts"] == len(parts)
    assert "part" not in whole.meta and "carried_rows" not in whole.meta


def test_a_new_part_that_cannot_be_made_loses_nothing(tmp_path, monkeypatch) -> None:
    real = Recorder._make_part
    fails = {"left": 3}

    def full_disk(self, folder, index):  # noqa: ANN001, ANN202
        if index == 2 and fails["left"]:
            fails["left"] -= 1
            folder.mkdir()  # half made, as a full disk leaves it
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, folder, index)

    monkeypatch.setattr(Recorder, "_make_part", full_disk)
    monkeypatch.setattr(rolling_mod, "ROLL_RETRY_S", 0.05)
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05, parts=PartPolicy(bytes=20 * ITEM_BYTES, finalize="none"))
    rec.start()
    f = 0
    while rec.part_index < 3:  # the writer goes on in part 1 until part 2 can be made, then rolls on
        rec.append_many(frame_item(f))
        f += 1
        time.sleep(0.001)
    rec.stop(finalize=False)
    assert rec.stats.roll_errors == 3 and not fails["left"]
    assert not rec.stats.dropped_rows and rec.stats.write_errors == 0
    check_whole_frames(tmp_path / "r", f)
    sizes = [sum(x.stat().st_size for x in p.iterdir() if x.suffix == ".bin") for p in part_dirs(tmp_path / "r")]
    assert sizes[0] > 20 * ITEM_BYTES  # part 1 went on past its size while part 2 could not be made
    assert rec.last_error is not None and "cannot start part 2" in rec.last_error


def _record(folder, n_parts: int, part_bytes: int, parts: bool) -> Recorder:  # noqa: ANN001
    """n_parts parts' worth of frames, at a rig's pace: a part takes minutes to fill, finalising it seconds,
    so each closed part is finalised in the background before the next one closes (waited for here)."""
    rec = Recorder(folder, flush_interval_s=0.05, on_full="block",
                   parts=PartPolicy(bytes=part_bytes) if parts else None)
    rec.start()
    per_part = part_bytes // ITEM_BYTES
    f = 0
    for k in range(n_parts):
        for _ in range(per_part):
            rec.append_many(frame_item(f))
            f += 1
        end = time.monotonic() + 120
        while parts and rec.stats.parts_finalised_background < k and time.monotonic() < end:
            time.sleep(0.02)  # (a condition: the background finaliser has caught up)
    return rec


@pytest.mark.slow
def test_stop_finalises_one_part_whatever_the_length(tmp_path) -> None:
    part_bytes = 400 * ITEM_BYTES
    at_stop = {}
    for n_parts in (2, 6):
        rec = _record(tmp_path / f"p{n_parts}", n_parts, part_bytes, parts=True)
        rec.stop()
        st = rec.stats
        parts = part_dirs(tmp_path / f"p{n_parts}")
        assert len(parts) in (n_parts, n_parts + 1) and all((p / H5_NAME).exists() for p in parts)
        assert st.parts_finalised_background == len(parts) - 1  # every part but the last, in the background
        at_stop[n_parts] = st.finalise_at_stop_bytes
        assert 0 < st.finalise_at_stop_bytes <= part_bytes + 64 << 10, st  # one part (and its text log, meta)
        total = sum(f.stat().st_size for p in parts for f in p.iterdir() if f.is_file() and f.name != H5_NAME)
        print(f"{n_parts} parts' worth ({total / 1e6:.2f} MB, {len(parts)} parts): finalised at stop "
              f"{st.finalise_at_stop_bytes / 1e6:.3f} MB "
              f"in {st.finalise_at_stop_s:.2f} s; {st.parts_finalised_background} in the background "
              f"({st.finalise_background_s:.1f} s)")
        assert load_recording(tmp_path / f"p{n_parts}").table("data2d_distorted").size == 3 * n_parts * (
            part_bytes // ITEM_BYTES)
    assert at_stop[6] <= 1.2 * at_stop[2] + (16 << 10)  # does not grow with the number of parts
    # Unparted, stop finalises everything: the bytes grow with the length.
    whole = {}
    for n_parts in (2, 6):
        rec = _record(tmp_path / f"w{n_parts}", n_parts, part_bytes, parts=False)
        rec.stop()
        whole[n_parts] = rec.stats.finalise_at_stop_bytes
    print(f"unparted: finalised at stop {whole[2] / 1e6:.3f} MB (2 parts' worth), {whole[6] / 1e6:.3f} MB (6)")
    assert whole[6] > 2.5 * whole[2]


def _rows(tf: list[int], flags: int = 0) -> np.ndarray:
    r = np.zeros(len(tf), DATA2D)
    r["trigger_frame"], r["flags"] = tf, flags
    r["frame_pt_idx"] = np.arange(len(tf))
    return r


def test_frame_blocks_regroup_late_rows_and_report_those_too_late() -> None:
    # part 1: frames 0-9; part 2: a late row of 8, frames 10-19, a rejected row (frame 2), a row with no
    # frame; part 3: a row of 19 (late, but within a part: it joins its frame), one of 5 (more than a part
    # late: 5 was handed on with part 1's block), frames 20-24.
    parts = [
        {"data2d_distorted": _rows(list(range(10)))},
        {"data2d_distorted": np.concatenate([_rows([8]), _rows(list(range(10, 20))), _rows([2], 16), _rows([-1])])},
        {"data2d_distorted": np.concatenate([_rows([19, 5]), _rows(list(range(20, 25)))])},
    ]
    blocks = list(frame_blocks(parts))
    tfs = [b.tables["data2d_distorted"]["trigger_frame"].tolist() for b in blocks]
    assert tfs[0] == list(range(8))  # 8 and 9 wait: part 2 holds a row of 8
    assert sorted(t for t in tfs[1] if t >= 0 and t != 2) == [8] + list(range(8, 19))  # 8 whole: both its rows
    assert 2 in tfs[1] and -1 in tfs[1]  # a rejected row and one with no frame go out with their part
    assert sorted(tfs[2]) == [19, 19] + list(range(20, 25))  # 5 did not hold back frames 8-18
    assert blocks[2].late["data2d_distorted"]["trigger_frame"].tolist() == [5] and blocks[2].n_late == 1
    assert sum(len(t) for t in tfs) + 1 == sum(len(p["data2d_distorted"]) for p in parts)  # once each
