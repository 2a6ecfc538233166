"""A synthetic driving world with a VGGT oracle, for development and benchmarks without weights.

    from swiftjax.synthetic import VGGTOracle, build_world, loop_route
    poses = loop_route()
    oracle = VGGTOracle(build_world(poses), poses)
    pred = oracle.predict_chunk(np.arange(75))     # a ChunkPrediction, as VGGT's runners return

Modules: :mod:`~swiftjax.synthetic.world` (procedural street around a trajectory),
:mod:`~swiftjax.synthetic.render` (JAX ray casting), :mod:`~swiftjax.synthetic.oracle`
(VGGT's outputs with VGGT's kinds of error, including its failure on loop chunks whose halves
share no view; its error model in :mod:`~swiftjax.synthetic.noise`, its pixel kernel in
:mod:`~swiftjax.synthetic.pixel_noise` over the counter-based :mod:`~swiftjax.synthetic.hash_rng`,
its float64 NumPy SE(3) maps in :mod:`~swiftjax.synthetic.se3_np`), :mod:`~swiftjax.synthetic.covisibility` (co-visibility of frame sets from the
world), :mod:`~swiftjax.synthetic.places` (per-frame place tokens for loop detection, with
optional perceptual aliasing), :mod:`~swiftjax.synthetic.routes` (a generated loop route), :mod:`~swiftjax.synthetic.demo` (the
demo runs: the oracle on a route, as ``swiftjax demo`` runs it).
"""

from swiftjax.synthetic.noise import Hallucination, OracleNoise
from swiftjax.synthetic.oracle import LoopChunkTruth, VGGTOracle, kitti_intrinsics
from swiftjax.synthetic.places import PlaceTokenConfig, make_place_params, place_tokens, plant_aliasing
from swiftjax.synthetic.routes import loop_route
from swiftjax.synthetic.world import World, WorldConfig, build_world

__all__ = [
    "Hallucination",
    "LoopChunkTruth",
    "OracleNoise",
    "PlaceTokenConfig",
    "VGGTOracle",
    "World",
    "WorldConfig",
    "build_world",
    "kitti_intrinsics",
    "loop_route",
    "make_place_params",
    "place_tokens",
    "plant_aliasing",
]
