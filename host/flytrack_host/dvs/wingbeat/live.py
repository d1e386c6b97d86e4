"""Wing beats live from a DVS edge: `flytrack-edge --wingbeat 1` tracks the fly at the edge (the C twin of
this package's EKF, edge/events/algos/wingbeat.c) and sends a DVS_WINGBEAT datagram (protocol/SPEC.md 1.7)
every few milliseconds of event time; this module receives them over UDP, keeps the per-wing series
(records 0 and 1: angle, amplitude, frequency, phase; records 2-5: the four edges), counts what was wrong
(malformed datagrams, other message types, datagrams lost by sequence number), writes the CSV and the
figure, and scores the series against a simulated fly's truth.

`start_edge` runs the real daemon on an event file (played at its recorded pace): with the simulator,
the whole path from events to the host's numbers is the real one.
"""

from __future__ import annotations

import csv
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flytrack_host.dvs.wingbeat.analysis import WingbeatResult, WingScore, WingTrack, score_wings
from flytrack_host.dvs.wingbeat.plot import plot_truth_beats, save_figure
from flytrack_host.dvs.wingbeat.wra import BeatSeries
from flytrack_host.protocol import DvsWingbeat, EdgeStatus, ProtocolError, decode_datagram
from flytrack_host.util import children

DEFAULT_PORT = 7700  # flytrack-edge's default --port
N_WINGS = 2
N_RECORDS = 6  # wings 0, 1, then edges (wing 0 leading, wing 0 trailing, wing 1 leading, wing 1 trailing)
RECORD_NAMES = ("wing 0", "wing 1", "wing 0 leading", "wing 0 trailing", "wing 1 leading", "wing 1 trailing")


class NoEdgeError(RuntimeError):
    """Nothing arrived from an edge within the timeout."""


@dataclass
class LiveCounts:
    datagrams: int = 0
    wingbeat: int = 0
    with_fly: int = 0  # datagrams carrying records (the edge has found the fly)
    status: int = 0
    malformed: int = 0
    other: int = 0  # well-formed datagrams of other types (e.g. DVS_CLUSTERS: the edge is not in wingbeat mode)
    lost: int = 0  # by the edge's sequence numbers
    errors: dict[str, int] = field(default_factory=dict)  # malformed, by SPEC error name
    other_types: dict[str, int] = field(default_factory=dict)


CSV_HEADER = ["t_us", "record", "name", "angle_rad", "amplitude_rad", "frequency_hz", "phase_rad"]


class WingbeatReceiver:
    """A UDP socket on `port` that takes DVS_WINGBEAT and STATUS from one or more edges.

    With `csv_path` every record of every datagram is appended there as it arrives (flushed every second,
    so a run killed at any moment keeps all but its last second); in memory only the two wings' records
    are kept (for the table, the plot and the scores: ~400 rows a second at the edge's default rate)."""

    def __init__(self, port: int = DEFAULT_PORT, bind: str = "0.0.0.0", camera_index: int | None = None,
                 csv_path: Path | None = None) -> None:
        self._csv_fh = None
        if csv_path is not None:
            csv_path.parent.mkdir(parents=True, exist_ok=True)
            self._csv_fh = open(csv_path, "w", newline="")  # noqa: SIM115 - open for the receiver's life
            self._csv = csv.writer(self._csv_fh)
            self._csv.writerow(CSV_HEADER)
        self._csv_flushed = time.monotonic()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        try:
            self.sock.bind((bind, port))
        except OSError as exc:
            self.sock.close()
            if self._csv_fh is not None:
                self._csv_fh.close()
            raise OSError(f"cannot listen on UDP {bind}:{port}: {exc.strerror or exc}") from None
        self.port = self.sock.getsockname()[1]
        self.camera_index = camera_index
        self.counts = LiveCounts()
        # the wings' records: t_us, record, angle, amplitude, frequency, phase
        self.rows: list[tuple[int, int, float, float, float, float]] = []
        self.last_status: EdgeStatus | None = None
        self.last: DvsWingbeat | None = None
        self.first_mono: float | None = None
        self.last_mono: float | None = None
        self.first_error: str | None = None
        self._seq: dict[tuple, int] = {}

    def poll(self, timeout: float) -> int:
        """Takes what arrives within `timeout` s (returns after draining once something came)."""
        got = 0
        self.sock.settimeout(timeout)
        try:
            while True:
                data, addr = self.sock.recvfrom(65536)
                self._take(data, addr)
                got += 1
                self.sock.settimeout(0.0)
        except (TimeoutError, BlockingIOError):
            pass
        if self._csv_fh is not None and time.monotonic() - self._csv_flushed >= 1.0:
            self._csv_fh.flush()
            self._csv_flushed = time.monotonic()
        return got

    def _take(self, data: bytes, addr: tuple) -> None:
        c = self.counts
        c.datagrams += 1
        now = time.monotonic()
        self.first_mono = self.first_mono or now
        self.last_mono = now
        try:
            msg = decode_datagram(data)
        except ProtocolError as exc:
            c.malformed += 1
            c.errors[exc.name] = c.errors.get(exc.name, 0) + 1
            self.first_error = self.first_error or f"{addr[0]}:{addr[1]}: {exc}"
            return
        if self.camera_index is not None and getattr(msg, "camera_index", self.camera_index) != self.camera_index:
            return
        seq = getattr(msg, "seq", None)
        if seq is not None:  # per sender, +1 per datagram of any type
            key = (addr, getattr(msg, "camera_index", 0))
            prev = self._seq.get(key)
            if prev is not None:
                gap = (seq - prev) & 0xFFFFFFFF
                if 1 < gap < 1 << 31:
                    c.lost += gap - 1
            self._seq[key] = seq
        if isinstance(msg, EdgeStatus):
            c.status += 1
            self.last_status = msg
        elif isinstance(msg, DvsWingbeat):
            c.wingbeat += 1
            self.last = msg
            if msg.n_edges:
                c.with_fly += 1
            for r in msg.edges:
                row = (int(msg.t_us), int(r["edge_id"]), float(r["angle"]), float(r["amplitude"]),
                       float(r["frequency"]), float(r["phase"]))
                if row[1] < N_WINGS:
                    self.rows.append(row)
                if self._csv_fh is not None:
                    name = RECORD_NAMES[row[1]] if row[1] < len(RECORD_NAMES) else f"record {row[1]}"
                    self._csv.writerow([row[0], row[1], name, f"{row[2]:.6f}", f"{row[3]:.6f}", f"{row[4]:.4f}",
                                        f"{row[5]:.6f}"])
        else:
            c.other += 1
            name = type(msg).__name__
            c.other_types[name] = c.other_types.get(name, 0) + 1

    def series(self) -> dict[int, np.ndarray]:
        """Per wing (record 0, 1): rows (t_us, angle, amplitude, frequency, phase), time-ordered."""
        a = np.array(self.rows, dtype=np.float64).reshape(-1, 6)
        out = {}
        for rid in range(N_WINGS):
            sel = a[a[:, 1] == rid]
            out[rid] = sel[np.argsort(sel[:, 0], kind="stable")][:, [0, 2, 3, 4, 5]]
        return out

    def close(self) -> None:
        self.sock.close()
        if self._csv_fh is not None:
            self._csv_fh.close()
            self._csv_fh = None


def as_result(rx: WingbeatReceiver) -> WingbeatResult | None:
    """The wings' series as the file path's result type (for scoring); None before the fly was found."""
    s = rx.series()
    if any(len(s[w]) == 0 for w in range(N_WINGS)):
        return None
    wings = [WingTrack(w, {}, BeatSeries(s[w][:, 0], s[w][:, 3], s[w][:, 2])) for w in range(N_WINGS)]
    return WingbeatResult("ekf", None, (float("nan"),) * 2, wings, 0, 0, 0.0)  # type: ignore[arg-type]


def score_live(rx: WingbeatReceiver, truth, skip_s: float = 0.15) -> list[WingScore]:
    """Each wing's live estimates against the simulator's truth, after `skip_s` of convergence from the
    first estimate; as the file path, the frequency against the truth's mean over the beat before it."""
    res = as_result(rx)
    if res is None:
        return []
    return score_wings(res, truth.freq_at, truth.amplitude_at, skip_s=skip_s)


def start_edge(binary: Path, events_file: Path, port: int, realtime: bool = True,
               extra: tuple[str, ...] = ()) -> subprocess.Popen:
    """flytrack-edge on an event file in wing-beat mode, sending to 127.0.0.1:port."""
    args = [str(binary), "--source", "events", "--input", str(events_file), "--wingbeat", "1",
            "--host", "127.0.0.1", "--port", str(port), "--control-port", "0",
            "--realtime", "1" if realtime else "0", "--camera-name", "wingbeat", *extra]
    return children.popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # ends with this process


def plot_live(rx: WingbeatReceiver, path: Path, truth=None) -> Path:
    """Frequency and amplitude of each wing over time, as the edge sent them (and the truth when known)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = rx.series()
    fig, axes = plt.subplots(2, 2, figsize=(12, 6.5), sharex=True)
    for w in range(N_WINGS):
        d = s[w]
        for row, (col, label, scale) in enumerate(((3, "frequency (Hz)", 1.0), (2, "amplitude (deg)", 180 / np.pi))):
            ax = axes[row, w]
            if len(d):
                ax.plot(d[:, 0] * 1e-6, d[:, col] * scale, ".-", ms=2, lw=0.6, color="tab:red", label="edge EKF (live)")
            if truth is not None:
                plot_truth_beats(ax, truth, w, col == 3, scale)
            ax.set_title(f"wing {w}", fontsize=9)
            ax.set_ylabel(label)
            ax.set_xlabel("event time (s)")
            ax.legend(fontsize=7)
    fig.suptitle("Wing beats live from a DVS edge (DVS_WINGBEAT)")
    fig.tight_layout()
    return save_figure(fig, path)
