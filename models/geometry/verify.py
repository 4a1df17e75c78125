"""Is a revisit candidate the same scene, and how is the camera placed relative to it
(docs/design/science.md §12.2–§12.3)?

Ratio-test matching, RANSAC fits of a homography H and a fundamental matrix F, model selection between
them by Torr's GRIC, then, with both frames' cameras known, the relative rotation and translation
direction (essential matrix and `recoverPose` for F, the homography's decomposition for H).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from models.geometry.features import NORMS, Features

__all__ = ["Camera", "Verification", "camera_problems", "gric", "is_rotation", "match", "quaternion",
           "verify"]

#: Lowe's ratio: a match is kept when its best distance is below this fraction of the second best.
RATIO = 0.8
#: A verified revisit needs at least this many inliers of the selected model and this inlier ratio
#: (inliers / ratio-test matches). docs/results.md §12: unrelated real pairs reach at most 14 inliers
#: with ORB, related ones 100+.
MIN_INLIERS = 25
MIN_INLIER_RATIO = 0.25
#: RANSAC's threshold in pixels (the reprojection error of H, the epipolar distance of F), at native
#: resolution.
RANSAC_PX = 2.0
#: GRIC's keypoint noise sigma in pixels. docs/results.md §12: on the 45 rotation warps and the stereo
#: pair, sigma 1.5 and 2.0 chose H for every warp and F for the stereo pair with ORB and SIFT; 1.0 sent 4
#: of the 45 ORB warps to F (ORB's keypoints from coarse pyramid levels are noisier than a pixel), where
#: the essential matrix of a pure rotation is degenerate (one came out 175 degrees wrong). Estimating
#: sigma per pair from F's residuals was worse still: F, underdetermined on a rotation, absorbs the noise.
SIGMA_PX = 1.5
#: The inliers must cover at least this fraction of each frame (their convex hull), and a homography's
#: linear part must keep orientation and scale within this factor: an H that folds the keyframe onto a
#: line fits repeated texture (bricks against a rocket's gantry, with 49 "inliers") and is no revisit.
MIN_SPREAD = 0.02
MAX_SCALE = 10.0
#: A camera makes geometric sense for a frame whose longer side is L pixels when its focal lengths are
#: within FOCAL_RANGE times L (a 170-degree fisheye's is ~0.1 L, a 1-degree telephoto's ~57 L... at 50 L
#: the view is 1.1 degrees wide), its principal point is inside the frame, and its distortion, undone
#: and done again, brings a grid over the frame back within ROUND_TRIP_PX (a distortion OpenCV cannot
#: invert there makes every normalised point, and so the pose, wrong; docs/design/science.md §12.3).
FOCAL_RANGE = (0.05, 50.0)
ROUND_TRIP_PX = 0.5
#: How far from orthonormal (R R^T - I, det R - 1) a rotation may be: numerical noise (and the 6 decimals a
#: logged one keeps) pass, a NaN, zero or scaled matrix does not.
ROTATION_TOLERANCE = 1e-3
#: The iterations of `Camera.normalise`'s undistortion (OpenCV's default of 5 leaves strong real lenses,
#: k1 ~ -0.4 at a wide frame's corners, pixels off).
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
#: A homography whose inliers a pure rotation also explains (this fraction of them within RANSAC_PX)
#: has no translation to tell: the direction is unobservable (a rotation, or a plane far away).
ROTATION_ONLY = 0.9


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels of the native frame, OpenCV's distortion (k1, k2, p1, p2[, k3 ...])."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @property
    def K(self) -> np.ndarray:  # noqa: N802  (the matrix's name)
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float64)

    def normalise(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) pixels -> (n, 2) undistorted normalised image coordinates."""
        dist = np.array(self.distortion, np.float64) if self.distortion else np.zeros(4)
        return cv2.undistortPoints(xy.reshape(-1, 1, 2).astype(np.float64), self.K, dist,
                                   criteria=_UNDISTORT).reshape(-1, 2)

    def project(self, normalised: np.ndarray) -> np.ndarray:
        """(n, 2) undistorted normalised image coordinates -> (n, 2) pixels (the inverse of `normalise`)."""
        dist = np.array(self.distortion, np.float64) if self.distortion else np.zeros(4)
        rays = np.c_[normalised, np.ones(len(normalised))].reshape(-1, 1, 3)
        out, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), self.K, dist)
        return out.reshape(-1, 2)


def camera_problems(camera: Camera, size: tuple[int, int]) -> list[tuple[str, str]]:
    """What makes `camera` no camera of a (width, height) frame (FOCAL_RANGE, ROUND_TRIP_PX), as
    (field, message) pairs with field one of fx, fy, cx, cy, distortion; [] for a sensible one."""
    w, h = size
    side = max(w, h)
    lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    out = []
    values = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
    for name, v in values.items():
        if not math.isfinite(v):
            out.append((name, f"{v} is not finite"))
    for name in ("fx", "fy"):
        if math.isfinite(values[name]) and not lo <= values[name] <= hi:
            out.append((name, f"{values[name]:g} px is outside {FOCAL_RANGE[0]:g}..{FOCAL_RANGE[1]:g} times "
                              f"the frame's longer side ({side} px): {lo:g}..{hi:g} px"))
    for name, extent in (("cx", w), ("cy", h)):
        if math.isfinite(values[name]) and not 0 <= values[name] <= extent:
            out.append((name, f"{values[name]:g} px is outside the {w}x{h} frame (0..{extent})"))
    if not all(math.isfinite(d) for d in camera.distortion):
        out.append(("distortion", "coefficients must be finite"))
    if out or not camera.distortion:
        return out
    gx, gy = np.meshgrid(np.linspace(0, w, 9), np.linspace(0, h, 9))
    grid = np.c_[gx.ravel(), gy.ravel()]
    with np.errstate(all="ignore"):
        try:
            back = camera.project(camera.normalise(grid))
            err = float(np.max(np.linalg.norm(back - grid, axis=1)))
        except cv2.error:
            err = math.inf
    if not err <= ROUND_TRIP_PX:  # NaN too
        moved = f"by up to {err:.3g} px" if math.isfinite(err) else "off any finite position"
        out.append(("distortion", f"undistorting and distorting again moves points of the frame {moved} (at "
                                  f"most {ROUND_TRIP_PX:g} px): OpenCV cannot invert it there"))
    return out


@dataclass(frozen=True)
class Verification:
    """The outcome of one verification (docs/design/service.md §1.2, `place.verification`).

    Attributes:
        verified: the selected model has >= MIN_INLIERS inliers and >= MIN_INLIER_RATIO of the matches.
        matches: ratio-test matches. inliers: of the selected model. inlier_ratio: inliers / matches.
        model: `homography` | `fundamental` (GRIC's choice), None when nothing could be fitted.
        rotation: (3, 3) R, and translation: (3,) unit t, with X_query = R X_keyframe + t (camera frames);
            None without cameras (rotation) or where it is unobservable (translation, a homography
            of a pure rotation).
        reason: why it is not verified or has no pose (`too-small`, `too-few-features`,
            `too-few-matches`, `too-few-inliers`, `degenerate`, `no-pose`: with both cameras no finite
            rotation came out, `geometry-failed`: OpenCV or numpy failed on the pair, `no-camera`,
            `translation-unobservable`), else None.
    """

    verified: bool
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    model: str | None = None
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    reason: str | None = None

    @property
    def rotation_deg(self) -> float | None:
        """The rotation's angle in degrees."""
        return None if self.rotation is None else rotation_angle(self.rotation)


def rotation_angle(R: np.ndarray) -> float:
    """The angle of rotation matrix `R` (3, 3) in degrees."""
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w), w >= 0, of rotation matrix `R` (3, 3)."""
    m = np.asarray(R, np.float64)
    w = math.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return x / n, y / n, z / n, w / n


def match(a: Features, b: Features, ratio: float = RATIO) -> np.ndarray:
    """(m, 2) int indices (i in a, j in b) of the matches that pass Lowe's ratio test."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    knn = cv2.BFMatcher(NORMS[a.kind]).knnMatch(a.desc, b.desc, k=2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn
             if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    return np.array(pairs, np.int64).reshape(-1, 2)


def _sampson_sq(F: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n,) squared Sampson distances of q^T F p = 0 (pixels^2)."""
    ph, qh = np.c_[p, np.ones(len(p))], np.c_[q, np.ones(len(q))]
    Fp, Ftq = ph @ F.T, qh @ F
    num = np.einsum("ij,ij->i", qh, Fp) ** 2
    return num / np.maximum(Fp[:, 0] ** 2 + Fp[:, 1] ** 2 + Ftq[:, 0] ** 2 + Ftq[:, 1] ** 2, 1e-12)


def _transfer_sq(H: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n,) squared transfer errors |q - H p|^2 (pixels^2)."""
    hp = np.c_[p, np.ones(len(p))] @ H.T
    w = np.where(np.abs(hp[:, 2:]) < 1e-12, 1e-12, hp[:, 2:])
    return np.sum((q - hp[:, :2] / w) ** 2, axis=1)


def gric(errors_sq: np.ndarray, *, d: int, k: int, sigma: float = SIGMA_PX, r: int = 4) -> float:
    """Torr's Geometric Robust Information Criterion (docs/design/science.md §12.2): the robust residual
    sum plus the penalties of the model's dimension `d` (H: 2, F: 3) and its parameters `k` (H: 8, F: 7),
    for `r` = 4 observed coordinates per correspondence. Lower is better."""
    n = len(errors_sq)
    rho = np.minimum(errors_sq / sigma**2, 2.0 * (r - d))
    return float(rho.sum() + math.log(r) * d * n + math.log(r * n) * k)


def verify(query: Features, keyframe: Features, query_camera: Camera | None = None,
           keyframe_camera: Camera | None = None, *, min_inliers: int = MIN_INLIERS,
           min_inlier_ratio: float = MIN_INLIER_RATIO) -> Verification:
    """Verify that `query` sees `keyframe`'s scene (docs/design/science.md §12.2–§12.3).

    Args:
        query, keyframe: the two frames' features, of one extractor.
        query_camera, keyframe_camera: each frame's intrinsics; with both, the relative pose.
        min_inliers, min_inlier_ratio: what a verified revisit needs.

    Returns:
        Verification; never raises on frames that cannot be verified (the reason says why), nor where
        the fits fail (OpenCV's "SVD did not converge" on points a wild distortion threw far away:
        `geometry-failed`). With both cameras a verified answer has a finite rotation, else it is not
        verified (`no-pose`): a pose graph cannot take a closure without one.
    """
    if query.kind != keyframe.kind:
        raise ValueError(f"features of {query.kind} and {keyframe.kind} cannot be matched")
    try:
        with np.errstate(all="ignore"):  # non-finite points are caught below, not warned about
            return _verify(query, keyframe, query_camera, keyframe_camera, min_inliers, min_inlier_ratio)
    except (cv2.error, np.linalg.LinAlgError, ArithmeticError):
        return Verification(False, reason="geometry-failed")


def _verify(query: Features, keyframe: Features, query_camera: Camera | None, keyframe_camera: Camera | None,
            min_inliers: int, min_inlier_ratio: float) -> Verification:
    """`verify` without its guard against the fits' failures."""
    if query.too_small or keyframe.too_small:
        return Verification(False, reason="too-small")
    if min(len(query), len(keyframe)) < min_inliers:
        return Verification(False, reason="too-few-features")
    pairs = match(keyframe, query)
    m = len(pairs)
    if m < max(min_inliers, 8):
        return Verification(False, matches=m, reason="too-few-matches")
    p = keyframe.xy[pairs[:, 0]].astype(np.float64)
    q = query.xy[pairs[:, 1]].astype(np.float64)
    H, mask_h = cv2.findHomography(p, q, cv2.RANSAC, RANSAC_PX, maxIters=2000, confidence=0.999)
    F, mask_f = cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, RANSAC_PX, 0.999)
    if F is not None and F.shape != (3, 3):  # several 7-point solutions: not one model
        F = None
    if H is None and F is None:
        return Verification(False, matches=m, reason="too-few-inliers")
    # GRIC over every match (its robust cap scores outliers alike for both): H where the scene is a
    # rotation or a plane (F is then underdetermined, and E's pose meaningless), F otherwise.
    scores = {}
    if H is not None:
        scores["homography"] = gric(_transfer_sq(H, p, q), d=2, k=8)
    if F is not None:
        scores["fundamental"] = gric(_sampson_sq(F, p, q), d=3, k=7)
    model = min(scores, key=scores.__getitem__)
    inl = (mask_h if model == "homography" else mask_f).ravel().astype(bool)
    n_in = int(inl.sum())
    base = {"matches": m, "inliers": n_in, "inlier_ratio": n_in / m, "model": model}
    if n_in < min_inliers or n_in / m < min_inlier_ratio:
        return Verification(False, **base, reason="too-few-inliers")
    if _degenerate(H if model == "homography" else None, p[inl], q[inl], keyframe.size, query.size):
        return Verification(False, **base, reason="degenerate")
    if query_camera is None or keyframe_camera is None:
        return Verification(True, **base, reason="no-camera")
    nk, nq = keyframe_camera.normalise(p[inl]), query_camera.normalise(q[inl])
    f_px = (query_camera.fx + query_camera.fy) / 2
    R, t = _pose_h(nk, nq, f_px) if model == "homography" else _pose_e(nk, nq, f_px)
    if not is_rotation(R) or (t is not None and not np.all(np.isfinite(t))):
        return Verification(False, **base, reason="no-pose")
    return Verification(True, **base, rotation=R, translation=t,
                        reason=None if t is not None else "translation-unobservable")


def is_rotation(R: np.ndarray | None) -> bool:
    """`R` is a finite (3, 3) proper rotation (orthonormal, determinant 1, within ROTATION_TOLERANCE)."""
    if R is None or R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    return bool(np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOLERANCE)
                and abs(np.linalg.det(R) - 1) < ROTATION_TOLERANCE)


def _degenerate(H: np.ndarray | None, p: np.ndarray, q: np.ndarray, size_p: tuple[int, int],
                size_q: tuple[int, int]) -> bool:
    """The inliers cover less than MIN_SPREAD of either frame, or the homography mirrors, collapses or
    blows up the keyframe (its linear part's determinant outside [1 / MAX_SCALE^2, MAX_SCALE^2])."""
    for pts, (w, h) in ((p, size_p), (q, size_q)):
        if cv2.contourArea(cv2.convexHull(pts.astype(np.float32))) < MIN_SPREAD * w * h:
            return True
    if H is None:
        return False
    det = float(np.linalg.det(H[:2, :2] / H[2, 2]))
    return not 1 / MAX_SCALE**2 <= det <= MAX_SCALE**2


def _pose_e(nk: np.ndarray, nq: np.ndarray, f_px: float) -> tuple[np.ndarray | None, np.ndarray | None]:
    """R, unit t from the essential matrix of normalised inlier points (X_q = R X_k + t); `f_px`: the
    query camera's focal length, to put RANSAC's pixel threshold in normalised units."""
    thr = RANSAC_PX / f_px
    E, mask = cv2.findEssentialMat(nk, nq, np.eye(3), cv2.RANSAC, 0.999, thr)
    if E is None or E.shape != (3, 3):
        return None, None
    _, R, t, _ = cv2.recoverPose(E, nk, nq, np.eye(3), mask=mask)
    return R, t.ravel() / max(float(np.linalg.norm(t)), 1e-12)


def _rotation_only(nk: np.ndarray, nq: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation that best turns the keyframe's bearings onto the query's (Kabsch)."""
    bk = np.c_[nk, np.ones(len(nk))]
    bq = np.c_[nq, np.ones(len(nq))]
    bk /= np.linalg.norm(bk, axis=1, keepdims=True)
    bq /= np.linalg.norm(bq, axis=1, keepdims=True)
    u, _, vt = np.linalg.svd(bq.T @ bk)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _pose_h(nk: np.ndarray, nq: np.ndarray, f_px: float) -> tuple[np.ndarray | None, np.ndarray | None]:
    """R and, when observable, unit t from the homography between normalised inlier points.

    When a pure rotation explains ROTATION_ONLY of the inliers within RANSAC_PX (`f_px`: the query
    camera's focal length), that rotation, and no translation. Otherwise the decompositions of H that
    put the points in front of both cameras: R when they agree on it, t when they also agree on it."""
    R0 = _rotation_only(nk, nq)
    moved = np.c_[nk, np.ones(len(nk))] @ R0.T
    err = f_px * np.linalg.norm(moved[:, :2] / moved[:, 2:] - nq, axis=1)
    if np.mean(err <= RANSAC_PX) >= ROTATION_ONLY:
        return R0, None
    Hn, _ = cv2.findHomography(nk, nq, 0)
    if Hn is None:
        return None, None
    _, Rs, ts, normals = cv2.decomposeHomographyMat(Hn, np.eye(3))
    keep = cv2.filterHomographyDecompByVisibleRefpoints(Rs, normals, nk.reshape(-1, 1, 2).astype(np.float32),
                                                        nq.reshape(-1, 1, 2).astype(np.float32))
    idx = [int(i) for i in np.ravel(keep)] if keep is not None and np.size(keep) else list(range(len(Rs)))
    R = Rs[idx[0]]
    if any(rotation_angle(Rs[i] @ R.T) > 2.0 for i in idx):
        return None, None
    norms = [max(float(np.linalg.norm(ts[i])), 1e-12) for i in idx]
    units = [ts[i].ravel() / n for i, n in zip(idx, norms, strict=True)]
    if any(float(u @ units[0]) < math.cos(math.radians(5)) for u in units):
        return R, None
    return R, units[0]
