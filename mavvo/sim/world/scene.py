"""The simulated world: a textured ground plane (z = 0 in NED) and optional raised textured boxes.

The ground is textured by several periodic layers, each 8 times coarser than the one before, so that
a camera finds corners at every altitude from 2 m to well above 100 m; the renderer cross-fades the
layers by the ground distance of each pixel, as mip-mapping does. Every texture is procedural and
seeded: the same spec gives the same world, byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from mavvo.options import bounded

TextureKind = Literal["corners", "checker", "flat", "grass", "concrete"]

_TILE_PX = 1024
_LAYER_RATIO = 8.0
_BOX_TILE_PX = 256
_CHECKER_SQUARE_PX = 64
_GRASS_SHADES = 8


@dataclass(frozen=True)
class BoxSpec:
    """A raised box standing on the ground; ``length_m`` runs north before ``yaw_deg`` turns it."""

    north_m: float = bounded(0.0, "centre of the footprint, north of the origin")
    east_m: float = bounded(0.0, "centre of the footprint, east of the origin")
    length_m: float = bounded(4.0, "footprint along north (before yaw)", gt=0)
    width_m: float = bounded(4.0, "footprint along east (before yaw)", gt=0)
    height_m: float = bounded(3.0, "height above the ground", gt=0)
    yaw_deg: float = bounded(0.0, "rotation of the footprint about down")


@dataclass(frozen=True)
class PatchSpec:
    """A plain patch of floor (a rug, a sheet of plywood, a plain tile) painted mid-grey over the
    texture: where a camera low above it finds nothing to track. ``length_m`` runs north before
    ``yaw_deg`` turns it."""

    north_m: float = bounded(0.0, "centre, north of the origin")
    east_m: float = bounded(0.0, "centre, east of the origin")
    length_m: float = bounded(1.0, "along north (before yaw)", gt=0)
    width_m: float = bounded(1.0, "along east (before yaw)", gt=0)
    yaw_deg: float = bounded(0.0, "rotation about down")


@dataclass(frozen=True)
class WorldSpec:
    """What the ground looks like and what stands on it."""

    texture: TextureKind = bounded(
        "corners",
        "corners: multi-scale corners; checker: a checkerboard; flat: featureless grey; grass: a lawn seen from above; concrete: a trowelled floor",
    )
    texture_seed: int = bounded(0, "seed of the procedural texture", ge=0)
    finest_m_per_px: float = bounded(0.004, "ground size of one texel of the finest layer", gt=0)
    layers: int = bounded(5, "number of texture layers, each 8x coarser", ge=1, le=8)
    checker_size_m: float = bounded(1.0, "side of one checkerboard square", gt=0)
    contrast: float = bounded(
        1.0,
        "the ground's grey levels around mid-grey are scaled by this (0.15: a plain floor whose corners FAST finds only at low thresholds)",
        gt=0,
        le=1,
    )
    boxes: tuple[BoxSpec, ...] = field(default=(), metadata={"help": "raised textured boxes"})
    plain_patches: tuple[PatchSpec, ...] = field(default=(), metadata={"help": "plain mid-grey patches of floor"})


@dataclass(frozen=True)
class TextureLayer:
    """One periodic ground texture: ``tile`` (T,T) uint8 covering ``T * m_per_px`` metres each way.

    Texel (col, row) is centred at north = -(row + 0.5) * m_per_px, east = (col + 0.5) * m_per_px,
    modulo the period: a top view with north up.
    """

    tile: np.ndarray
    m_per_px: float


@dataclass(frozen=True)
class Box:
    """A box ready to draw: ``corners_ned`` (8,3), bottom four then top four; ``faces`` index quads
    (top and four sides, corners in order around the face); ``texture`` (S,S) uint8."""

    corners_ned: np.ndarray
    texture: np.ndarray

    faces: tuple[tuple[int, int, int, int], ...] = (
        (4, 5, 6, 7),
        (0, 1, 5, 4),
        (1, 2, 6, 5),
        (2, 3, 7, 6),
        (3, 0, 4, 7),
    )


@dataclass(frozen=True)
class World:
    """The built world: ground layers, finest first, and boxes."""

    layers: tuple[TextureLayer, ...]
    boxes: tuple[Box, ...]
    spec: WorldSpec
    patches_ned: tuple[np.ndarray, ...] = ()  # each plain patch's corners (4,3) on the ground, in order

    @classmethod
    def build(cls, spec: WorldSpec = WorldSpec()) -> "World":
        rng = np.random.default_rng(spec.texture_seed)
        if spec.texture == "checker":
            tile = checker_tile(_CHECKER_SQUARE_PX)
            layers = (TextureLayer(tile, spec.checker_size_m / _CHECKER_SQUARE_PX),)
        elif spec.texture == "flat":
            layers = (TextureLayer(np.full((8, 8), 128, np.uint8), spec.finest_m_per_px),)
        else:
            draw = {"grass": grass_tile, "concrete": concrete_tile}.get(spec.texture, corner_tile)
            layers = tuple(
                TextureLayer(draw(_TILE_PX, rng), spec.finest_m_per_px * _LAYER_RATIO**k) for k in range(spec.layers)
            )
        if spec.contrast != 1.0:
            layers = tuple(TextureLayer(_scaled_contrast(la.tile, spec.contrast), la.m_per_px) for la in layers)
        boxes = tuple(_build_box(b, np.random.default_rng([spec.texture_seed, i])) for i, b in enumerate(spec.boxes))
        patches = tuple(np.column_stack([_footprint(q), np.zeros(4)]) for q in spec.plain_patches)
        return cls(layers, boxes, spec, patches)


def corner_tile(size_px: int, rng: np.random.Generator) -> np.ndarray:
    """A periodic (size,size) uint8 texture of random rectangles and triangles of 6 to 64 texels.

    Shapes that cross an edge are drawn again on the opposite side, so the tile repeats seamlessly.
    """
    img = np.full((size_px, size_px), 128, np.uint8)
    mean_area = 700.0
    n = int(1.6 * size_px * size_px / mean_area)
    sizes = np.exp(rng.uniform(np.log(6.0), np.log(64.0), n))
    centres = rng.uniform(0, size_px, (n, 2))
    angles = rng.uniform(0, np.pi, n)
    aspect = rng.uniform(0.4, 1.0, n)
    levels = rng.integers(0, 256, n)
    triangle = rng.random(n) < 0.3
    unit_square = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    unit_triangle = np.array([[-0.5, 0.4], [0.5, 0.4], [0.0, -0.5]])
    shifts = [(dx, dy) for dx in (-size_px, 0, size_px) for dy in (-size_px, 0, size_px)]
    for i in range(n):
        shape = unit_triangle if triangle[i] else unit_square
        c, s = np.cos(angles[i]), np.sin(angles[i])
        pts = (shape * [sizes[i], sizes[i] * aspect[i]]) @ np.array([[c, s], [-s, c]]) + centres[i]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        for dx, dy in shifts:
            if hi[0] + dx < 0 or lo[0] + dx >= size_px or hi[1] + dy < 0 or lo[1] + dy >= size_px:
                continue
            q = np.round((pts + [dx, dy]) * 16).astype(np.int32)
            cv2.fillConvexPoly(img, q, int(levels[i]), lineType=cv2.LINE_AA, shift=4)
    return img


def grass_tile(size_px: int, rng: np.random.Generator) -> np.ndarray:
    """A periodic (size,size) uint8 lawn seen from above: blades (strokes 1-2 texels wide, 5 to 30
    long, every direction) over dark soil and shadow, brighter blades on top, in clumps that a
    smooth field of about 60 texels makes lighter or darker.

    No corner stands out the way a printed shape's does: what a tracker gets is many thin edges
    crossing at random, aliasing once a blade is narrower than a pixel. Blades that cross an edge are
    drawn again on the opposite side, so the tile repeats seamlessly.
    """
    n = int(0.06 * size_px * size_px)  # the soil shows between the blades
    length = np.exp(rng.uniform(np.log(5.0), np.log(30.0), n))
    angle = rng.uniform(0.0, np.pi, n)
    start = rng.uniform(0.0, size_px, (n, 2))
    end = start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    width = np.where(rng.random(n) < 0.6, 1, 2)
    shade = rng.integers(0, _GRASS_SHADES, n)  # one drawing call per shade and width, darkest first
    # Drawn on a canvas a blade's length wider all round, then cropped: a line OpenCV clips at the
    # canvas's edge is anti-aliased differently there, which would show as a seam between tiles.
    m = 32
    canvas = np.full((size_px + 2 * m, size_px + 2 * m), 30, np.uint8)
    shifts = [(dx + m, dy + m) for dx in (-size_px, 0, size_px) for dy in (-size_px, 0, size_px)]
    for k in range(_GRASS_SHADES):
        level = int(60 + 110 * k / (_GRASS_SHADES - 1))
        for w in (1, 2):
            pick = (shade == k) & (width == w)
            seg = np.stack([start[pick], end[pick]], axis=1)
            for dx, dy in shifts:
                lo, hi = seg.min(axis=1) + [dx, dy], seg.max(axis=1) + [dx, dy]
                near = np.all((hi >= m - 2) & (lo < size_px + m + 2), axis=1)
                if np.any(near):
                    q = np.round((seg[near] + [dx, dy]) * 16).astype(np.int32)
                    cv2.polylines(canvas, list(q), False, level, w, cv2.LINE_AA, 4)
    img = canvas[m : m + size_px, m : m + size_px]
    clumps = 1.0 + 0.25 * _periodic_smooth_noise(size_px, 60.0, rng)
    return np.clip(img * clumps + 0.5, 0, 255).astype(np.uint8)


def concrete_tile(size_px: int, rng: np.random.Generator) -> np.ndarray:
    """A periodic (size,size) uint8 concrete floor: mottling at three scales (about 40, 10 and 3
    texels) around mid-grey, dark pores of 1-3 texels and light specks of aggregate.

    What a tracker finds on it is blobs rather than corners: Shi-Tomasi's minimum eigenvalue is high
    at a pore or a speck and on the mottling's curved edges, FAST's segment test finds few corners.
    """
    grey = 128.0 + 18.0 * _periodic_smooth_noise(size_px, 40.0, rng)
    grey += 10.0 * _periodic_smooth_noise(size_px, 10.0, rng) + 6.0 * _periodic_smooth_noise(size_px, 3.0, rng)
    img = np.clip(grey + 0.5, 0, 255).astype(np.uint8)
    for count, level in ((int(0.004 * size_px * size_px), 60), (int(0.002 * size_px * size_px), 200)):
        centre = np.round(rng.uniform(0.0, size_px, (count, 2)) * 16).astype(np.int32)
        radius = np.round(rng.uniform(0.5, 1.5, count) * 16).astype(np.int32)
        for (u, v), r in zip(centre, radius):
            # Near an edge also drawn where it wraps to: the tile repeats seamlessly.
            for du in _wraps(int(u), size_px * 16):
                for dv in _wraps(int(v), size_px * 16):
                    cv2.circle(img, (int(u + du), int(v + dv)), int(r), level, -1, cv2.LINE_AA, 4)
    return img


def _wraps(x: int, period: int) -> tuple[int, ...]:
    """Shifts by which a dot at ``x`` (within 4 texels of an edge, 16ths) is drawn again."""
    margin = 4 * 16
    return (0, -period) if x > period - margin else (0, period) if x < margin else (0,)


def _periodic_smooth_noise(size_px: int, scale_px: float, rng: np.random.Generator) -> np.ndarray:
    """(size,size) float noise of unit standard deviation, smooth over about ``scale_px`` and periodic
    (white noise low-passed by a Gaussian in the frequency domain, which wraps around)."""
    f = np.fft.fftfreq(size_px)
    gain = np.exp(-0.5 * (2 * np.pi * scale_px / 4) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    field = np.fft.ifft2(np.fft.fft2(rng.standard_normal((size_px, size_px))) * gain).real
    return field / field.std()


def _scaled_contrast(tile: np.ndarray, contrast: float) -> np.ndarray:
    """``tile``'s grey levels pulled toward 128 by ``contrast`` (0..1)."""
    return np.clip(128.0 + contrast * (tile.astype(np.float32) - 128.0) + 0.5, 0, 255).astype(np.uint8)


def checker_tile(square_px: int) -> np.ndarray:
    """A (2s,2s) uint8 tile of a 2x2 checkerboard, dark top-left: X-corners at multiples of s."""
    tile = np.full((2 * square_px, 2 * square_px), 230, np.uint8)
    tile[:square_px, :square_px] = 25
    tile[square_px:, square_px:] = 25
    return tile


def _footprint(b: BoxSpec | PatchSpec) -> np.ndarray:
    """(4,2) north/east corners of a box's or patch's footprint, in order around it."""
    yaw = np.radians(b.yaw_deg)
    c, s = np.cos(yaw), np.sin(yaw)
    half = np.array([[1, -1], [1, 1], [-1, 1], [-1, -1]]) * [b.length_m / 2, b.width_m / 2]
    return half @ np.array([[c, s], [-s, c]]) + [b.north_m, b.east_m]


def _build_box(b: BoxSpec, rng: np.random.Generator) -> Box:
    ne = _footprint(b)
    bottom = np.column_stack([ne, np.zeros(4)])
    top = np.column_stack([ne, np.full(4, -b.height_m)])
    return Box(np.vstack([bottom, top]), corner_tile(_BOX_TILE_PX, rng))
