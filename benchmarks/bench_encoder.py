"""Encoder benchmark (issue: front end). Run: `make bench` or `python benchmarks/bench_encoder.py`.

Batch-1 latency and batch-16 throughput of the whole encoder (640x480 JPEG bytes -> sLSBH codes)
side by side, in the same run, with a bare conv1-conv3 forward on random tensors: the ratio is what
counts on a noisy machine. Dense and sparse projections, AlexNet; EfficientNet-Lite0 for reference.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from models.evaluation.bench import bench_encoder

CONFIGS = [
    {"backbone": "alexnet", "projection": "dense"},
    {"backbone": "alexnet", "projection": "sparse"},
    {"backbone": "efficientnet-lite0", "projection": "dense"},
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "encoder.json")
    args = ap.parse_args()
    results = []
    for cfg in CONFIGS:
        r = bench_encoder(repeats=args.repeats, **cfg)
        results.append(r)
        st = r["batch16_stage_ms_median"]
        print(f"{r['encoder']} ({cfg['projection']}): batch 1 {r['batch1_ms_median']:.1f} ms; batch 16 "
              f"{r['batch16_images_per_s']:.1f} img/s vs bare backbone "
              f"{r['bare_conv3_batch16_images_per_s']:.1f} img/s, ratio {r['ratio_to_bare']:.2f}; "
              "stages (ms) "
              + ", ".join(f"{k} {v:.1f}" for k, v in st.items()),
              flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
