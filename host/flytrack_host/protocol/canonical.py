"""SPEC §5 canonical field text: what both codecs print for a decoded vector, compared as strings.

Conventions (the C vector runner prints the same):
- `key=value` pairs joined by one space. UDP: `type`, `flags`, then the fixed fields in table order,
  then the records as `points[i].field`; subarrays as `objects[i].cov[k]`. Reserved fields are left out.
  IMAGE chunks end with `data=<lowercase hex of the chunk bytes>`. Serial: `msg_id`, `seq`, payload
  fields. DVS packets: `n_words`, then per word `words[i].x/y/polarity/ts/reset/wrap/sync` (raw bits) and,
  for event and SYNC words only, `words[i].t_us` (a decoder starting at offset 0).
- Integers in decimal; f32 as `%.9g` of the float32 value, f64 as `%.17g`; `nan` (any sign or payload),
  `inf`, `-inf`.
- Text: the bytes up to the first NUL, printable ASCII 0x21..0x7E as is except backslash; space,
  backslash and every other byte as `\\xHH` with lowercase hex.
"""

from __future__ import annotations

import math

import numpy as np

from .dvs import DvsPacket, dvs_event_times
from .text import escape_text
from .trigger_link import SerialMessage
from .udp import UdpMessage


def fmt_f32(v: float) -> str:
    f = float(np.float32(v))
    return "nan" if math.isnan(f) else f"{f:.9g}"  # the same text as C printf("%.9g")


def fmt_f64(v: float) -> str:
    f = float(v)
    return "nan" if math.isnan(f) else f"{f:.17g}"


def _record_items(prefix: str, recs: np.ndarray) -> list[str]:
    out: list[str] = []
    dt = recs.dtype
    names = [n for n in dt.names if not n.startswith("reserved")]
    for i in range(len(recs)):
        r = recs[i]
        for n in names:
            sub = dt.fields[n][0]
            base = sub.base if sub.subdtype else sub
            fmt = fmt_f32 if base.kind == "f" else (lambda v: str(int(v)))
            if sub.shape:
                out += [f"{prefix}[{i}].{n}[{k}]={fmt(v)}" for k, v in enumerate(np.ravel(r[n]))]
            else:
                out.append(f"{prefix}[{i}].{n}={fmt(r[n])}")
    return out


def canonical_fields(msg: UdpMessage | SerialMessage | DvsPacket, seq: int | None = None) -> str:
    """The canonical text of a decoded message (serial messages need their frame's `seq`)."""
    items: list[str] = []
    if isinstance(msg, UdpMessage):
        items += [f"type={int(msg.TYPE)}", f"flags={msg.header_flags()}"]
        for name, _code, kind in msg._FIELDS:
            if kind == "x":
                continue
            v = getattr(msg, name)
            if kind == "f":
                items.append(f"{name}={fmt_f32(v)}")
            elif kind == "d":
                items.append(f"{name}={fmt_f64(v)}")
            elif kind == "s":
                items.append(f"{name}={escape_text(v)}")
            else:
                items.append(f"{name}={int(v)}")
        if msg._ARRAY is not None:
            recs = getattr(msg, msg._ARRAY)
            if msg._DTYPE is None:
                items.append(f"{msg._ARRAY}={bytes(recs).hex()}")
            else:
                items += _record_items(msg._ARRAY, np.asarray(recs))
    elif isinstance(msg, SerialMessage):
        if seq is None:
            raise TypeError("canonical_fields of a serial message needs its frame's seq")
        items += [f"msg_id={int(msg.MSG_ID)}", f"seq={seq}"]
        for name, v in zip(msg.field_names(), msg.values(), strict=True):
            items.append(f"{name}={escape_text(v)}" if name in msg._TEXT else f"{name}={int(v)}")
    elif isinstance(msg, DvsPacket):
        w = msg.words
        t = dvs_event_times(msg)
        items.append(f"n_words={len(w)}")
        for i in range(len(w)):
            items += [f"words[{i}].{n}={int(w[n][i])}" for n in ("x", "y", "polarity", "ts", "reset", "wrap", "sync")]
            if t[i] >= 0:
                items.append(f"words[{i}].t_us={int(t[i])}")
    else:
        raise TypeError(f"no canonical form for {type(msg).__name__}")
    return " ".join(items)
