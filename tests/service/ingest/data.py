"""Sources for the ingest tests, written here: image folders and ROS 1 / ROS 2 bags (rosbags' writers).

A "route" is a list of places; place p is a fixed random low-frequency 240x320 BGR picture, so the same
place posted twice is the same pixels (a revisit) and different places differ everywhere.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROUTE = (0, 1, 2, 3, 0, 1, 2)  # a loop driven once and then partly again: revisits from the 5th frame
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000  # 10 Hz


def place_bgr(place: int) -> np.ndarray:
    rng = np.random.default_rng(place)
    return cv2.resize(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), (320, 240),
                      interpolation=cv2.INTER_CUBIC)


def png(pixels: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", pixels)
    assert ok
    return buf.tobytes()


def jpeg(pixels: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", pixels)
    assert ok
    return buf.tobytes()


def stamp(i: int) -> int:
    """header.stamp of message i in ns (the bag's record time is 7 ms later: the stamp must win)."""
    return T0_NS + i * PERIOD_NS


def _header(ns: int, typestore: Any) -> Any:
    t = typestore.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    extra = {"seq": 0} if any(f[0] == "seq" for f in typestore.fielddefs["std_msgs/msg/Header"][1]) else {}
    return typestore.types["std_msgs/msg/Header"](stamp=t, frame_id="cam0", **extra)


def image_msg(typestore: Any, pixels: np.ndarray, encoding: str, ns: int) -> Any:
    """A sensor_msgs/msg/Image of `pixels` (BGR or grey) in `encoding` (rgb8 swaps to R,G,B)."""
    data = pixels[..., ::-1] if encoding == "rgb8" else pixels
    data = np.ascontiguousarray(data)
    header = _header(ns, typestore)
    h, w = pixels.shape[:2]
    return typestore.types["sensor_msgs/msg/Image"](
        header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
        step=data.strides[0], data=data.reshape(-1).view(np.uint8))


def compressed_msg(typestore: Any, data: bytes, ns: int) -> Any:
    header = _header(ns, typestore)
    return typestore.types["sensor_msgs/msg/CompressedImage"](
        header=header, format="jpeg", data=np.frombuffer(data, np.uint8))


#: topic -> (message type, what the reference posts for place p: the same pixels as PNG, or the JPEG).
TOPICS: dict[str, tuple[str, Callable[[int], bytes]]] = {
    "/cam/rgb": ("sensor_msgs/msg/Image", lambda p: png(place_bgr(p))),
    "/cam/bgr": ("sensor_msgs/msg/Image", lambda p: png(place_bgr(p))),
    "/cam/mono": ("sensor_msgs/msg/Image", lambda p: png(cv2.cvtColor(place_bgr(p), cv2.COLOR_BGR2GRAY))),
    "/cam/compressed": ("sensor_msgs/msg/CompressedImage", lambda p: jpeg(place_bgr(p))),
}
_ENCODING = {"/cam/rgb": "rgb8", "/cam/bgr": "bgr8", "/cam/mono": "mono8"}


def _messages(typestore: Any, topic: str, route: Sequence[int]) -> Iterator[tuple[int, Any]]:
    msgtype, reference = TOPICS[topic]
    for i, p in enumerate(route):
        if msgtype.endswith("CompressedImage"):
            yield i, compressed_msg(typestore, reference(p), stamp(i))
        else:
            pixels = place_bgr(p)
            if _ENCODING[topic] == "mono8":
                pixels = cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
            yield i, image_msg(typestore, pixels, _ENCODING[topic], stamp(i))


def write_ros2_bag(path: Path, route: Sequence[int] = ROUTE, *, topics: Sequence[str] = tuple(TOPICS),
                   storage: str = "sqlite3", extra_topics: Sequence[tuple[str, str]] = ()) -> Path:
    """A ROS 2 bag folder with `route` on each of `topics`; `extra_topics` (topic, type) stay empty."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        for topic, msgtype in extra_topics:
            w.add_connection(topic, msgtype, typestore=ts)
        for topic in topics:
            conn = w.add_connection(topic, TOPICS[topic][0], typestore=ts)
            for i, msg in _messages(ts, topic, route):
                w.write(conn, stamp(i) + 7_000_000, ts.serialize_cdr(msg, conn.msgtype))
    return path


def write_ros1_bag(path: Path, route: Sequence[int] = ROUTE, *,
                   topics: Sequence[str] = tuple(TOPICS)) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(path) as w:
        for topic in topics:
            conn = w.add_connection(topic, TOPICS[topic][0], typestore=ts)
            for i, msg in _messages(ts, topic, route):
                w.write(conn, stamp(i) + 7_000_000, ts.serialize_ros1(msg, conn.msgtype))
    return path


def write_folder(path: Path, route: Sequence[int] = ROUTE) -> list[bytes]:
    """Frames as JPEG and PNG files whose name order is the route order; returns the bytes in that order
    (plus a notes.txt that is not an image)."""
    path.mkdir(parents=True)
    out = []
    for i, p in enumerate(route):
        data = jpeg(place_bgr(p)) if i % 2 else png(place_bgr(p))
        (path / f"frame_{i:04d}.{'jpg' if i % 2 else 'png'}").write_bytes(data)
        out.append(data)
    (path / "notes.txt").write_text("not an image")
    return out


def comparable(answer: dict[str, Any]) -> dict[str, Any]:
    """What must be equal between two maps fed the same frames: everything but ids, times and names."""
    return {"learned": answer["learned"], "seq": answer["seq"], "sequence": answer["sequence"],
            "matches": [(m["rank"], m["seq"], m["overlap"], m["score"], m["label"])
                        for m in answer["matches"]],
            "projection": answer["versions"]["projection"]}


#: Damaged bags as found in the field (issue 19 item 5): `write_damaged_bag` makes each.
DAMAGE = ["truncated-db3-0.5", "truncated-db3-0.05", "truncated-mcap-0.5", "truncated-bag-0.5",
          "truncated-bag-0.05", "metadata-syntax", "metadata-shape", "random-bag", "random-metadata",
          "random-mcap", "random-db3"]


def write_damaged_bag(kind: str, root: Path) -> Path:
    """A bag under `root` damaged as `kind` (one of `DAMAGE`): cut to a fraction of its bytes, a broken
    metadata.yaml, or random bytes in place of the bag, its metadata or its storage file."""
    def cut(p: Path, keep: float) -> None:
        p.write_bytes(p.read_bytes()[: int(p.stat().st_size * keep)])

    if kind.startswith("truncated"):
        _, fmt, keep = kind.split("-")
        if fmt == "bag":
            bag = write_ros1_bag(root / "run.bag", topics=["/cam/rgb"])
            cut(bag, float(keep))
            return bag
        storage = "mcap" if fmt == "mcap" else "sqlite3"
        bag = write_ros2_bag(root / "bag", topics=["/cam/rgb"], storage=storage)
        cut(next(bag.glob(f"*.{fmt}")), float(keep))
        return bag
    if kind.startswith("metadata"):
        bag = write_ros2_bag(root / "bag", topics=["/cam/rgb"])
        text = "rosbag2_bagfile_information: [\n  : :" if kind == "metadata-syntax" else "just a string\n"
        (bag / "metadata.yaml").write_text(text)
        return bag
    noise = np.random.default_rng(7).bytes(100_000)
    if kind == "random-bag":
        (root / "x.bag").write_bytes(noise)
        return root / "x.bag"
    if kind == "random-metadata":
        (root / "bag").mkdir()
        (root / "bag" / "metadata.yaml").write_bytes(noise[:5_000])
        return root / "bag"
    mcap = kind == "random-mcap"
    bag = write_ros2_bag(root / "bag", topics=["/cam/rgb"], storage="mcap" if mcap else "sqlite3")
    next(bag.glob("*.mcap" if mcap else "*.db3")).write_bytes(noise)
    return bag


def write_ros2_bag_with(path: Path, sizes: Sequence[tuple[int, int]], topic: str = "/cam/rgb") -> Path:
    """A ROS 2 bag of rgb8 frames of the given (height, width): place i's picture, resized."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=9) as w:
        conn = w.add_connection(topic, "sensor_msgs/msg/Image", typestore=ts)
        for i, (h, w_) in enumerate(sizes):
            pixels = cv2.resize(place_bgr(i), (w_, h), interpolation=cv2.INTER_NEAREST)
            w.write(conn, stamp(i), ts.serialize_cdr(image_msg(ts, pixels, "rgb8", stamp(i)), conn.msgtype))
    return path
