"""The default limits on one upload, in a module that imports nothing heavy (docs/design/service.md §3).

`service.settings` reads its defaults from here before OpenCV is loaded: `cortexloc serve` must set
`OPENCV_IO_MAX_IMAGE_PIXELS` from the settings first, and importing `models.frontend.images` loads cv2.
"""

DEFAULT_MAX_BYTES = 10 * 2**20
DEFAULT_MAX_PIXELS = 25_000_000
#: Bytes a pixel the pixel cap is sized for: an 8-bit RGB frame. A PNG may carry up to 8 (16-bit RGBA),
#: and its decode costs by the bytes, so its raster is held to `max_pixels` x this many bytes.
PIXEL_CAP_BYTES = 3
# docs/design/service.md §1.2: "long side more than 16× the short side" is a degenerate image. The cap also
# bounds the Resize(256) intermediate: a 1×4000 upload would otherwise become a 256×1,024,000 array (786 MB).
DEFAULT_MAX_ASPECT = 16.0
#: Pixels the short side of a frame must have at least ("degenerate" below it): a view of a place has some.
#: A 2x2 checkerboard was learned and matched real views at confidence 0.725 (an outside probe); the
#: backbone's 224 x 224 input would be that many pixels enlarged. The smallest real frames the repository
#: evaluates on are 64x32 (Nordland, docs/results.md).
DEFAULT_MIN_SIDE = 16

#: Images per backbone call while the pool prepares the next ones (`Embedder`'s `chunk`,
#: CORTEXLOC_ENCODE_CHUNK): the forward's cost per image is flat from batch 1 to 16 on ONNX Runtime
#: (1 thread), so small chunks start the backbone sooner. (Here, beside the upload limits, because
#: `service.settings` reads it before the backbone's modules load.)
DEFAULT_CHUNK = 4
