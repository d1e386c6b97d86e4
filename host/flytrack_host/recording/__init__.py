"""Recording: crash-safe append-only capture of a run in parts, finalised to HDF5 (writer.py, parts.py), read
whole (reader.py) or part by part (source.py, stream.py); docs/recordings.md.

May import: util, protocol, geometry, tracking, intake.
"""

from flytrack_host.recording.finalize import FinalizeReport, RecordingError, finalize
from flytrack_host.recording.reader import Recording, load_recording
from flytrack_host.recording.writer import Recorder

__all__ = ["FinalizeReport", "Recorder", "Recording", "RecordingError", "finalize", "load_recording"]
