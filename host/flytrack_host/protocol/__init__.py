"""Python codec of the FlyTrack wire protocol (protocol/SPEC.md).

- UDP datagrams (udp.py, split by family into udp_header/udp_frame/udp_eventcam/udp_live/udp_codec): decode_datagram,
  encode, encode_features, join_feature_parts, the message
  dataclasses and record dtypes.
- Trigger serial link (trigger_link.py): CRC-16, COBS, frames, typed messages, FrameSplitter.
- DVS128 USB words (dvs.py): DvsDecoder, encode_events.
- canonical_fields (canonical.py): the SPEC §5 text the golden vectors compare.

May import: util.
"""

PROTOCOL_VERSION = 2

from .canonical import canonical_fields, fmt_f32, fmt_f64  # noqa: E402
from .dvs import (  # noqa: E402
    DVS_WORD_DTYPE,
    EVENT_DTYPE,
    WRAP_US,
    DvsDecoder,
    DvsEncoder,
    DvsPacket,
    decode_dvs_words,
    encode_dvs_words,
    encode_events,
)
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
from .udp import (  # noqa: E402
    CAMERA_ANY,
    CLUSTER_DTYPE,
    CLUSTERS_MAX,
    FEATURES_MAX_POINTS,
    HEADER_SIZE,
    IMAGE_MAX_CHUNK,
    LIVE_MAX_OBJECTS,
    MAX_DATAGRAM,
    MAX_PARTS,
    OBJECT_DTYPE,
    POINT_DTYPE,
    UDP_MESSAGE_TYPES,
    WINGEDGE_DTYPE,
    WINGEDGES_MAX,
    AckStatus,
    CameraState,
    Command,
    Control,
    ControlAck,
    DvsClusters,
    DvsFlags,
    DvsWingbeat,
    EdgeStatus,
    FeatureFlags,
    FeatureFrame,
    ImageChunk,
    ImageKind,
    LiveEstimates,
    LiveFlags,
    MsgType,
    PixelFormat,
    UdpMessage,
    assemble_image,
    decode_datagram,
    encode,
    encode_features,
    encode_live_estimates,
    image_chunks,
    join_feature_parts,
    make_points,
)

__all__ = [
    "PROTOCOL_VERSION", "ERROR_NAMES", "ProtocolError", "canonical_fields", "fmt_f32", "fmt_f64",
    # dvs
    "EVENT_DTYPE", "DVS_WORD_DTYPE", "WRAP_US", "DvsDecoder", "DvsEncoder", "DvsPacket",
    "decode_dvs_words", "encode_dvs_words", "encode_events",
    # trigger link
    "FRAME_NOW", "MAX_BODY", "MAX_WIRE_FRAME", "PRESCALER_DIVISORS", "SERIAL_MESSAGE_TYPES",
    "Ack", "Clock", "ClockQuery", "Error", "ErrorCode", "Event", "FrameSplitter", "GetInfo", "Info",
    "Mcu", "MsgId", "Pulse", "Rate", "SerialMessage", "SetName", "SetOutput", "SetRate", "Start", "Stop",
    "StopReset", "cobs_decode", "cobs_encode", "crc16_ccitt_false", "decode_frame", "decode_message",
    "encode_frame", "encode_message",
    # udp
    "CAMERA_ANY", "CLUSTER_DTYPE", "CLUSTERS_MAX", "FEATURES_MAX_POINTS", "HEADER_SIZE", "IMAGE_MAX_CHUNK",
    "LIVE_MAX_OBJECTS", "MAX_DATAGRAM", "MAX_PARTS", "OBJECT_DTYPE", "POINT_DTYPE", "UDP_MESSAGE_TYPES",
    "WINGEDGE_DTYPE", "WINGEDGES_MAX", "AckStatus", "CameraState", "Command", "Control", "ControlAck",
    "DvsClusters", "DvsWingbeat", "EdgeStatus", "FeatureFlags", "FeatureFrame", "ImageChunk", "ImageKind",
    "LiveEstimates", "LiveFlags", "DvsFlags", "MsgType", "PixelFormat", "UdpMessage", "decode_datagram", "encode",
    "encode_features", "join_feature_parts", "make_points", "encode_live_estimates", "image_chunks",
    "assemble_image",
]  # fmt: skip
