"""The backbone's forward on a GPU beside the CPU (issue 40, item 4), in one process: torch on the CPU at
this machine's thread counts, torch on CUDA in fp32 and in fp16 autocast, at batch 1, 16 and 64, repeats
interleaved; and which ONNX Runtime providers are installed (the service's CUDA path,
`CORTEXLOC_DEVICE=cuda`, needs onnxruntime-gpu's CUDAExecutionProvider).

Run: `cortexloc bench gpu [--repeats 20] [--backbones efficientnet-lite0]`. Writes
benchmarks/results/gpu.json: per backbone and runtime the median ms per batch and images/s, the ratio to
torch on the CPU with this machine's 2-core budget (`--cpu-threads`, default 2: the development machine),
and the largest descriptor difference to the CPU's on the same input. Exits with a message where CUDA is
not available (the CPU-only development machines and CI).
"""

from __future__ import annotations

import copy
import os
import time
from typing import Any

import numpy as np

from benchmarks._common import machine, quick_mode, write_json
from models.frontend import backbones as registry
from models.frontend import weights

BATCHES = (1, 16, 64)


def _timed(f: Any, x: Any, sync: Any) -> float:
    t0 = time.perf_counter()
    f(x)
    sync()
    return time.perf_counter() - t0


def bench_backbone(name: str, cpu_threads: list[int], repeats: int) -> dict[str, Any]:
    import torch

    bb = registry.get(name)({"weights_path": weights.find_alexnet(), "random_seed": 0})
    rng = np.random.default_rng(0)
    xs = {n: rng.standard_normal((n, 3, 224, 224), np.float32) for n in BATCHES}
    gpu = torch.device("cuda")

    def on_cpu(threads: int) -> Any:
        @torch.inference_mode()
        def f(x: np.ndarray) -> np.ndarray:
            torch.set_num_threads(threads)
            return bb.describe(torch.from_numpy(x)).numpy()
        return f

    def on_gpu(half: bool) -> Any:
        model = copy.deepcopy(bb.module).to(gpu).eval()
        describe = getattr(model, "descriptor", None) or model

        @torch.inference_mode()
        def f(x: np.ndarray) -> np.ndarray:
            t = torch.from_numpy(x).to(gpu)
            with torch.autocast("cuda", dtype=torch.float16, enabled=half):
                y = describe(t)
            return y.float().cpu().numpy()
        return f

    runs = {f"torch-cpu-{t}t": on_cpu(t) for t in cpu_threads}
    runs["torch-cuda-fp32"] = on_gpu(False)
    runs["torch-cuda-fp16"] = on_gpu(True)
    ref = runs[f"torch-cpu-{cpu_threads[0]}t"](xs[16])
    diff = {k: float(np.abs(np.asarray(f(xs[16])).reshape(ref.shape) - ref).max()) for k, f in runs.items()}
    for f in runs.values():  # warm-up: cuDNN's algorithm choice, the allocator
        for x in xs.values():
            f(x)
    times: dict[str, dict[int, list[float]]] = {k: {n: [] for n in BATCHES} for k in runs}
    for _ in range(repeats):
        for k, f in runs.items():
            sync = torch.cuda.synchronize if "cuda" in k else (lambda: None)
            for n, x in xs.items():
                if "cpu" in k and n == 64 and repeats > 3 and _ % 3:
                    continue  # the CPU at batch 64 is slow: every third repeat
                times[k][n].append(_timed(f, x, sync))
    base = float(np.median(times[f"torch-cpu-{cpu_threads[0]}t"][16])) / 16
    out: dict[str, Any] = {}
    for k in runs:
        out[k] = {f"batch{n}_ms": float(np.median(times[k][n]) * 1e3) for n in BATCHES}
        out[k].update({f"batch{n}_images_per_s": n / float(np.median(times[k][n])) for n in BATCHES})
        out[k]["batch16_vs_cpu"] = base / (float(np.median(times[k][16])) / 16)
        out[k]["max_abs_diff_to_cpu"] = diff[k]
    return {"backbone": name, "arch": bb.arch, "weights": bb.weights_id,
            "device": torch.cuda.get_device_name(0), "runtimes": out}


def main(*, repeats: int, cpu_threads: list[int] | None, backbones: list[str] | None,
         quick: bool) -> None:
    if cpu_threads is None:
        cpu_threads = [2, os.cpu_count() or 2]
    import torch

    if not torch.cuda.is_available():
        raise SystemExit("no CUDA device: this benchmark runs on a GPU machine (docs/benchmarks.md)")
    try:
        import onnxruntime as ort
        providers = ort.get_available_providers()
    except ImportError:
        providers = []
    repeats = 3 if quick_mode(quick) else repeats
    results = []
    for name in backbones or registry.names():
        r = bench_backbone(name, cpu_threads, repeats)
        results.append(r)
        for k, v in r["runtimes"].items():
            print(f"{name} {k}: " + ", ".join(f"b{n} {v[f'batch{n}_ms']:.1f} ms "
                                               f"({v[f'batch{n}_images_per_s']:.0f} img/s)" for n in BATCHES)
                  + f"; b16 {v['batch16_vs_cpu']:.1f}x cpu-{cpu_threads[0]}t, "
                  f"max |Δ| {v['max_abs_diff_to_cpu']:.1e}", flush=True)
    print("onnxruntime providers:", providers)
    write_json("gpu.json", {"machine": machine(), "torch": torch.__version__, "repeats": repeats,
                            "onnxruntime_providers": providers, "results": results})

