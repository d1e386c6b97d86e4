"""Python access to the edge feature extractor (the C library libflytrack_features, via ctypes)."""

from flytrack_host.features._lib import FeatureLibraryError
from flytrack_host.features.extractor import (
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
