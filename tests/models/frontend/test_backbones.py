"""AlexNet conv1..conv3 front end (docs/design/science.md §6): shapes, normalisation, keys, random weights,
ids."""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import numpy as np
import pytest
import torch

from models.frontend import slsbh
from models.frontend.backbones.alexnet import (
    AlexNetConv3,
    alexnet_conv3,
    load_alexnet_state,
    random_alexnet_state,
)
from models.frontend.weights import ALEXNET_CONV3_SHAPES, WeightsError

TORCHVISION_KEYS = [f"features.{i}.{p}" for i in (0, 3, 6) for p in ("weight", "bias")]


def _batch(n: int, seed: int = 0) -> torch.Tensor:
    """(n, 3, 224, 224) float32 roughly like ImageNet-normalised pixels."""
    rng = np.random.Generator(np.random.PCG64(seed))
    return torch.from_numpy(rng.standard_normal((n, 3, 224, 224), dtype=np.float32))


@pytest.fixture(scope="module")
def random_model() -> AlexNetConv3:
    model, _ = alexnet_conv3(None, seed=0)
    return model


def test_output_is_64896_floats_of_unit_norm(random_model: AlexNetConv3) -> None:
    with torch.inference_mode():
        out = random_model(_batch(3))
    assert out.shape == (3, slsbh.D_CONV3) == (3, 384 * 13 * 13)
    assert out.dtype == torch.float32
    np.testing.assert_allclose(out.norm(dim=1).numpy(), 1.0, rtol=1e-5)


def test_output_is_conv3_before_relu_flattened_chw(random_model: AlexNetConv3) -> None:
    x = _batch(2, seed=1)
    with torch.inference_mode():
        out = random_model(x)
        # Reference in the plain NCHW layout, the seven modules applied one by one.
        y = x.contiguous()
        for module in random_model.features:
            y = module(y)
        assert y.shape == (2, 384, 13, 13)
        ref = y.reshape(2, -1)
        ref = ref / ref.norm(dim=1, keepdim=True)
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-6)
    # Pre-ReLU: a good share of negative values (a ReLU output would have none).
    frac_negative = float((out < 0).float().mean())
    assert 0.2 < frac_negative < 0.8


def test_channels_last_and_nchw_agree() -> None:
    state = random_alexnet_state(3)
    a, b = AlexNetConv3(channels_last=True).eval(), AlexNetConv3(channels_last=False).eval()
    a.load_state_dict(state)
    b.load_state_dict(state)
    x = _batch(2, seed=2)
    with torch.inference_mode():
        torch.testing.assert_close(a(x), b(x), rtol=1e-4, atol=1e-6)


def test_zero_features_stay_zero() -> None:
    model = AlexNetConv3().eval()
    model.load_state_dict({k: torch.zeros(s) for k, s in ALEXNET_CONV3_SHAPES.items()})
    with torch.inference_mode():
        out = model(_batch(1))
    assert torch.count_nonzero(out) == 0
    assert not torch.isnan(out).any()


def test_rejects_wrong_input_shape(random_model: AlexNetConv3) -> None:
    with pytest.raises(ValueError, match="N, 3, H, W"):
        random_model(torch.zeros(1, 1, 224, 224))


def test_state_dict_keys_and_parameter_count_match_torchvision() -> None:
    model = AlexNetConv3()
    sd = model.state_dict()
    assert list(sd) == TORCHVISION_KEYS
    assert {k: tuple(v.shape) for k, v in sd.items()} == ALEXNET_CONV3_SHAPES
    assert sum(p.numel() for p in model.parameters()) == 994_624


def test_random_weights_deterministic_per_seed_and_distinct_across_seeds() -> None:
    a, b, c = random_alexnet_state(0), random_alexnet_state(0), random_alexnet_state(1)
    assert list(a) == TORCHVISION_KEYS
    for key, shape in ALEXNET_CONV3_SHAPES.items():
        assert tuple(a[key].shape) == shape and a[key].dtype == torch.float32
        assert torch.equal(a[key], b[key])
        assert not torch.equal(a[key], c[key])


def test_random_weights_follow_the_documented_recipe() -> None:
    state = random_alexnet_state(0)
    # Recompute the first tensor from the raw PCG64 stream exactly as the docstring says.
    bitgen = np.random.Generator(np.random.PCG64(0)).bit_generator
    n = 64 * 3 * 11 * 11
    u = (bitgen.random_raw(n) >> np.uint64(11)).astype(np.float64) * 2.0**-53
    expected = ((2 * u - 1) * np.sqrt(6 / 363)).astype(np.float32).reshape(64, 3, 11, 11)
    np.testing.assert_array_equal(state["features.0.weight"].numpy(), expected)
    # Bounds: weights within sqrt(6/fan_in), biases within 1/sqrt(fan_in).
    for layer, fan_in in (("features.0", 363), ("features.3", 1600), ("features.6", 1728)):
        assert float(state[f"{layer}.weight"].abs().max()) <= np.sqrt(6 / fan_in)
        assert float(state[f"{layer}.bias"].abs().max()) <= 1 / np.sqrt(fan_in)


def test_random_weights_give_sane_activations(random_model: AlexNetConv3) -> None:
    x = _batch(2, seed=4)
    with torch.inference_mode():
        y = random_model.features(x)
    std = float(y.std())
    assert 0.1 < std < 10.0, std  # He scaling: neither vanishing nor exploding through three convs


def test_random_seed_is_validated() -> None:
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="seed"):
            random_alexnet_state(bad)  # type: ignore[arg-type]


def test_weights_ids_and_eval_mode(tmp_path: Path) -> None:
    model, wid = alexnet_conv3(None)
    assert wid == "random-seed0"
    assert not model.training
    assert all(not p.requires_grad for p in model.parameters())
    assert alexnet_conv3(None, seed=7)[1] == "random-seed7"

    path = tmp_path / "conv3.pt"
    state = random_alexnet_state(5)
    buf = io.BytesIO()
    torch.save(state, buf)
    path.write_bytes(buf.getvalue())
    digest = hashlib.sha256(buf.getvalue()).hexdigest()
    loaded, got = load_alexnet_state(path)
    assert got == digest
    assert list(loaded) == TORCHVISION_KEYS
    model, wid = alexnet_conv3(path)
    assert wid == f"file-{digest[:8]}"  # AlexNet-shaped, but not torchvision's checkpoint
    for key, value in model.state_dict().items():
        assert torch.equal(value, state[key])


def test_unrelated_json_beside_the_file_is_ignored(tmp_path: Path) -> None:
    path = tmp_path / "conv3.pt"
    torch.save(random_alexnet_state(0), path)
    path.with_suffix(".json").write_text('{"something": "else"}')
    _, wid = alexnet_conv3(path)
    assert wid.startswith("file-")


def test_missing_file_is_a_weights_error(tmp_path: Path) -> None:
    with pytest.raises(WeightsError, match="does not exist"):
        alexnet_conv3(tmp_path / "nope.pt")


def test_wrong_shape_and_missing_key_are_named(tmp_path: Path) -> None:
    state = random_alexnet_state(0)
    state["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    path = tmp_path / "bad.pt"
    torch.save(state, path)
    msg = r"features\.3\.weight has shape \(192, 64, 3, 3\).*\(192, 64, 5, 5\)"
    with pytest.raises(WeightsError, match=msg):
        load_alexnet_state(path)

    state = random_alexnet_state(0)
    del state["features.6.bias"]
    torch.save(state, path)
    with pytest.raises(WeightsError, match=r"missing features\.6\.bias"):
        load_alexnet_state(path)


def test_non_finite_and_non_checkpoint_files_are_refused(tmp_path: Path) -> None:
    state = random_alexnet_state(0)
    state["features.0.bias"][3] = float("nan")
    path = tmp_path / "nan.pt"
    torch.save(state, path)
    with pytest.raises(WeightsError, match=r"features\.0\.bias contains NaN"):
        load_alexnet_state(path)

    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="not a loadable PyTorch checkpoint"):
        load_alexnet_state(junk)
