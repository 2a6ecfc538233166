"""π³X's extras the pipeline calls: intrinsics as the ray condition, the metric scale, and
conditioning a chunk on the previous chunk's overlap poses."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from inference.pi3.conditioning import (
    Conditions,
    intrinsics_condition,
    official_intrinsics,
    overlap_pose_conditions,
    rays_from_intrinsics,
)
from inference.pi3.convert import metric_scale, to_chunk_prediction
from inference.pi3.golden import _load, compare, golden_conditions
from inference.pi3.preprocess import geometry


@pytest.fixture(scope="module")
def tiny(shared_dir: pathlib.Path):
    d = shared_dir / "golden" / "pi3"
    if not (d / "tiny_golden_pi3x.npz").is_file():
        pytest.skip(f"π³ golden data not found in {d}")
    return _load(d, "pi3x")


def test_swiftjax_intrinsics_give_the_rays_swiftjax_means() -> None:
    """Pixel (u, v) gets K^-1 (u, v, 1) with swiftjax's integer pixel centres, checked
    against swiftjax.camera.pixel_rays (JAX, independent code)."""
    from swiftjax.camera import pixel_rays

    K = np.array([[61.0, 0, 34.5], [0, 59.0, 20.0], [0, 0, 1]])
    rays = rays_from_intrinsics(official_intrinsics(K)[None, None], 42, 70)[0, 0].numpy()
    ref = np.asarray(pixel_rays(K.astype(np.float32), 42, 70))[..., :2]
    np.testing.assert_allclose(rays, ref, atol=1e-6)


def test_intrinsics_condition_equals_the_official_ray_path(tiny) -> None:
    """The golden ``cond`` run's K, given in swiftjax's convention through
    intrinsics_condition, reproduces the official ray embedding."""
    model, golden = tiny
    K_official = golden["cond.cond_input.intrinsics"][0]
    K_swiftjax = K_official.copy()
    K_swiftjax[:, 0, 2] -= 0.5
    K_swiftjax[:, 1, 2] -= 0.5
    cond = intrinsics_condition(K_swiftjax, 4)
    torch.testing.assert_close(cond.intrinsics[0], torch.from_numpy(K_official))
    trace: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        model(torch.from_numpy(golden["input_imgs"]), cond, trace=trace)
    assert compare("torch", "ray_embed_out", trace["ray_embed_out"].numpy(), golden["cond.ray_embed_out"]).passed
    with pytest.raises(ValueError, match="intrinsics must be"):
        intrinsics_condition(np.zeros((3, 3, 3)), 4)


def test_model_geometry_maps_intrinsics_like_the_resize() -> None:
    from swiftjax.intrinsics import map_intrinsics

    g = geometry(376, 1241)
    assert g.model_hw == (266, 924)
    K = map_intrinsics(np.array([[718.856, 0, 607.19], [0, 718.856, 185.22], [0, 0, 1]]), g)
    np.testing.assert_allclose(K[0, 0], 718.856 * 924 / 1241)
    np.testing.assert_allclose(K[1, 2], (185.22 + 0.5) * 266 / 376 - 0.5)


def test_metric_scale_is_the_golden_metric_and_depth_is_metric(tiny) -> None:
    model, golden = tiny
    with torch.no_grad():
        out = model(torch.from_numpy(golden["input_imgs"]), Conditions())
    assert metric_scale(out) == pytest.approx(float(golden["uncond.metric"][0]), rel=1e-5)
    scene = {k: v[0] for k, v in out.items() if k != "metric"}
    pred = to_chunk_prediction(scene)
    np.testing.assert_allclose(pred.depth, golden["uncond.local_points"][0, ..., 2], atol=1e-4, rtol=1e-4)


def _similarity(rng: np.random.Generator) -> np.ndarray:
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = 3.7 * R, rng.normal(size=3) * 10
    return S


def test_overlap_pose_condition_layout_and_frame_invariance(tiny) -> None:
    model, golden = tiny
    rng = np.random.default_rng(0)
    c2w = golden["cond.cond_input.poses"][0][:3].astype(np.float64)  # 3 overlap views
    E = np.linalg.inv(c2w)[:, :3, :]
    cond = overlap_pose_conditions(E, 4)
    np.testing.assert_array_equal(cond.mask_pose.numpy(), [[True, True, True, False]])
    np.testing.assert_allclose(cond.poses[0, 0].numpy(), np.eye(4), atol=1e-6)
    np.testing.assert_allclose(cond.poses[0, 3].numpy(), np.eye(4))
    # the previous chunk's world frame and scale do not matter: a similarity S of its world
    # maps camera-to-world T to S T (with scale on the translation only)
    S = _similarity(rng)
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    moved = S @ c2w
    moved[:, :3, :3] /= s
    cond2 = overlap_pose_conditions(np.linalg.inv(moved)[:, :3, :], 4)
    imgs = torch.from_numpy(golden["input_imgs"])
    with torch.no_grad():
        a, b, u = model(imgs, cond), model(imgs, cond2), model(imgs, Conditions())
    torch.testing.assert_close(a["camera_poses"], b["camera_poses"], atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(a["points"], b["points"], atol=2e-4, rtol=1e-4)
    assert (a["points"] - u["points"]).abs().max() > 1e-3  # the condition is not a no-op


def test_overlap_pose_condition_equals_the_official_path_when_rebased(tiny) -> None:
    """With the first overlap pose the identity (upstream's VO then builds the same inputs),
    the poses and masks equal the official construction (``prior_poses[:, :O]``, eye elsewhere)."""
    model, golden = tiny
    c2w = golden["cond.cond_input.poses"][0].astype(np.float64)
    rel = np.linalg.inv(c2w[0]) @ c2w
    official = Conditions(
        poses=torch.from_numpy(np.concatenate([rel[:2], np.eye(4)[None].repeat(2, 0)]).astype(np.float32))[None],
        mask_pose=torch.tensor([[True, True, False, False]]),
    )
    ours = overlap_pose_conditions(np.linalg.inv(c2w[:2])[:, :3, :], 4)
    torch.testing.assert_close(ours.poses, official.poses, atol=1e-6, rtol=0)
    imgs = torch.from_numpy(golden["input_imgs"])
    with torch.no_grad():
        torch.testing.assert_close(model(imgs, ours)["points"], model(imgs, official)["points"], atol=1e-4, rtol=1e-4)
    keep = dataclasses.replace(golden_conditions(golden, "cond"), poses=None, mask_pose=None)
    both = overlap_pose_conditions(np.linalg.inv(c2w[:2])[:, :3, :], 4, base=keep)
    assert both.intrinsics is not None and both.depths is not None and both.mask_pose[0, :2].all()
    with pytest.raises(ValueError, match="prev_extrinsic must be"):
        overlap_pose_conditions(np.zeros((1, 3, 4)), 4)
