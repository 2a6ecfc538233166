"""Ready-made synthetic runs: the README's demo route and the synthetic KITTI 00 benchmark.

Both build a procedural street world around a camera trajectory and wrap the VGGT oracle in
an :class:`~swiftjax.pipeline.OraclePredictor`, with the ground-truth poses beside it.

The oracle fails like VGGT (:mod:`swiftjax.synthetic.oracle`, "Loop-centric chunks"): a loop
chunk whose halves share no view comes back superimposed.  Perceptual aliasing
(:func:`swiftjax.synthetic.places.plant_aliasing`) plants look-alike far-apart segment pairs
whose place tokens share a component: ``aliasing=rate`` asks for ``rate`` false candidates per
true loop chunk pair.  The demo route and synthetic KITTI 00 turn it on by default at
:data:`DEMO_ALIASING` / :data:`KITTI00_ALIASING` (0.3: 30 % extra false candidates; the demo
route gets one look-alike pair, KITTI 00 nine), so their headline numbers include
false candidates; ``aliasing=0`` is the alias-free run.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from swiftjax.pipeline import OraclePredictor

__all__ = [
    "DEMO_ALIASING",
    "KITTI00_ALIASING",
    "OracleSpec",
    "SyntheticRun",
    "kitti00_run",
    "loop_route_run",
    "trajectory_run",
]

#: Look-alike pairs planted in the demo route by default (rate; :func:`loop_route_run`).
DEMO_ALIASING = 0.3
#: ... and in synthetic KITTI 00 (:func:`kitti00_run`).
KITTI00_ALIASING = 0.3


@dataclasses.dataclass
class SyntheticRun:
    """A predictor over a synthetic world and its truth."""

    predictor: OraclePredictor
    ground_truth: np.ndarray  # [N, 4, 4] camera-to-world, metres
    aliasing: tuple[tuple[int, int, int], ...] = ()  # planted look-alike pairs (s_a, s_b, L)


@dataclasses.dataclass(frozen=True, eq=False)
class OracleSpec:
    """The recipe of a :func:`trajectory_run` predictor: a worker process rebuilds the world
    and the oracle from it (kilobytes to send instead of the world's geometry).
    ``options``: :func:`trajectory_run`'s keyword arguments."""

    cam_to_world: np.ndarray
    options: dict = dataclasses.field(default_factory=dict)

    def build(self) -> OraclePredictor:
        return trajectory_run(self.cam_to_world, **self.options).predictor


def trajectory_run(
    cam_to_world: np.ndarray,
    *,
    seed: int = 0,
    image_hw: tuple[int, int] = (154, 518),
    name: str = "trajectory",
    noise: object | None = None,
    aliasing: float | tuple[tuple[int, int, int], ...] = 0.0,
    alias_strength: float | None = None,
    hallucination: object | None = "default",
    moving_cars: int = 0,
) -> SyntheticRun:
    """The oracle driving along ``cam_to_world [N, 4, 4]`` (e.g. KITTI 00's ground truth).

    ``aliasing``: a rate for :func:`~swiftjax.synthetic.places.plant_aliasing` (as many pairs
    as fit, seed ``seed``) or explicit ``(s_a, s_b, L)`` segment pairs; ``alias_strength``:
    their ``lambda`` (default :data:`~swiftjax.synthetic.places.DEFAULT_ALIAS_STRENGTH`).
    ``hallucination``: a :class:`~swiftjax.synthetic.noise.Hallucination`, ``"default"``, or
    ``None`` (honest loop chunks).  The planted pairs are in
    ``run.aliasing`` and in the predictor's fingerprint.  ``moving_cars``: cars driving along
    the road (:mod:`swiftjax.synthetic.world`; their true masks are the oracle's semantic
    label :data:`~swiftjax.synthetic.world.CAR`).
    """
    options = {k: v for k, v in locals().items() if k != "cam_to_world"}  # OracleSpec: every keyword
    from swiftjax.synthetic import places
    from swiftjax.synthetic.noise import Hallucination, OracleNoise
    from swiftjax.synthetic.oracle import VGGTOracle
    from swiftjax.synthetic.world import WorldConfig, build_world

    poses = np.asarray(cam_to_world, np.float64)
    if isinstance(aliasing, (int, float)):
        segs = places.plant_aliasing(poses, float(aliasing), seed=seed, strict=False) if aliasing else ()
    else:
        segs = tuple(tuple(int(v) for v in seg) for seg in aliasing)
    strength = places.DEFAULT_ALIAS_STRENGTH if alias_strength is None else float(alias_strength)
    world = build_world(poses, WorldConfig(seed=seed, num_movers=moving_cars))
    oracle = VGGTOracle(
        world,
        poses,
        image_hw=image_hw,
        seed=seed,
        noise=noise if noise is not None else OracleNoise(),
        place_config=places.PlaceTokenConfig(seed=seed, aliasing=segs, alias_strength=strength),
        hallucination=Hallucination() if hallucination == "default" else hallucination,
    )
    desc = {"name": name, "image_hw": list(image_hw), "frames": int(poses.shape[0])}
    if segs:
        desc["aliasing"] = {"segments": [list(x) for x in segs], "strength": strength}
    if oracle.hallucination is None:
        desc["hallucination"] = None
    if moving_cars:
        desc["moving_cars"] = int(moving_cars)
    return SyntheticRun(OraclePredictor(oracle, desc, spec=OracleSpec(poses, options)), poses, segs)


def loop_route_run(
    frames: int | None = None,
    *,
    seed: int = 0,
    image_hw: tuple[int, int] = (154, 518),
    aliasing: float | tuple[tuple[int, int, int], ...] = DEMO_ALIASING,
    spacing_m: float = 1.0,
    **options,
) -> SyntheticRun:
    """The demo: a generated rounded-rectangle route driven ~1.25 times (a revisit to close).

    ``frames`` truncates the route (default: the whole route, about 620 frames at 1 m);
    ``spacing_m`` is the distance between frames (4 m: the same route in ~155 frames).
    ``aliasing`` and ``options`` (``alias_strength``, ``hallucination``, ``noise``) as
    :func:`trajectory_run`; a truncated route without a revisit gets no look-alike pair.
    """
    from swiftjax.synthetic.routes import loop_route

    poses = loop_route(spacing_m=spacing_m)
    if frames is not None:
        if frames < 1:
            raise ValueError(f"--frames must be >= 1, got {frames}")
        if frames > poses.shape[0]:
            poses = loop_route(laps=1.25 * frames / poses.shape[0] + 0.01, spacing_m=spacing_m)
        poses = poses[:frames]
    return trajectory_run(poses, seed=seed, image_hw=image_hw, name="loop_route", aliasing=aliasing, **options)


def kitti00_run(
    shared: pathlib.Path,
    *,
    seed: int = 0,
    frames: int | None = None,
    aliasing: float | tuple[tuple[int, int, int], ...] = KITTI00_ALIASING,
    **options,
) -> SyntheticRun:
    """The oracle along the real KITTI 00 ground truth (``shared/data/trajectories``);
    ``aliasing`` and ``options`` as :func:`trajectory_run`."""
    from swiftjax.io.trajectory import read_kitti

    poses = read_kitti(pathlib.Path(shared) / "data" / "trajectories" / "KITTI_00_gt.txt")
    if frames is not None:
        poses = poses[:frames]
    return trajectory_run(poses, seed=seed, name="kitti00", aliasing=aliasing, **options)
