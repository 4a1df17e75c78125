"""Verification within bounds (issue 34 items 1-3; docs/design/science.md §12): features of a large frame
taken at a bounded resolution and given in native pixels, cameras that make no geometric sense named,
no verified answer without a finite pose, and a failure of the fits a failed verification, never an
exception."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from models.geometry import EXTRACT_MAX_SIDE, Camera, available, camera_problems, extract, verify
from models.geometry.verify import rotation_angle

pytest.importorskip("skimage", reason="scikit-image (dev extra) ships the real images")

from models.evaluation.geometry import photo, photo_camera, rotation, warp

EXTRACTORS = [k for k in ("orb", "sift") if k in available()]


def scene(w: int, h: int) -> np.ndarray:
    return cv2.resize(photo("astronaut"), (w, h), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("kind", EXTRACTORS)
def test_a_large_frame_is_described_at_the_bounded_side_in_native_pixels(kind):
    side = EXTRACT_MAX_SIDE[kind]
    small = scene(side, side * 3 // 4)
    # Each pixel doubled: scaled back to the bound (INTER_AREA) it is `small` exactly.
    big = cv2.resize(small, (2 * side, side * 3 // 2), interpolation=cv2.INTER_NEAREST)
    a, b = extract(small, kind), extract(big, kind)
    assert b.size == (2 * side, side * 3 // 2) and len(b) == len(a) > 100
    assert np.array_equal(b.desc, a.desc)
    assert np.allclose(b.xy, 2 * (a.xy + 0.5) - 0.5, atol=1e-3)  # OpenCV's pixel centres, native pixels


def test_a_large_turned_frame_verifies_with_its_camera_in_native_pixels():
    img = scene(3200, 2400)
    cam = photo_camera(img)
    turn = rotation(4, 1, 0)
    v = verify(extract(warp(img, cam, turn)), extract(img), cam, cam)
    assert v.verified and v.rotation is not None, v
    assert rotation_angle(v.rotation @ turn.T) < 0.5


SIZE = (320, 240)
GOOD = Camera(288.0, 288.0, 160.0, 120.0, (-0.3, 0.1, 0.0, 0.0))


@pytest.mark.parametrize(("camera", "fields"), [
    (GOOD, []),
    (Camera(288.0, 288.0, 160.0, 120.0), []),
    (Camera(1e-300, 1e-300, 0.0, 0.0), ["fx", "fy"]),          # the issue's: a null rotation, verified
    (Camera(288.0, 1e-6, 160.0, 120.0), ["fy"]),
    (Camera(288.0, 1e5, 160.0, 120.0), ["fy"]),                 # 312 x the longer side
    (Camera(288.0, 288.0, -1.0, 120.0), ["cx"]),
    (Camera(288.0, 288.0, 160.0, 241.0), ["cy"]),
    (Camera(float("nan"), 288.0, 160.0, 120.0), ["fx"]),
    (Camera(288.0, 288.0, 160.0, 120.0, (1000.0,) * 14), ["distortion"]),  # the 500s
    (Camera(288.0, 288.0, 160.0, 120.0, (0.0, 0.0, 0.0, float("inf"))), ["distortion"]),
])
def test_a_camera_that_makes_no_geometric_sense_is_named(camera, fields):
    assert [name for name, _ in camera_problems(camera, SIZE)] == fields


def test_a_sensible_distortion_round_trips():
    back = GOOD.project(GOOD.normalise(np.array([[0.0, 0.0], [320.0, 240.0], [17.0, 200.0]])))
    assert np.abs(back - [[0.0, 0.0], [320.0, 240.0], [17.0, 200.0]]).max() < 0.01


def turned_pair() -> tuple:
    img = scene(320, 240)
    cam = photo_camera(img)
    return extract(warp(img, cam, rotation(5, 0, 0))), extract(img), cam


def test_a_verification_without_a_finite_pose_is_not_verified():
    query, keyframe, _ = turned_pair()
    tiny = Camera(1e-300, 1e-300, 0.0, 0.0)  # past validation only by a direct call
    v = verify(query, keyframe, tiny, tiny)
    assert not v.verified and v.reason in ("no-pose", "geometry-failed") and v.rotation is None, v
    assert v.inliers >= 25 or v.reason == "geometry-failed"  # the scene matched: the pose did not


def test_a_wild_distortion_fails_the_verification_not_the_caller():
    """Independent of the camera check (which refuses this camera at the HTTP boundary)."""
    query, keyframe, cam = turned_pair()
    wild = Camera(cam.fx, cam.fy, cam.cx, cam.cy, (1000.0,) * 14)
    v = verify(query, keyframe, wild, wild)
    assert not v.verified and v.reason in ("no-pose", "geometry-failed") and v.rotation is None, v


@pytest.mark.parametrize("fit", ["findHomography", "findFundamentalMat", "undistortPoints"])
def test_an_opencv_failure_is_a_failed_verification(monkeypatch, fit):
    query, keyframe, cam = turned_pair()

    def fail(*args, **kwargs):
        raise cv2.error("OpenCV(5.0.0) lapack.cpp: error: (-215) SVD did not converge")

    monkeypatch.setattr(cv2, fit, fail)
    v = verify(query, keyframe, cam, cam)
    assert not v.verified and v.reason == "geometry-failed", v


def test_a_numpy_failure_is_a_failed_verification(monkeypatch):
    query, keyframe, cam = turned_pair()

    def fail(*args, **kwargs):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(np.linalg, "svd", fail)
    v = verify(query, keyframe, cam, cam)
    assert not v.verified and v.reason == "geometry-failed", v
