"""Image bytes -> 8-bit RGB -> normalised network input (docs/design/science.md §6 "Front end",
Preprocessing).

The one place that knows image formats. Everything is OpenCV + NumPy (and libjpeg-turbo through
simplejpeg to check a JPEG's scan data, `jpeg._jpeg_check_scan_data`): no torchvision, no PIL.

Decoding follows the order of work of docs/design/service.md §1.2 and §3, so a hostile upload costs almost
nothing before it is refused: byte limit -> magic bytes (JPEG, PNG, BMP, WebP; everything else is refused
before OpenCV sees it, which keeps OpenCV's many other codecs out of reach) -> width and height read from the
header by small pure-Python parsers -> pixel cap, aspect-ratio cap and minimum side (16 pixels) -> a
structural completeness check (truncated uploads are refused rather than decoded into half-grey frames,
and so are a JPEG whose scans and an RLE bitmap whose rows stop short of the image) -> a decoding-cost
check ->
the PNG's bounded inflate or the JPEG's scan-data check -> `cv2.imdecode`.

Decoding cost is bounded by the declared raster, not only by the byte limit: a 10 MB PNG can hold ~10 GB
of deflated zeros (libpng inflates all of it, ~25 s), and a 300 kB progressive JPEG thousands of empty
scans over a 25-megapixel frame (~100 s). So the header walk refuses PNG image data larger than its
raster could need compressed and JPEGs with more than `JPEG_MAX_SCANS` scans (both cheap, before
anything is queued), and `decode` inflates the PNG data once with a bounded decompressor that stops at
the raster's exact size, so no upload costs more than a legitimate image of its declared size. These
parsers stay ours rather than Pillow's lazy `open`: Pillow's bomb guard is a pixel count (the cap we
already check) and says nothing about compression ratios or scan counts, and a second codec library
would be more attack surface than these few hundred lines.

Preprocessing reproduces torchvision's `Resize(256)` + `CenterCrop(224)` + `ToTensor` + `Normalize`
geometry and arithmetic (docs/design/science.md §6), with OpenCV's `INTER_AREA` standing in for antialiased
bilinear when shrinking, plus the `squash` mode (straight to 224×224).

Modules: `common` (limits, formats, `ImageError`), `probing` (magic bytes, dispatch to a header parser,
the checks in order), one parser per format (`jpeg`, `png` with the bounded inflate, `bmp_webp`),
`raw` (uncompressed sensor frames: `RawFrame`, rgb8 | bgr8 | mono8 | mono16), `decoding` (`decode`:
OpenCV), `preprocessing` (`preprocess_batch`) and `thumbnails` (a small JPEG for people). Import from
this package.

Example:
    >>> rgb = decode(open("frame.jpg", "rb").read())      # (H, W, 3) uint8 RGB
    >>> x = preprocess_batch([rgb], mode="crop")           # (1, 3, 224, 224) float32
"""

from __future__ import annotations

import os

from models.frontend import limits

# OpenCV's own decompression-bomb guard, read once when cv2 is loaded (docs/design/service.md §3: "set to the
# same value before OpenCV is imported"). It is the second line of defence behind the header check below;
# setdefault so that a deployment (or a test) that sets it first keeps its value. If cv2 was already
# imported elsewhere this is a harmless no-op.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(limits.DEFAULT_MAX_PIXELS))

# The submodules come after the line above: decode and preprocess import cv2.
from models.frontend.images.common import (
    DEFAULT_MAX_ASPECT,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_PIXELS,
    DEFAULT_MIN_SIDE,
    ERROR_CODES,
    FORMATS,
    IMAGENET_MEAN,
    IMAGENET_STD,
    MODES,
    ImageError,
    ImageInfo,
)
from models.frontend.images.decoding import decode
from models.frontend.images.information import contrast
from models.frontend.images.jpeg import JPEG_MAX_SCANS
from models.frontend.images.preprocessing import preprocess, preprocess_batch
from models.frontend.images.probing import probe, sniff
from models.frontend.images.raw import RAW_ENCODINGS, RawFrame
from models.frontend.images.thumbnails import THUMBNAIL_SIDE, thumbnail

__all__ = [
    "DEFAULT_MAX_ASPECT",
    "DEFAULT_MAX_BYTES",
    "DEFAULT_MAX_PIXELS",
    "DEFAULT_MIN_SIDE",
    "ERROR_CODES",
    "FORMATS",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "JPEG_MAX_SCANS",
    "MODES",
    "RAW_ENCODINGS",
    "THUMBNAIL_SIDE",
    "ImageError",
    "ImageInfo",
    "RawFrame",
    "contrast",
    "decode",
    "preprocess",
    "preprocess_batch",
    "probe",
    "sniff",
    "thumbnail",
]
