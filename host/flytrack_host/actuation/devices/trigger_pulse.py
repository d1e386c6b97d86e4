"""A pulse on the FlyTrack trigger firmware's output at an exact trigger frame (SPEC PULSE), or a
stimulus line set at once (SET_OUTPUT, channels 1-3).

Channel 0 is the firmware's hardware compare output (OC1B): the pulse starts with the trigger pulse
of the frame asked for, to the timer tick, so a high-speed camera wired there has its buffer's
trigger point at exactly that trigger frame (recorded as `scheduled_frame`, flag FRAME_EXACT). The
firmware arms the pulse for frame n at the end of frame n-1's trigger pulse, hence `arm_frames = 1`
in the reachability the engine computes. A PULSE that arrives too late is refused (BAD_ARG); the
high-speed camera still gets its pulse, at the next frame the firmware can reach, and the firing
records that frame (from the trigger clock) and that it was late.
"""

from __future__ import annotations

import math
from typing import Any

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.trigger.common import TriggerError
from flytrack_host.util import hostclock

DEFAULT_WIDTH_MS = 1.0


def _baud(dev: Any) -> float:
    """The device's serial rate (the firmware's own when it cannot tell)."""
    from flytrack_host.trigger.device import FIRMWARE_BAUD

    return float(getattr(getattr(dev, "_ser", None), "baudrate", FIRMWARE_BAUD) or FIRMWARE_BAUD)


def _request_wire_s(dev: Any) -> float:
    """Time a PULSE request takes on the wire (delimiter + frame, 10 bits a byte) and the firmware's
    dispatch, from the protocol's own encoder."""
    from flytrack_host.protocol import trigger_link as tl
    from flytrack_host.trigger.device import FIRMWARE_SAMPLE_DELAY_S

    n = len(b"\0" + tl.encode_message(tl.Pulse(0, 0, 1), 1))
    return n * 10 / _baud(dev) + FIRMWARE_SAMPLE_DELAY_S


def _ack_wire_s(dev: Any) -> float:
    """Time the firmware's ACK takes on the wire (delimiter + frame, 10 bits a byte)."""
    from flytrack_host.protocol import trigger_link as tl

    return len(b"\0" + tl.encode_message(tl.Ack(int(tl.MsgId.PULSE)), 1)) * 10 / _baud(dev)


class TriggerPulseOutput(Output):
    kind = "trigger_pulse"
    ack_means = ("the firmware's ACK of the PULSE request: armed for its trigger frame, where the pin fires "
                 "(exactly, FRAME_EXACT), after the ACK")
    arm_frames = 1
    # Until measured: a PULSE on the wire (~12 bytes with framing: 0.12 ms at 1 Mbaud, 1 ms at 115200), the
    # firmware's dispatch, and a clock query it may wait behind (the link carries one request at a time).
    initial_lead_s = 0.003

    def _lead_sample(self, job: Job, done: Done) -> float:
        """A PULSE reaches its frame when the firmware has read it, not when its ACK is back: the
        firmware answers as soon as it has armed the pulse, so it had the PULSE at the latest when its
        ACK started back, the ACK's arrival less its time on the wire (0.07 ms at 1 Mbaud). That
        keeps whatever delayed the request (a clock query ahead of it, a lagging simulator) in the lead.
        A PULSE that is too late anyway is refused and pulsed at once, recorded as late."""
        try:
            back = _ack_wire_s(self._device())
        except OutputError:
            return math.nan
        return done.time_ack - job.queued_at - back

    def _device(self) -> Any:
        get = self.context.get("trigger")
        dev = get() if callable(get) else get
        if dev is None:
            raise OutputError("no FlyTrack trigger is open (needs [trigger] kind = \"flytrack\" or \"software\", "
                              "and flytrack run without --no-trigger)")
        if not hasattr(dev, "pulse_timed"):
            raise OutputError(f"the trigger ({type(dev).__name__}) has no pulse outputs; the FlyTrack firmware has")
        return dev

    def _connect(self) -> None:
        self._device()

    def _perform(self, job: Job) -> Done:
        dev = self._device()
        a = job.action
        if self.cfg.channel != 0:
            t0 = hostclock.now()
            dev.set_output(self.cfg.channel, a.level or 0)
            return Done(t0, hostclock.now())
        width = (a.width_ms or DEFAULT_WIDTH_MS) / 1e3
        try:
            t0, t1 = dev.pulse_timed(0, job.scheduled_frame, width, on_written=self.written)
            return Done(t0, t1, job.scheduled_frame, True)
        except TriggerError as exc:
            if "BUSY" in str(exc):
                raise OutputError("the firmware holds one pulse at a time and one is still waiting for its "
                                  "frame (or the trigger is stopped): this pulse is dropped") from None
            if "BAD_ARG" not in str(exc) or job.scheduled_frame < 0:
                raise
        # Too late for that frame: pulse at the earliest frame the firmware can still reach.
        t0, t1 = dev.pulse_timed(0, None, width, on_written=self.written)
        clock = self.context.get("clock")
        est = -1
        if clock is not None:
            # The PULSE reached the firmware its wire time after it was written (t0 is taken just
            # before the write; the ACK's arrival also waits for this host's reader thread); it then
            # takes the frame after next (the next one's arming point is 100 us into this frame).
            f = clock.host_time_to_frame(t0 + _request_wire_s(dev))
            if math.isfinite(f):
                est = int(math.floor(f)) + 2
        return Done(t0, t1, est, False, note=f"late: frame {job.scheduled_frame} had passed; pulsed at the "
                                             f"earliest frame (~{est})")
