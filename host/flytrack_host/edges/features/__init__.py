"""Python access to the edge feature extractor (the C library libflytrack_features, via ctypes)."""

from flytrack_host.edges.features._lib import FeatureLibraryError
from flytrack_host.edges.features.extractor import (
    POINT_DTYPE,
    ExtractorParams,
    FeatureError,
    FeatureExtractor,
    FrameFeatures,
)

__all__ = [
    "POINT_DTYPE",
    "ExtractorParams",
    "FeatureError",
    "FeatureExtractor",
    "FeatureLibraryError",
    "FrameFeatures",
]
