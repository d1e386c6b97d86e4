"""The real trigger firmware (avr-gcc build, unchanged .elf) in simavr, driven over its pty.

Figures are printed and collected in the terminal summary: period error (cycles), frames checked,
clock-model residual (us), pulse placement and width error (ticks), event timestamp error (ticks).
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from flytrack_host.protocol import trigger_link as tl
from flytrack_host.trigger.clock_model import ClockModel
from flytrack_host.trigger.crystal import record_crystal_run, score_fit
from flytrack_host.trigger.device import FIRMWARE_BAUD, TriggerDevice, TriggerError, clock_link_timing
from flytrack_host.trigger.simulator import (
    SimulatedTrigger,
    read_pacing_anchor,
    rising,
)
from flytrack_host.util.placement import run_as_hardware


def _falling(edges, name):
    return [e.cycle for e in edges if e.signal == name and e.level == 0]


def test_period_exact_and_frame_count_matches_edges(built, figures) -> None:
    harness, elf = built
    with SimulatedTrigger(elf=elf, harness=harness) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        fps = dev.set_rate(4000.0)  # /1, TOP 3999: 4000 cycles a frame
        assert dev.rate is not None
        period = (dev.rate.top + 1) * dev.rate.divisor
        dev.start()
        readings = []
        while True:
            r = dev.query_clock()
            readings.append(r)
            if r.frame_count >= 10_500:
                break
        dev.stop()
        final = dev.query_clock()
        dev.close()
    f_cpu, edges = sim.edges()
    rises = np.array(rising(edges, "trigger"), dtype=np.int64)
    falls = np.array(_falling(edges, "trigger"), dtype=np.int64)
    periods = np.diff(rises)
    err = int(np.max(np.abs(periods - period)))
    widths = falls[: len(rises)] - rises[: len(falls)]
    print(f"\nperiod: {fps:.3f} fps = {period} cycles; frames checked {len(periods)}; "
          f"max period error {err} cycles; trigger width {set(widths.tolist())} cycles")
    figures["period error (cycles)"] = f"{err} over {len(periods)} frame periods at {fps:g} fps"
    assert len(periods) >= 10_000
    assert err == 0
    # Every pulse has the same width, the last one too: STOP waits for the pulse under way to end.
    assert len(set(widths.tolist())) == 1, set(widths.tolist())
    # The frame count the firmware reports equals the rising edges the harness saw.
    assert final.running is False
    assert final.frame_count == len(rises)
    figures["frame count vs edges"] = f"CLOCK {final.frame_count} == {len(rises)} edges counted"
    # No wrap race: device time of successive replies never goes back, never skips a frame.
    dev_t = np.array([r.device_time_s for r in readings if r.running])
    assert np.all(np.diff(dev_t) > 0)
    assert all(0 <= r.ticks <= r.top for r in readings)


def test_clock_model_residual_and_bias_realtime(built, figures) -> None:
    """Paced run: the model's host time of every trigger edge against the truth, i.e. the edge's
    cycle placed on the host clock by the harness's pacing anchor (cycle c due at t0 + c / f_cpu)."""
    harness, elf = built
    with SimulatedTrigger(elf=elf, harness=harness, realtime=True) as sim:
        run_as_hardware(sim.proc.pid)  # silicon's clock is not delayed by a busy host (crystal.py)
        dev = TriggerDevice(sim.pty, reset_wait_s=0, model=ClockModel(window=200, max_rtt_s=0.02))
        dev.set_rate(100.0)
        dev.start()
        t_end = time.monotonic() + 3.0
        readings = []
        while time.monotonic() < t_end:
            readings.append(dev.query_clock())
            time.sleep(0.01)
        m = dev.model
        # Predict a later frame's host time and check it against a fresh query.
        r = dev.query_clock()
        frame_now = (r.frame_count - 1) + r.ticks / (r.top + 1)
        predicted = m.frame_to_host_time(frame_now)
        dev.stop()
        dev.close()
    f_cpu, edges = sim.edges()
    anchor = read_pacing_anchor(sim.edge_log)
    assert anchor is not None
    rises = np.array(rising(edges, "trigger"), dtype=np.int64)
    frames = np.arange(readings[0].frame_count, r.frame_count)  # the span the queries covered
    true_t = anchor + rises[frames] / f_cpu
    err = np.array([m.frame_to_host_time(int(n)) for n in frames]) - true_t
    # Where in the round trip the device really sampled (the model's wire-time estimate vs truth).
    run = [q for q in readings if q.running and q.frame_count > 0]
    sampled = np.array([anchor + (rises[q.frame_count - 1] + q.ticks * dev.rate.divisor) / f_cpu for q in run])
    after_t0 = np.median(sampled - np.array([q.host_t0 for q in run]))
    rtts = np.array([q.host_t1 - q.host_t0 for q in readings])
    est = m.link.request_s + m.link.device_s if m.link else float("nan")
    print(f"\nclock model: {m.n_samples} samples used of {len(rtts)}, median rtt {np.median(rtts) * 1e3:.2f} ms, "
          f"gain {m.gain:.9f}, residual {m.residual_s * 1e6:.1f} us; device sampled {after_t0 * 1e6:.0f} us "
          f"after the request was sent (model: {est * 1e6:.0f} us); trigger edge host times over {len(frames)} "
          f"frames: mean signed error {err.mean() * 1e6:+.1f} us, sd {err.std() * 1e6:.1f} us")
    figures["clock residual (us)"] = f"{m.residual_s * 1e6:.1f} (gain {m.gain:.6f}, {m.n_samples} samples, 3 s paced)"
    figures["trigger edge host time error (us)"] = (
        f"mean {err.mean() * 1e6:+.1f}, sd {err.std() * 1e6:.1f} over {len(frames)} edges (paced, 100 fps)")
    assert m.fitted and m.n_samples >= 15  # one in 5 of ~170-200 queries kept, a few dropped as outliers
    assert abs(m.gain - 1) < 2e-3
    assert m.residual_s < 100e-6
    assert abs(err.mean()) < 100e-6
    # One fresh query places its sample only within its own round trip (long when the host is
    # loaded): the prediction must fall within that, or 2 ms when the round trip is shorter.
    assert abs(predicted - m.sample_host_time(r.host_t0, r.host_t1)) < max(2e-3, r.host_t1 - r.host_t0)


def test_clock_model_recovers_a_crystal_off_by_37_ppm_and_drifting(built, figures) -> None:
    """The harness paces the MCU as a crystal 37 ppm fast and drifting by 0.5 ppm/s: the device clock
    really runs off the host's, so a gain of 1 would be 37 ppm wrong. 12 s of clock queries at
    ~100 Hz over the pty, fitted by the model with its delay filter (the tightest round trip of
    each 10, none shorter than the wire): the gain must match the crystal's true rate at the middle
    of the span within 2 ppm (1 ppm is the idle benchmark's goal), or 3 of the fit's own standard
    errors when the load scatters the round trips more, and that standard error must itself stay
    small; every trigger edge's host time must match the harness's truth."""
    ppm, drift = 37.0, 0.5
    harness, elf = built
    run = record_crystal_run(12.0, ppm, drift, elf=elf, harness=harness)
    m = ClockModel(window=100_000, max_rtt_s=0.05, keep_fraction=0.1, link=clock_link_timing(FIRMWARE_BAUD))
    f = score_fit(run, m)
    true_gain = run.true_gain(0.5 * (run.host_t0[0] + run.host_t1[-1]))
    print(f"\ncrystal +{ppm:.0f} ppm drifting {drift} ppm/s: fitted gain {m.gain:.9f}, true {true_gain:.9f} "
          f"(error {f['gain_err_ppm']:+.3f} ppm, standard error {f['gain_se_ppm']:.3f} ppm; a gain of 1 would be "
          f"{(1 - true_gain) * 1e6:+.1f} ppm off); {f['used']:.0f} of {f['queries']:.0f} queries over "
          f"{f['span_s']:.1f} s (round trip median {f['rtt_median_ms']:.2f} ms, P90 {f['rtt_p90_ms']:.2f} ms, "
          f"{m.short_rtt} shorter than the wire); trigger edge host time error over {f['edges']:.0f} edges: "
          f"mean {f['edge_mean_us']:+.1f} us, sd {f['edge_sd_us']:.1f} us, worst {f['edge_max_us']:.1f} us; "
          f"harness at nice -5: {run.priority_raised}, simulator behind the wall clock by up to "
          f"{f['sim_behind_max_ms']:.2f} ms; {run.timeouts} replies lost to the timeout")
    figures["crystal +37 ppm, 0.5 ppm/s: gain error (ppm)"] = (
        f"{f['gain_err_ppm']:+.3f} (se {f['gain_se_ppm']:.3f}; {f['used']:.0f} of {f['queries']:.0f} queries, "
        f"{f['span_s']:.1f} s)")
    figures["crystal +37 ppm: trigger edge host time error (us)"] = (
        f"mean {f['edge_mean_us']:+.1f}, sd {f['edge_sd_us']:.1f}, worst {f['edge_max_us']:.1f}")
    assert f["used"] >= 0.05 * f["queries"] and f["span_s"] > 10.0  # half of the groups of 10 at least
    # The standard error is the larger of the textbook one and a block jackknife's (a loaded host's
    # delays drift over seconds). Measured in 15 runs of 12 s at load 0-10: standard error 0.19-0.93
    # ppm, error -0.86..+0.44 ppm, with two tails of -1.43 and -1.47 ppm (one in CI, 3.1 textbook
    # standard errors); without the wire timing (midpoint samples) edges were +340..+360 us.
    # So 2 ppm here, at any load and whether or not the starved harness fell behind the wall clock
    # (its truth is then void for the late queries, which the delay filter drops); the 1 ppm goal is
    # the benchmark's, over 10 s windows on an idle machine (`make bench-trigger-clock`).
    # The standard error grows with the load's scatter of the round trips (1.73 ppm at a load of 6 on 2
    # cores); what it must not do is widen the bound below past what the test is for: under 4 ppm, 3 of
    # them stay a third of the crystal's 37 ppm, so a model that missed the crystal fails at any load.
    assert f["gain_se_ppm"] < 4.0
    assert abs(f["gain_err_ppm"]) < max(2.0, 3.0 * f["gain_se_ppm"])
    # Measured: edges +20 us (the host's read latency is longer than its write latency, and the
    # model splits the excess evenly), sd 2-5 us (a straight line over a drifting rate).
    assert abs(f["edge_mean_us"]) < 80.0 and f["edge_sd_us"] < 25.0


def test_stop_never_cuts_a_pulse_short(built, figures) -> None:
    """STOP at any moment of the frame: every trigger pulse keeps its full width. At /1 (one tick a
    cycle) a STOP checked a few dozen ticks before TOP froze the timer just after the next pulse began:
    the firmware before this check left 70 runts of 42-56 cycles in 400 STOPs. 400 STOPs after 0-3
    clock queries each land all over the frame."""
    harness, elf = built
    with SimulatedTrigger(elf=elf, harness=harness) as sim:
        # The queries only move the STOPs around the frame: a loaded machine may answer them late.
        dev = TriggerDevice(sim.pty, reset_wait_s=0, timeout_s=10.0)
        dev.set_rate(4000.0)  # /1, TOP 3999
        assert dev.rate is not None and dev.rate.divisor == 1
        for i in range(400):
            dev.start()
            for _ in range(i % 4):
                dev.query_clock()
            dev.stop()
        dev.close()
    _, edges = sim.edges()
    rises = np.array(rising(edges, "trigger"), dtype=np.int64)
    falls = np.array(_falling(edges, "trigger"), dtype=np.int64)
    widths = falls[: len(rises)] - rises[: len(falls)]
    figures["pulse widths over 400 STOPs at /1"] = f"{sorted(set(widths.tolist()))} cycles, {len(widths)} pulses"
    assert len(widths) > 400 and len(set(widths.tolist())) == 1, np.unique(widths, return_counts=True)


def test_pulse_at_frame_has_its_width(built, figures) -> None:
    harness, elf = built
    widths_asked = [37, 5, 200]
    with SimulatedTrigger(elf=elf, harness=harness) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        dev.set_rate(1000.0)  # /8 (0.5 us ticks), TOP 1999
        assert dev.rate is not None
        div = dev.rate.divisor
        dev.start()
        targets = []
        for w in widths_asked:
            r = dev.query_clock()
            target = r.frame_count + 300
            dev.pulse(0, frame=target, width_s=w * dev.rate.tick_s)
            targets.append(target)
            while dev.query_clock().frame_count <= target + 1:
                pass
        # A frame that has begun is refused.
        r = dev.query_clock()
        with pytest.raises(TriggerError, match="BAD_ARG"):
            dev.pulse(0, frame=r.frame_count - 1, width_s=10 * dev.rate.tick_s)
        # "now": the earliest reachable frame.
        r = dev.query_clock()
        dev.pulse(0, frame=None, width_s=20 * dev.rate.tick_s)
        time.sleep(0.05)
        dev.stop()
        dev.close()
    _, edges = sim.edges()
    trig = rising(edges, "trigger")
    p_up, p_dn = rising(edges, "pulse0"), _falling(edges, "pulse0")
    assert len(p_up) == len(widths_asked) + 1 and len(p_dn) == len(p_up)
    worst_place, worst_width = 0, 0
    for target, w, up, dn in zip(targets, widths_asked, p_up, p_dn, strict=False):
        frame_start = trig[target]  # frame n begins at the n+1-th rising edge
        place = (up - frame_start) / div
        werr = (dn - up) / div - w
        worst_place, worst_width = max(worst_place, abs(place)), max(worst_width, abs(werr))
        assert frame_start <= up < trig[target + 1]
    now_frame = next(i for i, c in enumerate(trig) if c == p_up[-1])
    assert now_frame >= r.frame_count  # not in a frame that had begun
    print(f"\npulse placement error {worst_place:g} ticks, width error {worst_width:g} ticks "
          f"(widths {widths_asked} ticks, 0.5 us each)")
    figures["pulse placement error (ticks)"] = f"{worst_place:g} (width error {worst_width:g} ticks)"
    assert worst_place <= 1 and worst_width <= 1


def test_garbage_never_breaks_the_link(built, figures) -> None:
    harness, elf = built
    rng = np.random.default_rng(7)
    good = tl.encode_message(tl.GetInfo(), 200)
    bad_crc = bytearray(tl.encode_message(tl.ClockQuery(), 201))
    bad_crc[2] ^= 0x01
    attacks = {
        "random bytes": bytes(rng.integers(0, 256, 300, dtype=np.uint8)),
        "truncated frame": good[:3] + b"\0",
        "bad CRC": bytes(bad_crc),
        "over-long frame": bytes(rng.integers(1, 256, 200, dtype=np.uint8)) + b"\0",
        "wrong version": tl.cobs_encode(b"F\x02\x01\x05\x00\x00") + b"\0",
        "reply id sent to device": tl.encode_message(tl.Ack(1), 9),
        "no delimiter then valid": bytes(rng.integers(1, 256, 40, dtype=np.uint8)),
    }
    with SimulatedTrigger(elf=elf, harness=harness) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        dev.set_rate(500.0)
        dev.start()
        before = dev.query_clock().frame_count
        for name, blob in attacks.items():
            dev._ser.write(blob)
            if name == "no delimiter then valid":
                dev._ser.write(b"\0")  # the host's resync delimiter
            info = dev.info()
            assert info.name == "flytrack-trigger", name
            r = dev.query_clock()
            assert r.running, name
        after = dev.query_clock().frame_count
        stats = dict(dev.stats)
        dev.stop()
        dev.close()
    # Frames kept counting: no watchdog reset happened.
    assert after > before
    assert stats["stray_replies"] >= 3  # the ERROR replies to the bad frames that carry a header
    figures["garbage"] = f"{len(attacks)} kinds of bad input, every next request answered; stats {stats}"


@pytest.mark.parametrize(
    ("mcu", "fps", "paced"),
    [("atmega328p", 100.0, False), ("atmega328p", 1000.0, False), ("atmega32u4", 100.0, False),
     ("atmega32u4", 1000.0, False), ("atmega328p", 1000.0, True), ("atmega32u4", 1000.0, True)],
)
def test_input_events_are_timestamped(built, figures, mcu: str, fps: float, paced: bool) -> None:
    """Edges injected at known cycles come back as (frame count, ticks) within 2 ticks of the truth.

    328P: INT0 stub + compensated fixed latency; 32U4: ICP3 (Timer3 in lock-step with Timer1).
    100 fps runs at /8 (0.5 us ticks), 1000 fps at /1 (62.5 ns ticks = 1 cycle). Paced: the harness
    skips the firmware's idle loops; the timestamps must come out as cycle-exact as when it runs
    every instruction."""
    from flytrack_host.trigger import simulator

    harness, elf = built if mcu == "atmega328p" else simulator.build(mcu)
    with SimulatedTrigger(elf=elf, harness=harness, mcu=mcu, realtime=paced, event_period_cycles=400_037,
                          event_phase_cycles=1_000_003, event_high_cycles=50_000) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        dev.set_rate(fps)
        assert dev.rate is not None
        div, top = dev.rate.divisor, dev.rate.top
        dev.start()
        got = []
        t_end = time.monotonic() + 10
        while sum(ev.frame >= 0 for ev in got) < 30 and time.monotonic() < t_end:
            got += dev.events()
            time.sleep(0.01)
        last = dev.query_clock()
        dev.stop()
        dev.close()
    # Keep events sampled while the timer ran and after frame 0 began (earlier ones have no frame).
    got = [ev for ev in got if 0 <= ev.frame < last.frame_count - 1]
    _, edges = sim.edges()
    trig = np.array(rising(edges, "trigger"), dtype=np.int64)
    ev_edges = [e for e in edges if e.signal == "event_in"]
    assert len(got) >= 15
    errs = []
    for ev in got:
        frame_idx = int(np.floor(ev.frame))
        ticks = round((ev.frame - frame_idx) * (top + 1))
        reported = trig[frame_idx] + ticks * div  # the cycle the device's (frame, ticks) names
        true = min(ev_edges, key=lambda e: abs(e.cycle - reported))
        assert true.level == ev.edge
        # The truth in the protocol's own terms: the frame under way at the edge and its tick.
        true_frame = int(np.searchsorted(trig, true.cycle, side="right")) - 1
        true_ticks = (true.cycle - trig[true_frame]) / div
        err = (frame_idx - true_frame) * (top + 1) + ticks - true_ticks
        errs.append(err)
    e = np.array(errs)
    how = "INT0, fixed latency compensated" if mcu == "atmega328p" else "ICP3 input capture"
    tick_us = div / 16.0
    label = f"{mcu} /{div}{' paced' if paced else ''}"
    print(f"\nevents {label}: {len(e)} timestamped, error {e.min():+.3f}..{e.max():+.3f} ticks "
          f"({tick_us:g} us/tick, {how})")
    figures[f"event timestamp error (ticks) {label}"] = (
        f"{e.min():+.3f}..{e.max():+.3f} over {len(e)} edges at {tick_us:g} us/tick ({how})")
    if mcu == "atmega328p" and div == 1:
        # INT0 at 1 cycle per tick: an edge that arrives while the UART receive interrupt or a
        # request's cli() section runs (the host is talking) waits for it; the rest are exact.
        assert np.median(np.abs(e)) == 0 and np.all(e >= -2) and np.all(e <= 40)
    else:
        assert np.all(np.abs(e) <= 2)


@pytest.mark.skipif(os.environ.get("FLYTRACK_SKIP_32U4") == "1", reason="asked to skip")
def test_atmega32u4_build_runs(built, figures) -> None:
    from flytrack_host.trigger import simulator

    harness, elf = simulator.build("atmega32u4")
    with SimulatedTrigger(elf=elf, harness=harness, mcu="atmega32u4") as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        info = dev.info()
        dev.set_rate(2000.0)
        dev.start()
        while dev.query_clock().frame_count < 500:
            pass
        dev.stop()
        final = dev.query_clock()
        dev.close()
    _, edges = sim.edges()
    rises = rising(edges, "trigger")
    assert info.mcu == tl.Mcu.ATMEGA32U4
    assert set(np.diff(rises).tolist()) == {8000}
    assert final.frame_count == len(rises)
