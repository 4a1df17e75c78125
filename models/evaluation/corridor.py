"""A synthetic indoor corridor, rendered: the route of issue 35's "indoor corridor" check (160x120 frames,
a slow robot, the second lap through another lens), deterministic for a seed. numpy + cv2 only.

The world: straight corridors 2 m wide, 2.5 m high, flat walls (low texture: each 0.5 m strip one
shade, darker with depth), a floor and a ceiling, dark skirting boards, ceiling lights every `light`
metres, doors about every `door` metres (irregular gaps, mostly alternating sides, a colour from a small
palette: the structure repeats and aliases) and a poster now and then (a coloured panel with one inner
block). A corridor's layout comes from its own seed; a second corridor (other wall and floor colours,
other spacing) is the "unrelated stretch" of a loop. The gaps are irregular so that no place is a copy
of another: with doors exactly every 4 m on alternating sides (the first version) a place 8 m on was one,
and most revisits the service called while mapping named a row 7-9 m back.

The camera: a pinhole 1.2 m above the floor looking down the corridor, swaying laterally by up to 0.1 m
(`Lens`: focal length in pixels and one radial distortion coefficient k1, applied by remapping a larger
pinhole render, so a lens with k1 != 0 bends the straight lines). Frames get σ-2 pixel noise seeded by
(the corridor's seed, the frame's position), so two frames at one pose differ as a camera's do.

Labels: metres along the corridor (`floor(s)`), offset per corridor so two corridors never share one
(`models.evaluation.slam.revisit_truth`'s `away` = 10 labels = 10 m).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Corridor", "Lens", "render"]

WIDTH, HEIGHT = 160, 120
HALF_W, CEIL, EYE = 1.0, 2.5, 1.2
FAR = 25.0  # metres drawn ahead
SHIFT = 4  # cv2 sub-pixel bits: a 0.1 m step moves edges by fractions of a pixel


@dataclass(frozen=True)
class Lens:
    """A camera: `f` focal length in pixels at 160x120, `k1` radial distortion (0: a pinhole)."""

    f: float = 100.0
    k1: float = 0.0


@dataclass(frozen=True)
class Corridor:
    """One straight corridor of `length` metres; `seed` lays out its doors, posters and colours."""

    length: float
    seed: int
    wall: tuple[int, int, int] = (168, 170, 164)
    floor: tuple[int, int, int] = (95, 100, 105)
    door: float = 4.0
    light: float = 2.5
    poster: float = 7.0
    label0: int = 0

    def features(self) -> list[tuple[str, float, float, tuple[int, int, int]]]:
        """(kind, x along the corridor in metres, side +1 left / -1 right, colour), laid out by `seed`:
        doors `door` metres apart on average (each gap 0.6-1.4 times it, the side flipped 3 times in
        4), a colour of five; posters likewise every `poster` metres."""
        rng = np.random.default_rng(self.seed)
        palette = [(60, 80, 120), (40, 55, 85), (110, 90, 70), (70, 110, 150), (90, 90, 95)]  # BGR
        out: list[tuple[str, float, float, tuple[int, int, int]]] = []
        x, side = 1.0, 1.0
        while x < self.length:
            out.append(("door", float(x), side, palette[int(rng.integers(len(palette)))]))
            x += self.door * rng.uniform(0.6, 1.4)
            side = -side if rng.random() < 0.75 else side
        x = 3.0
        while x < self.length:
            colour = tuple(int(c) for c in rng.integers(30, 230, 3))
            out.append(("poster", float(x), float(rng.choice([-1.0, 1.0])), colour))  # type: ignore[arg-type]
            x += self.poster * rng.uniform(0.6, 1.4)
        return out


def _project(lens_f: float, cx: float, cy: float, s: float, sway: float,
             pts: np.ndarray) -> np.ndarray:
    """(n, 2) pixel coordinates (cv2 fixed point, SHIFT bits) of world points (n, 3) = (x, y, z)."""
    d = np.maximum(pts[:, 0] - s, 0.05)
    u = cx - lens_f * (pts[:, 1] - sway) / d
    v = cy - lens_f * (pts[:, 2] - EYE) / d
    return np.round(np.stack([u, v], axis=1) * (1 << SHIFT)).astype(np.int32)


def _shade(colour: tuple[int, int, int], d: float) -> tuple[int, int, int]:
    k = 0.35 + 0.65 * np.exp(-max(d, 0.0) / 12.0)
    return tuple(int(c * k) for c in colour)  # type: ignore[return-value]


def _pinhole(c: Corridor, s: float, f: float, size: tuple[int, int]) -> np.ndarray:
    """The view from `s` metres along `c` through a pinhole of focal `f`, on a canvas of `size` (W, H)."""
    w, h = size
    cx, cy = w / 2.0, h / 2.0
    sway = 0.1 * np.sin(s / 3.0)
    img = np.full((h, w, 3), 25, np.uint8)
    end = min(s + FAR, c.length + 2.0)

    def quad(p: list[tuple[float, float, float]], colour: tuple[int, int, int]) -> None:
        cv2.fillConvexPoly(img, _project(f, cx, cy, s, sway, np.asarray(p, np.float64)), colour,
                           cv2.LINE_AA, SHIFT)

    if end >= c.length + 2.0:  # the corridor's end wall
        x = c.length + 2.0
        quad([(x, HALF_W, 0), (x, -HALF_W, 0), (x, -HALF_W, CEIL), (x, HALF_W, CEIL)], _shade((90, 95, 90),
                                                                                              x - s))
    # strips far to near: each surface one shade per 0.5 m (low texture, darker with depth)
    for x0 in np.arange(np.floor(end * 2) / 2, np.floor(s * 2) / 2 - 0.5, -0.5):
        x1 = x0 + 0.5
        if x1 <= s:
            continue
        d = x0 - s
        quad([(x0, HALF_W, 0), (x1, HALF_W, 0), (x1, -HALF_W, 0), (x0, -HALF_W, 0)],
             _shade(c.floor, d))
        quad([(x0, HALF_W, CEIL), (x1, HALF_W, CEIL), (x1, -HALF_W, CEIL), (x0, -HALF_W, CEIL)],
             _shade((205, 205, 200), d))
        for side in (1.0, -1.0):
            y = side * HALF_W
            quad([(x0, y, 0), (x1, y, 0), (x1, y, CEIL), (x0, y, CEIL)], _shade(c.wall, d))
            quad([(x0, y, 0), (x1, y, 0), (x1, y, 0.1), (x0, y, 0.1)], _shade((50, 50, 50), d))
    items: list[tuple[float, str, float, tuple[int, int, int]]] = []
    for x in np.arange(0.5, c.length, c.light):
        items.append((float(x), "light", 0.0, (245, 245, 240)))
    items.extend((x, kind, side, colour) for kind, x, side, colour in c.features())
    for x, kind, side, colour in sorted(items, reverse=True):  # painter's order: far first
        if not s < x < end:
            continue
        d = x - s
        if kind == "light":
            quad([(x, 0.25, CEIL - 0.01), (x + 1.2, 0.25, CEIL - 0.01), (x + 1.2, -0.25, CEIL - 0.01),
                  (x, -0.25, CEIL - 0.01)], _shade(colour, d * 0.5))
        elif kind == "door":
            y = side * (HALF_W - 0.01)
            quad([(x - 0.08, y, 0), (x + 0.98, y, 0), (x + 0.98, y, 2.15), (x - 0.08, y, 2.15)],
                 _shade((70, 70, 70), d))
            quad([(x, y, 0), (x + 0.9, y, 0), (x + 0.9, y, 2.05), (x, y, 2.05)], _shade(colour, d))
        else:
            y = side * (HALF_W - 0.01)
            quad([(x, y, 1.1), (x + 0.7, y, 1.1), (x + 0.7, y, 1.9), (x, y, 1.9)], _shade(colour, d))
            inner = tuple(255 - v for v in colour)
            quad([(x + 0.15, y, 1.3), (x + 0.45, y, 1.3), (x + 0.45, y, 1.6), (x + 0.15, y, 1.6)],
                 _shade(inner, d))  # type: ignore[arg-type]
    return img


@functools.lru_cache(maxsize=8)
def _remap(lens: Lens) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """The maps from the 160x120 output to a 1.5x pinhole canvas of the same focal length: a pixel at
    normalised radius r reads the pinhole at r (1 + k1 r²)."""
    pad = (WIDTH // 4, HEIGHT // 4)
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float32), np.arange(HEIGHT, dtype=np.float32))
    x, y = (u - WIDTH / 2) / lens.f, (v - HEIGHT / 2) / lens.f
    k = 1.0 + lens.k1 * (x * x + y * y)
    return ((x * k * lens.f + WIDTH / 2 + pad[0]).astype(np.float32),
            (y * k * lens.f + HEIGHT / 2 + pad[1]).astype(np.float32),
            (WIDTH + 2 * pad[0], HEIGHT + 2 * pad[1]))


def render(c: Corridor, s: float, lens: Lens, noise: float = 2.0) -> np.ndarray:
    """(120, 160, 3) uint8 BGR: the view from `s` metres along corridor `c` through `lens`, with σ-`noise`
    pixel noise seeded by (c.seed, s)."""
    mx, my, size = _remap(lens)
    img = cv2.remap(_pinhole(c, s, lens.f, size), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    rng = np.random.default_rng([c.seed, round(float(s) * 1000)])
    return np.clip(img + rng.normal(0.0, noise, img.shape), 0, 255).astype(np.uint8)
