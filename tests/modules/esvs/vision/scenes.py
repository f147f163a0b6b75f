"""Small ray-cast stereo scenes with known geometry, for testing the vision pipeline.

A flat textured ground (z = 0 in the vehicle frame), optional painted stripes on it
(y = c0 + c1 x + c2 x^2), and upright axis-aligned textured boxes. Texture is a function of the
world point, so the left and right images agree wherever both cameras see a surface, and the
left view's true disparity is exact. Each camera adds its own sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from modules.esvs.geometry import RASCAL_RIG, StereoRig

_TABLE = np.random.default_rng(12345).random(1 << 16).astype(np.float64)


@dataclass(frozen=True)
class Box:
    """Upright box: near face at ``x_m`` (vehicle frame), centred on ``y_m``."""

    x_m: float
    y_m: float
    width_m: float = 1.0
    depth_m: float = 1.0
    height_m: float = 1.0
    albedo: float = 150.0


@dataclass(frozen=True)
class Stripe:
    """A painted line on the ground: |y - (c0 + c1 x + c2 x^2)| < width / 2 for x in [x_min, x_max]."""

    c0: float
    c1: float = 0.0
    c2: float = 0.0
    width_m: float = 0.15
    x_min_m: float = 0.0
    x_max_m: float = 100.0
    albedo: float = 235.0


@dataclass(frozen=True)
class Scene:
    boxes: tuple[Box, ...] = ()
    stripes: tuple[Stripe, ...] = ()
    ground_albedo: float = 105.0
    texture_contrast: float = 60.0
    noise_std: float = 1.5
    seed: int = 0


def value_noise(a: np.ndarray, b: np.ndarray, scale: float, salt: int) -> np.ndarray:
    """Smooth lattice noise in [0, 1) with features about ``scale`` metres across."""
    ga, gb = a / scale, b / scale
    ia, ib = np.floor(ga), np.floor(gb)
    fa, fb = ga - ia, gb - ib
    fa, fb = fa * fa * (3 - 2 * fa), fb * fb * (3 - 2 * fb)
    ia, ib = ia.astype(np.int64), ib.astype(np.int64)

    def lattice(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return _TABLE[((i * 73856093) ^ (j * 19349663) ^ (salt * 83492791)) & 0xFFFF]

    top = lattice(ia, ib) * (1 - fa) + lattice(ia + 1, ib) * fa
    bottom = lattice(ia, ib + 1) * (1 - fa) + lattice(ia + 1, ib + 1) * fa
    return top * (1 - fb) + bottom * fb


def texture(a: np.ndarray, b: np.ndarray, salt: int) -> np.ndarray:
    """Multi-scale noise in about [-1, 1]: gravel to patches."""
    total = np.zeros_like(a)
    for octave, scale in enumerate((0.08, 0.16, 0.32, 0.64, 1.28)):
        total += value_noise(a, b, scale, salt * 16 + octave) - 0.5
    return total / 1.25


def render(
    scene: Scene, rig: StereoRig = RASCAL_RIG, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left and right uint8 grey images and the left view's true disparity (0 on the sky)."""
    rng = rng or np.random.default_rng(scene.seed)
    left, depth = _shade(scene, rig, right=False)
    right, _ = _shade(scene, rig, right=True)
    disparity = np.where(np.isfinite(depth), rig.focal_px * rig.baseline_m / np.where(np.isfinite(depth), depth, 1), 0)
    images = []
    for image in (left, right):
        noisy = image + rng.normal(0.0, scene.noise_std, image.shape)
        images.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
    return images[0], images[1], disparity.astype(np.float32)


@lru_cache(maxsize=16)
def rendered(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``render`` on the RASCAL rig, once per scene per test session (read-only arrays)."""
    images = render(scene)
    for image in images:
        image.flags.writeable = False
    return images


def nearest_range(box: Box) -> float:
    """Distance from the vehicle origin to the box's nearest point on the ground."""
    lateral = float(np.clip(0.0, box.y_m - box.width_m / 2, box.y_m + box.width_m / 2))
    return float(np.hypot(box.x_m, lateral))


def _shade(scene: Scene, rig: StereoRig, right: bool) -> tuple[np.ndarray, np.ndarray]:
    """Intensity and camera depth (inf on the sky) of every pixel of one camera."""
    rows, cols = np.mgrid[0 : rig.height_px, 0 : rig.width_px].astype(np.float64)
    rays_cam = np.stack([(cols - rig.cx_px) / rig.focal_px, (rows - rig.cy_px) / rig.focal_px, np.ones_like(cols)], -1)
    rotation = rig.camera_to_vehicle_rotation
    rays = rays_cam @ rotation.T
    origin = rig.right_camera_position if right else rig.left_camera_position
    # Ground plane z = 0.
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(rays[..., 2] < -1e-9, -origin[2] / rays[..., 2], np.inf)
    t_best = t_ground
    surface = np.zeros(t_best.shape, np.int64)  # 0 ground, 1 + i box i, -1 sky
    surface[~np.isfinite(t_best)] = -1
    for index, box in enumerate(scene.boxes):
        t_box = _hit_box(box, origin, rays)
        closer = t_box < t_best
        t_best = np.where(closer, t_box, t_best)
        surface[closer] = index + 1
    hit = origin + rays * np.where(np.isfinite(t_best), t_best, 0.0)[..., None]
    x, y, z = hit[..., 0], hit[..., 1], hit[..., 2]
    # Sky: a smooth gradient, brighter towards the horizon.
    intensity = 170.0 + 40.0 * np.clip(rows / rig.height_px, 0, 1)
    ground = surface == 0
    shade = scene.ground_albedo + scene.texture_contrast * texture(x[ground], y[ground], scene.seed)
    for stripe in scene.stripes:
        xs, ys = x[ground], y[ground]
        centre = stripe.c0 + stripe.c1 * xs + stripe.c2 * xs * xs
        painted = (np.abs(ys - centre) < stripe.width_m / 2) & (xs >= stripe.x_min_m) & (xs <= stripe.x_max_m)
        shade = np.where(painted, stripe.albedo + 8.0 * texture(xs, ys, scene.seed + 7), shade)
    intensity[ground] = shade
    for index, box in enumerate(scene.boxes):
        on = surface == index + 1
        # Faces facing x use (y, z) for texture; side faces (x, z).
        front = np.abs(x[on] - box.x_m) < 1e-6
        across = np.where(front, y[on], x[on] + 17.0)
        intensity[on] = box.albedo + scene.texture_contrast * texture(across, z[on], scene.seed + 3 + index)
    depth = np.where(surface >= 0, t_best * rays_cam[..., 2], np.inf)
    return intensity, depth


def _hit_box(box: Box, origin: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit on the box (slab method), inf on a miss."""
    low = np.array([box.x_m, box.y_m - box.width_m / 2, 0.0])
    high = np.array([box.x_m + box.depth_m, box.y_m + box.width_m / 2, box.height_m])
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / rays
        t1, t2 = (low - origin) * inverse, (high - origin) * inverse
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((near <= far) & (near > 0), near, np.inf)
