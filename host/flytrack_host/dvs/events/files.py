"""Event-camera files through libflytrack_events: streaming readers for AEDAT 2.0/3.1/4.0 and
Prophesee EVT 2.0/3.0/DAT, writers for AEDAT 4.0 and EVT 3.0.

Every format comes out as one NumPy layout, EVENT_DTYPE (t int64 microseconds, x, y uint16, p uint8
with 1 = ON), in chunks of bounded size. A damaged file yields every event before the damage, then
raises EventFileError naming the byte offset.

    with EventReader("rec.aedat4") as r:
        for chunk in r:             # structured arrays of EVENT_DTYPE
            ...
    events = read_events("rec.raw")  # everything at once
    events, triggers = read_events_and_triggers("rec.raw")  # and the sync events' times

    with EventWriter("out.aedat4", width=346, height=260, compression="lz4") as w:
        w.write(events)
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flytrack_host.dvs.events._lib import Info, lib
from flytrack_host.protocol.dvs import EVENT_DTYPE  # noqa: F401 (the event layout; re-exported here)

#: One external trigger / sync event, the C struct ft_ev_trigger: t (us, the events' time base),
#: value (1 rising edge, pulse or sync; 0 falling edge), channel (trigger input id, 0 if none).
TRIGGER_DTYPE = np.dtype({"names": ["t", "value", "channel"], "formats": ["<i8", "u1", "u1"],
                          "offsets": [0, 8, 9], "itemsize": 16})

FORMATS = ("aedat2", "aedat3", "aedat4", "evt2", "evt3", "dat")  # codes 1..6 in events.h
COMPRESSIONS = ("none", "lz4", "lz4_high", "zstd", "zstd_high")  # AEDAT 4.0 CompressionType
DEFAULT_CHUNK = 1 << 18


class EventFileError(ValueError):
    """An event file that cannot be opened or is damaged. `offset` is the byte offset of the damaged
    unit (None when the file could not be opened); `events` holds what was read before the damage
    when read_events() raised it."""

    def __init__(self, message: str, offset: int | None = None,
                 events: np.ndarray | None = None) -> None:
        super().__init__(message)
        self.offset = offset
        self.events = events if events is not None else np.empty(0, EVENT_DTYPE)


@dataclass(frozen=True)
class EventFileInfo:
    format: str
    width: int   # from the header, 0 when the file does not say
    height: int
    compression: str  # AEDAT 4.0; "none" otherwise
    n_events: int     # returned so far
    n_triggers: int   # external trigger / sync events seen so far
    n_skipped: int    # units of other kinds skipped
    offset: int       # bytes consumed so far
    time_offset: int = 0  # us added to every time: the header's "% time_offset_us" (EVT 3.0 written here)


def _format_code(fmt: str | None) -> int:
    if fmt is None or fmt == "auto":
        return 0
    if fmt not in FORMATS:
        raise ValueError(f"unknown event file format {fmt!r}; one of {', '.join(FORMATS)}")
    return FORMATS.index(fmt) + 1


class EventReader:
    """Streams events from a file in chunks of at most `chunk` events (memory stays bounded).
    `fmt` None detects the format from the header (and a `.dat` name for DAT)."""

    def __init__(self, path: str | os.PathLike[str] | bytes | bytearray | memoryview,
                 fmt: str | None = None, chunk: int = DEFAULT_CHUNK, name: str | None = None,
                 triggers: bool = False) -> None:
        self._so = lib()
        self._chunk = max(16, int(chunk))
        self._mem: bytes | None = None
        err = ctypes.create_string_buffer(512)
        if isinstance(path, (bytes, bytearray, memoryview)):  # bytes in memory (tests, network)
            self._mem = bytes(path)
            self.path = name or "<memory>"
            self._r = self._so.ft_ev_open_mem(self._mem, len(self._mem), _format_code(fmt),
                                              self.path.encode(), err, len(err))
        else:
            self.path = str(path)
            self._r = self._so.ft_ev_open(os.fsencode(self.path), _format_code(fmt), err, len(err))
        if not self._r:
            raise EventFileError(err.value.decode(errors="replace"))
        self._buf = np.empty(self._chunk, EVENT_DTYPE)
        self._done = False
        if triggers:  # keep the sync events' times for read_triggers()
            self._so.ft_ev_keep_triggers(self._r, 1)

    @property
    def info(self) -> EventFileInfo:
        self._check_open()
        i = Info()
        self._so.ft_ev_get_info(self._r, ctypes.byref(i))
        comp = COMPRESSIONS[i.compression] if 0 <= i.compression < len(COMPRESSIONS) else str(i.compression)
        return EventFileInfo(FORMATS[i.format - 1], i.width, i.height, comp, i.n_events, i.n_triggers,
                             i.n_skipped, i.offset, i.time_offset)

    def _check_open(self) -> None:
        if not self._r:
            raise ValueError(f"{self.path}: the reader is closed")

    def read_chunk(self) -> np.ndarray | None:
        """The next chunk (a new array), None at the end; raises EventFileError at damage."""
        self._check_open()
        if self._done:
            return None
        n = self._so.ft_ev_read(self._r, self._buf.ctypes.data, self._chunk)
        if n < 0:
            self._done = True
            raise EventFileError(self._so.ft_ev_error(self._r).decode(errors="replace"),
                                 int(self._so.ft_ev_error_offset(self._r)))
        if n == 0:
            self._done = True
            return None
        return _copy(self._buf[:n])

    def read_triggers(self) -> np.ndarray:
        """The trigger / sync events decoded since the last call (TRIGGER_DTYPE, oldest first); only
        with EventReader(..., triggers=True), else always empty."""
        self._check_open()
        parts = []
        while True:
            buf = np.zeros(4096, TRIGGER_DTYPE)
            n = self._so.ft_ev_triggers(self._r, buf.ctypes.data, len(buf))
            parts.append(buf[:n])
            if n < len(buf):
                return _cat_triggers(parts)

    def __iter__(self) -> Iterator[np.ndarray]:
        while (c := self.read_chunk()) is not None:
            yield c

    def close(self) -> None:
        if self._r:
            self._so.ft_ev_close(self._r)
            self._r = None

    def __enter__(self) -> EventReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_r", None):
            self.close()


def _copy(a: np.ndarray) -> np.ndarray:
    """A copy of a contiguous EVENT_DTYPE array as raw bytes (NumPy copies a dtype with padding
    field by field, several times slower)."""
    out = np.empty(len(a), EVENT_DTYPE)
    out.view(np.uint8)[:] = a.view(np.uint8)
    return out


# Events per file byte to size read_events' buffer: the most a byte can hold where the format bounds
# it (EVT 3.0 without vectors, uncompressed AEDAT 4.0 at 16 bytes and LZ4/Zstd at 4:1); it grows by
# doubling when short.
_EVENTS_PER_BYTE = {"aedat2": 1 / 8, "aedat3": 1 / 8, "aedat4": 1 / 4, "evt2": 1 / 4, "evt3": 1 / 2, "dat": 1 / 8}


def read_events(path: str | os.PathLike[str], fmt: str | None = None) -> np.ndarray:
    """All events of a file as one EVENT_DTYPE array, decoded straight into it. On damage raises
    EventFileError whose `events` holds every event before it."""
    return _read_all(path, fmt, None)


def read_events_and_triggers(path: str | os.PathLike[str],
                             fmt: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """All events (EVENT_DTYPE) and all trigger / sync events (TRIGGER_DTYPE) of a file. On damage
    raises EventFileError with the events before it."""
    trig: list[np.ndarray] = []
    ev = _read_all(path, fmt, trig)
    return ev, _cat_triggers(trig)


def _cat_triggers(parts: list[np.ndarray]) -> np.ndarray:
    """Concatenated, in TRIGGER_DTYPE's own padded layout (np.concatenate would pack the fields)."""
    out = np.zeros(sum(len(p) for p in parts), TRIGGER_DTYPE)
    i = 0
    for p in parts:
        out[i:i + len(p)] = p
        i += len(p)
    return out


def _read_all(path: str | os.PathLike[str], fmt: str | None, triggers: list[np.ndarray] | None) -> np.ndarray:
    with EventReader(path, fmt, chunk=16, triggers=triggers is not None) as r:
        so, handle = r._so, r._r
        size = os.path.getsize(r.path)
        cap = max(1024, int(size * _EVENTS_PER_BYTE[r.info.format]) + 64)
        buf = np.empty(cap, EVENT_DTYPE)
        n = 0
        while True:
            if cap - n < 16:
                cap *= 2
                grown = np.empty(cap, EVENT_DTYPE)
                grown.view(np.uint8)[: 16 * n] = buf.view(np.uint8)[: 16 * n]
                buf = grown
            got = so.ft_ev_read(handle, buf.ctypes.data + 16 * n, cap - n)
            if triggers is not None:
                triggers.append(r.read_triggers())
            if got < 0:
                raise EventFileError(so.ft_ev_error(handle).decode(errors="replace"),
                                     int(so.ft_ev_error_offset(handle)), _trim(buf, n))
            if got == 0:
                return _trim(buf, n)
            n += got


def _trim(buf: np.ndarray, n: int) -> np.ndarray:
    # A view, no copy: the pages of the buffer past n were never written, so they hold no memory.
    return buf[:n]


def as_events(arr: np.ndarray) -> np.ndarray:
    """Any structured array with t, x, y and p (or polarity / on) fields as a contiguous
    EVENT_DTYPE array (what the writers and the C side take)."""
    if arr.dtype == EVENT_DTYPE and arr.flags.c_contiguous:
        return arr
    out = np.empty(len(arr), EVENT_DTYPE)
    names = arr.dtype.names or ()
    pol = next((k for k in ("p", "polarity", "on") if k in names), None)
    if not {"t", "x", "y"} <= set(names) or pol is None:
        raise ValueError(f"need fields t, x, y and p (or polarity), got {names}")
    out["t"], out["x"], out["y"] = arr["t"], arr["x"], arr["y"]
    out["p"] = np.asarray(arr[pol]) != 0
    return out


class EventWriter:
    """Writes AEDAT 4.0 (`.aedat4`, readable by dv-processing; compression none, lz4, lz4_high,
    zstd or zstd_high) or EVT 3.0 (`.raw`). Events must come in non-decreasing time. External
    triggers (TRIGGER_DTYPE) go in with write_triggers(): EVT 3.0 always, AEDAT 4.0 when opened with
    `triggers=True` (a trigger stream, as dv-processing writes one)."""

    def __init__(self, path: str | os.PathLike[str], width: int, height: int, fmt: str | None = None,
                 compression: str = "lz4", triggers: bool = False) -> None:
        self.path = str(path)
        if fmt is None:
            fmt = "evt3" if Path(self.path).suffix == ".raw" else "aedat4"
        if fmt not in ("aedat4", "evt3"):
            raise ValueError(f"{self.path}: writing {fmt!r} is not supported (aedat4 or evt3)")
        if compression not in COMPRESSIONS:
            raise ValueError(f"unknown compression {compression!r}; one of {', '.join(COMPRESSIONS)}")
        self._so = lib()
        err = ctypes.create_string_buffer(512)
        self.format = fmt
        self._w = self._so.ft_ev_writer_open_ex(os.fsencode(self.path), _format_code(fmt), int(width),
                                                int(height), COMPRESSIONS.index(compression),
                                                1 if triggers else 0, err, len(err))
        if not self._w:
            raise EventFileError(err.value.decode(errors="replace"))
        self.n_written = 0
        self.n_triggers = 0  # triggers written
        self._time_offset = 0

    def write(self, events: np.ndarray) -> None:
        """Appends events (any array as_events() accepts). A step back in time raises ValueError and
        writes nothing of this call; the writer stays usable."""
        if not self._w:
            raise ValueError(f"{self.path}: the writer is closed")
        ev = as_events(events)
        if self._so.ft_ev_write(self._w, ev.ctypes.data, len(ev)) != 0:
            raise ValueError(self._so.ft_ev_writer_error(self._w).decode(errors="replace"))
        self.n_written += len(ev)

    def write_triggers(self, triggers: np.ndarray) -> int:
        """Appends external triggers (TRIGGER_DTYPE, in time order, as EventReader.read_triggers
        returns them). EVT 3.0 places them among the events by time (held until an event at or after
        their time, or close); AEDAT 4.0 writes a trigger packet (rising edge for value 1, falling
        for 0; it has no channel id). Returns how many the format cannot hold and were left out: a
        time before what is already written, an EVT 3.0 channel over 15."""
        if not self._w:
            raise ValueError(f"{self.path}: the writer is closed")
        tr = np.zeros(len(triggers), TRIGGER_DTYPE)
        for k in ("t", "value", "channel"):
            tr[k] = triggers[k]
        dropped = int(self._so.ft_ev_write_triggers(self._w, tr.ctypes.data, len(tr)))
        if dropped < 0:
            raise ValueError(self._so.ft_ev_writer_error(self._w).decode(errors="replace"))
        self.n_triggers += len(tr) - dropped
        return dropped

    @property
    def time_offset(self) -> int:
        """EVT 3.0: the whole 2^24 us ranges before the first event, taken off every time written and
        kept in the header line "% time_offset_us" (the readers here add it back); 0 otherwise."""
        return int(self._so.ft_ev_writer_time_offset(self._w)) if self._w else self._time_offset

    def close(self) -> None:
        if self._w:
            self._time_offset = int(self._so.ft_ev_writer_time_offset(self._w))
            err = ctypes.create_string_buffer(512)
            rc = self._so.ft_ev_writer_close(self._w, err, len(err))
            self._w = None
            if rc != 0:
                raise EventFileError(err.value.decode(errors="replace"))

    def __enter__(self) -> EventWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_w", None):
            self.close()


def write_events(path: str | os.PathLike[str], events: np.ndarray, width: int, height: int,
                 fmt: str | None = None, compression: str = "lz4") -> None:
    """Writes a whole array to a new file (see EventWriter)."""
    with EventWriter(path, width, height, fmt, compression) as w:
        w.write(events)
