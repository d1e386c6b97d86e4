"""Frame synchronisation: per-camera frames -> one bundle per trigger frame.

Pure logic: every call takes the host time `now`, so tests drive it without sleeping.

Mapping camera frames to trigger frames, as flydra and Braid do: the trigger is stopped, cameras go
quiet, the trigger starts, and each camera's first frame is tied to trigger frame 0 (`offset =
camera_frame`). When the edge already fills `trigger_frame` (>= 0) that number is used. A camera that
appears later, or whose counter restarts, is mapped by its arrival time through the trigger clock
model and the arrival lag of the other cameras. Afterwards the mapping is checked on every frame:

- drift (a camera whose counter hides a missed or extra pulse: its frame rate is not the trigger's)
  is judged on arrival times only relative to the other cameras, per trigger frame: d = arrival of
  this camera's frame - median arrival of the others' frames of the same trigger frame. Stalls and
  bursts (one camera's, or every camera's at once: a GIL or scheduler stall) and steps of the trigger
  clock model never re-map a camera: a camera is re-mapped by s frames only when, over
  `drift_frames` trigger frames spanning at least `drift_min_s` (0.5 s), d departs from the camera's
  own baseline by s periods on every one of them (to within 0.4 period, the median within 0.25) and
  its frames came in paced, not in a burst (a burst's frames
  arrive together and their d falls by a period per frame, so they can never agree);
- frame numbers that jump back or far ahead are suspect: such frames are not tracked (the pipeline
  still records them); when several consecutive frames agree on the new numbering it is a clock jump:
  logged and the mapping re-established;
- a frame whose trigger time lies in the future (or far ahead of the other cameras) is future-dated
  and rejected unless it is confirmed as a jump;
- a frame that arrives earlier than its camera ever does (its arrival lag to the trigger clock below
  the lowest of the last second by more than `early_fraction` periods + `early_slack_s`), and that does not
  continue its camera's counter, is misnumbered: it claims a pulse that had not happened yet.
  Frames cannot come before their pulse, so this is no stall or burst; a replayed or misbehaving
  edge mixing wrong numbers into a good stream is caught frame by frame (its good frames keep the
  mapping, so the wrong ones never confirm a jump). Camera frames
  that jump back to numbers already seen are suspect the same way;
- an edge restart (the receiver saw a new sender after silence, `CameraFrame.restarted`) maps the
  camera again by arrival, never by the frame-0 tie. A starting edge delivers its first frames late
  and bunched (they queued while it started), so arrival alone places it too late. A frame cannot
  arrive before its pulse plus the least lag the cameras have: each held frame bounds where the new
  counter starts, and the lowest bound is the placement once `restart_settle_frames` frames in a
  row came paced without lowering it (the edge caught up). Counted in frames, never seconds: on a
  loaded host the edge takes longer to catch up and its frames wait until it did (recorded, not
  tracked), instead of being tracked misnumbered. The trigger frames it missed while down are
  counted (`missed`);
- with the fixed-rate clock (no trigger), a frame arriving before its expected time moves the anchor
  earlier (the first frame came late); a pause of every camera (all frames paced but late by more
  than 2 periods for `reanchor_s`) re-anchors the clock, so later latencies are not the pause's.

The frame-0 tie after `synchronize()` (cameras quiet, trigger about to start): every camera's first
frame within `tie_window_s` of the first camera's is trigger frame 0, however late or bursty it
arrives; a camera first seen later is a late joiner. Without `synchronize()` (cameras already
running) the tie only spans 0.9 period.

A bundle is closed (handed to the tracker) as soon as every live camera reported, or when a deadline
(`deadline_fraction` of the frame period after its first packet) passes. Bundles close in frame
order; data for a closed frame is late (recorded, not tracked). A camera silent for `dead_timeout_s`
is dead (bundles stop waiting for it) until its packets return.
"""

from flytrack_host.intake.sync.clock import FixedRateClock, FrameClock
from flytrack_host.intake.sync.state import _Cam, _Pending
from flytrack_host.intake.sync.synchronizer import FrameSynchronizer
from flytrack_host.intake.sync.types import (
    CameraFrame,
    CameraSyncStats,
    SyncedBundle,
    SyncEvent,
    SyncOutput,
    UntrackedFrame,
)
from flytrack_host.intake.sync.windows import _LagWindow, _Window

__all__ = [
    "CameraFrame",
    "CameraSyncStats",
    "FixedRateClock",
    "FrameClock",
    "FrameSynchronizer",
    "SyncEvent",
    "SyncOutput",
    "SyncedBundle",
    "UntrackedFrame",
    "_Cam",
    "_LagWindow",
    "_Pending",
    "_Window",
]
