"""Braid's live event stream, message version 3 ("Braid pose API"), as JSON server-sent events.

Read from Braid's model server (strand-braid, flydra2 `model_server.rs`) for the shapes; the code is
ours. Every event is

    event: braid
    data: {"v": 3, "msg": MSG, "latency": SECONDS, "synced_frame": FRAME, "trigger_timestamp": T}

with MSG one of `{"Birth": ROW}`, `{"Update": ROW}`, `{"Death": OBJ_ID}`, `{"EndOfFrame": FRAME}`,
`{"CalibrationFlydraXml": "<xml ...>"}` (sent once to each client on connect). ROW is Braid's
`SendKalmanEstimatesRow`: obj_id, frame, x, y, z, xvel, yvel, zvel, P00, P01, P02, P11, P12, P22, P33,
P44, P55 (no timestamp: the frame's trigger time is `trigger_timestamp`). `latency` is now minus the
trigger time when the event is written; serde_json writes a NaN as null, and so do we.

Per frame Braid sends a Birth when a target becomes visible, then an Update for every visible target
(the newborn included), a Death for each target removed, then EndOfFrame. FlyTrack's confirmed
targets (FrameResult.born / estimates / died) map one to one on that, so the Update rows of a run are
exactly the rows of its `kalman_estimates` table.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

from flytrack_host.tracking.types import FrameResult
from flytrack_host.util import hostclock

BRAID_VERSION = 3
EVENT_NAME = "braid"
ROW_FIELDS = ("obj_id", "frame", "x", "y", "z", "xvel", "yvel", "zvel",
              "P00", "P01", "P02", "P11", "P12", "P22", "P33", "P44", "P55")
# Flat indices into a row-major (6, 6) covariance, in ROW_FIELDS' P order.
_P_FLAT = (0, 1, 2, 7, 8, 14, 21, 28, 35)

_encoder = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None


def kalman_row(obj_id: int, frame: int, state: Any, covariance: Any) -> dict[str, Any]:
    """Braid's SendKalmanEstimatesRow for one estimate (non-finite values become null)."""
    s = state.tolist() if hasattr(state, "tolist") else list(state)
    c = covariance.ravel().tolist() if hasattr(covariance, "ravel") else [v for r in covariance for v in r]
    vals = s[:6] + [c[i] for i in _P_FLAT]
    row: dict[str, Any] = {"obj_id": int(obj_id), "frame": int(frame)}
    for name, v in zip(ROW_FIELDS[2:], vals, strict=True):
        row[name] = v if math.isfinite(v) else None
    return row


def envelope(msg: dict[str, Any], synced_frame: int, trigger_timestamp: float | None,
             now: float | None = None) -> dict[str, Any]:
    """The ToListener wrapper around one message."""
    tt = trigger_timestamp if trigger_timestamp is not None and math.isfinite(trigger_timestamp) else None
    latency = None if tt is None else _num((hostclock.now() if now is None else now) - tt)
    return {"v": BRAID_VERSION, "msg": msg, "latency": latency, "synced_frame": int(synced_frame),
            "trigger_timestamp": tt}


def sse_event(data: dict[str, Any], event: str = EVENT_NAME) -> bytes:
    """One server-sent event, as Braid frames it (`event:` line, one `data:` line, blank line)."""
    return b"event: " + event.encode() + b"\ndata: " + _encoder.encode(data).encode() + b"\n\n"


def frame_messages(result: FrameResult) -> list[dict[str, Any]]:
    """The Braid messages of one tracked frame in Braid's order: per target a Birth if it became
    visible in this frame, then its Update; then a Death per removed target; then EndOfFrame."""
    frame = int(result.trigger_frame)
    born = set(result.born)
    out: list[dict[str, Any]] = []
    for e in result.estimates:
        row = kalman_row(e.obj_id, frame, e.state, e.covariance)
        if e.obj_id in born:
            out.append({"Birth": row})
        out.append({"Update": row})
    out.extend({"Death": int(i)} for i in result.died)
    out.append({"EndOfFrame": frame})
    return out


def _js(v: float) -> str:
    # float.__repr__ is what json.dumps writes for a float; JSON has no NaN/inf: null, as serde_json.
    return repr(v) if math.isfinite(v) else "null"


_ROW = ('{"obj_id":%d,"frame":%d,"x":%s,"y":%s,"z":%s,"xvel":%s,"yvel":%s,"zvel":%s,"P00":%s,"P01":%s,'
        '"P02":%s,"P11":%s,"P12":%s,"P22":%s,"P33":%s,"P44":%s,"P55":%s}')


def encode_frame(result: FrameResult, trigger_timestamp: float, now: float | None = None) -> bytes:
    """All events of one frame as one byte string."""
    return b"".join(frame_events(result, trigger_timestamp, now))


def frame_events(result: FrameResult, trigger_timestamp: float, now: float | None = None) -> list[bytes]:
    """The frame's events, one byte string each: the same bytes as `sse_event(envelope(m, ...))` for
    each of `frame_messages(result)`, built faster with string formatting (the publisher encodes
    every frame; see test_braid_messages)."""
    now = hostclock.now() if now is None else now
    frame = int(result.trigger_frame)
    tt_ok = trigger_timestamp is not None and math.isfinite(trigger_timestamp)
    lat = _js(now - trigger_timestamp) if tt_ok else "null"
    tt = _js(trigger_timestamp) if tt_ok else "null"
    tail = f',"latency":{lat},"synced_frame":{frame},"trigger_timestamp":{tt}}}\n\n'
    head = 'event: braid\ndata: {"v":3,"msg":'
    born = set(result.born)
    parts = []
    for e in result.estimates:
        s = e.state.tolist() if hasattr(e.state, "tolist") else list(e.state)
        c = e.covariance.ravel().tolist() if hasattr(e.covariance, "ravel") else [v for r in e.covariance for v in r]
        row = _ROW % (int(e.obj_id), frame, *(_js(float(v)) for v in s[:6]), *(_js(float(c[i])) for i in _P_FLAT))
        if e.obj_id in born:
            parts.append(head + '{"Birth":' + row + "}" + tail)
        parts.append(head + '{"Update":' + row + "}" + tail)
    parts.extend(f'{head}{{"Death":{int(i)}}}{tail}' for i in result.died)
    parts.append(f'{head}{{"EndOfFrame":{frame}}}{tail}')
    return [p.encode() for p in parts]


def calibration_event(xml: str, synced_frame: int = 0) -> bytes:
    """The calibration as flydra XML, sent to each client when it connects (trigger time unknown)."""
    return sse_event(envelope({"CalibrationFlydraXml": xml}, synced_frame, None))


# --- client side ---------------------------------------------------------------------------------
@dataclass
class SseEvent:
    event: str
    data: str

    def json(self) -> Any:
        return json.loads(self.data)


def open_event_stream(url: str, timeout: float = 10.0) -> IO[bytes]:
    """Open Braid's event stream (`.../events`, with the page's token if it has one) as a client must:
    with `Accept: text/event-stream`, which the server, like Braid's, requires. Read it with iter_sse."""
    import urllib.request

    return urllib.request.urlopen(urllib.request.Request(url, headers={"Accept": "text/event-stream"}),
                                  timeout=timeout)


def iter_sse(stream: IO[bytes]) -> Iterator[SseEvent]:
    """Parse a text/event-stream (WHATWG rules for event/data lines; comments and id/retry ignored)."""
    event, data = "message", []
    for raw in stream:
        line = raw.decode("utf-8").rstrip("\r\n")
        if not line:
            if data:
                yield SseEvent(event, "\n".join(data))
            event, data = "message", []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "event":
            event = value
        elif name == "data":
            data.append(value)
