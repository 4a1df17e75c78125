"""The media types the API reads and writes besides JSON (docs/design/service.md §1.2, §1.5, §2)."""

from __future__ import annotations

__all__ = ["IMAGE_MEDIA_TYPES", "PROBLEM_MEDIA_TYPE", "TAR_MEDIA_TYPE"]

#: Every error body (RFC 9457).
PROBLEM_MEDIA_TYPE = "application/problem+json"
#: What the observation route accepts (the `allowed` member of 415 unsupported-media-type).
IMAGE_MEDIA_TYPES = ("image/jpeg", "image/png", "image/webp", "image/bmp", "application/octet-stream")
#: A snapshot's download.
TAR_MEDIA_TYPE = "application/x-tar"
