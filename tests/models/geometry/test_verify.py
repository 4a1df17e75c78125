"""Geometric verification on real images (issue 27 items 1, 2 and 4; docs/design/science.md §12): the
real rectified stereo pair, real photographs warped by known rotations, unrelated pairs, frames too small,
and the compact bytes of a keyframe."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from models.geometry import Camera, available, extract, pack, unpack, verify
from models.geometry.verify import rotation_angle

pytest.importorskip("skimage", reason="scikit-image (dev extra) ships the real images")

from models.evaluation.geometry import PHOTOS, photo, photo_camera, rotation, stereo, warp

EXTRACTORS = [k for k in ("orb", "sift") if k in available()]


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.parametrize("kind", EXTRACTORS)
def test_the_real_stereo_pair_verifies_with_identity_rotation_and_baseline_along_x(kind):
    left, right, cam_l, cam_r = stereo()
    v = verify(extract(right, kind), extract(left, kind), cam_r, cam_l)
    assert v.verified and v.model == "fundamental" and v.inliers >= 100, v
    assert rotation_angle(v.rotation) < 1.0
    # X_right = X_left - b x: the translation direction is -x.
    assert angle_between(v.translation, np.array([-1.0, 0.0, 0.0])) < 3.0, v.translation


def test_without_cameras_a_stereo_pair_verifies_but_has_no_pose():
    left, right, _, _ = stereo()
    v = verify(extract(right), extract(left))
    assert v.verified and v.rotation is None and v.translation is None and v.reason == "no-camera"


@pytest.mark.parametrize(("name", "angles"), [("astronaut", (5, 0, 0)), ("coffee", (-10, 0, 0)),
                                              ("rocket", (0, 6, 0)), ("camera", (0, 0, 10)),
                                              ("coins", (8, 4, 6)), ("gravel", (5, 0, 0))])
def test_a_known_camera_rotation_is_recovered_from_a_warped_photograph(name, angles):
    img = photo(name)
    cam, R = photo_camera(img), rotation(*angles)
    v = verify(extract(warp(img, cam, R)), extract(img), cam, cam)
    assert v.verified and v.model == "homography", v
    assert rotation_angle(v.rotation @ R.T) < 2.0, (rotation_angle(v.rotation), rotation_angle(R))
    # A pure rotation has no translation to tell.
    assert v.translation is None and v.reason == "translation-unobservable"


@pytest.mark.parametrize("kind", EXTRACTORS)
def test_unrelated_photographs_are_never_verified(kind):
    feats = [extract(photo(n), kind) for n in PHOTOS] + [extract(stereo()[0], kind)]
    verdicts = [verify(a, b) for a, b in itertools.combinations(feats, 2)]
    assert not any(v.verified for v in verdicts), [(v.inliers, v.model) for v in verdicts if v.verified]


def test_a_homography_that_folds_repeated_texture_onto_a_line_is_degenerate():
    if "sift" not in available():
        pytest.skip("SIFT is not in this OpenCV build")
    # SIFT finds 49 homography inliers between the rocket and the brick wall: all on one line of the rocket.
    v = verify(extract(photo("rocket"), "sift"), extract(photo("brick"), "sift"))
    assert not v.verified and v.reason == "degenerate" and v.inliers >= 25


@pytest.mark.parametrize("shape", [(32, 64), (64, 64), (95, 400)])
def test_frames_too_small_are_not_verifiable_even_against_themselves(shape):
    img = np.ascontiguousarray(photo("astronaut")[: shape[0], : shape[1]])
    f = extract(img)
    assert len(f) == 0 and f.too_small and f.size == (shape[1], shape[0])
    v = verify(f, f, Camera(50, 50, 32, 16), Camera(50, 50, 32, 16))
    assert not v.verified and v.reason == "too-small" and v.rotation is None


def test_a_featureless_frame_is_not_verifiable():
    flat = np.full((240, 320, 3), 128, np.uint8)
    f = extract(flat)
    assert not verify(f, f).verified and verify(f, f).reason == "too-few-features"


@pytest.mark.parametrize("kind", EXTRACTORS)
def test_keyframe_bytes_round_trip_exactly_and_are_compact(kind):
    f = extract(photo("astronaut"), kind, 300)
    blob = pack(f)
    g = unpack(blob)
    assert (g.kind, g.size) == (kind, (512, 512)) and np.array_equal(g.xy, f.xy)
    assert np.array_equal(g.desc, f.desc) and g.desc.dtype == np.uint8
    assert len(blob) == 16 + len(f) * (8 + f.desc.shape[1])
    with pytest.raises(ValueError):
        unpack(blob[:-1])
    # uint8 SIFT descriptors verify as the float ones did
    left, right, cam_l, cam_r = stereo()
    again = verify(unpack(pack(extract(right, kind))), unpack(pack(extract(left, kind))), cam_r, cam_l)
    assert again.verified


def test_an_extractor_outside_the_build_or_the_registry_is_refused():
    with pytest.raises(ValueError, match="not in this OpenCV build"):
        extract(photo("coins"), "surf")
