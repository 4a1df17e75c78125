"""Decoded RGB -> network input: torchvision's Resize + CenterCrop + ToTensor + Normalize in OpenCV and
NumPy (docs/design/science.md §6, Preprocessing)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from models.frontend.images.common import IMAGENET_MEAN, IMAGENET_STD, MODES


def _resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize with INTER_AREA on shrinking axes and INTER_LINEAR on enlarging ones
    (docs/design/science.md §6).

    INTER_AREA is the antialiased choice when shrinking (a box filter; torchvision's bilinear with
    antialias=True is a triangle filter, close to it); INTER_LINEAR when enlarging, where INTER_AREA
    degenerates towards nearest neighbour. Aspect-preserving resizes move both axes the same way; a
    squash may shrink one and enlarge the other, and then each axis gets its own pass.
    """
    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img
    if width <= w and height <= h:
        return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    if width >= w and height >= h:
        return cv2.resize(img, (width, height), interpolation=cv2.INTER_LINEAR)
    if width < w:
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    else:
        img = cv2.resize(img, (w, height), interpolation=cv2.INTER_AREA)
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_LINEAR)


def _fit(rgb: np.ndarray, mode: str, size: int, resize: int) -> np.ndarray:
    """(size, size, 3) uint8: Resize(resize) + CenterCrop(size), or a straight squash to size × size."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got shape {rgb.shape} dtype {rgb.dtype}")
    if mode == "squash":
        return _resize(rgb, size, size)
    h, w = rgb.shape[:2]
    # torchvision Resize(int): the short side becomes `resize`, the long side int(resize * long / short),
    # computed in floating point exactly as torchvision's _compute_resized_output_size does.
    if w <= h:
        new_w, new_h = resize, int(resize * h / w)
    else:
        new_w, new_h = int(resize * w / h), resize
    img = _resize(rgb, new_w, new_h)
    # torchvision CenterCrop: int(round(...)), Python's round-half-to-even (16.5 -> 16, 17.5 -> 18).
    top = round((new_h - size) / 2.0)  # round() of a float is already an int
    left = round((new_w - size) / 2.0)
    return img[top:top + size, left:left + size]


def _check_params(mode: str, size: int, resize: int, mean: Sequence[float],
                  std: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if size < 1:
        raise ValueError(f"size must be positive, got {size}")
    if mode == "crop" and resize < size:
        raise ValueError(f"resize ({resize}) must be at least size ({size}) in crop mode")
    m = np.asarray(mean, dtype=np.float32).reshape(-1)
    s = np.asarray(std, dtype=np.float32).reshape(-1)
    if m.shape != (3,) or s.shape != (3,):
        raise ValueError(f"mean and std need 3 values each, got {tuple(mean)} and {tuple(std)}")
    if np.any(s == 0):
        raise ValueError(f"std must be nonzero, got {tuple(std)}")
    return m.reshape(1, 3, 1, 1), s.reshape(1, 3, 1, 1)


def preprocess_batch(images: Sequence[np.ndarray], mode: str = "crop", size: int = 224,
                     mean: Sequence[float] = IMAGENET_MEAN, std: Sequence[float] = IMAGENET_STD,
                     resize: int = 256, out: np.ndarray | None = None) -> np.ndarray:
    """Network input for a batch of decoded images (docs/design/science.md §6, Preprocessing).

    Per image: "crop" = Resize(`resize`) (short side to `resize`, long side int(resize·long/short)) then
    CenterCrop(`size`) with top = round((h−size)/2), left = round((w−size)/2); "squash" = resize straight
    to size × size (keeps the whole field of view; matters for tiny frames, e.g. 64×32 Nordland images
    lose 56 % of their width to the centre crop). Then, for the whole batch at once and in float32 as
    torchvision's ToTensor + Normalize: x / 255, − mean, / std per channel.

    Args:
        images: N (H_i, W_i, 3) uint8 RGB images (from `decode`); sizes may differ.
        mode: "crop" or "squash" (part of the encoder identity).
        size: output side (224).
        mean: per-channel mean of the [0, 1] input (ImageNet by default).
        std: per-channel standard deviation.
        resize: short side before the centre crop (256); ignored in "squash" mode.
        out: (N, 3, size, size) float32 C-contiguous buffer to write into (e.g. rows of the batch the
            backbone will run on, so no image is copied twice); None: a new array.

    Returns:
        (N, 3, size, size) float32, C-contiguous (CHW per image, channels R, G, B): `out` when given.

    Raises:
        ValueError: an image is not (H, W, 3) uint8, or a parameter (or `out`) is invalid.
    """
    m, s = _check_params(mode, size, resize, mean, std)
    shape = (len(images), 3, size, size)
    if out is None:
        out = np.empty(shape, dtype=np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}, got {out.shape} "
                         f"{out.dtype}")
    for i, rgb in enumerate(images):
        # HWC uint8 -> CHW float32 in one casting copy into the batch buffer.
        out[i] = _fit(np.asarray(rgb), mode, size, resize).transpose(2, 0, 1)
    # Same float32 operations, in the same order, as ToTensor (div 255) and Normalize (sub, div).
    out /= np.float32(255.0)
    out -= m
    out /= s
    return out


def preprocess(rgb: np.ndarray, mode: str = "crop", size: int = 224,
               mean: Sequence[float] = IMAGENET_MEAN, std: Sequence[float] = IMAGENET_STD,
               resize: int = 256, out: np.ndarray | None = None) -> np.ndarray:
    """Network input for one decoded image; see `preprocess_batch` for the steps (docs/design/science.md §6).

    Args:
        rgb: (H, W, 3) uint8 RGB.
        mode: "crop" or "squash".
        size: output side (224).
        mean: per-channel mean of the [0, 1] input.
        std: per-channel standard deviation.
        resize: short side before the centre crop (256).
        out: (3, size, size) float32 C-contiguous buffer to write into (a row of a batch); None: new.

    Returns:
        (3, size, size) float32, C-contiguous: `out` when given.
    """
    rows = None if out is None else out[np.newaxis]
    return preprocess_batch([rgb], mode=mode, size=size, mean=mean, std=std, resize=resize, out=rows)[0]
