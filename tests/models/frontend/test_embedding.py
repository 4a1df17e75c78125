"""The whole encoder: image bytes -> sLSBH codes, with identity, timings, weights and errors."""

from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from models import sdr
from models.evaluation.bench import synthetic_jpegs
from models.frontend import images, limits, slsbh
from models.frontend.backbones import alexnet as backbones
from models.frontend.embedding import STAGES, Embedder, merge_conf
from service.cli import app


@pytest.fixture(autouse=True)
def empty_weights_cache(tmp_path, monkeypatch):
    # Never pick up weights a developer installed in ~/.cache: the tests decide what is installed.
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "weights-cache"))


@pytest.fixture(scope="module")
def encoder() -> Embedder:
    # k=128 keeps the projection small (64,896 x 128) so the module stays fast.
    return Embedder({"slsbh": {"k": 128, "s": 0.25, "seed": 3}})


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img[:, :, ::-1])
    assert ok
    return buf.tobytes()


def scene(seed: int, noise: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8), (320, 240),
                      interpolation=cv2.INTER_CUBIC).astype(np.float32)
    if noise:
        base += np.random.default_rng(seed + 1000).normal(0, noise, base.shape)
    return np.clip(base, 0, 255).astype(np.uint8)


def test_codes_have_exactly_2n_sorted_ones_and_are_deterministic(encoder):
    data = [png(scene(1)), png(scene(2))]
    a = encoder.encode(data)
    b = encoder.encode(data)
    n = slsbh.n_ones(128, 0.25)
    assert a.codes.shape == (2, 2 * n) and a.codes.dtype == np.int32
    assert all((np.diff(c) > 0).all() and c.max() < 256 for c in a.codes)
    np.testing.assert_array_equal(a.codes, b.codes)
    assert set(a.timings_ms) == set(STAGES)
    assert a.features is None


def test_batched_and_single_encoding_agree(encoder):
    data = [png(scene(s)) for s in range(10)]  # more than one pipelined chunk
    batch = encoder.encode(data, return_features=True)
    single = [encoder.encode([d], return_features=True) for d in data]
    np.testing.assert_allclose(batch.features, np.concatenate([s.features for s in single]), atol=1e-5)
    assert batch.features.shape == (10, slsbh.D_CONV3)
    np.testing.assert_allclose(np.linalg.norm(batch.features, axis=1), 1.0, atol=1e-5)


def test_frames_decoded_beside_the_backbone_encode_as_one_at_a_time(encoder):
    """The decode threads (frames prepared into their rows of the batch, chunks forwarded as they are
    ready) give the codes and features of the plain sequential path."""
    data = [png(scene(s)) for s in range(2 * limits.DEFAULT_CHUNK + 1)]  # three chunks, the last short
    rgbs = [images.decode(d) for d in data]
    ref_feats = np.concatenate([encoder.features(images.preprocess_batch([r])) for r in rgbs])
    ref_codes = encoder.hasher(ref_feats)
    out = encoder.encode(data, return_features=True)
    np.testing.assert_array_equal(out.codes, ref_codes)
    np.testing.assert_allclose(out.features, ref_feats, atol=1e-6)
    assert set(out.timings_ms) == set(STAGES) and out.timings_ms["hash"] > 0
    prepared = [encoder.prepare(d) for d in data]
    got = encoder.embed_prepared(prepared)
    np.testing.assert_allclose(got.features, ref_feats, atol=1e-6)
    np.testing.assert_array_equal(got.contrast, [images.contrast(r) for r in rgbs])  # each frame's, in order
    # A thumbnail is made from the frame already decoded, for the frames that ask for one.
    asked = [i % 2 == 0 for i in range(len(data))]
    thumbs = encoder.embed(data, thumbnails=asked).thumbnails
    assert thumbs == [images.thumbnail(r) if a else None for r, a in zip(rgbs, asked, strict=True)]
    # A bad frame among prepared ones is its own future's error; embed_prepared raises it.
    bad = encoder.prepare(data[0][:100])
    with pytest.raises(images.ImageError):
        bad.result(timeout=30)
    with pytest.raises(images.ImageError):
        encoder.embed_prepared([encoder.prepare(data[1]), bad])


def test_a_batch_takes_its_resize_mode_as_an_encoder_made_with_it_would(encoder):
    """One network serves maps of both resize modes (a map's `resize` option): the mode is per call."""
    wide = png(np.ascontiguousarray(np.hstack([scene(4), scene(5)])))  # 640 x 240: crop and squash differ
    squashing = Embedder({"resize": "squash", "slsbh": {"k": 128, "s": 0.25, "seed": 3}})
    np.testing.assert_allclose(encoder.embed([wide], resize="squash").features,
                               squashing.embed([wide]).features, atol=1e-6)
    assert not np.allclose(encoder.embed([wide]).features, squashing.embed([wide]).features, atol=1e-3)
    assert encoder.identity_for("squash") == squashing.identity and encoder.identity.endswith(":crop")
    with pytest.raises(ValueError, match="resize must be one of crop, squash"):
        encoder.embed([wide], resize="stretch")


def test_similar_images_share_more_bits_than_different_ones(encoder):
    codes = encoder.encode([png(scene(5)), png(scene(5, noise=8.0)), png(scene(6))]).codes
    same, other = sdr.overlap(codes[0], codes[1]), sdr.overlap(codes[0], codes[2])
    assert same > other


def test_random_weights_are_announced(caplog):
    with caplog.at_level(logging.WARNING, logger="cortexloc.encoder"):
        enc = Embedder({"slsbh": {"k": 16}, "random_seed": 4})
    assert enc.identity == "alexnet-conv3/random-seed4:crop"
    assert enc.describe()["weights"] == "random"
    assert any("RANDOM weights" in r.message and "cortexloc weights" in r.message for r in caplog.records)


def test_weights_file_is_used_and_named(tmp_path, monkeypatch):
    from models.frontend import weights

    state = backbones.random_alexnet_state(seed=9)
    path = tmp_path / "conv3.pt"
    torch.save(state, path)
    enc = Embedder({"weights_path": str(path), "slsbh": {"k": 16}, "resize": "squash"})
    # An AlexNet-shaped file that is not torchvision's checkpoint is not called pretrained.
    assert not enc.pretrained and enc.describe()["weights"] == "file"
    assert enc.identity.startswith("alexnet-conv3/file-") and enc.identity.endswith(":squash")
    monkeypatch.setattr(weights, "ALEXNET_SHA256_PREFIX", weights.sha256_file(path)[:8])
    enc = Embedder({"weights_path": str(path), "slsbh": {"k": 16}, "resize": "squash"})
    assert enc.pretrained and enc.identity.startswith("alexnet-conv3/imagenet-")
    ref = backbones.AlexNetConv3()
    ref.load_state_dict(state)
    x = np.zeros((1, 3, 224, 224), np.float32)
    with torch.inference_mode():
        np.testing.assert_allclose(enc.features(x), ref(torch.from_numpy(x)).numpy(), atol=1e-6)


def test_bad_images_raise_one_typed_error(encoder):
    with pytest.raises(images.ImageError) as e:
        encoder.encode([b"not an image at all"])
    assert e.value.code == "unsupported-format"
    good = png(scene(1))
    with pytest.raises(images.ImageError) as e:
        encoder.encode([good, good[: len(good) // 2]])  # one bad upload in a batch
    assert e.value.code == "truncated"


def test_projection_must_fit_and_is_identified(encoder):
    with pytest.raises(ValueError, match="projection shape"):
        Embedder({"slsbh": {"k": 16}}, projection=np.zeros((10, 16), np.float32))
    assert encoder.projection_sha256 == slsbh.projection_sha256(encoder.projection)
    sparse = Embedder({"slsbh": {"k": 64, "projection": "sparse"}})
    assert "projection" not in sparse.describe()  # reported per map by the service, never built for it
    assert sparse.projection_sha256 == sparse.hasher.sha256()
    assert sparse.encode([png(scene(1))]).codes.shape == (1, 2 * slsbh.n_ones(64, 0.25))


def test_conf_validation():
    with pytest.raises(ValueError, match="unknown encoder option"):
        merge_conf({"bogus": 1})
    with pytest.raises(ValueError, match="resize"):
        merge_conf({"resize": "stretch"})
    with pytest.raises(ValueError, match="sLSBH"):
        merge_conf({"slsbh": {"q": 1}})
    with pytest.raises(ValueError, match="backbone"):
        Embedder({"backbone": "vgg"})


def test_efficientnet_backbone_encodes():
    enc = Embedder({"backbone": "efficientnet-lite0", "slsbh": {"k": 32}})
    assert enc.pretrained and enc.identity.startswith("efficientnet-lite0-stage7/imagenet-")
    out = enc.encode(synthetic_jpegs(2), return_features=True)
    assert out.codes.shape == (2, 2 * slsbh.n_ones(32, 0.25))
    assert out.features.shape[1] == enc.feature_dim
    s5 = Embedder({"backbone": "efficientnet-lite0-s5", "slsbh": {"k": 32}})
    assert s5.identity.startswith("efficientnet-lite0-stage5-pool2/imagenet-") and s5.feature_dim == 5488
    assert s5.encode(synthetic_jpegs(2), return_features=True).features.shape == (2, 5488)


def test_weights_import_command_installs_and_refuses(tmp_path):
    from models.frontend import weights

    full = tmp_path / "alexnet-full.pth"
    torch.save({**backbones.random_alexnet_state(seed=1), "classifier.1.weight": torch.zeros(2, 2)}, full)
    digest = weights.sha256_file(full)
    cli = CliRunner()
    bad = cli.invoke(app, ["weights", "import", str(full), "--dest", str(tmp_path / "cache")])
    assert bad.exit_code == 1 and "7be5be79" in bad.output  # not torchvision's file: refused
    assert not list((tmp_path / "cache").glob("*.pt"))
    installed = weights.import_alexnet(full, tmp_path / "cache", expected_prefix=digest[:8])
    assert installed.exists() and json.loads(weights.sidecar_path(installed).read_text())


def test_bench_encoder_reports_the_contract(tmp_path, monkeypatch):
    import models.evaluation.bench as bench

    monkeypatch.setattr(bench, "synthetic_jpegs", lambda n: synthetic_jpegs(n, 96, 64))
    out = tmp_path / "e.json"
    r = CliRunner().invoke(app, ["bench", "encoder", "--repeats", "1", "--projection", "sparse",
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    payload = json.loads(out.read_text())
    for key in ("batch1_ms_median", "batch16_images_per_s", "bare_batch16_images_per_s"):
        assert payload[key] > 0
    assert (payload["runtime"], payload["device"]) == ("onnxruntime", "cpu")
    # the size a map's dense projection would take (docs/scaling.md quotes it from this command)
    assert (payload["feature_dim"], payload["k"]) == (64_896, 1_024)  # AlexNet conv3, the default k
    assert payload["dense_projection_bytes"] == 64_896 * 1_024 * 4
    assert "D = 64,896 features, k = 1,024, dense projection 253.5 MiB" in r.output


def test_the_thread_budget_covers_the_blas_of_the_projection():
    """`torch_threads` bounds NumPy's BLAS too (the sLSBH projection), not only the backbone."""
    import threadpoolctl

    with threadpoolctl.threadpool_limits(2, user_api="blas"):
        Embedder({"slsbh": {"k": 16}, "torch_threads": 1})
        blas = [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
        assert blas and all(n == 1 for n in blas)
