"""Horizontal lidar, simulated: one planar scan of the scenario's obstacles, ray-cast with numpy.

The scan plane at the mount height cuts every upright obstacle (cylinders and boxes on flat
ground) taller than it in its footprint and passes over every lower one. Each obstacle is
intersected only with the rays through its bounding circle, all (ray, obstacle) pairs at once,
and each ray keeps its nearest hit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from brain.pose import Pose
from modules.lidar.scan import Mount, Scan, ScanSpec, sensor_pose
from modules.sim.world import Shape, WorldObstacle

# Directions this close to parallel to a box face are nudged off it, so the slab test never
# divides zero by zero; the nudge moves a hit by far less than a nanometre.
_PARALLEL_EPS = 1e-12


@dataclass(frozen=True)
class Scene:
    """The obstacles as arrays (ENU), split by shape, built once per world; and every obstacle's
    bounding circle, cylinders first, so one pass finds the rays that may hit anything."""

    circle_xy: np.ndarray  # (n, 2) centres
    circle_r: np.ndarray
    circle_h: np.ndarray
    box_xy: np.ndarray  # (m, 2) centres
    box_half: np.ndarray  # (m, 2) half length, half width
    box_yaw: np.ndarray
    box_h: np.ndarray
    bound_xy: np.ndarray  # (n + m, 2): circle_xy, then box_xy
    bound_r: np.ndarray  # circle_r, then each box's half diagonal
    bound_h: np.ndarray

    @classmethod
    def from_obstacles(cls, obstacles: tuple[WorldObstacle, ...] | list[WorldObstacle]) -> Scene:
        """The arrays for ``obstacles`` (any number, including none)."""
        circles = [o for o in obstacles if o.shape is Shape.CYLINDER]
        boxes = [o for o in obstacles if o.shape is Shape.BOX]
        circle_xy = np.array([(o.east_m, o.north_m) for o in circles], dtype=float).reshape(-1, 2)
        circle_r = np.array([o.radius_m for o in circles], dtype=float)
        circle_h = np.array([o.height_m for o in circles], dtype=float)
        box_xy = np.array([(o.east_m, o.north_m) for o in boxes], dtype=float).reshape(-1, 2)
        box_half = np.array([(o.length_m / 2, o.width_m / 2) for o in boxes], dtype=float).reshape(-1, 2)
        box_h = np.array([o.height_m for o in boxes], dtype=float)
        return cls(
            circle_xy=circle_xy,
            circle_r=circle_r,
            circle_h=circle_h,
            box_xy=box_xy,
            box_half=box_half,
            box_yaw=np.array([o.yaw_rad for o in boxes], dtype=float),
            box_h=box_h,
            bound_xy=np.concatenate((circle_xy, box_xy)),
            bound_r=np.concatenate((circle_r, np.hypot(box_half[:, 0], box_half[:, 1]))),
            bound_h=np.concatenate((circle_h, box_h)),
        )


def cast(
    scene: Scene,
    pose: Pose,
    mount: Mount,
    spec: ScanSpec | None = None,
    rng: np.random.Generator | None = None,
    noise_scale: float = 1.0,
) -> Scan:
    """Scan ``scene`` from ``mount`` on a vehicle at ``pose``. Range noise is Gaussian with
    ``spec.range_noise_std_m * noise_scale`` when ``rng`` is given, none otherwise."""
    spec = spec or ScanSpec()
    bearings = spec.bearings_rad()
    origin, yaw = sensor_pose(pose, mount)
    scan = Scan(mount, spec, bearings, ray_ranges(origin, yaw + bearings, scene, mount.z_m, spec.max_range_m))
    if rng is not None:
        add_noise(scan, rng, noise_scale)
    return scan


def add_noise(scan: Scan, rng: np.random.Generator, noise_scale: float = 1.0) -> None:
    """Gaussian range noise, ``range_noise_std_m * noise_scale``, on the scan's returns (in place;
    a scan without returns draws nothing)."""
    std = scan.spec.range_noise_std_m * noise_scale
    hit = scan.returns
    if std > 0 and hit.size:
        # Noise cannot put a return behind the scanner or past its limit.
        scan.ranges_m[hit] = np.clip(scan.ranges_m[hit] + rng.normal(0.0, std, hit.size), 0.0, scan.spec.max_range_m)


def ray_ranges(
    origin: np.ndarray, angles_rad: np.ndarray, scene: Scene, plane_height_m: float, max_range_m: float
) -> np.ndarray:
    """Distance from ``origin`` (ENU) along each ray to the nearest footprint cut by the plane at
    ``plane_height_m``; inf where nothing is hit within ``max_range_m``. ``angles_rad`` are ENU
    ray angles, evenly spaced and increasing, as a scanner's are."""
    rays, t, _ = _footprint_hits(origin, angles_rad, scene, plane_height_m, max_range_m)
    return _nearest(len(angles_rad), rays, t, max_range_m)


def descending_ray_ranges(
    origin: np.ndarray,
    angles_rad: np.ndarray,
    height_m: float,
    slopes: np.ndarray,
    scene: Scene,
    max_range_m: float,
) -> np.ndarray:
    """Horizontal distance along each ray of a scanner pitched down (ray i starts ``height_m``
    above the ground at ``origin`` and falls ``slopes[i]`` per metre) to the first footprint it
    enters below the obstacle's top; inf where none within ``max_range_m``. A ray that enters
    above the top and comes down onto it is taken to miss: for the narrow obstacles of a scenario
    that top is a few centimetres long."""
    rays, t, tops = _footprint_hits(origin, angles_rad, scene, 0.0, max_range_m)
    under = height_m - slopes[rays] * t < tops
    return _nearest(len(angles_rad), rays[under], t[under], max_range_m)


def _footprint_hits(
    origin: np.ndarray, angles_rad: np.ndarray, scene: Scene, plane_height_m: float, max_range_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ray index, distance to the footprint's entry, obstacle height) of every ray that enters
    an obstacle taller than ``plane_height_m`` (inf distances where a pair misses)."""
    rays, obstacles = _ray_pairs(
        origin, angles_rad, scene.bound_xy, scene.bound_r, scene.bound_h, plane_height_m, max_range_m
    )
    if not rays.size:
        return rays, np.zeros(0), np.zeros(0)
    is_box = obstacles >= len(scene.circle_r)
    circle_rays, circles = rays[~is_box], obstacles[~is_box]
    box_rays, boxes = rays[is_box], obstacles[is_box] - len(scene.circle_r)
    circle_t = _circle_hits(origin, angles_rad[circle_rays], scene.circle_xy[circles], scene.circle_r[circles])
    box_t = _box_hits(origin, angles_rad[box_rays], scene.box_xy[boxes], scene.box_half[boxes], scene.box_yaw[boxes])
    return (
        np.concatenate((circle_rays, box_rays)),
        np.concatenate((circle_t, box_t)),
        scene.bound_h[np.concatenate((circles, boxes + len(scene.circle_r)))],
    )


def _nearest(count: int, rays: np.ndarray, t: np.ndarray, max_range_m: float) -> np.ndarray:
    """Each ray's nearest hit among the (ray, distance) pairs; inf beyond ``max_range_m``."""
    nearest = np.full(count, np.inf)
    if not rays.size:
        return nearest
    np.minimum.at(nearest, rays, t)
    nearest[nearest > max_range_m] = np.inf
    return nearest


def _ray_pairs(
    origin: np.ndarray,
    angles_rad: np.ndarray,
    centres: np.ndarray,
    radii: np.ndarray,
    heights: np.ndarray,
    plane_height_m: float,
    max_range_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(ray index, obstacle index) of every ray that passes through an obstacle's bounding circle,
    for the obstacles taller than the scan plane and within range. A typical obstacle spans a few
    rays, so intersecting only these pairs costs a small fraction of all rays x obstacles."""
    empty = np.zeros(0, dtype=np.intp)
    if not len(centres):
        return empty, empty
    offset = centres - origin
    distance = np.hypot(offset[:, 0], offset[:, 1])
    keep = np.flatnonzero((heights > plane_height_m) & (distance - radii <= max_range_m))
    if not keep.size:
        return empty, empty
    step = (angles_rad[-1] - angles_rad[0]) / (len(angles_rad) - 1)
    # Bearing of each centre measured from the first ray, wrapped into the sweep's neighbourhood.
    middle = (angles_rad[0] + angles_rad[-1]) / 2
    bearing = np.arctan2(offset[keep, 1], offset[keep, 0]) - middle
    bearing = (bearing + math.pi) % (2 * math.pi) - math.pi + (middle - angles_rad[0])
    inside = distance[keep] <= radii[keep]
    half_width = np.arcsin(np.clip(radii[keep] / np.maximum(distance[keep], 1e-9), 0.0, 1.0))
    # One ray of margin each side, so rounding can never drop a ray that grazes the circle.
    first = np.where(inside, 0, np.ceil((bearing - half_width) / step) - 1).astype(np.intp)
    last = np.where(inside, len(angles_rad) - 1, np.floor((bearing + half_width) / step) + 1).astype(np.intp)
    first, last = np.maximum(first, 0), np.minimum(last, len(angles_rad) - 1)
    counts = np.maximum(last - first + 1, 0)
    total = int(counts.sum())
    if not total:
        return empty, empty
    obstacle = np.repeat(keep, counts)
    starts = np.repeat(first, counts)
    position = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    return starts + position, obstacle


def _circle_hits(origin: np.ndarray, angles_rad: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Per (ray, circle) pair: distance to the circle's first crossing, inf where missed."""
    dx, dy = np.cos(angles_rad), np.sin(angles_rad)
    ox, oy = centres[:, 0] - origin[0], centres[:, 1] - origin[1]
    along = dx * ox + dy * oy  # distance along the ray to the foot of the centre
    disc = along**2 - (ox**2 + oy**2 - radii**2)
    t = along - np.sqrt(np.maximum(disc, 0.0))  # a miss (disc < 0) is masked below
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _box_hits(
    origin: np.ndarray, angles_rad: np.ndarray, centres: np.ndarray, half: np.ndarray, yaw: np.ndarray
) -> np.ndarray:
    """Per (ray, box) pair: distance to the box's entry point (slab method in the box's own
    frame), inf where missed."""
    c, s = np.cos(yaw), np.sin(yaw)
    rx, ry = origin[0] - centres[:, 0], origin[1] - centres[:, 1]
    ox, oy = rx * c + ry * s, -rx * s + ry * c
    # The ray angle in the box frame gives the direction without a rotation per component.
    local = angles_rad - yaw
    dx, dy = np.cos(local), np.sin(local)
    dx = np.where(np.abs(dx) < _PARALLEL_EPS, _PARALLEL_EPS, dx)
    dy = np.where(np.abs(dy) < _PARALLEL_EPS, _PARALLEL_EPS, dy)
    tx1, tx2 = (-half[:, 0] - ox) / dx, (half[:, 0] - ox) / dx
    ty1, ty2 = (-half[:, 1] - oy) / dy, (half[:, 1] - oy) / dy
    t_near = np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2))
    t_far = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
