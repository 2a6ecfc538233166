"""Ready-made synthetic runs: the README's demo route and the synthetic KITTI 00 benchmark.

Both build a procedural street world around a camera trajectory and wrap the VGGT oracle in
an :class:`~swiftjax.pipeline.OraclePredictor`, with the ground-truth poses beside it.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from swiftjax.pipeline import OraclePredictor

__all__ = ["SyntheticRun", "loop_route_run", "trajectory_run"]


@dataclasses.dataclass
class SyntheticRun:
    """A predictor over a synthetic world and its truth."""

    predictor: OraclePredictor
    ground_truth: np.ndarray  # [N, 4, 4] camera-to-world, metres


def trajectory_run(
    cam_to_world: np.ndarray,
    *,
    seed: int = 0,
    image_hw: tuple[int, int] = (154, 518),
    name: str = "trajectory",
    noise: object | None = None,
) -> SyntheticRun:
    """The oracle driving along ``cam_to_world [N, 4, 4]`` (e.g. KITTI 00's ground truth)."""
    from swiftjax.synthetic.oracle import OracleNoise, VGGTOracle
    from swiftjax.synthetic.world import WorldConfig, build_world

    poses = np.asarray(cam_to_world, np.float64)
    world = build_world(poses, WorldConfig(seed=seed))
    oracle = VGGTOracle(
        world, poses, image_hw=image_hw, seed=seed, noise=noise if noise is not None else OracleNoise()
    )
    desc = {"name": name, "image_hw": list(image_hw), "frames": int(poses.shape[0])}
    return SyntheticRun(OraclePredictor(oracle, desc), poses)


def loop_route_run(
    frames: int | None = None, *, seed: int = 0, image_hw: tuple[int, int] = (154, 518)
) -> SyntheticRun:
    """The demo: a generated rounded-rectangle route driven ~1.25 times (a revisit to close).

    ``frames`` truncates the route (default: the whole route, about 620 frames at 1 m).
    """
    from swiftjax.synthetic.routes import loop_route

    poses = loop_route()
    if frames is not None:
        if frames < 1:
            raise ValueError(f"--frames must be >= 1, got {frames}")
        if frames > poses.shape[0]:
            poses = loop_route(laps=1.25 * frames / poses.shape[0] + 0.01)
        poses = poses[:frames]
    return trajectory_run(poses, seed=seed, image_hw=image_hw, name="loop_route")


def kitti00_run(shared: pathlib.Path, *, seed: int = 0, frames: int | None = None) -> SyntheticRun:
    """The oracle along the real KITTI 00 ground truth (``shared/data/trajectories``)."""
    from swiftjax.io.trajectory import read_kitti

    poses = read_kitti(pathlib.Path(shared) / "data" / "trajectories" / "KITTI_00_gt.txt")
    if frames is not None:
        poses = poses[:frames]
    return trajectory_run(poses, seed=seed, name="kitti00")
