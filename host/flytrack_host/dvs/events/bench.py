"""`make bench-events`: event-file decode speed, libflytrack_events against the readers a user would
otherwise pick, on the same files in one run.

Section 1, decode: for each format, N synthetic events (640x480 sensor, time-ordered, both
polarities) are written once to a temporary file (EVT 2.0 and DAT by expelliarmus' writer, EVT 3.0
and AEDAT 4.0 by ours, AEDAT 2.0/3.1 packed here), then every reader decodes the whole file to a
NumPy array, repeatedly, the readers interleaved. Figures are mean events per second over the
repeats (file in the page cache; one warm-up each). Peers: expelliarmus (EVT 2.0, EVT 3.0, DAT,
its C decoder through Wizard.read, with the faster of two buffer sizes found in the warm-up) and
dv-processing (AEDAT 4.0, MonoCameraRecording batches to NumPy), plus aedat (AEDAT 4.0, Rust) for
reference. The ratio is ours over the faster peer.

Section 2 (issue 13, event algorithms, bench_algos.py): noise filter and cluster tracker throughput
on one core, beside dv-processing's background-activity filter on the same events.
BENCH_JSON=PATH (or --json PATH) writes the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from flytrack_host.dvs.events import EVENT_DTYPE, read_events, write_events

W, H = 640, 480


def synthetic(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = 1000 + np.cumsum(rng.integers(0, 3, n))  # ~1 M events/s of sensor time
    ev["x"] = rng.integers(0, W, n)
    ev["y"] = rng.integers(0, H, n)
    ev["p"] = rng.integers(0, 2, n)
    return ev


def _expelliarmus_array(ev: np.ndarray) -> np.ndarray:
    arr = np.empty(len(ev), np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")]))
    arr["t"], arr["x"], arr["y"], arr["p"] = ev["t"], ev["x"], ev["y"], ev["p"]
    return arr


def write_aedat2(path: Path, ev: np.ndarray) -> None:
    """jAER AEDAT 2.0 with DVS128 addresses (x, y folded into 0..127)."""
    x, y = ev["x"].astype(np.uint32) % 128, ev["y"].astype(np.uint32) % 128
    addr = (y << 8) | ((127 - x) << 1) | (1 - ev["p"].astype(np.uint32))
    rec = np.empty((len(ev), 2), ">u4")
    rec[:, 0], rec[:, 1] = addr, ev["t"].astype(np.uint32)
    path.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: DVS128\r\n" + rec.tobytes())


def write_aedat3(path: Path, ev: np.ndarray, per_packet: int = 8192) -> None:
    """AEDAT 3.1 polarity packets of 8192 events."""
    out = [b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DVXplorer\r\n#!END-HEADER\r\n"]
    for i in range(0, len(ev), per_packet):
        part = ev[i:i + per_packet]
        n = len(part)
        t = part["t"].astype(np.int64)
        overflow = int(t[0] >> 31)
        data = (part["x"].astype(np.uint32) << 17) | (part["y"].astype(np.uint32) << 2) \
            | (part["p"].astype(np.uint32) << 1) | 1
        rec = np.empty((n, 2), "<u4")
        rec[:, 0], rec[:, 1] = data, (t & 0x7FFFFFFF).astype(np.uint32)
        out.append(struct.pack("<hhiiiiii", 1, 1, 8, 4, overflow, n, n, n) + rec.tobytes())
    path.write_bytes(b"".join(out))


def _dv_read(path: Path) -> int:
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    parts = []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        parts.append(batch.numpy())
    return len(np.concatenate(parts))


def _aedat_read(path: Path) -> int:
    import aedat

    return len(np.concatenate([p["events"] for p in aedat.Decoder(str(path)) if "events" in p]))


def _expelliarmus_reader(enc: str, buff_size: int) -> Callable[[Path], int]:
    from expelliarmus import Wizard

    def read(path: Path) -> int:
        return len(Wizard(encoding=enc, fpath=str(path), buff_size=buff_size).read())
    return read


def _timed(fn: Callable[[Path], int], path: Path) -> tuple[float, int]:
    t0 = time.perf_counter()
    n = fn(path)
    return time.perf_counter() - t0, n


def decode_section(args: argparse.Namespace) -> dict:
    n = args.events
    ev = synthetic(n)
    figures: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="ft-bench-events-") as tmp:
        d = Path(tmp)
        files: dict[str, Path] = {}
        from expelliarmus import Wizard

        files["evt2"] = d / "e2.raw"
        Wizard(encoding="EVT2").save(str(files["evt2"]), _expelliarmus_array(ev))
        files["evt3"] = d / "e3.raw"
        write_events(files["evt3"], ev, W, H, fmt="evt3")
        files["dat"] = d / "d.dat"
        Wizard(encoding="DAT").save(str(files["dat"]), _expelliarmus_array(ev))
        for comp in ("lz4", "zstd", "none"):
            files[f"aedat4-{comp}"] = d / f"a-{comp}.aedat4"
            write_events(files[f"aedat4-{comp}"], ev, W, H, compression=comp)
        files["aedat2"] = d / "a2.aedat"
        write_aedat2(files["aedat2"], ev)
        files["aedat3"] = d / "a3.aedat"
        write_aedat3(files["aedat3"], ev)

        def ours(path: Path) -> int:
            return len(read_events(path))

        peers: dict[str, dict[str, Callable[[Path], int]]] = {}
        for fmt, enc in (("evt2", "EVT2"), ("evt3", "EVT3"), ("dat", "DAT")):
            # expelliarmus at its best: the faster of its default buffer and a large one
            cands = {b: _expelliarmus_reader(enc, b) for b in (4096, 1 << 20)}
            best = min(cands, key=lambda b: min(_timed(cands[b], files[fmt])[0] for _ in range(2)))
            peers[fmt] = {f"expelliarmus (buff_size {best})": cands[best]}
        for comp in ("lz4", "zstd", "none"):
            peers[f"aedat4-{comp}"] = {"dv-processing": _dv_read, "aedat": _aedat_read}
        peers["aedat2"] = {}
        peers["aedat3"] = {}

        print(f"decode: {n:,} events per file, mean of {args.repeats} runs after a warm-up, "
              "whole file to a NumPy array")
        print(f"{'format':<14}{'MB':>7}  {'ours Mev/s':>11}  {'peer':<32}{'peer Mev/s':>11}  {'ours/peer':>9}")
        for name, path in files.items():
            readers = {"ours": ours, **peers[name]}
            counts = {k: fn(path) for k, fn in readers.items()}  # warm-up and event counts
            times: dict[str, list[float]] = {k: [] for k in readers}
            for _ in range(args.repeats):
                for k, fn in readers.items():
                    times[k].append(_timed(fn, path)[0])
            rate = {k: counts[k] / float(np.mean(v)) for k, v in times.items()}
            size_mb = path.stat().st_size / 1e6
            row = {"events": counts["ours"], "file_mb": round(size_mb, 2),
                   "ours_events_per_s": round(rate["ours"])}
            peer_rates = {k: r for k, r in rate.items() if k != "ours"}
            for k, r in peer_rates.items():
                row[f"{k.split(' ')[0]}_events_per_s"] = round(r)
                row[f"{k.split(' ')[0]}_events"] = counts[k]
            # the faster peer among those the issue names (aedat is shown for reference)
            named = {k: r for k, r in peer_rates.items() if not k.startswith("aedat")}
            if named:
                peer, pr = max(named.items(), key=lambda kv: kv[1])
                row["ratio_vs_faster_peer"] = round(rate["ours"] / pr, 2)
                print(f"{name:<14}{size_mb:>7.1f}  {rate['ours'] / 1e6:>11.1f}  {peer:<32}{pr / 1e6:>11.1f}  "
                      f"{rate['ours'] / pr:>8.2f}x")
                for k, r in peer_rates.items():
                    if k != peer:
                        print(f"{'':<14}{'':>7}  {'':>11}  {k:<32}{r / 1e6:>11.1f}  {rate['ours'] / r:>8.2f}x")
            else:
                print(f"{name:<14}{size_mb:>7.1f}  {rate['ours'] / 1e6:>11.1f}  {'(no peer reads it)':<32}")
            for k, c in counts.items():
                if c != counts["ours"]:
                    print(f"{'':<14}note: {k} returned {c:,} events, ours {counts['ours']:,}")
            figures[name] = row
    return figures


# Benchmark sections, run in order; each takes the parsed args and returns its figures.
def _algos(args: argparse.Namespace) -> dict:
    from flytrack_host.dvs.events.bench_algos import algos_section

    return algos_section(args)


SECTIONS: dict[str, Callable[[argparse.Namespace], dict]] = {"decode": decode_section, "algorithms": _algos}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--events", type=int, default=5_000_000, help="events per file")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per reader and file")
    ap.add_argument("--json", default=os.environ.get("BENCH_JSON") or None, help="write figures here")
    args = ap.parse_args(argv)
    fig: dict = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count()}
    for name, section in SECTIONS.items():
        fig[name] = section(args)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(fig, fh, indent=2)
        print(f"figures written to {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
