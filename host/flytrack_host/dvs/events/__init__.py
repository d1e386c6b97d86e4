"""Event cameras: event files read and written through the C library libflytrack_events (ctypes).

Public API: EVENT_DTYPE (t int64 us, x, y uint16, p uint8 with 1 = ON), EventReader (chunks),
read_events, read_events_and_triggers (with the sync events' times, TRIGGER_DTYPE), EventWriter,
write_events, EventFileError (names the byte offset of damage), as_events.
"""

from flytrack_host.dvs.events._lib import EventLibraryError
from flytrack_host.dvs.events.files import (
    COMPRESSIONS,
    EVENT_DTYPE,
    FORMATS,
    TRIGGER_DTYPE,
    EventFileError,
    EventFileInfo,
    EventReader,
    EventWriter,
    as_events,
    read_events,
    read_events_and_triggers,
    write_events,
)

__all__ = [
    "COMPRESSIONS",
    "EVENT_DTYPE",
    "FORMATS",
    "TRIGGER_DTYPE",
    "EventFileError",
    "EventFileInfo",
    "EventLibraryError",
    "EventReader",
    "EventWriter",
    "as_events",
    "read_events",
    "read_events_and_triggers",
    "write_events",
]
