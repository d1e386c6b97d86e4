"""The one exception of the protocol codecs: it carries the SPEC error name (protocol/SPEC.md)."""

from __future__ import annotations

# The error names of SPEC.md, in the order a reader checks them.
ERROR_NAMES: tuple[str, ...] = (
    "TRUNCATED",
    "BAD_MAGIC",
    "BAD_VERSION",
    "UNKNOWN_TYPE",
    "LENGTH_MISMATCH",
    "COUNT_OVERFLOW",
    "NOT_FINITE",
    "BAD_FIELD",
    "BAD_COBS",
    "BAD_CRC",
)


class ProtocolError(ValueError):
    """Bytes (or a message to encode) that break protocol/SPEC.md.

    `.name` is the SPEC error name (e.g. "TRUNCATED"); the message says what exactly was wrong.
    """

    def __init__(self, name: str, detail: str) -> None:
        if name not in ERROR_NAMES:
            raise AssertionError(f"unknown protocol error name {name!r}")
        super().__init__(f"{name}: {detail}")
        self.name = name
        self.detail = detail

    def __reduce__(self):  # keep .name when pickled (e.g. across processes)
        return (type(self), (self.name, self.detail))
