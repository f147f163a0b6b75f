"""Procedural textures for the simulated cameras: seamless tiles with a mip pyramid, sampled by
world (or surface) coordinates in metres.

Tiles are synthesised in the Fourier domain, so they wrap without a seam and a world-anchored
texture can be sampled anywhere by taking coordinates modulo the tile. The noise has an amplitude
spectrum falling as 1/f (every octave carries the same contrast), so a distant patch sampled from
a coarse mip level still has texture at the pixel scale for stereo to match. Everything is
generated from a fixed seed: the desert does not change from one run to the next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from modules.sim.world import Texture

FloatImage = NDArray[np.float32]
Image = TypeVar("Image", NDArray[np.float32], NDArray[np.uint8])

# cv2.remap converts coordinates to 16-bit fixed point and refuses images this large or larger.
_REMAP_LIMIT = 32767
_FLAT_BLOCK = 4096  # 1-D lookups are folded into rows this long for cv2.remap
FIXED_ONE = 2**14  # a brightness factor of 1 in MipTexture.fixed; factors up to 4 fit uint16


def periodic_noise(
    size: int, rng: np.random.Generator, slope: float = 1.0, stretch: tuple[float, float] = (1.0, 1.0)
) -> FloatImage:
    """A seamless ``size`` x ``size`` tile, zero mean and unit standard deviation, with amplitude
    falling as 1/f**slope. ``stretch`` (along columns, along rows) > 1 damps that direction's
    frequencies, elongating features along it (wood grain)."""
    white = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size)[:, None] * size * stretch[1]
    fx = np.fft.rfftfreq(size)[None, :] * size * stretch[0]
    radius = np.hypot(fx, fy)
    amplitude = np.zeros_like(radius)
    np.power(radius, -slope, out=amplitude, where=radius > 0)
    tile = np.fft.irfft2(np.fft.rfft2(white) * amplitude, s=(size, size))
    tile -= tile.mean()
    return (tile / tile.std()).astype(np.float32)


def periodic_blobs(size: int, rng: np.random.Generator, count: int, radius_px: float) -> FloatImage:
    """Seamless tile of ``count`` soft round spots of random sign (pebbles, leaves), peak +-1."""
    impulses = np.zeros((size, size))
    rows, cols = rng.integers(0, size, count), rng.integers(0, size, count)
    np.add.at(impulses, (rows, cols), rng.choice([-1.0, 1.0], count) * rng.uniform(0.5, 1.0, count))
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    gaussian = np.exp(-2.0 * (math.pi * radius_px) ** 2 * (fx**2 + fy**2))
    tile = np.fft.irfft2(np.fft.rfft2(impulses) * gaussian, s=(size, size))
    peak = np.abs(tile).max()
    return (tile / peak if peak > 0 else tile).astype(np.float32)


@dataclass(frozen=True)
class MipTexture:
    """A seamless square tile and its 2x2-averaged pyramid; level k has texels ``texel_m * 2**k``
    wide. Values are linear brightness factors (1 = the material's mean)."""

    levels: tuple[FloatImage, ...]
    texel_m: float
    # The same levels in units of 1 / FIXED_ONE, for sample_ground: half the memory of float32,
    # and cv2 interpolates them faster; the rounding is a hundredth of a grey level.
    fixed: tuple[NDArray[np.uint16], ...]

    @classmethod
    def from_tile(cls, tile: FloatImage, texel_m: float, smallest_px: int = 4) -> MipTexture:
        size = tile.shape[0]
        if tile.shape != (size, size) or size & (size - 1) or size >= _REMAP_LIMIT:
            raise ValueError(f"a texture tile must be square with a power-of-two side below {_REMAP_LIMIT}")
        levels = [np.ascontiguousarray(tile, dtype=np.float32)]
        while levels[-1].shape[0] > smallest_px:
            side = levels[-1].shape[0] // 2
            levels.append(levels[-1].reshape(side, 2, side, 2).mean(axis=(1, 3), dtype=np.float32))
        fixed = [np.clip(np.rint(level * FIXED_ONE), 0, np.iinfo(np.uint16).max).astype(np.uint16) for level in levels]
        for level in levels + fixed:
            level.flags.writeable = False
        return cls(tuple(levels), texel_m, tuple(fixed))

    @property
    def period_m(self) -> float:
        return self.levels[0].shape[0] * self.texel_m

    def level_for(self, footprint_m: float) -> int:
        """The mip level whose texels are about one pixel footprint wide."""
        if footprint_m <= self.texel_m:
            return 0
        return min(int(math.log2(footprint_m / self.texel_m)), len(self.levels) - 1)

    def sample(self, x_m: NDArray[np.floating], y_m: NDArray[np.floating], level: int) -> FloatImage:
        """Bilinear lookup at surface coordinates (metres; x along tile columns, y along rows),
        wrapped onto the tile. Inputs of any shape; float64 keeps world coordinates exact."""
        image = self.levels[level]
        side = image.shape[0]
        texel = self.texel_m * 2**level
        # Texel k covers [k, k+1) texels, so its centre sits at k + 0.5: consistent across levels.
        cols = _wrap(np.asarray(x_m, dtype=np.float64) / texel - 0.5, side)
        rows = _wrap(np.asarray(y_m, dtype=np.float64) / texel - 0.5, side)
        return remap_wrapped(image, cols, rows)

    def sample_ground(
        self,
        forward_m: NDArray[np.float32],
        left_m: NDArray[np.float32],
        east_m: float,
        north_m: float,
        yaw_rad: float,
        level: int,
    ) -> NDArray[np.uint16]:
        """Lookup at vehicle-frame ground points (2-D float32 arrays, within a few km of the
        vehicle) of a vehicle at (east_m, north_m, yaw_rad), anchored to the world; brightness
        factors in units of 1 / FIXED_ONE. The rotation into world axes is folded into one
        affine map per coordinate, relative to the tile corner nearest the vehicle, so no
        per-pixel double-precision arithmetic is needed: float32 holds a texel coordinate to
        cv2's 1/32 texel up to 2**19 texels (5 km at 1 cm)."""
        if forward_m.ndim != 2 or max(forward_m.shape) >= _REMAP_LIMIT:
            raise ValueError(f"ground lookups take 2-D arrays smaller than {_REMAP_LIMIT}, got {forward_m.shape}")
        image = self.fixed[level]
        texel = self.texel_m * 2**level
        period = self.period_m
        # The vehicle's position within its tile; whole tiles drop out of a periodic lookup.
        east0, north0 = east_m - math.floor(east_m / period) * period, north_m - math.floor(north_m / period) * period
        c, s = math.cos(yaw_rad) / texel, math.sin(yaw_rad) / texel
        side = image.shape[0]
        cols = _wrap_in_place(cv2.addWeighted(forward_m, c, left_m, -s, east0 / texel - 0.5), side)
        rows = _wrap_in_place(cv2.addWeighted(forward_m, s, left_m, c, north0 / texel - 0.5), side)
        return cv2.remap(image, cols, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _wrap(coordinate: NDArray[np.float64], side: int) -> NDArray[np.float32]:
    return (coordinate - np.floor(coordinate * (1.0 / side)) * side).astype(np.float32)


def _wrap_in_place(coordinate: NDArray[np.float32], side: int) -> NDArray[np.float32]:
    """Texel coordinates moved onto the tile by whole tiles (exact: ``side`` is a power of two).
    cv2.remap takes a slow per-pixel border path for every lookup off the image, which is nearly
    all of them unwrapped: wrapped, only the tile's last row and column do."""
    tiles = coordinate * np.float32(1.0 / side)
    np.floor(tiles, out=tiles)
    tiles *= np.float32(side)
    coordinate -= tiles
    return coordinate


def remap_wrapped(
    image: Image,
    cols: NDArray[np.float32],
    rows: NDArray[np.float32],
    border: int = cv2.BORDER_WRAP,
) -> Image:
    """cv2.remap (bilinear) for coordinate arrays of any shape, including 1-D ones longer than
    cv2's 32767 limit (folded into rows). Returns the image's type in the coordinates' shape."""
    shape = cols.shape
    if cols.ndim == 2 and max(shape) < _REMAP_LIMIT:
        out = cv2.remap(image, cols, rows, cv2.INTER_LINEAR, borderMode=border)
    else:
        flat_c, flat_r = cols.reshape(-1), rows.reshape(-1)
        count = flat_c.size
        if count == 0:
            return np.zeros(shape, dtype=image.dtype)
        width = min(count, _FLAT_BLOCK)
        padded = -(-count // width) * width
        map_c = np.zeros(padded, dtype=np.float32)
        map_r = np.zeros(padded, dtype=np.float32)
        map_c[:count], map_r[:count] = flat_c, flat_r
        out = cv2.remap(image, map_c.reshape(-1, width), map_r.reshape(-1, width), cv2.INTER_LINEAR, borderMode=border)
        out = out.reshape(-1)[:count]
    return out.reshape(shape)


@dataclass(frozen=True)
class Material:
    """How a surface looks: mean grey level (0-255 under full sun), its texture, and a BGR tint."""

    albedo_dn: float
    texture: MipTexture
    tint_bgr: tuple[float, float, float]


@dataclass(frozen=True)
class TextureSet:
    """Every texture the renderer uses, built once per seed."""

    ground: Material  # desert soil, 1 cm texels, 10 m tile
    ground_mottle: MipTexture  # large-scale soil colour changes, 0.5 m texels, 128 m tile
    materials: dict[Texture, Material]


def _material_tile(texture: Texture, rng: np.random.Generator, size: int) -> FloatImage:
    """Brightness factor tiles (mean ~1) with each material's character."""
    if texture is Texture.ROCK:
        base = periodic_noise(size, rng, slope=1.0)
        cracks = np.abs(periodic_noise(size, rng, slope=1.2))
        tile = 1.0 + 0.28 * base - 0.35 * np.clip(0.25 - cracks, 0.0, None) / 0.25
    elif texture is Texture.WOOD:
        grain = periodic_noise(size, rng, slope=1.0, stretch=(1.0, 12.0))  # streaks run along z (rows)
        knots = periodic_blobs(size, rng, 12, 3.0)
        tile = 1.0 + 0.25 * grain - 0.3 * np.abs(knots)
    elif texture is Texture.METAL:
        sheen = periodic_noise(size, rng, slope=1.8)
        rust = periodic_noise(size, rng, slope=1.3)
        tile = 1.0 + 0.05 * sheen - 0.35 * np.clip(rust - 0.8, 0.0, 1.0) + 0.08 * periodic_noise(size, rng, slope=0.8)
    elif texture is Texture.VEGETATION:
        leaves = periodic_blobs(size, rng, size * size // 60, 1.6)
        tile = 1.0 + 0.35 * periodic_noise(size, rng, slope=0.8) + 0.6 * leaves
    else:  # CONCRETE
        tile = 1.0 + 0.12 * periodic_noise(size, rng, slope=0.9) + 0.15 * periodic_blobs(size, rng, 400, 1.0)
    return np.clip(tile, 0.15, 2.2).astype(np.float32)


_MATERIAL_LOOK: dict[Texture, tuple[float, tuple[float, float, float]]] = {
    Texture.ROCK: (118.0, (0.92, 0.97, 1.08)),
    Texture.WOOD: (92.0, (0.72, 0.92, 1.25)),
    Texture.METAL: (160.0, (1.05, 1.0, 0.95)),
    Texture.VEGETATION: (78.0, (0.75, 1.18, 0.9)),
    Texture.CONCRETE: (182.0, (1.0, 1.0, 1.0)),
}


@lru_cache(maxsize=4)
def texture_set(seed: int) -> TextureSet:
    """The textures for ``seed`` (cached: building them costs ~0.2 s)."""
    rng = np.random.default_rng([seed, 0xC0FFEE])
    soil = 1.0 + 0.2 * periodic_noise(1024, rng, slope=1.0) + 0.35 * periodic_blobs(1024, rng, 6000, 1.5)
    ground = Material(
        albedo_dn=150.0,
        texture=MipTexture.from_tile(np.clip(soil, 0.3, 2.0).astype(np.float32), texel_m=0.01),
        tint_bgr=(0.78, 0.96, 1.12),
    )
    mottle = MipTexture.from_tile((1.0 + 0.1 * periodic_noise(256, rng, slope=1.5)).astype(np.float32), texel_m=0.5)
    materials = {
        texture: Material(albedo, MipTexture.from_tile(_material_tile(texture, rng, 256), texel_m=0.01), tint)
        for texture, (albedo, tint) in _MATERIAL_LOOK.items()
    }
    return TextureSet(ground, mottle, materials)
