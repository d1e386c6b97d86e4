"""Python codec of the FlyTrack wire protocol (protocol/SPEC.md)."""

PROTOCOL_VERSION = 1

from .errors import ERROR_NAMES, ProtocolError  # noqa: E402
from .trigger_link import (  # noqa: E402
    FRAME_NOW,
    MAX_BODY,
    MAX_WIRE_FRAME,
    PRESCALER_DIVISORS,
    SERIAL_MESSAGE_TYPES,
    Ack,
    Clock,
    ClockQuery,
    Error,
    ErrorCode,
    Event,
    FrameSplitter,
    GetInfo,
    Info,
    Mcu,
    MsgId,
    Pulse,
    Rate,
    SerialMessage,
    SetName,
    SetOutput,
    SetRate,
    Start,
    Stop,
    StopReset,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
    decode_frame,
    decode_message,
    encode_frame,
    encode_message,
)

__all__ = [
    "PROTOCOL_VERSION", "ERROR_NAMES", "ProtocolError",
    "FRAME_NOW", "MAX_BODY", "MAX_WIRE_FRAME", "PRESCALER_DIVISORS", "SERIAL_MESSAGE_TYPES",
    "Ack", "Clock", "ClockQuery", "Error", "ErrorCode", "Event", "FrameSplitter", "GetInfo", "Info",
    "Mcu", "MsgId", "Pulse", "Rate", "SerialMessage", "SetName", "SetOutput", "SetRate", "Start", "Stop",
    "StopReset", "cobs_decode", "cobs_encode", "crc16_ccitt_false", "decode_frame", "decode_message",
    "encode_frame", "encode_message",
]  # fmt: skip
