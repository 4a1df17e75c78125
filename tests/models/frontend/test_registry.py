"""The backbone registry: names, look-up, and a third backbone added as one registration."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import pytest
import torch
from typer.testing import CliRunner

from models.frontend import backbones
from models.frontend.embedding import Embedder
from models.frontend.images import IMAGENET_MEAN, IMAGENET_STD
from service.cli import app


@pytest.fixture(autouse=True)
def empty_weights_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "weights-cache"))


@pytest.fixture
def tiny_backbone() -> Iterator[str]:
    """Registers `tiny-test`: mean colour per channel, (N, 3, 224, 224) -> (N, 3) unit rows."""

    class Tiny(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.nn.functional.normalize(x.mean(dim=(2, 3)), dim=1)

    @backbones.register("tiny-test")
    def build(conf: Mapping[str, Any]) -> backbones.Backbone:
        model = Tiny()
        return backbones.Backbone(model, model, f"random-seed{conf['random_seed']}", "tiny-mean",
                                  IMAGENET_MEAN, IMAGENET_STD)

    yield "tiny-test"
    del backbones._REGISTRY["tiny-test"]


def test_the_three_backbones_are_registered():
    assert backbones.names() == ("alexnet", "efficientnet-lite0", "efficientnet-lite0-s5")


def test_unknown_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="unknown backbone 'vgg'; known: alexnet, efficientnet-lite0, "
                                         "efficientnet-lite0-s5"):
        backbones.get("vgg")


def test_a_name_cannot_be_taken_twice():
    with pytest.raises(ValueError, match="registered twice"):
        backbones.register("alexnet")(lambda conf: None)  # type: ignore[arg-type,return-value]


def test_alexnet_builder_gives_the_encoders_backbone():
    bb = backbones.get("alexnet")({"weights_path": None, "random_seed": 3})
    assert (bb.arch, bb.weights_id) == ("alexnet-conv3", "random-seed3")
    with torch.inference_mode():
        out = bb.describe(torch.zeros(2, 3, 224, 224))
    assert out.shape == (2, 64_896)


def test_a_registered_backbone_is_usable_by_name_in_the_encoder(tiny_backbone):
    enc = Embedder({"backbone": tiny_backbone, "slsbh": {"k": 2}, "random_seed": 5})
    assert enc.identity == "tiny-mean/random-seed5:crop"
    assert enc.feature_dim == 3
    assert tiny_backbone in backbones.names()


def test_cli_refuses_a_backbone_the_registry_does_not_know():
    r = CliRunner().invoke(app, ["bench", "encoder", "--backbone", "vgg"])
    assert r.exit_code == 2
    said = " ".join(r.output.replace("│", " ").split())  # the error box wraps long lines
    assert "must be one of alexnet, efficientnet-lite0, efficientnet-lite0-s5" in said
