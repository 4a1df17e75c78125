"""The encoder's stages one by one, and its ratio to the bare forward (issue 24).

Run: `cortexloc bench profile-encoder [--repeats 9] [--backbone efficientnet-lite0-s5]`; writes
benchmarks/results/profile_encoder.json. Not part of `make bench` (bench_encoder.py is the contract).

Per image, on one thread each, medians over `--repeats` batches of 16 640x480 JPEGs: header probe,
JPEG decode, the scan-data check `decode` runs before it, the decode as `Embedder.prepare` runs it,
resize (crop and squash), to-tensor + normalise;
then the forward of 16 in chunks of 1, 2, 4, 8 and 16 (why the encoder forwards chunks of 4), the
sLSBH hash of 16 rows and its x·P; then, interleaved, the whole encoder at batch 16 against the bare
forward: wall ratio, and CPU per batch (`time.process_time`, all threads) so the work beside the forward
shows without the machine's noise.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from benchmarks._common import RESULTS, write_json
from models.evaluation.bench import synthetic_jpegs
from models.frontend import images
from models.frontend.embedding import Embedder
from models.frontend.images import jpeg as jpeg_mod


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return float(np.median(out) * 1e3)


def main(*, repeats: int, backbone: str, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "profile_encoder.json"
    n, reps = 16, repeats
    enc = Embedder({"backbone": backbone, "slsbh": {"projection": "dense"}})
    jpegs = synthetic_jpegs(n)
    rgbs = [images.decode(b) for b in jpegs]
    per_image = {
        "probe": median_ms(lambda: [images.probe(b) for b in jpegs], reps) / n,
        "imdecode": median_ms(lambda: [cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR_RGB)
                                       for b in jpegs], reps) / n,
        "jpeg_scan_check": median_ms(lambda: [jpeg_mod._jpeg_check_scan_data(b) for b in jpegs], reps) / n,
        "decode": median_ms(lambda: [images.decode(b) for b in jpegs], reps) / n,
        "imdecode_reduced_2": median_ms(lambda: [cv2.imdecode(np.frombuffer(b, np.uint8),
                                                              cv2.IMREAD_REDUCED_COLOR_2) for b in jpegs],
                                        reps) / n,
    }
    for mode in images.MODES:
        per_image[f"preprocess_{mode}"] = median_ms(
            lambda mode=mode: [images.preprocess(r, mode=mode) for r in rgbs], reps) / n
    x = images.preprocess_batch(rgbs, mode=enc.conf["resize"])
    per_image["to_tensor_normalise"] = median_ms(
        lambda: images.preprocess_batch([np.ascontiguousarray(r[:224, :224]) for r in rgbs], mode="squash"),
        reps) / n
    enc.features(x)
    forward_16_by_chunk = {c: median_ms(lambda c=c: [enc.features(x[s:s + c]) for s in range(0, n, c)], reps)
                           for c in (1, 2, 4, 8, 16)}
    feats = enc.features(x)
    enc.hasher(feats)
    hash_16 = median_ms(lambda: enc.hasher(feats), reps)
    project_16 = median_ms(lambda: enc.hasher.project(feats), reps)
    for _ in range(2):
        enc.encode(jpegs)
    wall_enc, wall_bare, cpu_enc, cpu_bare = [], [], [], []
    for _ in range(reps):
        for wall, cpu, fn in ((wall_enc, cpu_enc, lambda: enc.encode(jpegs)),
                              (wall_bare, cpu_bare, lambda: enc.features(x))):
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    runs = {"encode_wall": wall_enc, "bare_wall": wall_bare, "encode_cpu": cpu_enc, "bare_cpu": cpu_bare}
    med = {k: float(np.median(v) * 1e3) for k, v in runs.items()}
    ratio = med["bare_wall"] / med["encode_wall"]
    beside = (med["encode_cpu"] - med["bare_cpu"]) / n
    print(f"{enc.identity} on {enc.describe()['runtime']}: per image (ms) "
          + ", ".join(f"{k} {v:.2f}" for k, v in per_image.items()), flush=True)
    chunks = ", ".join(f"{c}: {v:.1f}" for c, v in forward_16_by_chunk.items())
    print(f"forward of 16 in chunks (ms): {chunks}; hash of 16 {hash_16:.1f} ms (x·P {project_16:.1f})",
          flush=True)
    print(f"batch 16: encoder {med['encode_wall']:.1f} ms, bare forward {med['bare_wall']:.1f} ms, ratio "
          f"{ratio:.3f}; CPU {med['encode_cpu']:.1f} against {med['bare_cpu']:.1f} ms: {beside:.2f} ms per "
          "image beside the forward", flush=True)
    write_json(out.name, {"encoder": enc.identity, **enc.describe(), "repeats": reps,
                               "per_image_ms": per_image, "forward_16_by_chunk_ms": forward_16_by_chunk,
                               "hash_16_ms": hash_16, "project_16_ms": project_16, "batch16_ms": med,
                               "ratio_to_bare": ratio, "cpu_ms_per_image_beside_forward": beside}, out)

