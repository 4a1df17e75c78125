"""Benchmarks of the model stages, shared by `benchmarks/` and `cortexloc bench` (no timed asserts).

Timings on shared machines are noisy: report medians, and compare in ratios within one run.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from models import presets
from models.memory.temporal_memory import TemporalMemory
from storage.base.process import rss_bytes


def rss_mb() -> float:
    """Resident set size of this process in MiB (Linux /proc; 0.0 where unavailable)."""
    return rss_bytes() / 2**20


def random_sequence(n: int, columns: int, active: int, seed: int = 0) -> list[np.ndarray]:
    """n random SDRs of exactly `active` ones out of `columns`, each (active,) int64 sorted."""
    rng = np.random.Generator(np.random.PCG64(seed))
    return [np.sort(rng.choice(columns, active, replace=False)) for _ in range(n)]


def bench_tm(columns: int = 2048, cells: int = 4, active: int = 40, steps: int = 5000,
             preset: str = "cortexloc-grid", period: int = 0, seed: int = 0,
             overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Time `steps` learning steps of a Temporal Memory on a random SDR sequence.

    Args:
        columns, cells: columnDimensions and cellsPerColumn (override the preset's).
        active: ones per input SDR.
        steps: learning steps timed.
        preset: TM preset supplying the other parameters (caps, thresholds).
        period: repeat a random sequence of this length (0: never repeat, every step is novel).
        overrides: further TM parameters (e.g. smaller caps for `numenta-defaults`).

    Returns:
        ms_per_step_median, ms_per_step_p90, rss_growth_mb (after allocation and compilation),
        segments, synapses, bytes, and the parameters used.
    """
    params = presets.tm_params(preset, {**(overrides or {}), "columnDimensions": columns,
                                        "cellsPerColumn": cells})
    # Compile the kernels on a tiny memory first, so compilation is neither timed nor counted in RSS.
    warm = TemporalMemory(presets.TmOptions.of({**params, "columnDimensions": 64, "maxSegmentsPerCell": 2}))
    for x in random_sequence(20, 64, min(active, 8), seed):
        warm.compute(x, learn=True)
        warm.compute(x, learn=False)
    seq = random_sequence(period or steps, columns, active, seed + 1)
    tm = TemporalMemory(presets.TmOptions.of(params))
    rss0 = rss_mb()
    times = np.empty(steps)
    clock = time.perf_counter
    predicted = 0
    for i in range(steps):
        x = seq[i % len(seq)]
        t0 = clock()
        tm.compute(x, learn=True)
        times[i] = clock() - t0
        predicted += tm.context.stats.predicted_columns
    rss1 = rss_mb()
    size = tm.size()
    return {
        "ms_per_step_median": float(np.median(times) * 1e3),
        "ms_per_step_p90": float(np.percentile(times, 90) * 1e3),
        "rss_growth_mb": rss1 - rss0,
        "segments": size["segments"],
        "synapses": size["synapses"],
        "evictions": size["evictions"],
        "bytes": size["bytes"],
        "predicted_column_fraction": predicted / (steps * active),
        "config": {"columns": columns, "cells": cells, "active": active, "steps": steps,
                   "preset": preset, "period": period, "seed": seed, "overrides": overrides or {}},
    }


def synthetic_jpegs(n: int, width: int = 640, height: int = 480, seed: int = 0) -> list[bytes]:
    """n camera-sized JPEGs of smooth random scenes (encoded once, so decoding is real work)."""
    import cv2

    rng = np.random.Generator(np.random.PCG64(seed))
    out = []
    for _ in range(n):
        small = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
        img = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        out.append(buf.tobytes())
    return out


def make_png(width: int, height: int, zlib_data: bytes, *, colour: int = 2, depth: int = 8,
             interlace: int = 0, idat_chunks: int = 1) -> bytes:
    """A PNG with this IHDR whose IDAT chunks hold `zlib_data` split into `idat_chunks` pieces (the image
    data is not checked: hostile inputs for tests and benchmarks)."""
    import struct
    import zlib

    def chunk(ctype: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", zlib.crc32(ctype + data))

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    step = max(1, -(-len(zlib_data) // idat_chunks))
    idats = [chunk(b"IDAT", zlib_data[i:i + step]) for i in range(0, len(zlib_data), step)]
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + b"".join(idats) + chunk(b"IEND", b"")


def deflated_zeros(n_bytes: int) -> bytes:
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


def png_bomb(width: int, height: int, inflated_bytes: int, idat_chunks: int = 1) -> bytes:
    """An 8-bit RGB PNG whose image data is `inflated_bytes` deflated zeros, whatever its raster needs
    (a decompression bomb when that is more: issue 11's was 100x100 with ~9.6 GB in 9.8 MB)."""
    return make_png(width, height, deflated_zeros(inflated_bytes), idat_chunks=idat_chunks)


def bench_encoder(backbone: str = "alexnet", repeats: int = 15, threads: int = 1,
                  projection: str = "dense", runtime: str | None = None) -> dict[str, Any]:
    """Whole-encoder latency and throughput beside a bare forward of the same backbone on the same
    runtime, in the same run.

    The bare forward is the backbone alone (`Embedder.features`) on a preprocessed batch of 16 random
    tensors; measurements alternate between the two so machine noise hits both alike: the ratio is the
    figure that counts.

    Args:
        runtime: `models.frontend.runtimes.RUNTIMES` (None: the encoder's default).

    Returns:
        batch1_ms_median, batch16_images_per_s, bare_batch16_images_per_s, ratio_to_bare, per-stage
        medians at batch 16 (ms), the encoder identity, runtime and device.
    """
    from models.frontend.embedding import Embedder

    conf: dict[str, Any] = {"backbone": backbone, "torch_threads": threads,
                            "slsbh": {"projection": projection}}
    if runtime is not None:
        conf["runtime"] = runtime
    enc = Embedder(conf)
    jpegs = synthetic_jpegs(16)
    bare_in = np.random.default_rng(0).standard_normal((16, 3, 224, 224), np.float32)
    clock = time.perf_counter
    for _ in range(2):  # warm-up: allocators, kernels, thread pools
        enc.encode(jpegs[:1])
        enc.encode(jpegs)
        enc.features(bare_in)
    one, sixteen, bare = [], [], []
    stages: dict[str, list[float]] = {}
    for i in range(repeats):
        t0 = clock()
        enc.encode([jpegs[i % 16]])
        one.append(clock() - t0)
        t0 = clock()
        r = enc.encode(jpegs)
        sixteen.append(clock() - t0)
        for k, v in r.timings_ms.items():
            stages.setdefault(k, []).append(v)
        t0 = clock()
        enc.features(bare_in)
        bare.append(clock() - t0)
    enc_ips = 16 / float(np.median(sixteen))
    bare_ips = 16 / float(np.median(bare))
    return {
        "batch1_ms_median": float(np.median(one) * 1e3),
        "batch16_images_per_s": enc_ips,
        "bare_batch16_images_per_s": bare_ips,
        "ratio_to_bare": enc_ips / bare_ips,
        "batch16_stage_ms_median": {k: float(np.median(v)) for k, v in stages.items()},
        "encoder": enc.identity,
        **enc.describe(),
        # What a map on this backbone holds: the dense D x k float32 projection (a map gets the sparse
        # one where that would break its size budget, service/maps/projection.py).
        "feature_dim": enc.feature_dim,
        "k": int(enc.conf["slsbh"]["k"]),
        "dense_projection_bytes": enc.feature_dim * int(enc.conf["slsbh"]["k"]) * 4,
        "config": {"backbone": backbone, "repeats": repeats, "threads": threads, "image": "640x480 JPEG",
                   "projection": projection},
    }
