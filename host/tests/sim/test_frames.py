import math
import os
import threading
import time

import numpy as np
import pytest

from flytrack_host.sim.flight import Arena, simulate_flight
from flytrack_host.sim.frames import EdgeLineParser, FrameFeeder
from flytrack_host.sim.render import RenderParams
from flytrack_host.sim.rig import make_cameras


def test_parser_reads_the_simavr_edge_log_and_plain_numbers():
    p = EdgeLineParser()
    lines = ["# flytrack-trigger-sim 1 mcu=atmega328p f_cpu=16000000", "# cycle signal level",
             "100 trigger 1", "140 trigger 0", "150 pulse0 1", "20100 trigger 1", "garbage here", "7"]
    assert [p.feed(s) for s in lines] == [None, None, 0, None, None, 1, None, 7]
    assert p.f_cpu == 16e6 and p.bad_lines == 1
    assert math.isnan(p.true_time())  # not paced: no anchor


def test_parser_gives_the_true_host_time_of_a_paced_edge():
    p = EdgeLineParser()
    for s in ["# flytrack-trigger-sim 1 mcu=atmega328p f_cpu=16000000",
              "# paced t0_monotonic=5.0 t0_realtime=1000.5", "160000 trigger 1"]:
        p.feed(s)
    assert p.true_time() == pytest.approx(1000.5 + 160000 / 16e6)


def _reader(fd, nbytes, out):
    data = bytearray()
    with os.fdopen(fd, "rb", buffering=0) as f:
        while True:
            b = f.read(1 << 20)
            if not b:
                break
            data += b
    out.append(bytes(data))


@pytest.mark.parametrize("fmt", ["raw", "y4m"])
def test_feeder_renders_one_frame_per_edge_for_every_camera(fmt):
    gt = simulate_flight(2, 0.1, 100.0, seed=0)  # 10 frames
    cams = make_cameras(2, Arena(), seed=0, width=160, height=120)
    pipes = [os.pipe() for _ in cams]
    src_r, src_w = os.pipe()
    feeder = FrameFeeder(gt, cams, [w for _, w in pipes], RenderParams(), seed=1, frame_format=fmt)
    for _, w in pipes:
        os.close(w)
    outs: list[list[bytes]] = [[] for _ in cams]
    threads = [threading.Thread(target=_reader, args=(r, 0, o)) for (r, _), o in zip(pipes, outs, strict=True)]
    for t in threads:
        t.start()
    feeder.set_source(src_r)
    os.close(src_r)
    feeder.preroll(2)  # frames before the trigger starts (no animals)
    time.sleep(0.3)
    os.write(src_w, b"# header\n" + b"".join(f"{i * 10} trigger 1\n{i * 10 + 5} trigger 0\n".encode()
                                             for i in range(12)))
    os.close(src_w)
    t_end = time.monotonic() + 20
    while not feeder.done and time.monotonic() < t_end:
        time.sleep(0.01)
    feeder.finish()  # the child also holds the stream's write end (forked after it was made)
    feeder.join(20)
    assert not feeder.alive()
    for t in threads:
        t.join(5)
    st = feeder.stats()
    assert st.frames_rendered == 10 and st.edges == 11  # the 11th edge is past the ground truth: stop
    assert feeder.preroll_frames == 2
    assert st.written_time.shape == (10, 2) and np.all(np.isfinite(st.written_time))
    assert np.all(np.isfinite(st.handoff_time)) and np.all(np.diff(st.handoff_time) >= 0)
    for o in outs:
        data = o[0]
        if fmt == "y4m":  # a stream header, then FRAME and the luma plane per frame
            header, _, data = data.partition(b"\n")
            assert header.startswith(b"YUV4MPEG2 W160 H120 F100000:1000") and b"Cmono" in header
            parts = [data[i * (6 + 160 * 120) : (i + 1) * (6 + 160 * 120)] for i in range(12)]
            assert all(p[:6] == b"FRAME\n" for p in parts)
            data = b"".join(p[6:] for p in parts)
        assert len(data) == 12 * 160 * 120
        frames = np.frombuffer(data, np.uint8).reshape(12, 120, 160)
        assert 100 < frames.mean() < 200


def test_next_frame_waits_in_the_pipe_for_its_pulse_but_its_last_bytes():
    """Frame n+1 is written ahead but for its tail; pulse n+1 writes only the tail (no frame copy on
    the pulse), and the edge gets whole frames in order."""
    gt = simulate_flight(1, 0.03, 100.0, seed=0)  # 3 frames
    cams = make_cameras(2, Arena(), seed=0, width=160, height=120)
    size = 160 * 120
    pipes = [os.pipe() for _ in cams]
    src_r, src_w = os.pipe()
    feeder = FrameFeeder(gt, cams, [w for _, w in pipes], RenderParams(), seed=1)
    for _, w in pipes:
        os.close(w)
    got = [bytearray() for _ in cams]

    def read(fd: int, buf: bytearray) -> None:
        with os.fdopen(fd, "rb", buffering=0) as f:
            while b := f.read(1 << 20):
                buf += b

    threads = [threading.Thread(target=read, args=(r, g), daemon=True) for (r, _), g in zip(pipes, got, strict=True)]
    for t in threads:
        t.start()
    feeder.set_source(src_r)
    os.close(src_r)
    try:
        _staged_run(feeder, src_w, got, size, threads)
    finally:
        feeder.stop()  # a failed check must not leave the child (and the readers) waiting


def _staged_run(feeder: FrameFeeder, src_w: int, got: list[bytearray], size: int, threads: list) -> None:
    from flytrack_host.sim.frames import STAGE_TAIL

    def wait_bytes(n: int) -> None:
        end = time.monotonic() + 10
        while any(len(g) < n for g in got) and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.2)  # and nothing more comes before the next pulse
        assert [len(g) for g in got] == [n] * len(got)

    os.write(src_w, b"# header\n10 trigger 1\n")
    wait_bytes(2 * size - STAGE_TAIL)  # frame 0, and frame 1 staged: incomplete until its pulse
    t_pulse = time.time()  # noqa: TID251 - compared with the feeder's wall-clock stamps
    os.write(src_w, b"20 trigger 1\n")
    wait_bytes(3 * size - STAGE_TAIL)  # frame 1 completed by its pulse; frame 2 staged
    os.write(src_w, b"30 trigger 1\n40 trigger 1\n")
    os.close(src_w)
    end = time.monotonic() + 20
    while not feeder.done and time.monotonic() < end:
        time.sleep(0.01)
    feeder.finish()
    feeder.join(20)
    for t in threads:
        t.join(5)
    st = feeder.stats()
    assert [len(g) for g in got] == [3 * size] * len(got)
    assert st.frames_staged == 2 * len(got) and st.frames_stale == 0
    assert np.all(st.written_time[1] >= t_pulse)  # frame 1 was handed over at its pulse, not before
    for g in got:
        frames = np.frombuffer(bytes(g), np.uint8).reshape(3, 120, 160)
        assert 100 < frames.mean() < 200


def test_render_ahead_waits_for_the_hosts_moment_unless_rendering_is_slow():
    from flytrack_host.sim.frames import RENDER_AHEAD_DELAY, render_ahead_delay

    assert render_ahead_delay(0.01, 0.0005) == RENDER_AHEAD_DELAY * 0.01  # fast rendering: the full delay
    assert abs(render_ahead_delay(0.01, 0.003) - 0.001) < 1e-12  # 3 x 3 ms must fit: 1 ms
    assert render_ahead_delay(0.01, 0.004) < 0  # slow rendering: at once, as before


def test_next_frame_is_staged_after_the_render_ahead_delay():
    """Once its render time is known, frame n+1 is rendered and staged RENDER_AHEAD_DELAY of a period
    after pulse n, not at once (the host handles frame n meanwhile). A lower bound: load only delays."""
    from flytrack_host.sim.frames import RENDER_AHEAD_DELAY, STAGE_TAIL

    fps = 20.0  # a 50 ms period: the 15 ms delay stands far above the time to render two small frames
    gt = simulate_flight(1, 0.2, fps, seed=0)
    cams = make_cameras(2, Arena(), seed=0, width=160, height=120)
    size = 160 * 120
    pipes = [os.pipe() for _ in cams]
    src_r, src_w = os.pipe()
    feeder = FrameFeeder(gt, cams, [w for _, w in pipes], RenderParams(), seed=1)
    for _, w in pipes:
        os.close(w)
    arrivals: list[list[tuple[float, int]]] = [[] for _ in cams]

    def read(fd: int, log: list) -> None:
        n = 0
        with os.fdopen(fd, "rb", buffering=0) as f:
            while b := f.read(1 << 20):
                n += len(b)
                log.append((time.monotonic(), n))

    threads = [threading.Thread(target=read, args=(r, a), daemon=True)
               for (r, _), a in zip(pipes, arrivals, strict=True)]
    for t in threads:
        t.start()
    feeder.set_source(src_r)
    os.close(src_r)
    try:
        pulses = []
        for k in range(3):
            time.sleep(0.3)  # each pulse's frames and the next ones' staging are done before the next
            pulses.append(time.monotonic())
            os.write(src_w, f"{10 * (k + 1)} trigger 1\n".encode())
        time.sleep(0.3)
        # After pulse 2 (the second render ahead: its time is known), frame 3 staged at the delay.
        staged = [next(t for t, n in a if n >= 4 * size - STAGE_TAIL) for a in arrivals]
        assert min(staged) - pulses[2] >= 0.9 * RENDER_AHEAD_DELAY / fps
    finally:
        os.close(src_w)
        feeder.stop()
