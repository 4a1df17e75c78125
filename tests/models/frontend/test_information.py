"""A decoded frame's contrast (docs/design/science.md §11.7): flat frames (near-black, blank, overexposed)
measure under the localiser's MIN_CONTRAST whatever a few specks in them, frames with structure above,
dim ones included; the encoder reports it for every frame it decodes."""

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


def flat(level: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.clip(level + rng.normal(0, 1.5, (240, 320, 3)), 0, 255)
    img[8:16, 260:300] = 255 - level  # a timestamp overlay
    img[118:124, 158:164] = 220  # the lamp at a tunnel's end
    return img.astype(np.uint8)


@pytest.mark.parametrize("level", [5.0, 128.0, 250.0])  # near-black, blank grey, overexposed
def test_flat_frames_with_specks_measure_no_information(level):
    assert images.contrast(flat(level)) < MIN_CONTRAST and not informative(images.contrast(flat(level)))


@pytest.mark.parametrize("gain", [1.0, 0.15])  # a scene, and the same scene at dusk
def test_frames_with_structure_are_informative(gain):
    c = images.contrast(scene(gain=gain))
    assert c >= MIN_CONTRAST and informative(c)
    assert informative(None)  # not measured (a frame posted before the measure): no change


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


def test_the_encoder_reports_each_decoded_frames_contrast():
    from models.frontend.embedding import Embedder

    enc = Embedder({"backbone": "alexnet", "decode_threads": 1})
    bodies = [cv2.imencode(".png", x)[1].tobytes() for x in (flat(5.0), scene())]
    out = enc.embed(bodies)
    assert out.contrast is not None and out.contrast.shape == (2,)
    assert out.contrast[0] < MIN_CONTRAST <= out.contrast[1]
