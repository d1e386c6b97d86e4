"""Fixed-size NUL-padded text fields (SPEC general rules), shared by the UDP and serial codecs."""

from __future__ import annotations

from .errors import ProtocolError


def decode_text(raw: bytes, field: str) -> str:
    """The text of a fixed-size field: up to the first NUL; every byte after it must be NUL.

    UTF-8 is not validated (the C codec does not either); undecodable bytes are kept as surrogate
    escapes so the field re-encodes byte for byte.
    """
    end = raw.find(b"\0")
    if end >= 0:
        if raw[end:].count(0) != len(raw) - end:
            raise ProtocolError("BAD_FIELD", f"text field {field!r} has non-NUL bytes after its first NUL")
        raw = raw[:end]
    return raw.decode("utf-8", "surrogateescape")


def encode_text(text: str, size: int, field: str) -> bytes:
    raw = text.encode("utf-8", "surrogateescape")
    if len(raw) > size:
        raise ProtocolError("BAD_FIELD", f"text field {field!r} is {len(raw)} bytes, the field holds {size}")
    if b"\0" in raw:
        raise ProtocolError("BAD_FIELD", f"text field {field!r} contains a NUL byte")
    return raw + b"\0" * (size - len(raw))


def escape_text(text: str) -> str:
    """SPEC §5 canonical text: printable ASCII as is; space, backslash, other bytes as \\xHH (lowercase)."""
    raw = text.encode("utf-8", "surrogateescape")
    return "".join(chr(b) if 0x21 <= b <= 0x7E and b != 0x5C else f"\\x{b:02x}" for b in raw)
