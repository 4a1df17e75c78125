"""The readers of `cortexloc ingest`: folders, ROS 2 bags (.db3, .mcap), ROS 1 bags, raw frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.frontend import images
from service.ingest.sources import RAW_ENCODINGS, SourceError, image_to_raw, open_source
from tests.service.ingest.data import (
    DAMAGE,
    ROUTE,
    TOPICS,
    png,
    stamp,
    write_damaged_bag,
    write_folder,
    write_ros1_bag,
    write_ros2_bag,
    write_ros2_bag_with,
)


def test_a_folder_is_read_in_name_order_skipping_what_is_not_an_image(tmp_path):
    data = write_folder(tmp_path / "frames")
    src = open_source(tmp_path / "frames")
    frames = list(src.frames())
    assert src.kind == "folder" and src.total == len(ROUTE)
    assert [f.data for f in frames] == data
    names = [f"frame_{i:04d}.{'jpg' if i % 2 else 'png'}" for i in range(len(ROUTE))]
    assert [f.name for f in frames] == names
    assert all(f.stamp_ns is None for f in frames)


def test_every_keeps_the_first_frame_and_every_nth_after_it(tmp_path):
    write_folder(tmp_path / "frames")
    src = open_source(tmp_path / "frames", every=3)
    assert src.total == 3 and [f.index for f in src.frames()] == [0, 3, 6]
    bag = open_source(write_ros2_bag(tmp_path / "bag", topics=["/cam/compressed"]), every=3)
    assert bag.total == 3 and [f.index for f in bag.frames()] == [0, 3, 6]


@pytest.mark.parametrize("topic", list(TOPICS))
def test_a_ros2_bag_gives_raw_frames_or_the_compressed_bytes_as_they_are(tmp_path, topic):
    src = open_source(write_ros2_bag(tmp_path / "bag"), topic=topic)
    frames = list(src.frames())
    assert src.kind == "ros2" and src.topic == topic and src.total == len(ROUTE)
    assert [f.stamp_ns for f in frames] == [stamp(i) for i in range(len(ROUTE))]  # header.stamp, not record
    assert {f.media_type for f in frames} == {"application/octet-stream"}
    if "compressed" in topic:  # the JPEG a user would post, byte for byte
        assert [f.data for f in frames] == [TOPICS[topic][1](p) for p in ROUTE]
        assert all(f.params == {} for f in frames)
        return
    # A raw frame that the service decodes to the RGB of the PNG a user would post of the same pixels.
    for f, p in zip(frames, ROUTE, strict=True):
        raw = images.RawFrame(f.data, f.params["encoding"], int(f.params["width"]), int(f.params["height"]))
        assert np.array_equal(images.decode(raw), images.decode(TOPICS[topic][1](p)))


def _frames(src):
    return [(f.index, f.stamp_ns, f.data) for f in src.frames()]


def test_mcap_ros1_and_a_db3_file_path_read_the_same_frames(tmp_path):
    db3 = write_ros2_bag(tmp_path / "db3")
    mcap = write_ros2_bag(tmp_path / "mcap", storage="mcap")
    ros1 = write_ros1_bag(tmp_path / "run.bag")
    for topic in TOPICS:
        want = _frames(open_source(db3, topic=topic))
        assert _frames(open_source(mcap, topic=topic)) == want
        assert _frames(open_source(ros1, topic=topic)) == want
        assert open_source(ros1, topic=topic).kind == "ros1"
    (file,) = db3.glob("*.db3")
    assert open_source(file, topic="/cam/mono").path == db3


def test_topic_selection_errors_list_the_topics(tmp_path):
    bag = write_ros2_bag(tmp_path / "bag", extra_topics=[("/imu", "sensor_msgs/msg/Imu")])
    with pytest.raises(SourceError, match=r"4 image topics, choose one with --topic: /cam/bgr, "
                                          r"/cam/compressed, /cam/mono, /cam/rgb;"):
        open_source(bag)
    with pytest.raises(SourceError, match=r"no topic '/cam/depth'; topics in .*/imu \(sensor_msgs/msg/Imu, "
                                          r"0 messages\)"):
        open_source(bag, topic="/cam/depth")
    with pytest.raises(SourceError, match=r"topic '/imu' carries sensor_msgs/msg/Imu, not"):
        open_source(bag, topic="/imu")
    imu = [("/imu", "sensor_msgs/msg/Imu")]
    one = write_ros2_bag(tmp_path / "one", topics=["/cam/rgb"], extra_topics=imu)
    assert open_source(one).topic == "/cam/rgb"  # the only image topic needs no --topic
    none = write_ros2_bag(tmp_path / "none", topics=[], extra_topics=[("/imu", "sensor_msgs/msg/Imu")])
    with pytest.raises(SourceError, match=r"no sensor_msgs/msg/Image or .*CompressedImage topic; topics"):
        open_source(none)


def test_sources_that_cannot_be_read_say_why(tmp_path):
    with pytest.raises(SourceError, match="no such file"):
        open_source(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match=r"no image files \(.jpg"):
        open_source(tmp_path / "empty")
    write_folder(tmp_path / "frames")
    with pytest.raises(SourceError, match="--topic applies to bags only"):
        open_source(tmp_path / "frames", topic="/cam")
    (tmp_path / "x.db3").write_bytes(b"")
    with pytest.raises(SourceError, match=r"metadata\.yaml"):
        open_source(tmp_path / "x.db3")
    with pytest.raises(SourceError, match="every must be >= 1"):
        open_source(tmp_path / "frames", every=0)


def _rgb_of(body: bytes, params: dict[str, str]) -> np.ndarray:
    return images.decode(images.RawFrame(body, params["encoding"], int(params["width"]),
                                         int(params["height"])))


def test_raw_encodings_become_raw_frames_of_the_same_pixels():
    rng = np.random.default_rng(0)
    bgra = rng.integers(0, 256, (17, 19, 4), dtype=np.uint8)  # a frame's short side is 16 pixels at least
    bgr, grey = bgra[..., :3].copy(), bgra[..., 0].copy()
    # rows padded to 96 bytes: the step, not the width, says where a row starts
    def padded(a: np.ndarray) -> tuple[bytes, int]:
        rows = a.reshape(a.shape[0], -1).view(np.uint8)
        out = np.zeros((a.shape[0], 96), np.uint8)
        out[:, : rows.shape[1]] = rows
        return out.tobytes(), 96

    for encoding, pixels, want in (("bgr8", bgr, bgr), ("rgb8", bgr[..., ::-1].copy(), bgr),
                                   ("mono8", grey, grey), ("bgra8", bgra, bgra),
                                   ("rgba8", bgra[..., [2, 1, 0, 3]].copy(), bgra)):
        data, step = padded(pixels)
        body, params = image_to_raw(data, height=17, width=19, step=step, encoding=encoding)
        assert (params["width"], params["height"]) == ("19", "17")
        # The decoder's RGB of the same pixels as a PNG (alpha dropped there as here).
        assert np.array_equal(_rgb_of(body, params), images.decode(png(want))), encoding
    deep = rng.integers(0, 65536, (17, 19), dtype=np.uint16)
    for big in (False, True):
        raw = deep.astype(">u2" if big else "<u2").tobytes()
        body, params = image_to_raw(raw, height=17, width=19, step=38, encoding="mono16", is_bigendian=big)
        assert params["encoding"] == "mono16" and body == deep.astype("<u2").tobytes()
        assert np.array_equal(_rgb_of(body, params), images.decode(png(deep)))
    assert set(RAW_ENCODINGS) == {"rgb8", "bgr8", "mono8", "mono16", "rgba8", "bgra8"}


def test_raw_images_that_cannot_be_converted_say_why():
    with pytest.raises(SourceError, match=r"encoding 'bayer_rggb8' is not supported; supported: rgb8") as e:
        image_to_raw(b"\0" * 12, height=2, width=2, step=2, encoding="bayer_rggb8")
    assert e.value.status == 415  # as the service answers it
    with pytest.raises(SourceError, match=r"rgb8 image 4x2 needs 2 rows of >= 12 bytes \(step 12\); the "
                                          r"message holds 20 bytes") as e:
        image_to_raw(b"\0" * 20, height=2, width=4, step=12, encoding="rgb8")
    assert e.value.status == 422


@pytest.mark.parametrize("kind", DAMAGE)
def test_a_damaged_bag_is_a_source_error_naming_it(tmp_path, kind):
    bag = write_damaged_bag(kind, tmp_path)
    with pytest.raises(SourceError, match=r"cannot read the bag") as e:
        open_source(bag)
    assert str(bag) in str(e.value) and "\n" not in str(e.value)


def test_a_message_that_cannot_be_read_mid_bag_is_a_source_error(tmp_path, monkeypatch):
    import struct

    from rosbags.highlevel import AnyReader

    src = open_source(write_ros2_bag(tmp_path / "bag", topics=["/cam/rgb"]))

    def broken(self, raw, msgtype):
        raise struct.error("unpack requires a buffer of 4 bytes")

    monkeypatch.setattr(AnyReader, "deserialize", broken)
    with pytest.raises(SourceError, match=r"cannot read the bag .*: error: unpack requires"):
        list(src.frames())


def test_a_file_over_the_limit_is_not_read(tmp_path, monkeypatch):
    """Its size is checked first: a 1.5 GB file took the ingest to 4.8 GB (issue 19 item 3)."""
    write_folder(tmp_path / "frames")
    big = tmp_path / "frames" / "frame_0003_big.jpg"
    with big.open("wb") as f:
        f.truncate(1_500_000_000)  # sparse: no disk, and it must not be read either
    read: list[str] = []
    original = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: read.append(self.name) or original(self))
    frames = list(open_source(tmp_path / "frames", max_bytes=10 * 2**20).frames())
    assert [f.name for f in frames if f.oversize is not None] == [big.name]
    assert frames[4].oversize == 1_500_000_000 and frames[4].data == b""
    assert big.name not in read and len(read) == len(ROUTE)
    assert all(f.oversize is None for f in open_source(tmp_path / "frames").frames() if f.name != big.name)


def test_bag_messages_over_the_limit_are_not_posted(tmp_path):
    """A 2600x4000 rgb8 message (31 MB) is not even deserialised; a 2000x2000 one (12 MB) is converted and
    then found too large; the frames around them come as before."""
    sizes = [(240, 320), (4000, 2600), (240, 320), (2000, 2000), (240, 320)]
    bag = write_ros2_bag_with(tmp_path / "bag", sizes)
    frames = list(open_source(bag, max_bytes=10 * 2**20).frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert frames[1].oversize is not None and frames[1].oversize > 4000 * 2600 * 3 and frames[1].data == b""
    assert frames[3].oversize == 2000 * 2000 * 3 and frames[3].data == b""
    assert all(f.oversize is None and len(f.data) == 240 * 320 * 3 for f in (frames[0], frames[2], frames[4]))
