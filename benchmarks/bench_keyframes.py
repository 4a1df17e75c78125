"""Keyframe extraction of large frames (issue 34 item 1): wall time and peak RSS growth of one
`service.maps.keyframes.extract_frame` (the decode and the features), then of one whole post of the
frame to a map with keyframes, each in a fresh process.

Run: `cortexloc bench keyframes [--out PATH]`. Writes benchmarks/results/keyframes.json (or
`--out`) and prints one line per case.

Frames: a 5000 x 5000 JPEG (SIFT), a 4000 x 3000 (12 MP) JPEG (SIFT) and a 5000 x 5000 JPEG (ORB), all
of the same synthetic texture (a natural image tiled, with noise at several scales, so every scale has
corners, as a real scene does), quality 90. Each case runs in its own Python process, which reads the
JPEG from a file: its peak RSS growth is the kernel's high-water mark (VmHWM) after the extraction less
its RSS (VmRSS) just before, so nothing of the frame's making is counted. Decode limits: the service's
defaults but for the pixel cap, raised to take 25 MP. The post: the app in process (`TestClient`,
default settings, AlexNet with random weights and sLSBH k = 16 as the service tests run it), a map with
`keyframes: {"features": KIND}`, two small frames posted first, then the large one (learned); its
time is the request's, its RSS growth the whole process's (the encoder's decode of the frame included).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from benchmarks._common import write_json

CASES = (("5000x5000", 5000, 5000, "sift"), ("4000x3000", 4000, 3000, "sift"),
         ("5000x5000", 5000, 5000, "orb"))

_CHILD = r"""
import json, sys, time
from pathlib import Path
from models.frontend import images
from service.maps.keyframes import extract_frame

def status(name):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(name + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(name)

body = Path(sys.argv[1]).read_bytes()
kind = sys.argv[2]
decode = lambda b, **how: images.decode(b, max_bytes=64 << 20, max_pixels=30_000_000, **how)
import cv2, numpy as np
small = cv2.imencode(".jpg", np.full((128, 128, 3), 128, np.uint8))[1].tobytes()
extract_frame(decode, small, {"features": kind, "max": 500}, None)  # imports and OpenCV's first call
rss = status("VmRSS")
t0 = time.perf_counter()
q = extract_frame(decode, body, {"features": kind, "max": 500}, None)
dt = time.perf_counter() - t0
print(json.dumps({"seconds": dt, "peak_growth_mb": (status("VmHWM") - rss) / 2**20,
                  "kept": len(q.features), "size": list(q.features.size)}))
"""


_POST_CHILD = r"""
import json, sys, tempfile, time
from pathlib import Path
import cv2, numpy as np
from fastapi.testclient import TestClient
from service.app import create_app
from service.frontend import build_embedder
from service.settings import Settings

def status(name):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(name + ":"):
            return int(line.split()[1]) * 1024

body, kind = Path(sys.argv[1]).read_bytes(), sys.argv[2]
small = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (480, 640, 3), np.uint8))[1].tobytes()
jpeg = {"Content-Type": "image/jpeg"}
with tempfile.TemporaryDirectory() as d:
    app = create_app(Settings(data_dir=Path(d), backbone="alexnet"),
                     encoder_factory=lambda s: build_embedder(s, slsbh={"k": 16}))
    with TestClient(app) as c:
        assert c.post("/v1/maps", json={"map_id": "kf", "keyframes": {"features": kind}}).status_code == 201
        for _ in range(2):
            assert c.post("/v1/maps/kf/observations", content=small, headers=jpeg).status_code == 200
        rss = status("VmRSS")
        t0 = time.perf_counter()
        r = c.post("/v1/maps/kf/observations", content=body, headers=jpeg)
        dt = time.perf_counter() - t0
        assert r.status_code == 200, r.text
        print(json.dumps({"seconds": dt, "peak_growth_mb": (status("VmHWM") - rss) / 2**20,
                          "features_ms": r.json()["timings_ms"]["features"]}))
"""


def texture(w: int, h: int) -> np.ndarray:
    """(h, w, 3) uint8: a natural image tiled at 512 px with noise at 2, 8 and 32 px scales."""
    from skimage import data

    rng = np.random.default_rng(0)
    tile = data.astronaut()
    img = np.tile(tile, (h // 512 + 1, w // 512 + 1, 1))[:h, :w].astype(np.float32)
    for scale, amp in ((2, 12.0), (8, 18.0), (32, 24.0)):
        n = rng.normal(0, amp, (h // scale + 1, w // scale + 1)).astype(np.float32)
        img += cv2.resize(n, (w, h), interpolation=cv2.INTER_LINEAR)[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


def main(*, out: Path | None) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, w, h, kind in CASES:
            path = Path(tmp) / f"{name}.jpg"
            if not path.exists():
                ok, buf = cv2.imencode(".jpg", cv2.cvtColor(texture(w, h), cv2.COLOR_RGB2BGR),
                                       [cv2.IMWRITE_JPEG_QUALITY, 90])
                assert ok
                path.write_bytes(buf.tobytes())
            for what, child in (("extract", _CHILD), ("post", _POST_CHILD)):
                out = subprocess.run([sys.executable, "-c", child, str(path), kind], capture_output=True,
                                     text=True, check=True)
                row = {"frame": name, "jpeg_mib": round(path.stat().st_size / 2**20, 2), "features": kind,
                       "measured": what, **json.loads(out.stdout.strip().splitlines()[-1])}
                print(f"{name} {kind} {what}: {row['seconds']:.2f} s, "
                      f"peak RSS +{row['peak_growth_mb']:.0f} MB "
                      f"({row['jpeg_mib']} MiB)", flush=True)
                rows.append(row)
    write_json("keyframes.json", {"cases": rows}, out)

