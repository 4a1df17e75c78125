"""A decoded frame's contrast (docs/design/science.md §11.7): flat frames (near-black, blank, overexposed)
measure under the localiser's MIN_CONTRAST whatever a few specks and pixel noise in them, frames with
structure above, dim ones included; the encoder reports it for every frame it decodes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from models.evaluation import datasets
from models.frontend import images
from models.localisation import MIN_CONTRAST, informative

NORDLAND = datasets.nordland_dir()


def scene(seed: int = 0, gain: float = 1.0, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), size[::-1],
                     interpolation=cv2.INTER_CUBIC)
    return np.clip(img.astype(np.float32) * gain, 0, 255).astype(np.uint8)


def flat(level: float, seed: int = 0, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.clip(level + rng.normal(0, 1.5, (*size, 3)), 0, 255)
    h, w = size
    img[h // 30:h // 15, w * 13 // 16:w * 15 // 16] = 255 - level  # a timestamp overlay
    # the lamp at a tunnel's end
    img[h // 2 - h // 80:h // 2 + h // 80 + 1, w // 2 - w // 106:w // 2 + w // 106 + 1] = 220
    return img.astype(np.uint8)


@pytest.mark.parametrize("level", [5.0, 128.0, 250.0])  # near-black, blank grey, overexposed
def test_flat_frames_with_specks_measure_no_information(level):
    assert images.contrast(flat(level)) < MIN_CONTRAST and not informative(images.contrast(flat(level)))


@pytest.mark.parametrize("gain", [1.0, 0.15])  # a scene, and the same scene at dusk
def test_frames_with_structure_are_informative(gain):
    c = images.contrast(scene(gain=gain))
    assert c >= MIN_CONTRAST and informative(c)
    assert informative(None)  # not measured (a frame posted before the measure): no change


def noisy(img: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
    """`img` with Gaussian pixel noise of σ `sigma` on each channel (a camera's gain turned up)."""
    rng = np.random.default_rng(seed)
    return np.clip(img.astype(np.float32) + rng.normal(0, sigma, img.shape), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("level", [0.0, 20.0, 128.0])  # black (the noise clips), a dark tunnel, grey
@pytest.mark.parametrize("sigma", [8.0, 16.0])
@pytest.mark.parametrize("size", [(32, 64), (240, 320)])  # measured as it is, and after the resize to 64 px
def test_pixel_noise_on_a_flat_frame_is_no_information(level, sigma, size):
    # the spread alone would count the noise: at 64 px σ 8 spreads a flat frame by 0.05-0.10 of the range
    c = images.contrast(noisy(flat(level, size=size), sigma))
    assert c < MIN_CONTRAST, c


@pytest.mark.parametrize("size", [(32, 64), (240, 320)])
def test_a_dim_scene_with_the_same_noise_keeps_its_information(size):
    dim = scene(gain=0.15, size=size)
    assert informative(images.contrast(noisy(dim, 8.0)))
    # and the noise takes little off a clean scene's measure (a ramp or a plane is no noise)
    blurred = cv2.GaussianBlur(dim, (0, 0), 1.0)
    assert images.contrast(dim) == pytest.approx(images.contrast(blurred), abs=0.02)


def test_grey_and_any_size_and_the_range():
    img = scene()
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    assert images.contrast(grey) == pytest.approx(images.contrast(img), abs=1e-9)
    assert 0.0 <= images.contrast(np.zeros((1, 1, 3), np.uint8)) == 0.0
    assert images.contrast(np.full((3000, 40, 3), 255, np.uint8)) == 0.0


@pytest.mark.skipif(not (NORDLAND / "winter").is_dir(), reason=f"Nordland not found in {NORDLAND}")
def test_nordland_tunnel_frames_measure_under_the_level_and_daylight_frames_above():
    def of(season: str, i: int) -> float:
        return images.contrast(images.decode((NORDLAND / season / f"images-{i * 10:05d}.png").read_bytes()))

    for s, i in [("summer", 997), ("summer", 1025), ("winter", 1026), ("winter", 1195)]:  # tunnels
        assert of(s, i) < MIN_CONTRAST
    for s, i in [("summer", 1027), ("winter", 1041), ("winter", 195), ("summer", 500)]:  # dim winter incl.
        assert of(s, i) >= MIN_CONTRAST

    def noisy_of(season: str, i: int) -> float:
        rgb = images.decode((NORDLAND / season / f"images-{i * 10:05d}.png").read_bytes())
        return images.contrast(noisy(rgb, 8.0, seed=i))

    # the same with pixel noise of σ 8: the tunnels stay flat (the growth route's noisy passes, issue 36)
    for s, i in [("summer", 997), ("summer", 1025), ("winter", 1026), ("winter", 1195)]:
        assert noisy_of(s, i) < MIN_CONTRAST
    for s, i in [("summer", 1027), ("winter", 1041), ("winter", 195), ("summer", 500)]:
        assert noisy_of(s, i) >= MIN_CONTRAST


def test_the_encoder_reports_each_decoded_frames_contrast():
    from models.frontend.embedding import Embedder

    enc = Embedder({"backbone": "alexnet", "decode_threads": 1})
    bodies = [cv2.imencode(".png", x)[1].tobytes() for x in (flat(5.0), scene())]
    out = enc.embed(bodies)
    assert out.contrast is not None and out.contrast.shape == (2,)
    assert out.contrast[0] < MIN_CONTRAST <= out.contrast[1]
