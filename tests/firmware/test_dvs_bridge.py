"""The DVS USB bridge firmware (firmware/dvs_usb, unchanged simulator .elf) in simavr.

The harness plays the sensor's AER bus with the four-phase handshake, pulses the sync input and serves the
USB seam; every word the bridge sends is decoded with the host's DvsDecoder and checked against the played
stream: x, y, polarity and time (truth = the cycle the sensor asserted /REQ, on the firmware's Timer3 epoch),
wraps, resets and sync words included. Figures are printed (run with -s) and listed in the summary.
"""

from __future__ import annotations

import re
import struct
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.dvs.bridge import simulator as sim
from flytrack_host.protocol.dvs import DvsDecoder
from flytrack_host.util.testing import missing_part

F = sim.F_CPU


@pytest.fixture(scope="module")
def bridge() -> tuple:
    if not sim.tools_available():
        missing_part("avr-gcc / simavr not installed: the DVS bridge firmware cannot run here")
    return sim.build()


def _random_events(n: int, rng: np.random.Generator, cycles: np.ndarray) -> np.ndarray:
    x, y, p = rng.integers(0, 128, n), rng.integers(0, 128, n), rng.integers(0, 2, n)
    return sim.aer_events(x, y, p, cycles)


def _start(cycle: int = 2000, master: bool = True) -> list[tuple[int, bytes]]:
    c = [sim.control_request(cycle, sim.VENDOR_OUT, sim.VR_TS_MASTER, value=int(master))]
    return c + [sim.control_request(cycle + 1, sim.VENDOR_OUT, sim.VR_START)]


def _status(cycle: int) -> tuple[int, bytes]:
    return sim.control_request(cycle, sim.VENDOR_IN, sim.VR_FT_STATUS, length=sim.STATUS_SIZE)


def _decode(run: sim.BridgeRun) -> tuple[np.ndarray, np.ndarray]:
    """All packets through one DvsDecoder, as a host reads the endpoint transfer by transfer."""
    dec = DvsDecoder()
    evs, syncs = [], []
    for _, pkt in run.packets:
        assert len(pkt) <= 64 and len(pkt) % 4 == 0
        e, s = dec.decode_with_sync(pkt)
        evs.append(e)
        syncs.append(s)
    return np.concatenate(evs), np.concatenate(syncs)


def _match(played: np.ndarray, run: sim.BridgeRun, got: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the played events the decoded ones are (in order, a dropped event is skipped) and
    each one's timestamp error (decoded t_us - truth us). A word that matches no played event fails."""
    truth = run.truth_us(run.req_cycles)
    addr = got["x"].astype(np.uint16) << 1 | got["p"].astype(np.uint16) | got["y"].astype(np.uint16) << 8
    idx = np.empty(len(got), np.int64)
    j = 0
    for i in range(len(got)):
        while j < len(run.req_cycles) and not (
            played["addr"][j] == addr[i] and abs(float(got["t"][i]) - truth[j]) < 2.0
        ):
            j += 1
        assert j < len(run.req_cycles), f"decoded event {i} {got[i]} matches no played event"
        idx[i] = j
        j += 1
    return idx, got["t"].astype(np.float64) - truth[idx]


def test_paced_300k_stream_every_event_exact(bridge, dvs_figures) -> None:
    """60k events offered at 300 k/s (12 counter wraps) with 1 kHz sync pulses and a timestamp reset in
    the middle, through the full-speed bulk model: every event arrives, in order, each within 1 us of the
    truth; a sync word for every pulse; the sensor never falls behind its schedule by more than a few us."""
    rng = np.random.default_rng(1)
    n = 60_000
    period = F / 300_000  # 53.3 cycles
    t0 = 20_000
    nominal = (t0 + np.arange(n) * period).astype(np.int64)
    played = _random_events(n, rng, nominal)
    reset_at = int(nominal[n // 2])
    pulses = int((nominal[-1] - 30_000) // 16_000)
    controls = _start() + [
        sim.control_request(reset_at, sim.VENDOR_OUT, sim.VR_RESET_TS),
        _status(int(nominal[-1]) + 200_000),
    ]
    run = sim.run_bridge(played, controls, sync=(16_000, 30_000, 800, pulses), built=bridge)
    assert not run.violations, run.violations[:5]
    assert run.end["played"] == n
    ev, sync_t = _decode(run)
    idx, err = _match(played, run, ev)
    assert len(ev) == n and np.array_equal(idx, np.arange(n)), f"{n - len(ev)} events lost"
    assert np.array_equal(ev["x"], played["addr"] >> 1 & 0x7F)
    assert np.array_equal(ev["y"], played["addr"] >> 8 & 0x7F)
    assert np.array_equal(ev["p"], played["addr"] & 1)
    assert np.max(np.abs(err)) <= 1.0, (err.min(), err.max())
    # the timestamp reset: served within 3 ms under this load (one epoch restart), and the times start
    # again from ~0 after it
    epochs = run.epoch_starts()
    assert any(0 <= c - reset_at < 48_000 for c in epochs[:, 0]), (reset_at, epochs)
    after = run.req_cycles > epochs[-1, 0]
    assert ev["t"][after].min() < 5 and ev["t"][~after].max() > 40_000
    # sync: one word per pulse, each within 1 us of the pulse's edge
    assert len(sync_t) == pulses == len(run.sync_cycles)
    s_err = sync_t.astype(np.float64) - run.truth_us(run.sync_cycles)
    assert np.max(np.abs(s_err)) <= 1.0, (s_err.min(), s_err.max())
    # sustained: the sensor kept to its 300 k/s schedule (lag = how late each /REQ came)
    lag_us = (run.req_cycles - nominal) / F * 1e6
    span = (run.req_cycles[-1] - run.req_cycles[0]) / F
    rate = (n - 1) / span
    st = run.status()
    assert st.overflow == 0 and st.sync_missed == 0 and st.sync_events == pulses
    assert lag_us.max() < 100, lag_us.max()
    assert rate >= 299_000
    print(f"\nDVS bridge sustained event rate: {rate / 1e3:.1f} k events/s offered 300 k/s through full-speed "
          f"bulk ({n} events, max sensor lag {lag_us.max():.1f} us, none lost)")
    print(f"DVS bridge timestamp error: {err.min():+.3f} .. {err.max():+.3f} us over {n} events "
          f"(mean {err.mean():+.3f}); sync {s_err.min():+.3f} .. {s_err.max():+.3f} us")
    print(f"DVS bridge sync events == pulses sent: {len(sync_t)} == {pulses}")
    dvs_figures["sustained event rate"] = f"{rate / 1e3:.1f} k events/s (300 k/s offered, full-speed bulk model)"
    dvs_figures["timestamp error"] = f"{err.min():+.3f} .. {err.max():+.3f} us ({n} events)"
    dvs_figures["sync events == pulses sent"] = (
        f"{len(sync_t)} == {pulses} (error {s_err.min():+.2f}..{s_err.max():+.2f} us)"
    )


def test_capacity_back_to_back(bridge, dvs_figures) -> None:
    """The sensor presenting events as fast as the handshake allows: the firmware's own capacity (USB not
    limiting) and what full-speed bulk lets through (the sensor is held off by the handshake, nothing lost)."""
    rng = np.random.default_rng(2)
    n = 30_000
    played = _random_events(n, rng, np.full(n, 20_000))
    out = {}
    for name, usb in (("firmware", 1), ("full-speed bulk", sim.USB_FS_PACKET_CYCLES)):
        run = sim.run_bridge(played, _start() + [_status(3_000_000)], usb_packet_cycles=usb, built=bridge,
                             drain_cycles=50_000, sync=(8_000, 25_000, 400, 150))  # fmt: skip
        assert not run.violations
        ev, sync_t = _decode(run)
        idx, err = _match(played, run, ev)
        assert len(ev) == n and np.max(np.abs(err)) <= 1.0
        # 2 kHz sync pulses while the loop is saturated: every one recorded, on time
        assert len(sync_t) == len(run.sync_cycles) == 150
        assert np.max(np.abs(sync_t.astype(np.float64) - run.truth_us(run.sync_cycles))) <= 1.0
        cyc = (run.req_cycles[-1] - run.req_cycles[0]) / (n - 1)
        out[name] = cyc
        print(f"\nDVS bridge back-to-back, {name}: {cyc:.1f} cycles/event = {F / cyc / 1e3:.0f} k events/s")
    assert out["firmware"] < 53.3  # the loop itself beats 300 k/s on a 16 MHz AVR
    dvs_figures["cycles per event"] = (f"{out['firmware']:.1f} (= {F / out['firmware'] / 1e3:.0f} k events/s); "
                                       f"through full-speed bulk {F / out['full-speed bulk'] / 1e3:.0f} k events/s")


def test_fifo_overflow_counted_words_intact(bridge, dvs_figures) -> None:
    """A host that takes a packet only every 6 ms: the FIFO fills, whole events are dropped and counted,
    every word that arrives is an exact played event, and WRAP words are never lost (times stay right
    across 3 wraps)."""
    rng = np.random.default_rng(3)
    n = 4_000
    played = _random_events(n, rng, 20_000 + np.arange(n) * 250)  # 64 k events/s for 62 ms
    run = sim.run_bridge(played, _start() + [_status(4_000_000)], usb_packet_cycles=100_000, built=bridge,
                         drain_cycles=250_000, sync=(16_000, 30_000, 800, 60))  # fmt: skip
    assert not run.violations
    ev, sync_t = _decode(run)
    idx, err = _match(played, run, ev)
    st = run.status()
    # sync words are never dropped silently: recorded (on time) or counted as missed
    assert len(sync_t) == st.sync_events and st.sync_events + st.sync_missed == 60
    truth = run.truth_us(run.sync_cycles)
    nearest = np.min(np.abs(sync_t.astype(np.float64)[:, None] - truth[None, :]), axis=1)
    assert np.max(nearest) <= 1.0 and len(sync_t) > 0
    lost = n - len(ev)
    assert lost > 1_000 and st.overflow == lost
    assert np.max(np.abs(err)) <= 1.0
    assert ev["t"].max() > 3 * 16_384
    assert np.all(np.diff(idx) > 0)
    print(f"\nDVS bridge FIFO overflow: {lost} of {n} events dropped and counted (status {st.overflow}), "
          f"FIFO max {st.fifo_max} words, every delivered word exact; sync {st.sync_events} recorded + "
          f"{st.sync_missed} counted missed of 60 pulses")
    dvs_figures["FIFO overflow"] = f"{lost}/{n} dropped == counted {st.overflow}; delivered words all exact"


def test_vendor_requests_through_the_seam(bridge) -> None:
    """Biases shifted out bit for bit, bad requests stalled, status, stop/start, array reset."""
    biases = bytes(range(1, 37))
    c0 = 2_000
    controls = [
        sim.control_request(c0, sim.VENDOR_OUT, sim.VR_BIASES, length=36, data=biases),
        sim.control_request(c0 + 1, sim.VENDOR_OUT, sim.VR_BIASES, length=35, data=biases[:35]),  # bad length
        sim.control_request(c0 + 2, sim.VENDOR_OUT, 0xA7),  # not a request of this device
        sim.control_request(c0 + 3, 0x00, sim.VR_START),  # a standard request type
        sim.control_request(c0 + 4, sim.VENDOR_OUT, sim.VR_RESET_ARRAY),
        _status(c0 + 5),
        *_start(50_000),
        sim.control_request(300_000, sim.VENDOR_OUT, sim.VR_STOP),
        _status(300_001),
        sim.control_request(600_000, sim.VENDOR_OUT, sim.VR_START),
        _status(900_000),
    ]
    rng = np.random.default_rng(4)
    cyc = np.concatenate([np.arange(100_000, 250_000, 1_000), np.arange(350_000, 550_000, 1_000),
                          np.arange(650_000, 850_000, 1_000)])  # fmt: skip
    played = _random_events(len(cyc), rng, cyc)
    run = sim.run_bridge(played, controls, built=bridge)
    assert not run.violations
    by = [(r.request, r.ok) for r in run.replies]
    assert by[:5] == [(0xB8, True), (0xB8, False), (0xA7, False), (0xB3, False), (0xBD, True)]
    assert run.biases == [biases]
    assert len(run.array_resets) == 1
    st0 = sim.BridgeStatus.parse(run.replies[5].data)
    assert not st0.running and st0.master
    stopped = sim.BridgeStatus.parse(run.replies[9].data)
    assert not stopped.running
    assert sim.BridgeStatus.parse(run.replies[-1].data).running
    ev, _ = _decode(run)
    idx, err = _match(played, run, ev)
    # the events while stopped were acknowledged (the sensor went on) but not sent
    assert run.end["played"] == len(cyc)
    sent = cyc[idx]
    assert np.all((sent < 300_000) | (sent > 600_000)) and len(ev) == 150 + 200
    assert np.max(np.abs(err)) <= 1.0
    # the second START begins a new epoch with a RESET word
    resets = [i for i in range(0, len(run.stream), 4) if run.stream[i + 3] & 0x40]
    assert len(resets) == 2


def test_slave_mode_zeroes_time_at_the_next_sync_pulse(bridge) -> None:
    """Timestamp slave: streaming starts without a reset; the next pulse on the sync input is time zero."""
    rng = np.random.default_rng(5)
    cyc = np.arange(100_000, 1_500_000, 997)
    played = _random_events(len(cyc), rng, cyc)
    pulse0 = 400_000
    run = sim.run_bridge(played, _start(50_000, master=False) + [_status(1_800_000)],
                         sync=(320_000, pulse0, 800, 4), built=bridge)  # fmt: skip
    assert not run.violations
    ev, sync_t = _decode(run)
    assert len(ev) == len(cyc) and len(sync_t) == 4
    after = run.req_cycles > pulse0 + 2_000
    t_rel = (run.req_cycles[after] - pulse0) / F * 1e6  # us since the pulse
    err = ev["t"][after].astype(np.float64) - t_rel
    assert np.max(np.abs(err)) <= 1.0, (err.min(), err.max())
    s_rel = (run.sync_cycles - pulse0) / F * 1e6
    assert np.max(np.abs(sync_t.astype(np.float64) - s_rel)) <= 1.0
    assert not sim.BridgeStatus.parse(run.replies[-1].data).master


def test_harness_cli_and_bad_input(bridge, tmp_path) -> None:
    """Every option in the usage text; bad inputs give one clear line and exit 2, no traceback."""
    harness, elf = bridge
    src = (Path(__file__).resolve().parents[2] / "firmware/dvs_usb/harness/dvs_sim.c").read_text()
    options = re.findall(r'\{"([a-z-]+)",', src.split("static const struct option opts[]", 1)[1].split("};", 1)[0])
    r = subprocess.run([str(harness), "--help"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 0 and len(options) >= 15
    assert not [o for o in options if f"--{o}" not in r.stderr]
    out = tmp_path / "out.txt"
    (tmp_path / "ev.bin").write_bytes(b"\x00" * 7)
    (tmp_path / "ctl.txt").write_text("100 40b3zz\n")
    (tmp_path / "short.txt").write_text("100 40b3\n")
    cases = [
        (["--events", str(tmp_path / "ev.bin")], "not a whole number of 6-byte records"),
        (["--control", str(tmp_path / "ctl.txt")], "bad hex"),
        (["--control", str(tmp_path / "short.txt")], "8 setup bytes"),
        (["--sync-count", "3", "--sync-period", "100", "--sync-high", "100"], "--sync-high"),
        (["--events", str(tmp_path / "missing.bin")], "cannot read"),
    ]
    for extra, msg in cases:
        r = subprocess.run([str(harness), "--elf", str(elf), "--out", str(out), *extra], capture_output=True,
                           text=True, timeout=10)  # fmt: skip
        assert r.returncode == 2 and msg in r.stderr, (extra, r.stderr)
    r = subprocess.run([str(harness), "--elf", str(tmp_path / "nope.elf"), "--out", str(out)], capture_output=True,
                       text=True, timeout=10)  # fmt: skip
    assert r.returncode == 2 and "cannot read firmware" in r.stderr


def test_trickle_latency_bounded(bridge, dvs_figures) -> None:
    """A slow trickle (2 k events/s, a bank would take 8 ms to fill): a partly filled bank goes out after
    1 ms, so no event waits much longer than that for the host."""
    rng = np.random.default_rng(6)
    cyc = 20_000 + np.arange(400) * 8_000 + rng.integers(0, 4_000, 400)
    played = _random_events(len(cyc), rng, cyc)
    run = sim.run_bridge(played, _start(), built=bridge)
    assert not run.violations
    dec = DvsDecoder()
    handed = []
    for c, pkt in run.packets:
        handed += [c] * len(dec.decode(pkt))
    assert len(handed) == len(cyc)
    lat_ms = (np.array(handed) - run.req_cycles) / F * 1e3
    short = sum(len(p) < 64 for _, p in run.packets)
    print(f"\nDVS bridge latency at 2 k events/s: REQ to packet handed to USB {lat_ms.mean():.2f} ms mean, "
          f"{lat_ms.max():.2f} ms max ({short} short packets of {len(run.packets)})")
    assert lat_ms.max() < 1.2
    dvs_figures["trickle latency"] = f"{lat_ms.mean():.2f} ms mean, {lat_ms.max():.2f} ms max at 2 k events/s"


@pytest.mark.parametrize("req_delay,next_delay", [(1, 1), (8, 16), (40, 80)])
def test_handshake_timings(bridge, req_delay: int, next_delay: int) -> None:
    """Sensors slower to release /REQ and to present the next event (up to 2.5 us / 5 us): the bridge
    waits for each phase, never breaks the handshake, and every event keeps its exact time."""
    rng = np.random.default_rng(7)
    n = 3_000
    played = _random_events(n, rng, np.full(n, 20_000))
    run = sim.run_bridge(played, _start(), req_delay=req_delay, next_delay=next_delay, built=bridge,
                         drain_cycles=40_000)  # fmt: skip
    assert not run.violations and run.end["played"] == n
    ev, _ = _decode(run)
    idx, err = _match(played, run, ev)
    assert len(ev) == n and np.max(np.abs(err)) <= 1.0
    cyc = (run.req_cycles[-1] - run.req_cycles[0]) / (n - 1)
    assert cyc >= req_delay + next_delay  # the bridge really waited on the sensor
    print(f"\nDVS bridge handshake /REQ release {req_delay} cycles, next /REQ {next_delay}: {cyc:.1f} cycles/event")


@pytest.mark.parametrize("seed", [11, 12])
def test_random_bursts_resets_slow_host(bridge, seed: int) -> None:
    """Bursty events (gaps from 0 to ~1 ms), 1.6 kHz sync, three timestamp resets at random moments and a
    host 7x slower than full speed (the FIFO fills in bursts): every delivered word is a played event at
    its exact time, in order; what is missing is what the status counts as dropped; every sync pulse is
    a SYNC word on time or counted."""
    rng = np.random.default_rng(seed)
    n = 12_000
    gaps = np.where(rng.random(n) < 0.7, rng.integers(0, 40, n), rng.exponential(2_000, n).astype(np.int64))
    cyc = 20_000 + np.cumsum(gaps)
    played = _random_events(n, rng, cyc)
    end = int(cyc[-1])
    resets = sorted(int(c) for c in rng.integers(40_000, end, 3))
    controls = _start() + [sim.control_request(c, sim.VENDOR_OUT, sim.VR_RESET_TS) for c in resets]
    controls.append(_status(end + 1_500_000))  # after the last event, however late backpressure makes it
    pulses = (end - 25_000) // 10_000
    run = sim.run_bridge(played, controls, sync=(10_000, 25_000, 500, pulses), usb_packet_cycles=6_000,
                         built=bridge)  # fmt: skip
    assert not run.violations
    ev, sync_t = _decode(run)
    idx, err = _match(played, run, ev)
    st = run.status()
    assert np.max(np.abs(err)) <= 1.0
    assert n - len(ev) == st.overflow
    assert len(run.epoch_starts()) == 2 + 3  # boot, START, three resets
    assert len(sync_t) == st.sync_events and st.sync_events + st.sync_missed == pulses
    # sync words: each within 1 us of a pulse in the epoch it was sent in (a clamped one may not be)
    truth = run.truth_us(run.sync_cycles)
    nearest = np.min(np.abs(sync_t.astype(np.float64)[:, None] - truth[None, :]), axis=1)
    assert np.sum(nearest > 1.0) <= st.clamped
    print(f"\nDVS bridge random seed {seed}: {len(ev)}/{n} events delivered exact ({st.overflow} dropped, counted), "
          f"sync {st.sync_events}/{pulses} (missed {st.sync_missed}, clamped {st.clamped}), FIFO max {st.fifo_max}")


def test_target_build_usb_descriptors(bridge) -> None:
    """The target build (real USB controller, not runnable here) enumerates as a DVS128: its device and
    configuration descriptors, read from the .elf, carry 152a:8400, bcdDevice 0x000E (type 0, firmware 14,
    what libcaer checks) and one bulk-IN endpoint 0x86 of 64 bytes."""
    elf = sim.build_dir() / "firmware" / sim.MCU / "flytrack_dvs.elf"
    make = ["make", "-s", "-C", str(sim.REPO_ROOT / "firmware" / "dvs_usb"), f"OUT={sim.build_dir() / 'firmware'}"]
    subprocess.run([*make, str(elf)], check=True, stdout=subprocess.DEVNULL)
    syms = {}
    nm = subprocess.run(["avr-nm", "-S", str(elf)], capture_output=True, text=True, check=True).stdout
    for line in nm.splitlines():
        parts = line.split()
        if len(parts) == 4:
            syms[parts[3]] = (int(parts[0], 16), int(parts[1], 16))
    with tempfile.TemporaryDirectory() as d:
        flash = Path(d) / "flash.bin"
        subprocess.run(["avr-objcopy", "-O", "binary", "-j", ".text", str(elf), str(flash)], check=True)
        image = flash.read_bytes()

    def blob(name: str) -> bytes:
        a, n = syms[name]
        return image[a : a + n]

    dev = blob("dev_desc")
    assert len(dev) == 18 and dev[1] == 1
    vid, pid, bcd = struct.unpack_from("<HHH", dev, 8)
    assert (vid, pid, bcd) == (0x152A, 0x8400, 0x000E)
    conf = blob("conf_desc")
    assert len(conf) == struct.unpack_from("<H", conf, 2)[0] == 25
    ep = conf[18:25]
    assert ep[1] == 5 and ep[2] == 0x86 and ep[3] == 2 and struct.unpack_from("<H", ep, 4)[0] == 64


@pytest.mark.parametrize("seed", [109, 110, 113, 134])
def test_random_scenarios(bridge, seed: int) -> None:
    """Random mixes (burst share, gap lengths, 0-3 resets, 0.8-5 kHz sync, host at full speed down to one
    packet per 1.25 ms, sensor handshake 1-10 / 1-20 cycles); these seeds once found ordering bugs."""
    rng = np.random.default_rng(seed)
    n = 6_000
    p_burst = rng.uniform(0.3, 0.95)
    gaps = np.where(rng.random(n) < p_burst, rng.integers(0, 60, n),
                    rng.exponential(rng.uniform(200, 5000), n).astype(np.int64))  # fmt: skip
    cyc = 20_000 + np.cumsum(gaps)
    played = _random_events(n, rng, cyc)
    end = int(cyc[-1])
    n_res = int(rng.integers(0, 4))
    resets = sorted(int(c) for c in rng.integers(40_000, end, n_res)) if n_res else []
    controls = _start() + [sim.control_request(c, sim.VENDOR_OUT, sim.VR_RESET_TS) for c in resets]
    controls.append(_status(end + 1_500_000))
    period = int(rng.integers(3000, 20000))
    pulses = max(1, (end - 25_000) // period)
    usb = int(rng.choice([842, 1500, 4000, 20000]))
    run = sim.run_bridge(played, controls, sync=(period, 25_000, 300, pulses), usb_packet_cycles=usb, built=bridge,
                         req_delay=int(rng.integers(1, 10)), next_delay=int(rng.integers(1, 20)))  # fmt: skip
    assert not run.violations
    ev, sync_t = _decode(run)
    idx, err = _match(played, run, ev)
    st = run.status()
    assert np.max(np.abs(err)) <= 1.0
    assert n - len(ev) == st.overflow
    assert len(sync_t) == st.sync_events and st.sync_events + st.sync_missed == pulses
    truth = run.truth_us(run.sync_cycles)
    nearest = np.min(np.abs(sync_t.astype(np.float64)[:, None] - truth[None, :]), axis=1)
    assert np.sum(nearest > 1.0) <= st.clamped
