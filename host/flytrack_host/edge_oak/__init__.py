"""OAK edge: frames of a Luxonis OAK camera (depthai) through the C feature extractor, out as FEATURES.

Python rather than C++: depthai's supported binding on PyPI is the Python wheel (depthai-core in C++
must be built from source with its own dependency tree, not packaged by Debian), and the C extractor
already has a Python binding (`flytrack_host.features`), so the points are computed by the same code
as `flytrack-edge`'s.
"""

from flytrack_host.edge_oak.edge import OakEdge, OakEdgeConfig
from flytrack_host.edge_oak.pipeline import build_pipeline
from flytrack_host.edge_oak.source import DepthaiSource, DeviceLost, FrameSource, OakFrame, frame_from_imgframe

__all__ = [
    "DepthaiSource",
    "DeviceLost",
    "FrameSource",
    "OakEdge",
    "OakEdgeConfig",
    "OakFrame",
    "build_pipeline",
    "frame_from_imgframe",
]
