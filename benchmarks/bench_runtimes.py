"""Backbone runtimes side by side (issue 24): torch (the reference) against the same network exported to
ONNX on ONNX Runtime, and on OpenVINO where it is installed, for every registered backbone at batch 1
and batch 16, in one process, repeats interleaved so machine noise hits all alike.

Run: `cortexloc bench runtimes [--threads 1] [--repeats 7]` (`--quick`: 2 repeats). Writes
benchmarks/results/runtimes.json: per backbone and runtime the median ms at batch 1, images/s at batch
16, the ratio to torch at batch 16, and the largest descriptor difference to torch on the same input.
OpenVINO is not a dependency (`pip install openvino` to include it); it reads the same ONNX file.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from benchmarks._common import quick_mode, write_json
from models.frontend import backbones as registry
from models.frontend import runtimes, weights


def _openvino(model: bytes, threads: int) -> Callable[[np.ndarray], np.ndarray] | None:
    try:
        import openvino as ov
    except ImportError:
        return None
    core = ov.Core()
    compiled = core.compile_model(core.read_model(model=model), "CPU",
                                  {"INFERENCE_NUM_THREADS": threads, "PERFORMANCE_HINT": "LATENCY",
                                   "INFERENCE_PRECISION_HINT": "f32"})
    return lambda x: compiled(x)[0]


def bench_backbone(name: str, threads: int, repeats: int) -> dict[str, Any]:
    import torch

    torch.set_num_threads(threads)
    bb = registry.get(name)({"weights_path": weights.find_alexnet(), "random_seed": 0})
    runs: dict[str, Callable[[np.ndarray], np.ndarray]] = {
        "torch": runtimes.TorchRunner(bb.describe),
        "onnxruntime": runtimes.make_runner(bb, "onnxruntime", "cpu", threads,
                                            weights.default_cache_dir() / "onnx"),
    }
    ov = _openvino(runtimes.onnx_model(bb, weights.default_cache_dir() / "onnx")[0], threads)
    if ov is not None:
        runs["openvino"] = ov
    rng = np.random.default_rng(0)
    x1 = rng.standard_normal((1, 3, 224, 224), np.float32)
    x16 = rng.standard_normal((16, 3, 224, 224), np.float32)
    ref = runs["torch"](x16)
    diff = {k: float(np.abs(np.asarray(f(x16)) - ref).max()) for k, f in runs.items()}  # also warms up
    times: dict[str, dict[int, list[float]]] = {k: {1: [], 16: []} for k in runs}
    for _ in range(repeats):
        for k, f in runs.items():
            for n, x in ((1, x1), (16, x16)):
                t0 = time.perf_counter()
                f(x)
                times[k][n].append(time.perf_counter() - t0)
    torch16 = float(np.median(times["torch"][16]))
    out = {}
    for k in runs:
        b16 = float(np.median(times[k][16]))
        out[k] = {"batch1_ms": float(np.median(times[k][1]) * 1e3), "batch16_images_per_s": 16 / b16,
                  "batch16_vs_torch": torch16 / b16, "max_abs_diff_to_torch": diff[k]}
    return {"backbone": name, "arch": bb.arch, "weights": bb.weights_id, "runtimes": out}


def main(*, threads: int, repeats: int, backbones: list[str] | None, quick: bool) -> None:
    repeats = 2 if quick_mode(quick) else repeats
    results = []
    for name in backbones or registry.names():
        r = bench_backbone(name, threads, repeats)
        results.append(r)
        for k, v in r["runtimes"].items():
            print(f"{name} {k}: batch 1 {v['batch1_ms']:.1f} ms, batch 16 "
                  f"{v['batch16_images_per_s']:.1f} img/s ({v['batch16_vs_torch']:.2f}x torch), "
                  f"max |Δ| {v['max_abs_diff_to_torch']:.1e}", flush=True)
    write_json("runtimes.json", {"threads": threads, "repeats": repeats, "results": results})

