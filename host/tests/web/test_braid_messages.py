"""Braid's message model (v3), checked against the shapes of strand-braid's model server."""

from __future__ import annotations

import io
import json
import math
import sys
from pathlib import Path

import numpy as np

from flytrack_host.live import braid

sys.path.insert(0, str(Path(__file__).parent))
from frames import make_result  # noqa: E402


def test_frame_messages_in_braids_order_with_its_fields():
    r = make_result(7, 3, born=[2], died=[9])
    msgs = braid.frame_messages(r)
    kinds = [next(iter(m)) for m in msgs]
    # Per target: Birth (when it became visible in this frame) then Update; Deaths; EndOfFrame.
    assert kinds == ["Update", "Birth", "Update", "Update", "Death", "EndOfFrame"]
    assert msgs[1]["Birth"] == msgs[2]["Update"]
    assert msgs[4] == {"Death": 9} and msgs[5] == {"EndOfFrame": 7}
    row = msgs[0]["Update"]
    assert tuple(row) == braid.ROW_FIELDS  # no timestamp: Braid's SendKalmanEstimatesRow has none
    e = r.estimates[0]
    assert row["obj_id"] == 1 and row["frame"] == 7
    assert [row[k] for k in ("x", "y", "z", "xvel", "yvel", "zvel")] == e.state.tolist()
    c = e.covariance
    assert [row[k] for k in ("P00", "P01", "P02", "P11", "P12", "P22", "P33", "P44", "P55")] == [
        c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2], c[3, 3], c[4, 4], c[5, 5]]


def test_sse_framing_envelope_and_nan_as_null():
    r = make_result(3, 1)
    r.estimates[0].state[4] = np.nan
    data = braid.encode_frame(r, 1000.0, now=1000.25)
    assert data.startswith(b"event: braid\ndata: {") and data.endswith(b"}\n\n")
    evs = list(braid.iter_sse(io.BytesIO(data)))
    assert [e.event for e in evs] == ["braid", "braid"]
    m = evs[0].json()
    assert list(m) == ["v", "msg", "latency", "synced_frame", "trigger_timestamp"]
    assert m["v"] == 3 and m["synced_frame"] == 3 and m["trigger_timestamp"] == 1000.0
    assert math.isclose(m["latency"], 0.25)
    assert m["msg"]["Update"]["yvel"] is None  # serde_json writes NaN as null; JSON has no NaN
    # An unknown trigger time: both null, as Braid sends them.
    m2 = json.loads(braid.encode_frame(r, math.nan).split(b"data: ")[1].split(b"\n")[0])
    assert m2["latency"] is None and m2["trigger_timestamp"] is None


def test_calibration_event_and_sse_parser_rules():
    ev = next(braid.iter_sse(io.BytesIO(braid.calibration_event("<multi_camera_reconstructor/>\n"))))
    assert ev.json()["msg"] == {"CalibrationFlydraXml": "<multi_camera_reconstructor/>\n"}
    text = b": comment\r\nevent: x\r\ndata: a\r\ndata: b\r\n\r\ndata: c\n\n"
    assert [(e.event, e.data) for e in braid.iter_sse(io.BytesIO(text))] == [("x", "a\nb"), ("message", "c")]


def test_fast_encoder_writes_the_same_bytes_as_the_message_model():
    r = make_result(11, 4, born=[1, 3], died=[7, 8])
    r.estimates[2].state[0] = np.inf
    r.estimates[1].covariance[0, 0] = -0.0
    slow = b"".join(braid.sse_event(braid.envelope(m, 11, 50.0, 50.5)) for m in braid.frame_messages(r))
    assert braid.encode_frame(r, 50.0, now=50.5) == slow
    slow_nan = b"".join(braid.sse_event(braid.envelope(m, 11, math.nan, 1.0)) for m in braid.frame_messages(r))
    assert braid.encode_frame(r, math.nan, now=1.0) == slow_nan
