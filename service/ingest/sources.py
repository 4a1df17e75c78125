"""Frame sources for `cortexloc ingest`: an image folder, a ROS 1 `.bag`, a ROS 2 bag (`.db3` or `.mcap`).

`open_source(path, topic=None, every=1)` checks the source up front (the topic exists and carries images)
and returns a `Source`; `Source.frames()` then reads lazily, so a long bag is never held in memory and
frames skipped by `every` are never converted.

Bags are read with `rosbags` (pure Python, no ROS install). From `sensor_msgs/msg/CompressedImage` the
`data` is posted as it is (the service tells JPEG from PNG by the bytes). `sensor_msgs/msg/Image` is posted
as a raw frame (`application/octet-stream` with `encoding`, `width`, `height`; docs/design/service.md
§1.2): its rows without padding, 16-bit samples little-endian, alpha dropped (`RAW_ENCODINGS`). Nothing is
re-encoded, and the service decodes it to the same RGB as a lossless PNG of those pixels, so the answer
is the same. A message's stamp is its `header.stamp` (when the sensor took it), or the time the bag
recorded it when the header carries none; the poster sends it as the observation's `stamp` metadata.

Example:
    >>> src = open_source(Path("run1"), topic="/cam0/image_raw", every=5)
    >>> src.total, next(iter(src.frames())).stamp_ns
    (120, 1700000000123456789)
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.frontend import images

__all__ = ["COMPRESSED_TYPE", "IMAGE_SUFFIXES", "IMAGE_TYPE", "RAW_ENCODINGS", "Frame", "Source",
           "SourceError", "image_to_raw", "open_source"]

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"

#: File name endings of the formats the encoder decodes (`models.frontend.images.FORMATS`); the service
#: decides which of them it accepts (a refused one is reported per frame, the ingest goes on).
_SUFFIXES_BY_FORMAT = {"jpeg": (".jpg", ".jpeg", ".jpe"), "png": (".png",), "bmp": (".bmp",),
                       "webp": (".webp",)}
IMAGE_SUFFIXES = tuple(s for fmt in images.FORMATS for s in _SUFFIXES_BY_FORMAT[fmt])

#: ROS `sensor_msgs/Image` encodings -> (channels, bytes per sample, the service's raw encoding). Alpha
#: is dropped, as the service's decoder drops it from a PNG (docs/design/science.md §6).
RAW_ENCODINGS: dict[str, tuple[int, int, str]] = {
    "rgb8": (3, 1, "rgb8"), "bgr8": (3, 1, "bgr8"), "mono8": (1, 1, "mono8"), "mono16": (1, 2, "mono16"),
    "rgba8": (4, 1, "rgb8"), "bgra8": (4, 1, "bgr8"),
}

#: Both an encoded image posted as it is (the service sniffs it) and a raw frame (with its parameters).
AS_IS_MEDIA = "application/octet-stream"


class SourceError(ValueError):
    """A source that cannot be read as asked (missing, no images, wrong or ambiguous topic, bad message)."""


class UnusableFrameError(SourceError):
    """A bag message that cannot be made a frame, with the status the service would refuse it with: 415
    an encoding it does not take, 422 a payload shorter than its shape (`models.frontend.images.raw`)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Frame:
    """One frame to post.

    Attributes:
        index: position in the source (0-based, before `every`): file order or message order on the topic.
        name: the file name, or `topic#index`.
        stamp_ns: the message time in nanoseconds since the epoch; None for files.
        data: the body to post (empty when `oversize`).
        media_type: its Content-Type.
        params: the query parameters it needs (a raw frame's `encoding`, `width`, `height`).
        oversize: the frame's size in bytes when it is over the source's `max_bytes`: it was not read
            (a file) or not kept (a bag message), and is not to be posted; None otherwise.
        unusable: a bag message that cannot be made a frame (`UnusableFrameError`: an encoding the service
            does not take, a payload shorter than its shape), not to be posted; None otherwise. The service
            would refuse it the same way: the ingest counts it and goes on, as the ROS 2 node skips it.
        unreadable: why a folder's file could not be read (the OS's words: no permission, gone since the
            folder was listed, an I/O error), not to be posted; None otherwise. One bad file is counted
            and the ingest goes on, as for a bag message.
    """

    index: int
    name: str
    stamp_ns: int | None
    data: bytes
    media_type: str
    params: dict[str, str] = field(default_factory=dict)
    oversize: int | None = None
    unusable: UnusableFrameError | None = None
    unreadable: str | None = None


@dataclass(frozen=True)
class Source:
    """A checked source: `kind` folder | ros1 | ros2, `topic` (bags), `total` frames after `every`; frames
    over `max_bytes` come as `Frame.oversize` (None: no limit)."""

    path: Path
    kind: str
    every: int
    total: int
    topic: str | None = None
    max_bytes: int | None = None
    _files: tuple[Path, ...] = ()

    def _over(self, size: int) -> bool:
        return self.max_bytes is not None and size > self.max_bytes

    def describe(self) -> str:
        where = f"{self.path} ({self.kind}" + (f", topic {self.topic}" if self.topic else "") + ")"
        return where + (f", every {self.every}th frame" if self.every > 1 else "")

    def frames(self) -> Iterator[Frame]:
        """The frames in source order, every `every`-th from the first; read lazily."""
        if self.kind == "folder":
            for i, f in enumerate(self._files):
                if i % self.every:
                    continue
                try:
                    size = f.stat().st_size  # before reading: a 1.5 GB file is never loaded
                    data = b"" if self._over(size) else f.read_bytes()
                except OSError as e:
                    yield Frame(i, f.name, None, b"", AS_IS_MEDIA, unreadable=e.strerror or str(e))
                    continue
                if self._over(size):
                    yield Frame(i, f.name, None, b"", AS_IS_MEDIA, oversize=size)
                else:
                    yield Frame(i, f.name, None, data, AS_IS_MEDIA)
            return
        yield from _bag_frames(self)


def open_source(path: Path, *, topic: str | None = None, every: int = 1,
                max_bytes: int | None = None) -> Source:
    """Check `path` and say what will be read.

    Args:
        path: a folder of images (read in name order: zero-pad numbered names), a ROS 1 `.bag`, or a ROS 2
            bag (its folder with `metadata.yaml`, or a `.db3` / `.mcap` file in it).
        topic: the image topic of a bag; None: the bag's only image topic.
        every: keep the first frame and every `every`-th after it.
        max_bytes: frames larger than this (the service's upload limit) come as `Frame.oversize`, unread.

    Raises:
        SourceError: with what was found (the image topics, the files) when it cannot be read as asked.
    """
    if every < 1:
        raise SourceError(f"every must be >= 1, got {every}")
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    if path.is_file() and path.suffix in (".db3", ".mcap"):
        if not (path.parent / "metadata.yaml").is_file():
            raise SourceError(f"{path}: a ROS 2 bag is read from its folder with metadata.yaml; "
                              "there is none beside this file")
        path = path.parent
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        if topic is not None:
            raise SourceError(f"{path} is a folder of images: --topic applies to bags only")
        files = tuple(sorted((f for f in path.iterdir() if f.is_file() and not f.name.startswith(".")
                              and f.suffix.lower() in IMAGE_SUFFIXES), key=lambda f: f.name))
        if not files:
            raise SourceError(f"{path}: no image files ({', '.join(IMAGE_SUFFIXES)}) and no metadata.yaml "
                              "(a ROS 2 bag)")
        return Source(path, "folder", every, _subsampled(len(files), every), max_bytes=max_bytes,
                      _files=files)
    if path.is_file() and path.suffix != ".bag":
        raise SourceError(f"{path}: not a folder of images, a ROS 1 .bag or a ROS 2 bag")
    kind = "ros1" if path.suffix == ".bag" else "ros2"
    with _damaged(path), _reader(path) as reader:
        chosen, count = _choose_topic(path, reader, topic)
    return Source(path, kind, every, _subsampled(count, every), topic=chosen, max_bytes=max_bytes)


def _subsampled(n: int, every: int) -> int:
    return (n + every - 1) // every


@contextmanager
def _damaged(path: Path) -> Iterator[None]:
    """Any failure to read the bag is a `SourceError` naming it. A bag is input from outside: a truncated
    file, broken metadata.yaml or random bytes make the reader fail in ways of its own (its own errors,
    UnicodeDecodeError, sqlite3, struct, KeyError, ...), and each is the same answer: this bag cannot be
    read (one line, exit 2; never a traceback)."""
    try:
        yield
    except SourceError:
        raise
    except Exception as e:
        raise SourceError(f"{path}: cannot read the bag (damaged or not a bag?): {type(e).__name__}: "
                          f"{' '.join(str(e).split())[:300]}") from e


def _reader(path: Path) -> Any:
    """An opened-on-enter `rosbags` AnyReader; bags without type definitions fall back to the latest LTS.
    Used inside `_damaged`, which turns its failures into a `SourceError`."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    return AnyReader([path], default_typestore=get_typestore(Stores.LATEST))


def _choose_topic(path: Path, reader: Any, topic: str | None) -> tuple[str, int]:
    """(topic, message count) of the requested or only image topic."""
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    for c in reader.connections:
        counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        types[c.topic] = c.msgtype
    image_topics = sorted(t for t, ty in types.items() if ty in (IMAGE_TYPE, COMPRESSED_TYPE))

    def listing() -> str:
        shown = ", ".join(f"{t} ({types[t]}, {counts[t]} messages)" for t in sorted(types)) or "none"
        return f"topics in {path}: {shown}"

    if topic is None:
        if len(image_topics) == 1:
            return image_topics[0], counts[image_topics[0]]
        if not image_topics:
            raise SourceError(f"no {IMAGE_TYPE} or {COMPRESSED_TYPE} topic; {listing()}")
        raise SourceError(f"{len(image_topics)} image topics, choose one with --topic: "
                          f"{', '.join(image_topics)}; {listing()}")
    if topic not in types:
        raise SourceError(f"no topic {topic!r}; {listing()}")
    if topic not in image_topics:
        raise SourceError(f"topic {topic!r} carries {types[topic]}, not {IMAGE_TYPE} or {COMPRESSED_TYPE}; "
                          f"{listing()}")
    return topic, counts[topic]


def _bag_frames(src: Source) -> Iterator[Frame]:
    with _damaged(src.path), _reader(src.path) as reader:
        conns = [c for c in reader.connections if c.topic == src.topic]
        for i, (conn, recorded_ns, raw) in enumerate(reader.messages(connections=conns)):
            if i % src.every:
                continue
            name = f"{src.topic}#{i}"
            # Surely over the limit, so not even deserialised: a body is at least 3/4 of its message's
            # bytes (rgba8 posts 3 bytes of 4), more than the limit once the message is twice it.
            if src._over(len(raw) // 2):
                yield Frame(i, name, int(recorded_ns), b"", AS_IS_MEDIA, oversize=len(raw))
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp
            stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) or int(recorded_ns)
            if conn.msgtype == COMPRESSED_TYPE:
                body, params = bytes(msg.data), {}
            else:
                try:
                    body, params = image_to_raw(msg.data, height=msg.height, width=msg.width, step=msg.step,
                                                encoding=msg.encoding, is_bigendian=bool(msg.is_bigendian))
                except UnusableFrameError as e:  # one message: counted and skipped, the bag goes on
                    yield Frame(i, name, stamp_ns, b"", AS_IS_MEDIA, unusable=e)
                    continue
            if src._over(len(body)):
                yield Frame(i, name, stamp_ns, b"", AS_IS_MEDIA, oversize=len(body))
            else:
                yield Frame(i, name, stamp_ns, body, AS_IS_MEDIA, params)


def image_to_raw(data: bytes | np.ndarray, *, height: int, width: int, step: int, encoding: str,
                 is_bigendian: bool = False) -> tuple[bytes, dict[str, str]]:
    """A `sensor_msgs/Image` payload as the service's raw frame: (body, query parameters).

    Args:
        data: `height` rows of `step` bytes each (a row may be padded past `width` pixels).
        encoding: one of `RAW_ENCODINGS`.
        is_bigendian: the byte order of 16-bit samples (the body is always little-endian).

    Returns:
        The pixels row after row without padding, and `{"encoding", "width", "height"}`.

    Raises:
        UnusableFrameError: an unknown encoding (415), or a payload shorter than its shape says (422).
    """
    if encoding not in RAW_ENCODINGS:
        raise UnusableFrameError(415, f"image encoding {encoding!r} is not supported; supported: "
                          f"{', '.join(RAW_ENCODINGS)}")
    channels, sample, sent_as = RAW_ENCODINGS[encoding]
    row = width * channels * sample
    buf = np.frombuffer(data, np.uint8) if isinstance(data, bytes | bytearray) else np.asarray(data, np.uint8)
    if height < 1 or width < 1 or step < row or buf.size < step * height:
        raise UnusableFrameError(422, f"{encoding} image {width}x{height} needs {height} rows of >= {row} "
                                      f"bytes (step {step}); the message holds {buf.size} bytes")
    rows = buf[: step * height].reshape(height, step)[:, :row]
    if sample == 2:
        pixels = rows.copy().view(">u2" if is_bigendian else "<u2").astype("<u2")
    elif channels == 4:
        pixels = rows.reshape(height, width, 4)[:, :, :3]
    else:
        pixels = rows
    return (np.ascontiguousarray(pixels).tobytes(),
            {"encoding": sent_as, "width": str(width), "height": str(height)})
