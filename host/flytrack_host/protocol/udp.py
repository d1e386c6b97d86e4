"""UDP datagram codec (protocol/SPEC.md §1): edge <-> host and host -> stimulus programs.

The codec is split by message family; this module keeps every name importable from one place:

- udp_header.py: the header, MsgType, the record checks and the UdpMessage base.
- udp_frame.py: frame-camera messages FEATURES, STATUS, CONTROL, CONTROL_ACK, IMAGE and their helpers.
- udp_eventcam.py: event-camera messages DVS_CLUSTERS, DVS_WINGBEAT.
- udp_live.py: host-side LIVE_ESTIMATES.
- udp_codec.py: decode_datagram, encode, and splitting FEATURES / LIVE_ESTIMATES over datagrams.
"""

from __future__ import annotations

from .udp_codec import UDP_MESSAGE_TYPES, decode_datagram, encode, encode_features, encode_live_estimates
from .udp_eventcam import (
    CLUSTER_DTYPE,
    CLUSTERS_MAX,
    WINGEDGE_DTYPE,
    WINGEDGES_MAX,
    DvsClusters,
    DvsFlags,
    DvsWingbeat,
)
from .udp_frame import (
    CAMERA_ANY,
    FEATURES_MAX_POINTS,
    IMAGE_MAX_CHUNK,
    POINT_DTYPE,
    AckStatus,
    CameraState,
    Command,
    Control,
    ControlAck,
    EdgeStatus,
    FeatureFlags,
    FeatureFrame,
    ImageChunk,
    ImageKind,
    PixelFormat,
    assemble_image,
    image_chunks,
    join_feature_parts,
    make_points,
)
from .udp_header import (
    HEADER,
    HEADER_SIZE,
    MAGIC,
    MAX_DATAGRAM,
    MAX_PARTS,
    UDP_VERSION,
    FieldSpec,
    MsgType,
    UdpMessage,
)
from .udp_live import LIVE_MAX_OBJECTS, OBJECT_DTYPE, LiveEstimates, LiveFlags

__all__ = [
    "MAGIC", "UDP_VERSION", "HEADER", "HEADER_SIZE", "MAX_DATAGRAM", "MAX_PARTS", "FieldSpec", "MsgType",
    "UdpMessage", "UDP_MESSAGE_TYPES", "decode_datagram", "encode", "encode_features", "encode_live_estimates",
    # frame camera
    "CAMERA_ANY", "FEATURES_MAX_POINTS", "IMAGE_MAX_CHUNK", "POINT_DTYPE", "AckStatus", "CameraState",
    "Command", "Control", "ControlAck", "EdgeStatus", "FeatureFlags", "FeatureFrame", "ImageChunk",
    "ImageKind", "PixelFormat", "assemble_image", "image_chunks", "join_feature_parts", "make_points",
    # event camera
    "CLUSTER_DTYPE", "CLUSTERS_MAX", "WINGEDGE_DTYPE", "WINGEDGES_MAX", "DvsClusters", "DvsFlags", "DvsWingbeat",
    # host side
    "LIVE_MAX_OBJECTS", "OBJECT_DTYPE", "LiveEstimates", "LiveFlags",
]  # fmt: skip
