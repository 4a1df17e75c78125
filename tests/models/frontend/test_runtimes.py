"""Backbone runtimes: the ONNX export against the torch reference (graph, values, store) and the device
choice, without a GPU (an unavailable CUDA provider)."""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import pytest
import torch

from models.frontend import backbones, runtimes
from models.frontend.backbones import efficientnet_lite0 as effnet
from models.frontend.embedding import Embedder

onnx = pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def s5() -> backbones.Backbone:
    return backbones.get("efficientnet-lite0-s5")({})


@pytest.fixture(scope="module")
def alexnet() -> backbones.Backbone:
    return backbones.get("alexnet")({"weights_path": None, "random_seed": 0})


def _tf_same_pads(kernel: int, stride: int, size: int) -> tuple[int, int]:
    total = max((-(-size // stride) - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def test_export_keeps_tf_same_padding_and_inference_batchnorm(s5):
    """Every convolution of the exported graph pads as TF 'SAME' (stride 2 on an even input: 0 before and
    1 after for k=3, 1 and 2 for k=5), and no BatchNorm runs on batch statistics: BN is folded into the
    convolutions with the running statistics and eps = 1e-3, which the values check (symmetric padding
    measured a max |Δ| of 0.08 and training-mode BatchNorm 0.12 on unit-norm descriptors)."""
    model = onnx.load_from_string(runtimes.export_onnx(s5))
    ops = [n.op_type for n in model.graph.node]
    assert "Conv" in ops
    assert all(a.i == 0 for n in model.graph.node if n.op_type == "BatchNormalization"
               for a in n.attribute if a.name == "training_mode")
    size, seen_stride2 = 224, 0
    for node in (n for n in model.graph.node if n.op_type == "Conv"):
        attrs = {a.name: list(a.ints) for a in node.attribute if a.ints}
        k, stride = attrs["kernel_shape"][0], attrs["strides"][0]
        pads = attrs.get("pads", [0, 0, 0, 0])
        before, after = _tf_same_pads(k, stride, size)
        assert pads == [before, before, after, after], (node.name, k, stride, size, pads)
        if stride == 2:
            seen_stride2 += 1
            assert after == before + 1  # the asymmetric case a symmetric pad gets wrong
            size = -(-size // 2)
    assert seen_stride2 == 4  # stem, stages 2, 3, 4: 224 -> 14
    runner = runtimes.OnnxRunner(model.SerializeToString(), ["CPUExecutionProvider"], threads=1)
    x = np.random.default_rng(0).standard_normal((3, 3, 224, 224), np.float32)
    ref = runtimes.TorchRunner(s5.describe)(x)
    np.testing.assert_allclose(runner(x), ref, atol=1e-5)
    assert effnet.BN_EPS == 1e-3


def test_onnx_runtime_matches_torch_on_every_backbone_and_batch_size(alexnet, tmp_path):
    runner = runtimes.make_runner(alexnet, "onnxruntime", "cpu", 1, tmp_path)
    ref = runtimes.TorchRunner(alexnet.describe)
    for n in (1, 5):
        x = np.random.default_rng(n).standard_normal((n, 3, 224, 224), np.float32)
        out = runner(x)
        assert out.shape == (n, 64896) and out.dtype == np.float32
        np.testing.assert_allclose(out, ref(x), atol=1e-5)


def test_exports_are_stored_content_addressed_and_verified(alexnet, tmp_path, monkeypatch):
    data, sha = runtimes.onnx_model(alexnet, tmp_path)
    path = tmp_path / f"{sha}.onnx"
    assert hashlib.sha256(path.read_bytes()).hexdigest() == sha == hashlib.sha256(data).hexdigest()
    monkeypatch.setattr(runtimes, "_EXPORTS", {})

    def no_export(backbone):
        raise AssertionError("a stored, intact export must be read, not exported again")

    monkeypatch.setattr(runtimes, "export_onnx", no_export)
    assert runtimes.onnx_model(alexnet, tmp_path) == (data, sha)
    # A damaged file is never run: its bytes no longer hash to its name, so the backbone is exported anew.
    path.write_bytes(data[:-10] + bytes(10))
    monkeypatch.setattr(runtimes, "export_onnx", lambda backbone: data)
    assert runtimes.onnx_model(alexnet, tmp_path) == (data, sha)
    assert path.read_bytes() == data


def test_a_read_only_store_costs_an_export_not_the_encoder(alexnet, tmp_path, caplog):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    with caplog.at_level(logging.WARNING, "cortexloc.encoder"):
        data, _ = runtimes.onnx_model(alexnet, blocked / "onnx")
    assert data and "cannot store the ONNX export" in caplog.text


def test_device_cpu_uses_only_the_cpu_provider():
    assert runtimes.providers_for("cpu", ["CUDAExecutionProvider", "CPUExecutionProvider"]) == [
        "CPUExecutionProvider"]


def test_device_cuda_without_a_cuda_provider_refuses_and_says_how_to_fix():
    with pytest.raises(runtimes.DeviceUnavailableError, match="gpu` extra"):
        runtimes.providers_for("cuda", ["CPUExecutionProvider"])


def test_device_auto_without_cuda_falls_back_to_the_cpu_with_a_log_line(alexnet, tmp_path, caplog):
    with caplog.at_level(logging.INFO, "cortexloc.encoder"):
        runner = runtimes.make_runner(alexnet, "onnxruntime", "auto", 1, tmp_path,
                                      available=["CPUExecutionProvider"])
    assert runner.device == "cpu"
    assert "device auto" in caplog.text and "runs on the CPU" in caplog.text


def test_a_cuda_provider_that_cannot_start_is_detected_not_assumed(alexnet, tmp_path, caplog):
    """The install claims CUDA, but the session cannot run on it (no GPU here): ONNX Runtime then falls
    back with only a warning, so the device is read back from the session: `auto` says so and runs on
    the CPU, `cuda` refuses to start."""
    offered = ["CUDAExecutionProvider", "CPUExecutionProvider"]
    with caplog.at_level(logging.INFO, "cortexloc.encoder"):
        runner = runtimes.make_runner(alexnet, "onnxruntime", "auto", 1, tmp_path, available=offered)
    assert runner.device == "cpu" and "could not start its CUDA provider" in caplog.text
    with pytest.raises(runtimes.DeviceUnavailableError, match="could not start its CUDA provider"):
        runtimes.make_runner(alexnet, "onnxruntime", "cuda", 1, tmp_path, available=offered)


def test_the_torch_reference_runs_on_the_cpu_only(alexnet):
    with pytest.raises(runtimes.DeviceUnavailableError, match="onnxruntime runtime"):
        runtimes.make_runner(alexnet, "torch", "cuda", 1)
    assert runtimes.make_runner(alexnet, "torch", "auto", 1).device == "cpu"


def test_unknown_runtime_or_device_is_refused(alexnet):
    with pytest.raises(ValueError, match="runtime must be one of"):
        runtimes.make_runner(alexnet, "tensorrt", "cpu", 1)
    with pytest.raises(ValueError, match="device must be one of"):
        runtimes.make_runner(alexnet, "torch", "tpu", 1)


def test_the_encoder_reports_its_runtime_and_device_and_keeps_its_identity(tmp_path):
    conf = {"slsbh": {"k": 64}, "export_dir": str(tmp_path)}
    onnx_enc = Embedder(conf)
    torch_enc = Embedder({**conf, "runtime": "torch"})
    assert onnx_enc.describe() | {"runtime": "torch"} == torch_enc.describe()
    assert onnx_enc.describe()["runtime"] == "onnxruntime" and onnx_enc.describe()["device"] == "cpu"
    assert onnx_enc.identity == torch_enc.identity  # same codes: maps do not care which runtime
    x = torch.randn(2, 3, 224, 224).numpy()
    np.testing.assert_allclose(onnx_enc.features(x), torch_enc.features(x), atol=1e-5)


def test_weights_export_builds_every_backbones_export_into_the_store(tmp_path, monkeypatch):
    """`cortexloc weights export` (run by the image build): what the encoder would export on first use."""
    from typer.testing import CliRunner

    from service.cli import app

    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "weights"))
    r = CliRunner().invoke(app, ["weights", "export"])
    assert r.exit_code == 0, r.output
    store = tmp_path / "weights" / "onnx"
    manifests = sorted(p.name for p in store.glob("*.json"))
    assert len(manifests) == len(backbones.names()), manifests
    for p in store.glob("*.onnx"):
        assert hashlib.sha256(p.read_bytes()).hexdigest() == p.stem
    enc = Embedder({"backbone": "efficientnet-lite0-s5", "slsbh": {"k": 16}})
    monkeypatch.setattr(runtimes, "export_onnx", lambda backbone: pytest.fail("exported again"))
    monkeypatch.setattr(runtimes, "_EXPORTS", {})
    assert Embedder({"backbone": "efficientnet-lite0-s5", "slsbh": {"k": 16}}).identity == enc.identity
