"""The soak's live clients, in a process of their own as a lab's are (a Braid client, a VR stimulus
program): a Braid event-stream client (live/braid.py iter_sse) and a pose client (live/pose.py
PoseClient). They count what they get and write the counts as JSON to a status file twice a second.

    python -m flytrack_host.sim.soak_clients STATUS.json

Prints `pose_port N` (the UDP port its pose client listens on), then reads one line from stdin: the
live server's base URL, whose /events stream it follows (reconnecting, counted, if it ends early). It
exits when stdin closes.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from flytrack_host.live.braid import iter_sse, open_event_stream
from flytrack_host.live.pose import PoseClient

WRITE_EVERY_S = 0.5


class Counts:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.d: dict[str, Any] = {
            "sse_connects": 0, "sse_events": 0, "sse_updates": 0, "sse_births": 0, "sse_deaths": 0,
            "sse_end_of_frame": 0, "sse_last_frame": -1, "sse_errors": 0, "sse_last_error": "",
            "pose_datagrams": 0, "pose_with_object": 0, "pose_no_object": 0, "pose_malformed": 0,
            "pose_age_ms_max": 0.0,
        }

    def add(self, **kw: float) -> None:
        with self.lock:
            for k, v in kw.items():
                self.d[k] += v

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            return dict(self.d)


def follow_events(url: str, counts: Counts, stop: threading.Event) -> None:
    """Braid's /events: count each message by kind; reconnect when the stream ends before `stop`."""
    while not stop.is_set():
        try:
            with open_event_stream(url + "events", timeout=30) as resp:
                counts.add(sse_connects=1)
                for ev in iter_sse(resp):
                    msg = ev.json().get("msg", {})
                    kw: dict[str, float] = {"sse_events": 1}
                    if "Update" in msg:
                        kw["sse_updates"] = 1
                    elif "Birth" in msg:
                        kw["sse_births"] = 1
                    elif "Death" in msg:
                        kw["sse_deaths"] = 1
                    elif "EndOfFrame" in msg:
                        kw["sse_end_of_frame"] = 1
                        with counts.lock:
                            counts.d["sse_last_frame"] = int(msg["EndOfFrame"])
                    counts.add(**kw)
                    if stop.is_set():
                        return
        except Exception as exc:  # counted; a stream that ends while the run goes on is a finding
            with counts.lock:
                counts.d["sse_errors"] += 1
                counts.d["sse_last_error"] = repr(exc)[:200]
        stop.wait(0.5)


def follow_pose(client: PoseClient, counts: Counts, stop: threading.Event) -> None:
    while not stop.is_set():
        m = client.recv(0.2)
        if m is None:
            continue
        counts.add(pose_datagrams=1, **({"pose_no_object": 1} if m.no_object else {"pose_with_object": 1}))
        if not m.no_object:
            with counts.lock:
                counts.d["pose_age_ms_max"] = max(counts.d["pose_age_ms_max"], m.age_s * 1e3)


def write_status(path: Path, counts: Counts, client: PoseClient) -> None:
    d = counts.snapshot()
    d["pose_malformed"] = client.stats.malformed
    d["time"] = time.time()  # noqa: TID251 - a label for whoever reads the file
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(d))
    os.replace(tmp, path)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    status = Path(argv[0])
    client = PoseClient(port=0)
    counts = Counts()
    stop = threading.Event()
    print(f"pose_port {client.port}", flush=True)
    threading.Thread(target=follow_pose, args=(client, counts, stop), daemon=True).start()
    url = sys.stdin.readline().strip()
    if url:
        threading.Thread(target=follow_events, args=(url, counts, stop), daemon=True).start()

    def writer() -> None:
        while not stop.wait(WRITE_EVERY_S):
            write_status(status, counts, client)

    threading.Thread(target=writer, daemon=True).start()
    sys.stdin.read()  # until the soak closes our stdin
    stop.set()
    write_status(status, counts, client)
    client.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
