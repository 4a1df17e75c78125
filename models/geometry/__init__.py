"""Geometric verification of a revisit (docs/design/science.md §12): local features per frame
(`features`), matching, RANSAC with model selection and the relative pose (`verify`). Pure numpy and
OpenCV: no storage, no threads."""

from models.geometry.features import (
    EXTRACT_MAX_SIDE,
    EXTRACTORS,
    Features,
    KeyframeOptions,
    KeyframeParams,
    available,
    extract,
    pack,
    unpack,
)
from models.geometry.verify import Camera, Verification, camera_problems, quaternion, verify

__all__ = ["EXTRACTORS", "EXTRACT_MAX_SIDE", "Camera", "Features", "KeyframeOptions", "KeyframeParams",
           "Verification", "available", "camera_problems", "extract", "pack", "quaternion", "unpack",
           "verify"]
