"""A procedural street world built around a camera trajectory (host-side, deterministic).

The world is what the synthetic "VGGT oracle" renders: a ground surface under the route,
building blocks (oriented boxes) along both sides, poles and trees (vertical cylinders) at
the kerb, and open sky (no hit: infinite depth).  It is built once per trajectory from a
seed, in float64 NumPy, and handed to the JAX renderer (:mod:`swiftjax.synthetic.render`)
as plain arrays.

Geometry (world frame = the trajectory's frame, metres; OpenCV cameras, y down):

* ``up`` = minus the mean camera y axis (cameras are roughly upright).
* The route is resampled every ``ground_sample_m`` metres of arc length.  At each sample the
  road surface is a plane through the camera position minus ``camera_height`` along its
  normal, and the normal is ``up`` made perpendicular to the local 3-D travel direction
  (smoothed over +-``slope_window_m``): the road follows the route's slope, so KITTI 00's 25 m
  of climb does not bury or float the cameras.  A camera uses the plane of its nearest sample
  (:func:`ground_planes`), so the ground a frame sees is a function of the frame alone.
* Buildings: on each side, consecutive blocks of random length, depth and height separated by
  random gaps (sometimes a cross-street gap); each is an oriented box whose axes are (local
  horizontal travel direction, left, ``up``), set back from the kerb, sunk ``sink_m`` below
  the road so it never floats.
* Poles at the kerb every ``pole_spacing_m`` (alternating sides), trees between kerb and
  façades with probability ``tree_prob`` per ``tree_spacing_m``.
* Clearance: any object whose footprint comes closer than ``clearance_m`` (buildings) or
  ``pole_clearance_m`` (cylinders) to ANY camera position of the trajectory is dropped, so
  loops, crossings and revisits never drive through a wall.

Moving objects (``num_movers > 0``, default none): cars (boxes ``car_size``) driving along
the route in a lane ``car_lane`` to the left or right of it, each at a constant arc-length
speed (a random fraction ``car_speed`` of the camera's mean speed, either direction; a
negative speed is oncoming traffic), from a random start.  Their pose is a function of the
frame index (time), :func:`mover_boxes`; a car off either end of the route, or within
``car_clearance_m`` of the camera at that frame, is not drawn.

Semantic ids: :data:`SKY` 0, :data:`GROUND` 1, :data:`BUILDING` 2, :data:`POLE` 3, :data:`TREE` 4,
:data:`CAR` 5.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "SKY",
    "GROUND",
    "BUILDING",
    "POLE",
    "TREE",
    "CAR",
    "SEMANTIC_NAMES",
    "Movers",
    "mover_boxes",
    "WorldConfig",
    "World",
    "build_world",
    "ground_planes",
]

SKY, GROUND, BUILDING, POLE, TREE, CAR = 0, 1, 2, 3, 4, 5
SEMANTIC_NAMES = ("sky", "ground", "building", "pole", "tree", "car")


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    """Parameters of the procedural street (all lengths in metres; ranges are ``(lo, hi)``)."""

    seed: int = 0
    camera_height: float = 1.65  # KITTI's camera height above the road
    ground_sample_m: float = 2.0
    slope_window_m: float = 10.0
    clearance_m: float = 5.0
    pole_clearance_m: float = 3.5
    building_length: tuple[float, float] = (12.0, 35.0)
    building_depth: tuple[float, float] = (8.0, 16.0)
    building_height: tuple[float, float] = (6.0, 22.0)
    building_setback: tuple[float, float] = (6.0, 10.0)  # kerb line to façade, from the route
    building_gap: tuple[float, float] = (1.0, 6.0)
    cross_street_prob: float = 0.15
    cross_street_gap: tuple[float, float] = (12.0, 20.0)
    sink_m: float = 3.0
    pole_spacing_m: float = 30.0
    pole_offset: tuple[float, float] = (4.5, 5.0)
    pole_radius: tuple[float, float] = (0.12, 0.2)
    pole_height: tuple[float, float] = (5.0, 8.0)
    tree_spacing_m: float = 18.0
    tree_prob: float = 0.5
    tree_offset: tuple[float, float] = (5.5, 7.0)
    tree_radius: tuple[float, float] = (0.4, 0.9)
    tree_height: tuple[float, float] = (4.0, 9.0)
    num_movers: int = 0
    car_size: tuple[float, float, float] = (4.2, 1.8, 1.5)  # length, width, height
    car_lane: tuple[float, float] = (2.6, 3.2)  # lateral offset from the route
    car_speed: tuple[float, float] = (0.4, 1.3)  # |speed| / the camera's mean speed
    car_clearance_m: float = 1.5


class Movers(NamedTuple):
    """Cars driving along the route (host NumPy float64; see the module docstring).

    Attributes:
        start: ``[C]`` arc length at frame 0 (metres).
        speed: ``[C]`` metres of arc length per frame (negative: against the route).
        lane: ``[C]`` signed lateral offset (positive: left of the route).
        half: ``[C, 3]`` half extents (length, width, height).
        route_s, route_ground, route_fwd: the route samples (``[M]``, ``[M, 3]``, ``[M, 3]``).
        camera: ``[N, 3]`` camera positions (a car never comes within ``clearance`` of the
            camera at the same frame).
        clearance: metres.
    """

    start: np.ndarray
    speed: np.ndarray
    lane: np.ndarray
    half: np.ndarray
    route_s: np.ndarray
    route_ground: np.ndarray
    route_fwd: np.ndarray
    camera: np.ndarray
    clearance: float

    @property
    def num(self) -> int:
        return int(self.start.shape[0])


class World(NamedTuple):
    """The static scene (host NumPy float64; world frame of the trajectory, metres).

    Attributes:
        up: ``[3]`` unit up vector.
        box_center: ``[B, 3]`` box centres.
        box_axes: ``[B, 3, 3]`` world-from-box rotation (columns: along-route, left, up).
        box_half: ``[B, 3]`` half extents along those axes.
        box_semantic: ``[B]`` int32 (all :data:`BUILDING`).
        cyl_base: ``[C, 3]`` bottom centre of each vertical cylinder (already sunk).
        cyl_radius: ``[C]``.
        cyl_height: ``[C]`` (from the base, along ``up``).
        cyl_semantic: ``[C]`` int32 (:data:`POLE` or :data:`TREE`).
        ground_points: ``[M, 3]`` a point of the road plane at each route sample.
        ground_normals: ``[M, 3]`` the plane's unit normal (pointing up).
        movers: :class:`Movers` (cars) or ``None`` (a static world).
    """

    up: np.ndarray
    box_center: np.ndarray
    box_axes: np.ndarray
    box_half: np.ndarray
    box_semantic: np.ndarray
    cyl_base: np.ndarray
    cyl_radius: np.ndarray
    cyl_height: np.ndarray
    cyl_semantic: np.ndarray
    ground_points: np.ndarray
    ground_normals: np.ndarray
    movers: Movers | None = None

    @property
    def num_boxes(self) -> int:
        return int(self.box_center.shape[0])

    @property
    def num_cylinders(self) -> int:
        return int(self.cyl_base.shape[0])


def _check_trajectory(cam_to_world: np.ndarray) -> np.ndarray:
    T = np.asarray(cam_to_world, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"cam_to_world must have shape [N, 4, 4] or [N, 3, 4], got {T.shape}")
    if T.shape[0] < 2:
        raise ValueError(f"cam_to_world needs at least 2 poses to build a route, got {T.shape[0]}")
    if not np.all(np.isfinite(T)):
        raise ValueError("cam_to_world holds non-finite values (nan/inf)")
    return T


class _Route(NamedTuple):
    s: np.ndarray  # [M] arc length of each sample
    p: np.ndarray  # [M, 3] camera position
    fwd: np.ndarray  # [M, 3] unit horizontal travel direction
    normal: np.ndarray  # [M, 3] road normal
    ground: np.ndarray  # [M, 3] road point under the camera


def _route(positions: np.ndarray, up: np.ndarray, cfg: WorldConfig) -> _Route:
    seg = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    s_cam = np.concatenate([[0.0], np.cumsum(seg)])
    total = s_cam[-1]
    if total < 4 * cfg.ground_sample_m:
        raise ValueError(
            f"the trajectory is only {total:.2f} m long; the street world needs at least "
            f"{4 * cfg.ground_sample_m:.1f} m of travel"
        )
    # drop repeated positions (a parked car) so the arc-length interpolation is monotone
    keep = np.concatenate([[True], seg > 1e-9])
    s_u, p_u = s_cam[keep], positions[keep]
    s = np.arange(0.0, total + 1e-9, cfg.ground_sample_m)
    p = np.stack([np.interp(s, s_u, p_u[:, k]) for k in range(3)], axis=1)
    w = cfg.slope_window_m
    ahead = np.stack([np.interp(np.minimum(s + w, total), s_u, p_u[:, k]) for k in range(3)], 1)
    behind = np.stack([np.interp(np.maximum(s - w, 0.0), s_u, p_u[:, k]) for k in range(3)], 1)
    d3 = ahead - behind
    d3 /= np.maximum(np.linalg.norm(d3, axis=1, keepdims=True), 1e-12)
    normal = up[None, :] - np.sum(up * d3, axis=1, keepdims=True) * d3
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    fwd = d3 - np.sum(up * d3, axis=1, keepdims=True) * up[None, :]
    fwd /= np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-12)
    ground = p - cfg.camera_height * normal
    return _Route(s, p, fwd, normal, ground)


def _at(route: _Route, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Road point and horizontal travel direction at arc length ``s`` (nearest sample)."""
    i = int(np.clip(np.rint(s / (route.s[1] - route.s[0])), 0, len(route.s) - 1))
    return route.ground[i], route.fwd[i]


def build_world(cam_to_world: np.ndarray, config: WorldConfig = WorldConfig()) -> World:
    """Build the street world around ``cam_to_world`` ``[N, 4, 4]`` (deterministic in ``config.seed``).

    Raises:
        ValueError: bad trajectory shape / values, or a route shorter than a few metres.
    """
    T = _check_trajectory(cam_to_world)
    cfg = config
    rng = np.random.default_rng(cfg.seed)
    up = -T[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    positions = T[:, :3, 3]
    route = _route(positions, up, cfg)
    total = route.s[-1]
    U = lambda r: rng.uniform(r[0], r[1])

    centers, axes, halves = [], [], []
    for side in (+1.0, -1.0):  # +1: left (up x forward), -1: right
        s = U(cfg.building_gap)
        while s < total:
            length = U(cfg.building_length)
            depth, height, setback = U(cfg.building_depth), U(cfg.building_height), U(cfg.building_setback)
            g, f = _at(route, min(s + 0.5 * length, total))
            left = np.cross(up, f)
            c = g + side * left * (setback + 0.5 * depth) + up * (0.5 * (height - cfg.sink_m))
            centers.append(c)
            axes.append(np.stack([f, left, up], axis=1))
            halves.append([0.5 * length, 0.5 * depth, 0.5 * (height + cfg.sink_m)])
            gap = U(cfg.cross_street_gap) if rng.random() < cfg.cross_street_prob else U(cfg.building_gap)
            s += length + gap
    box_center = np.asarray(centers).reshape(-1, 3)
    box_axes = np.asarray(axes).reshape(-1, 3, 3)
    box_half = np.asarray(halves, dtype=np.float64).reshape(-1, 3)

    bases, radii, heights, sems = [], [], [], []
    k = 0
    for s in np.arange(U((0.0, cfg.pole_spacing_m)), total, cfg.pole_spacing_m):
        g, f = _at(route, s)
        side = 1.0 if k % 2 == 0 else -1.0
        k += 1
        bases.append(g + side * np.cross(up, f) * U(cfg.pole_offset) - up * cfg.sink_m)
        radii.append(U(cfg.pole_radius))
        heights.append(U(cfg.pole_height) + cfg.sink_m)
        sems.append(POLE)
    for side in (+1.0, -1.0):
        for s in np.arange(U((0.0, cfg.tree_spacing_m)), total, cfg.tree_spacing_m):
            if rng.random() >= cfg.tree_prob:
                continue
            g, f = _at(route, s + rng.uniform(-3.0, 3.0))
            bases.append(g + side * np.cross(up, f) * U(cfg.tree_offset) - up * cfg.sink_m)
            radii.append(U(cfg.tree_radius))
            heights.append(U(cfg.tree_height) + cfg.sink_m)
            sems.append(TREE)
    cyl_base = np.asarray(bases, dtype=np.float64).reshape(-1, 3)
    cyl_radius = np.asarray(radii, dtype=np.float64)
    cyl_height = np.asarray(heights, dtype=np.float64)
    cyl_semantic = np.asarray(sems, dtype=np.int32)

    # ---- clearance: nothing within reach of any camera position
    tree = cKDTree(positions)
    keep_box = np.ones(len(box_center), bool)
    reach = np.hypot(box_half[:, 0], box_half[:, 1]) + cfg.clearance_m
    for i, near in enumerate(tree.query_ball_point(box_center, reach)):
        if not near:
            continue
        q = (positions[near] - box_center[i]) @ box_axes[i]  # box-frame coordinates
        dx = np.maximum(np.abs(q[:, 0]) - box_half[i, 0], 0.0)
        dy = np.maximum(np.abs(q[:, 1]) - box_half[i, 1], 0.0)
        keep_box[i] = np.all(np.hypot(dx, dy) >= cfg.clearance_m)
    keep_cyl = np.ones(len(cyl_base), bool)
    # 3-D ball query, generous enough to contain every camera whose HORIZONTAL distance is in
    # reach (cameras sit camera_height + sink_m above the base, plus the route's slope)
    reach_c = cyl_radius + cfg.pole_clearance_m + cfg.camera_height + cfg.sink_m + 10.0
    for i, near in enumerate(tree.query_ball_point(cyl_base, reach_c)):
        if not near:
            continue
        v = positions[near] - cyl_base[i]
        horiz = v - np.outer(v @ up, up)
        keep_cyl[i] = np.all(np.linalg.norm(horiz, axis=1) - cyl_radius[i] >= cfg.pole_clearance_m)

    nb = int(keep_box.sum())
    cyl_sem = cyl_semantic[keep_cyl]
    movers = None
    if cfg.num_movers > 0:
        # a separate stream: adding cars leaves the static world unchanged
        mrng = np.random.default_rng([cfg.seed, 5])
        C = int(cfg.num_movers)
        v_cam = total / max(len(positions) - 1, 1)
        speed = mrng.uniform(*cfg.car_speed, size=C) * v_cam * np.where(mrng.random(C) < 0.5, -1.0, 1.0)
        movers = Movers(
            start=mrng.uniform(0.0, total, size=C),
            speed=speed,
            lane=mrng.uniform(*cfg.car_lane, size=C) * np.where(mrng.random(C) < 0.5, -1.0, 1.0),
            half=np.tile(0.5 * np.asarray(cfg.car_size, np.float64), (C, 1)),
            route_s=route.s,
            route_ground=route.ground,
            route_fwd=route.fwd,
            camera=positions.copy(),
            clearance=float(cfg.car_clearance_m),
        )
    return World(
        up=up,
        box_center=box_center[keep_box],
        box_axes=box_axes[keep_box],
        box_half=box_half[keep_box],
        box_semantic=np.full(nb, BUILDING, np.int32),
        cyl_base=cyl_base[keep_cyl],
        cyl_radius=cyl_radius[keep_cyl],
        cyl_height=cyl_height[keep_cyl],
        cyl_semantic=cyl_sem,
        ground_points=route.ground,
        ground_normals=route.normal,
        movers=movers,
    )


def mover_boxes(world: World, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cars at each of ``frames [F]``: ``(centre [F, C, 3], axes [F, C, 3, 3], half [F, C, 3],
    visible [F, C])`` (world frame; axes' columns: travel direction, left, up).

    A car stands on the route's road point at its arc length (sunk 5 cm), ``lane`` to the
    side; it is invisible off the route or within ``clearance`` (plus its half diagonal) of
    that frame's camera.  ``C = 0`` for a static world.
    """
    f = np.asarray(frames, np.int64).reshape(-1)
    m = world.movers
    if m is None:
        z = np.zeros((len(f), 0))
        return z[..., None].repeat(3, -1), np.zeros((len(f), 0, 3, 3)), z[..., None].repeat(3, -1), z.astype(bool)
    s = m.start[None, :] + m.speed[None, :] * f[:, None].astype(np.float64)  # [F, C]
    total = m.route_s[-1]
    on = (s >= 0.0) & (s <= total)
    sc = np.clip(s, 0.0, total)
    g = np.stack([np.interp(sc, m.route_s, m.route_ground[:, k]) for k in range(3)], -1)
    fwd = np.stack([np.interp(sc, m.route_s, m.route_fwd[:, k]) for k in range(3)], -1)
    fwd /= np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-12)
    up = np.broadcast_to(world.up, fwd.shape)
    left = np.cross(up, fwd)
    left /= np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-12)
    fwd = np.cross(left, up)
    half = np.broadcast_to(m.half, (*s.shape, 3)).copy()
    centre = g + left * m.lane[None, :, None] + up * (half[..., 2:3] - 0.05)
    axes = np.stack([fwd, left, up], axis=-1)
    cam = m.camera[np.clip(f, 0, len(m.camera) - 1)]
    near = np.linalg.norm(centre - cam[:, None, :], axis=-1) < m.clearance + np.linalg.norm(half, axis=-1)
    return centre, axes, half, on & ~near


def ground_planes(world: World, positions: np.ndarray) -> np.ndarray:
    """The road plane each camera sees: ``[N, 3]`` positions -> ``[N, 4]`` ``(n, d)`` with ``n . x = d``.

    Nearest route sample's plane (a function of the camera position alone).
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    _, idx = cKDTree(world.ground_points + 0.0).query(p)
    n = world.ground_normals[idx]
    d = np.sum(n * world.ground_points[idx], axis=1)
    return np.concatenate([n, d[:, None]], axis=1)
