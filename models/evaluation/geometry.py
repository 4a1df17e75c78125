"""Geometric verification measured on real images (issue 27 item 4; docs/results.md §12,
docs/design/science.md §12).

    cortexloc eval geometry --extractors orb,sift

Cases, each per extractor:

* the real rectified stereo pair of scikit-image (`stereo_motorcycle`, Middlebury 2014 "Motorcycle" at a
  quarter of its 2964 x 2000 size, with the calibration Middlebury publishes, scaled): the right view
  against the left, truth R = I and t along -x (X_right = X_left - baseline x);
* real photographs (scikit-image's) warped by known camera rotations (H = K R K^-1, a 0.9-width focal
  length): truth R, translation unobservable;
* unrelated pairs (every pair of different photographs, and each against the stereo view): a verified
  one is a false verification.

Reported: verified, inliers, rotation and translation-direction errors (degrees), false verifications,
the median milliseconds of a verification and of an extraction, and the median bytes of a stored
keyframe. scikit-image is a dev dependency: this module imports it only when it runs.
"""

from __future__ import annotations

import itertools
import json
import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from models.geometry import Camera, available, extract, pack, verify
from models.geometry.verify import rotation_angle

__all__ = ["PHOTOS", "ROTATIONS", "STEREO_FULL_WIDTH", "evaluate", "photo", "photo_camera", "rotation",
           "stereo", "warp"]

#: scikit-image photographs (scikit-image.org/docs/stable/api/skimage.data.html); `cat` is `chelsea`.
PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "camera", "coins", "moon", "brick", "gravel", "clock")
#: Known camera rotations (yaw, pitch, roll in degrees) the photographs are warped by.
ROTATIONS = ((5, 0, 0), (-10, 0, 0), (0, 6, 0), (0, 0, 10), (8, 4, 6))
#: Middlebury 2014 Motorcycle calibration (vision.middlebury.edu/stereo/data/scenes2014): full width,
#: focal length, the two principal points (cam0, cam1) and the shared cy.
STEREO_FULL_WIDTH = 2964
_STEREO = {"f": 3979.911, "cx0": 1244.772, "cx1": 1369.115, "cy": 1019.507}


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) R = Rz(roll) Rx(pitch) Ry(yaw), angles in degrees, camera axes (x right, y down, z ahead)."""
    y, p, r = (math.radians(a) for a in (yaw, pitch, roll))
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    return rz @ rx @ ry


def photo(name: str) -> np.ndarray:
    """A scikit-image photograph as (H, W, 3) uint8 RGB."""
    from skimage import data  # dev dependency
    img = getattr(data, name)()
    return np.ascontiguousarray(np.dstack([img] * 3) if img.ndim == 2 else img[..., :3])


def photo_camera(img: np.ndarray) -> Camera:
    """The camera a photograph is taken to have: focal length 0.9 x width, the centre as principal point."""
    h, w = img.shape[:2]
    return Camera(0.9 * w, 0.9 * w, w / 2, h / 2)


def warp(img: np.ndarray, camera: Camera, R: np.ndarray) -> np.ndarray:
    """What the camera sees after turning by R (X_query = R X_keyframe): img warped by K R K^-1."""
    H = camera.K @ R @ np.linalg.inv(camera.K)
    return cv2.warpPerspective(img, H, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)


def stereo() -> tuple[np.ndarray, np.ndarray, Camera, Camera]:
    """(left, right, left camera, right camera) of scikit-image's rectified Motorcycle pair."""
    from skimage import data  # dev dependency
    left, right, _ = data.stereo_motorcycle()
    s = left.shape[1] / STEREO_FULL_WIDTH
    f, cy = _STEREO["f"] * s, _STEREO["cy"] * s
    return left, right, Camera(f, f, _STEREO["cx0"] * s, cy), Camera(f, f, _STEREO["cx1"] * s, cy)


@dataclass
class _Tally:
    verified: int = 0
    cases: int = 0
    rot_err: list[float] | None = None
    inliers: list[int] | None = None

    def add(self, ok: bool, inliers: int, err: float | None) -> None:
        self.cases += 1
        self.verified += ok
        self.inliers = [*(self.inliers or []), inliers]
        if err is not None:
            self.rot_err = [*(self.rot_err or []), err]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def evaluate(extractors: tuple[str, ...] = ("orb", "sift"), max_n: int = 500) -> list[dict[str, Any]]:
    """One row per extractor (module docstring); times are medians over the calls of this run."""
    left, right, cam_l, cam_r = stereo()
    photos = {n: photo(n) for n in PHOTOS}
    out = []
    for kind in extractors:
        ext_ms, sizes, ver_ms = [], [], []

        def feats(img: np.ndarray, kind: str = kind, ext_ms: list[float] = ext_ms,
                  sizes: list[int] = sizes) -> Any:
            t0 = time.perf_counter()
            f = extract(img, kind, max_n)
            ext_ms.append((time.perf_counter() - t0) * 1e3)
            sizes.append(len(pack(f)))
            return f

        def check(q: Any, k: Any, cq: Camera | None = None, ck: Camera | None = None,
                  ver_ms: list[float] = ver_ms) -> Any:
            t0 = time.perf_counter()
            v = verify(q, k, cq, ck)
            ver_ms.append((time.perf_counter() - t0) * 1e3)
            return v

        fl, fr = feats(left), feats(right)
        sv = check(fr, fl, cam_r, cam_l)
        r_err = None if sv.rotation is None else round(rotation_angle(sv.rotation), 3)
        t_err = None if sv.translation is None else round(_angle(sv.translation, np.array([-1.0, 0, 0])), 3)
        stereo_row = {"verified": sv.verified, "inliers": sv.inliers, "model": sv.model,
                      "rotation_error_deg": r_err, "translation_error_deg": t_err}
        warped = _Tally()
        models: dict[str, int] = {}
        base = {n: feats(img) for n, img in photos.items()}
        for (n, img), angles in itertools.product(photos.items(), ROTATIONS):
            cam, R = photo_camera(img), rotation(*angles)
            v = check(feats(warp(img, cam, R)), base[n], cam, cam)
            models[str(v.model)] = models.get(str(v.model), 0) + 1
            err = None if v.rotation is None else rotation_angle(v.rotation @ R.T)
            warped.add(v.verified, v.inliers, err)
        unrelated = [*itertools.combinations([*base.values(), fl], 2)]
        false = [check(a, b) for a, b in unrelated]
        errs = warped.rot_err or [math.nan]
        out.append({
            "extractor": kind, "max": max_n, "stereo": stereo_row,
            "warps": {"pairs": warped.cases, "verified": warped.verified,
                      "median_inliers": int(np.median(warped.inliers or [0])),
                      "median_rotation_error_deg": round(float(np.median(errs)), 3),
                      "max_rotation_error_deg": round(float(np.max(errs)), 3), "models": models},
            "unrelated": {"pairs": len(unrelated), "false_verifications": sum(v.verified for v in false),
                          "max_inliers": max(v.inliers for v in false)},
            "verify_ms_median": round(float(np.median(ver_ms)), 2),
            "extract_ms_median": round(float(np.median(ext_ms)), 2),
            "bytes_per_keyframe_median": int(np.median(sizes)),
        })
    return out


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as the markdown table of docs/results.md §12."""
    head = ("| extractor | stereo: verified, inliers, model | stereo R err ° | stereo t err ° | "
            "warps verified | warp inliers (median) | warp R err ° (median / max) | unrelated: false / pairs "
            "(max inliers) | verify ms | extract ms | bytes / keyframe |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        s, w, u = r["stereo"], r["warps"], r["unrelated"]
        cells = [f"{r['extractor']} (max {r['max']})", f"{s['verified']}, {s['inliers']}, {s['model']}",
                 s["rotation_error_deg"], s["translation_error_deg"], f"{w['verified']} / {w['pairs']}",
                 w["median_inliers"], f"{w['median_rotation_error_deg']} / {w['max_rotation_error_deg']}",
                 f"{u['false_verifications']} / {u['pairs']} ({u['max_inliers']})", r["verify_ms_median"],
                 r["extract_ms_median"], r["bytes_per_keyframe_median"]]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    return "\n".join(lines)


def run(*, extractors: list[str] | None, max_features: int, as_json: bool) -> None:
    """Print the table of `evaluate` (every available extractor when None), and its rows as JSON too."""
    if extractors is None:
        extractors = [k for k in ("orb", "sift") if k in available()]
    rows = evaluate(tuple(extractors), max_features)
    print(table(rows))
    if as_json:
        print(json.dumps(rows, indent=1))

