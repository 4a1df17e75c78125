"""Encoder benchmark (issues: front end, 24). Run: `make bench` or `cortexloc bench encoder-suite`.

Batch-1 latency and batch-16 throughput of the whole encoder (640x480 JPEG bytes -> decode, preprocess,
backbone, sLSBH codes) side by side, in the same run, with a bare forward of the same backbone on the
same runtime (random preprocessed tensors): the ratio is what counts on a noisy machine. The service
default (EfficientNet-Lite0 stage 5 on ONNX Runtime, dense projection) against issue 24's targets
(batch 16 >= 0.8x the bare forward, batch 1 <= 70 ms), the same on the torch reference, and AlexNet.
"""

from __future__ import annotations

from pathlib import Path

from benchmarks._common import RESULTS, write_json
from models.evaluation.bench import bench_encoder

CONFIGS = [
    {"backbone": "efficientnet-lite0-s5", "projection": "dense", "runtime": "onnxruntime"},
    {"backbone": "efficientnet-lite0-s5", "projection": "dense", "runtime": "torch"},
    {"backbone": "alexnet", "projection": "sparse", "runtime": "onnxruntime"},
]
TARGET_RATIO, TARGET_BATCH1_MS = 0.8, 70.0


def main(*, repeats: int, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "encoder.json"
    results = []
    for cfg in CONFIGS:
        r = bench_encoder(repeats=repeats, **cfg)
        r["met_ratio"] = r["ratio_to_bare"] >= TARGET_RATIO
        r["met_batch1"] = r["batch1_ms_median"] <= TARGET_BATCH1_MS
        results.append(r)
        st = r["batch16_stage_ms_median"]
        print(f"{r['encoder']} on {r['runtime']} ({cfg['projection']}): batch 1 "
              f"{r['batch1_ms_median']:.1f} ms; batch 16 {r['batch16_images_per_s']:.1f} img/s vs bare "
              f"forward "
              f"{r['bare_batch16_images_per_s']:.1f} img/s, ratio {r['ratio_to_bare']:.2f} (target >= "
              f"{TARGET_RATIO}); stages (ms) " + ", ".join(f"{k} {v:.1f}" for k, v in st.items()), flush=True)
    write_json(out.name, {"targets": {"ratio_to_bare": TARGET_RATIO, "batch1_ms": TARGET_BATCH1_MS},
                               "results": results}, out)

