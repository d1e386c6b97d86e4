"""Python codec of the FlyTrack wire protocol (protocol/SPEC.md)."""

PROTOCOL_VERSION = 1
