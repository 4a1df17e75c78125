"""Fixtures shared by the service tests and the benchmark smoke tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def tiny_default_preset(monkeypatch):
    """`cortexloc-default` shrunk to 128 columns and k = 64: the real code paths on a small map (the
    real TM and 64,896 x 1,024 projection would cost seconds and 266 MB per map)."""
    from models import presets

    tiny = {"description": "tiny default for tests",
            "tm": {**presets.confs["cortexloc-default"]["tm"], "columnDimensions": 128,
                   "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16, "maxNewSynapseCount": 8,
                   "activationThreshold": 4, "minThreshold": 2},
            "slsbh": {**presets.confs["cortexloc-default"]["slsbh"], "k": 64}}
    monkeypatch.setitem(presets.confs, "cortexloc-default", tiny)


def _png_chunk(ctype: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", zlib.crc32(ctype + data))


def _make_png(width: int, height: int, zlib_data: bytes, *, colour: int = 2, depth: int = 8,
              interlace: int = 0, idat_chunks: int = 1) -> bytes:
    """A PNG with this IHDR whose IDAT chunks hold `zlib_data` split into `idat_chunks` pieces."""
    import struct

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    step = max(1, -(-len(zlib_data) // idat_chunks))
    idats = [_png_chunk(b"IDAT", zlib_data[i:i + step]) for i in range(0, len(zlib_data), step)]
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + b"".join(idats) + _png_chunk(b"IEND", b"")


def _deflated_zeros(n_bytes: int) -> bytes:
    """zlib stream of `n_bytes` zeros at a real bomb's ratio (~1,000:1), built in milliseconds: each MiB
    is compressed independently (full flush), so one compressed MiB is repeated, then the stream ends
    with an empty final block and the Adler-32 of all the zeros."""
    import zlib

    mib = 1 << 20
    block = bytes(mib)
    c = zlib.compressobj(9)
    head = c.compress(b"") + c.flush(zlib.Z_FULL_FLUSH)  # the 2-byte zlib header
    piece = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    adler = 1
    for _ in range(n_bytes // mib):
        adler = zlib.adler32(block, adler)
    rest = bytes(n_bytes % mib)
    tail = c.compress(rest) + c.flush(zlib.Z_FULL_FLUSH)
    adler = zlib.adler32(rest, adler)
    return head + piece * (n_bytes // mib) + tail + b"\x03\x00" + adler.to_bytes(4, "big")


@pytest.fixture
def png_bomb():
    """`png_bomb(width, height, inflated_bytes, idat_chunks=1) -> bytes`: an 8-bit RGB PNG whose image
    data is `inflated_bytes` deflated zeros, whatever its raster needs (a decompression bomb when more)."""
    def build(width: int, height: int, inflated_bytes: int, idat_chunks: int = 1) -> bytes:
        return _make_png(width, height, _deflated_zeros(inflated_bytes), idat_chunks=idat_chunks)
    return build


@pytest.fixture
def make_png():
    """`make_png(width, height, zlib_data, colour=2, depth=8, interlace=0, idat_chunks=1) -> bytes`."""
    return _make_png
