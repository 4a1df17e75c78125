"""EfficientNet-Lite0 backbone: checkpoint loading, conventions (padding, normalisation), descriptor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn import functional

from models.frontend import images
from models.frontend.backbones import efficientnet_lite0 as effnet
from storage.base.files import sha256_file

skdata = pytest.importorskip("skimage.data")

CAT_CLASSES = {281, 282, 285}  # tabby, tiger cat, Egyptian cat
COFFEE_CLASSES = {967, 504, 968}  # espresso, coffee mug, cup


@pytest.fixture(scope="module")
def loaded() -> tuple[effnet.EfficientNetLite0, str]:
    return effnet.efficientnet_lite0()


@pytest.fixture(scope="module")
def model(loaded: tuple[effnet.EfficientNetLite0, str]) -> effnet.EfficientNetLite0:
    return loaded[0]


def _input(*rgbs: np.ndarray) -> torch.Tensor:
    """(N, 3, 224, 224): Resize(256, INTER_AREA) + CenterCrop(224) + the model's normalisation."""
    batch = images.preprocess_batch(list(rgbs), mode="crop", mean=effnet.INPUT_MEAN, std=effnet.INPUT_STD)
    return torch.from_numpy(batch)


def _top5(model: effnet.EfficientNetLite0, rgb: np.ndarray) -> list[int]:
    with torch.inference_mode():
        return model(_input(rgb))[0].topk(5).indices.tolist()


# ---------------------------------------------------------------------------------------------- weights


def test_loads_package_weights_strictly_in_eval_mode(loaded: tuple[effnet.EfficientNetLite0, str]) -> None:
    model, weights_id = loaded
    assert weights_id == "imagenet-57934424"
    assert not model.training
    assert model.descriptor_layer == effnet.DEFAULT_LAYER
    # Legacy-format .pth, readable with the safe unpickler; every key maps onto a parameter or buffer.
    state = torch.load(effnet.package_weights_path(), map_location="cpu", weights_only=True)
    assert len(state) == 296
    assert set(state) == set(model.state_dict())
    assert state["_blocks.15._project_conv.weight"].shape == (320, 1152, 1, 1)
    assert state["_fc.weight"].shape == (1000, 1280)


def test_weights_sha256_is_cached_and_names_the_file() -> None:
    path = effnet.package_weights_path()
    digest = sha256_file(path)
    assert digest == effnet.WEIGHTS_SHA256
    assert digest[:8] in path.name  # torch.hub convention: the file name carries the hash prefix
    assert sha256_file(path) is digest


def test_corrupted_package_file_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bad = tmp_path / "efficientnet-lite0-57934424.pth"
    bad.write_bytes(b"not the checkpoint")
    monkeypatch.setattr(effnet, "package_weights_path", lambda: bad)
    with pytest.raises(ValueError, match="sha256"):
        effnet.efficientnet_lite0()


def test_other_weights_file_gets_its_own_id(model: effnet.EfficientNetLite0, tmp_path: Path) -> None:
    path = tmp_path / "copy.pth"
    torch.save(model.state_dict(), path)
    other, weights_id = effnet.efficientnet_lite0(weights_path=path, layer="stage5")
    assert weights_id == f"file-{sha256_file(path)[:8]}"
    assert other.descriptor_layer == "stage5"


# ------------------------------------------------------------------------------------------ conventions


def test_same_conv_pads_like_tensorflow() -> None:
    torch.manual_seed(0)
    for k in (3, 5):
        conv = effnet._SameConv2d(2, 4, k, stride=2)
        x = torch.randn(1, 2, 8, 9)
        # TF 'SAME': total pad (ceil(i/s)-1)*s + k - i, the odd pixel after (bottom/right).
        pad_h, pad_w = 3 * 2 + k - 8, 4 * 2 + k - 9
        padded = functional.pad(x, [pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2])
        ref = functional.conv2d(padded, conv.weight, stride=2)
        assert conv(x).shape == (1, 4, 4, 5)
        torch.testing.assert_close(conv(x), ref)


def test_input_normalisation_matches_the_stem_batchnorm_statistics(model: effnet.EfficientNetLite0) -> None:
    """The stem BN's running statistics were collected under the training normalisation, so the stem
    activations of real photos fit them best under the right constants ((x-127)/128, TF-Lite)."""
    assert np.allclose(np.array(effnet.INPUT_MEAN) * 255, 127.0)
    assert np.allclose(np.array(effnet.INPUT_STD) * 255, 128.0)
    photos = [skdata.chelsea(), skdata.coffee(), skdata.astronaut(), skdata.rocket()]
    bn = model._bn0
    live = bn.running_var > 1e-4  # 4 of the 32 stem channels are dead (running_var 0)

    def mismatch(mean: tuple[float, ...], std: tuple[float, ...]) -> float:
        x = torch.from_numpy(images.preprocess_batch(photos, mode="crop", mean=mean, std=std))
        with torch.inference_mode():
            y = model._conv_stem(x)
        mu, var = y.mean((0, 2, 3))[live], y.var((0, 2, 3))[live]
        rm, rv = bn.running_mean[live], bn.running_var[live]
        return float(((mu - rm) / rv.sqrt()).abs().mean() + (var / rv).log().abs().mean())

    ours = mismatch(effnet.INPUT_MEAN, effnet.INPUT_STD)
    assert ours < 0.6 * mismatch(images.IMAGENET_MEAN, images.IMAGENET_STD)
    assert ours < 0.6 * mismatch((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))


# ------------------------------------------------------------------------------------------ classification


def test_classifies_chelsea_as_a_cat(model: effnet.EfficientNetLite0) -> None:
    top5 = _top5(model, skdata.chelsea())
    assert top5[0] in CAT_CLASSES, top5
    assert set(top5) >= CAT_CLASSES, top5


def test_classifies_coffee_as_coffee(model: effnet.EfficientNetLite0) -> None:
    top5 = _top5(model, skdata.coffee())
    assert top5[0] == 967, top5  # espresso
    assert COFFEE_CLASSES & set(top5), top5


def test_logits_shape_and_odd_input_sizes(model: effnet.EfficientNetLite0) -> None:
    with torch.inference_mode():
        assert model(torch.zeros(2, 3, 224, 224)).shape == (2, 1000)
        assert model(torch.zeros(1, 3, 225, 231)).shape == (1, 1000)
        assert model.forward_features(torch.zeros(1, 3, 225, 231), "stage5").shape == (1, 112, 15, 15)


# ------------------------------------------------------------------------------------------ descriptor


def test_feature_layers_at_224(model: effnet.EfficientNetLite0) -> None:
    expected = {"stage1": (16, 112), "stage2": (24, 56), "stage3": (40, 28), "stage4": (80, 14),
                "stage5": (112, 14), "stage6": (192, 7), "stage7": (320, 7), "head": (1280, 7)}
    assert set(expected) == set(effnet.LAYERS)
    x = torch.zeros(1, 3, 224, 224)
    with torch.inference_mode():
        for layer, (c, s) in expected.items():
            assert model.forward_features(x, layer).shape == (1, c, s, s), layer
    with pytest.raises(ValueError, match="unknown layer"):
        model.forward_features(x, "conv3")
    with pytest.raises(ValueError, match="unknown layer"):
        effnet.EfficientNetLite0(descriptor_layer="block3")


def test_descriptor_shape_norm_and_determinism(model: effnet.EfficientNetLite0) -> None:
    x = _input(skdata.chelsea(), skdata.coffee())
    with torch.inference_mode():
        d = model.descriptor(x)
        again = model.descriptor(x)
        single = model.descriptor(x[1:])
        d5 = model.descriptor(x, layer="stage5")
    assert d.shape == (2, 320 * 7 * 7) and d.dtype == torch.float32
    assert d5.shape == (2, 112 * 14 * 14)
    torch.testing.assert_close(d.norm(dim=1), torch.ones(2))
    assert torch.equal(d, again)
    # Batch composition must not change a descriptor (eval-mode BN, no cross-sample ops).
    torch.testing.assert_close(single[0], d[1], atol=1e-5, rtol=1e-4)


def test_the_two_registered_blocks_differ_in_descriptor_and_identity(model: effnet.EfficientNetLite0) -> None:
    from models.frontend import backbones

    x = _input(skdata.chelsea(), skdata.coffee())
    s5 = backbones.get("efficientnet-lite0-s5")({})
    s7 = backbones.get("efficientnet-lite0")({})
    # Each identity names its block, so maps and snapshots never mix descriptors of the two.
    assert (s7.arch, s5.arch) == ("efficientnet-lite0-stage7", "efficientnet-lite0-stage5-pool2")
    assert s5.weights_id == s7.weights_id == "imagenet-57934424"
    with torch.inference_mode():
        d = s5.describe(x)
        single = s5.describe(x[1:])
        f5 = model.forward_features(x, "stage5")  # (2, 112, 14, 14)
        # What a map that recorded `efficientnet-lite0` computes is unchanged: stage 7 as it was.
        torch.testing.assert_close(s7.describe(x), model.descriptor(x))
    # Stage 5 averaged over 2x2 cells by hand: (2, 112, 7, 7), flattened in (C, H, W) order.
    by_hand = (f5[:, :, 0::2, 0::2] + f5[:, :, 1::2, 0::2] + f5[:, :, 0::2, 1::2] + f5[:, :, 1::2, 1::2]) / 4
    by_hand = by_hand.flatten(1) / by_hand.flatten(1).norm(dim=1, keepdim=True)
    assert d.shape == (2, 112 * 7 * 7) and d.dtype == torch.float32
    torch.testing.assert_close(d, by_hand)
    torch.testing.assert_close(d.norm(dim=1), torch.ones(2))
    torch.testing.assert_close(single[0], d[1], atol=1e-5, rtol=1e-4)
    with pytest.raises(ValueError, match="descriptor_pool"):
        effnet.EfficientNetLite0(descriptor_pool=0)


def test_noised_photo_is_closer_than_a_different_photo(model: effnet.EfficientNetLite0) -> None:
    cat, coffee = skdata.chelsea(), skdata.coffee()
    rng = np.random.default_rng(0)
    noisy = np.clip(cat.astype(np.float32) + rng.normal(0.0, 8.0, cat.shape), 0, 255).astype(np.uint8)
    with torch.inference_mode():
        d = model.descriptor(_input(cat, noisy, coffee))
    same, different = float(d[0] @ d[1]), float(d[0] @ d[2])
    assert same > 0.8, same
    assert different < same - 0.5, (same, different)
