"""Golden-vector runner (SPEC §5): `python -m flytrack_host.protocol.vectors protocol/vectors`.

Every valid vector must decode to exactly its canonical fields and re-encode byte for byte; every
invalid vector must be rejected with exactly the named error. Prints
`Python codec: N vectors passed, M failed` (and the failures) and exits non-zero on any failure.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from .canonical import canonical_fields
from .dvs import decode_dvs_words, encode_dvs_words
from .errors import ProtocolError
from .trigger_link import decode_message, encode_message
from .udp import MsgType, decode_datagram, encode

FAMILIES: dict[str, MsgType | None] = {
    "features": MsgType.FEATURES,
    "status": MsgType.STATUS,
    "control": MsgType.CONTROL,
    "control_ack": MsgType.CONTROL_ACK,
    "image": MsgType.IMAGE,
    "dvs_clusters": MsgType.DVS_CLUSTERS,
    "dvs_wingbeat": MsgType.DVS_WINGBEAT,
    "live_estimates": MsgType.LIVE_ESTIMATES,
    "trigger_link": None,
    "dvs_words": None,
}


@dataclass(frozen=True)
class Vector:
    family: str
    valid: bool
    name: str
    data: bytes
    expect: str  # canonical fields (valid) or error name (invalid)
    line: int


def load_vectors(directory: str | Path) -> list[Vector]:
    out: list[Vector] = []
    for family in FAMILIES:
        path = Path(directory) / f"{family}.tsv"
        for lineno, line in enumerate(path.read_text(encoding="ascii").splitlines(), 1):
            if not line or line.startswith("#"):
                continue
            kind, name, hexdata, expect = line.split("\t")
            if kind not in ("valid", "invalid"):
                raise ValueError(f"{path}:{lineno}: first column must be valid or invalid, not {kind!r}")
            out.append(Vector(family, kind == "valid", name, bytes.fromhex(hexdata), expect, lineno))
    return out


def _decode(family: str, data: bytes) -> tuple[str, bytes]:
    """(canonical fields, re-encoded bytes) of one vector's bytes; raises ProtocolError."""
    if family == "trigger_link":
        if not data or data[-1] != 0:
            raise ValueError("a serial vector must end with its 0x00 delimiter")
        seq, msg = decode_message(data[:-1])
        return canonical_fields(msg, seq), encode_message(msg, seq)
    if family == "dvs_words":
        pkt = decode_dvs_words(data)
        return canonical_fields(pkt), encode_dvs_words(pkt)
    msg = decode_datagram(data)
    if msg.TYPE != FAMILIES[family]:
        raise ValueError(f"a {family} vector decoded as {msg.TYPE.name}")
    return canonical_fields(msg), encode(msg)


def check_vector(v: Vector) -> str | None:
    """None when the vector passes, else what went wrong."""
    try:
        canon, again = _decode(v.family, v.data)
    except ProtocolError as exc:
        if v.valid:
            return f"valid vector rejected: {exc}"
        return None if exc.name == v.expect else f"expected {v.expect}, got {exc.name} ({exc})"
    except Exception as exc:  # noqa: BLE001 - anything else is a codec bug, reported as a failure
        return f"{type(exc).__name__}: {exc}"
    if not v.valid:
        return f"expected {v.expect}, but it decoded: {canon}"
    if canon != v.expect:
        return f"canonical fields differ:\n    got      {canon}\n    expected {v.expect}"
    if again != v.data:
        return f"re-encoding differs:\n    got      {again.hex()}\n    expected {v.data.hex()}"
    return None


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    directory = args[0] if args else "protocol/vectors"
    vectors = load_vectors(directory)
    failed = 0
    for v in vectors:
        problem = check_vector(v)
        if problem is not None:
            failed += 1
            print(f"FAIL {v.family}.tsv:{v.line} {v.name}: {problem}")
    print(f"Python codec: {len(vectors) - failed} vectors passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
