"""The backbone layer (``inference.backbones``): DA3's conversion to ChunkPrediction on the
golden outputs (no network needed), DA3 preprocessing and its intrinsics map, checkpoint
headers refused by family / shape / truncation."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from inference import backbones
from inference.backbones import da3 as da3_backbone
from inference.backbones.header import HeaderError, describe_family, read_header
from swiftjax.intrinsics import da3_preprocess_geometry, map_intrinsics, map_points


@pytest.fixture(scope="module")
def da3_dir(da3_golden_dir):
    return da3_golden_dir


@pytest.fixture(scope="module")
def golden(da3_dir):
    return dict(np.load(da3_dir / "tiny_golden.npz"))


def _h(E34):
    E = np.zeros(E34.shape[:-2] + (4, 4))
    E[..., :3, :] = E34
    E[..., 3, 3] = 1.0
    return E


RUNS = ("first_", "saddle_", "middle_", "posecond_", "nested_")


def test_backbone_names_are_the_option_choices():
    from swiftjax.pipeline.config import BACKBONE_NAMES

    assert tuple(backbones.BACKBONES) == BACKBONE_NAMES
    assert backbones.get("vggt-1b").family == "vggt" and backbones.get("da3-small").impl.name == "da3"
    with pytest.raises(ValueError, match="--model 'da3-tiny' is not a backbone; choose one of vggt-1b, da3-small"):
        backbones.get("da3-tiny")


@pytest.mark.parametrize("run", RUNS)
def test_rebase_puts_every_strategy_in_the_first_cameras_frame(golden, run):
    """Whatever frame the network chose (reference view k: E_i E_k^-1), the chunk frame is the
    same: rebase(E E_k^-1) == rebase(E); camera 0 becomes [I|0]; relative poses and the world
    points' frame change are those of float64 4x4 inverses."""
    E = golden[run + "extrinsics"][0].astype(np.float64)  # [S,3,4]
    S = E.shape[0]
    ours = da3_backbone.rebase_extrinsics(E)
    np.testing.assert_allclose(ours[0], np.eye(3, 4), atol=1e-6)
    for k in range(S):  # every possible reference view
        in_k = (_h(E) @ np.linalg.inv(_h(E[k])))[:, :3]
        np.testing.assert_allclose(da3_backbone.rebase_extrinsics(in_k), ours, atol=2e-6)
    ref = (_h(E) @ np.linalg.inv(_h(E[0])))[:, :3]
    np.testing.assert_allclose(ours, ref, atol=1e-6)
    # a pixel's world point moves by E_0 (the new world is camera 0): X' = E_0 X
    depth, K = golden[run + "depth"][0], golden[run + "intrinsics"][0]
    i, v, u = 2, 17, 31
    x_cam = depth[i, v, u] * np.linalg.solve(K[i].astype(np.float64), [u, v, 1.0])
    X_old = np.linalg.solve(_h(E[i]), np.append(x_cam, 1.0))
    X_new = np.linalg.solve(_h(ours[i].astype(np.float64)), np.append(x_cam, 1.0))
    np.testing.assert_allclose(X_new, _h(E[0]) @ X_old, atol=1e-5 * max(1.0, np.abs(X_old).max()))


def test_first_and_saddle_differ_only_where_the_network_differs(golden):
    """The golden first_/saddle_ runs are two forward passes (the reference camera token goes to
    view 0 resp. view 1), so only the network's own change remains after the rebase: views 2 and
    3 hold a non-reference token in both runs and their relative pose agrees to 2e-3; views 0 and
    1 swap tokens and differ by more (random weights do not put the reference camera at I)."""
    a = _h(da3_backbone.rebase_extrinsics(golden["first_extrinsics"][0]).astype(np.float64))
    b = _h(da3_backbone.rebase_extrinsics(golden["saddle_extrinsics"][0]).astype(np.float64))
    rel = lambda E: E[3] @ np.linalg.inv(E[2])
    assert np.abs(rel(a) - rel(b)).max() < 2e-3
    assert np.abs(a[1] - b[1]).max() > 1e-2
    assert int(golden["saddle_ref_view_idx"][0]) == 1 and int(golden["first_ref_view_idx"][0]) == 0


def _input_order(golden, run):
    """The golden aux export is in the network's internal order (``view_order``)."""
    internal = golden[run + "prealt_patch_tokens"][0]
    out = np.empty_like(internal)
    out[golden[run + "view_order"]] = internal
    return out


@pytest.mark.parametrize("run", ("first_", "saddle_", "middle_"))
def test_loop_tokens_come_back_in_input_order(golden, run):
    """The golden aux export is in the network's internal order; undone, it equals the normalised
    half of the head's tokens at block alt_start-1 (out_layers[0] = 1), which are in input order
    (what inference.da3 returns as prealt_patch_tokens, checked end to end in test_da3_backbone_*)."""
    tokens = _input_order(golden, run)  # [S,h,w,C]
    C = tokens.shape[-1]
    head = golden[run + "feats_tokens"][0, 0, :, :, C:]  # [S,P,C]
    np.testing.assert_allclose(tokens.reshape(head.shape), head, rtol=0, atol=1e-5)


def test_chunk_prediction_from_golden_and_its_descriptors(golden):
    import jax.numpy as jnp

    from swiftjax import loops

    out = {k: golden["saddle_" + k][0] for k in ("depth", "depth_conf", "extrinsics", "intrinsics")}
    out["prealt_patch_tokens"] = _input_order(golden, "saddle_")
    pred = da3_backbone.to_prediction(golden["images_raw"][0], out)
    np.testing.assert_array_equal(pred.depth, out["depth"])
    np.testing.assert_array_equal(pred.conf, out["depth_conf"])
    assert pred.patch_tokens.shape == (4, 15, 64) and pred.images.shape == (4, 42, 70, 3)
    g = np.asarray(loops.frame_descriptor(jnp.asarray(pred.patch_tokens)))
    t = pred.patch_tokens / np.linalg.norm(pred.patch_tokens, axis=-1, keepdims=True)
    ref = t.mean(1)
    ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    np.testing.assert_allclose(g, ref, atol=1e-5)


@pytest.mark.parametrize("run", ("first_", "saddle_", "nested_"))
def test_confidence_semantics_hold_for_da3(golden, run):
    """DA3's depth_conf is 1 + exp(.) >= 1 as VGGT's; the reliability mask (gamma > lambda mean
    gamma per frame) computed by swiftjax equals a NumPy loop on it."""
    import jax.numpy as jnp

    from swiftjax.align.mask import reliability_mask

    conf = golden[run + "depth_conf"][0].astype(np.float64)
    assert conf.min() >= 1.0
    depth = golden[run + "depth"][0]
    ours = np.asarray(
        reliability_mask(
            jnp.asarray(depth[:2]),
            jnp.asarray(depth[2:]),
            jnp.asarray(conf[:2], jnp.float32),
            jnp.asarray(conf[2:], jnp.float32),
            1e9,
            0.5,
        )
    )
    want = np.zeros_like(ours)
    for f in range(2):
        ma, mb = conf[f].mean(), conf[f + 2].mean()
        want[f] = (conf[f] > 0.5 * ma) & (conf[f + 2] > 0.5 * mb)
    np.testing.assert_array_equal(ours, want)
    assert 0.5 < want.mean() <= 1.0


# ---------------------------------------------------------------------------- preprocessing


@pytest.mark.parametrize(
    "hw, mode, model_hw",
    [
        ((376, 1241), "resize", (154, 504)),  # KITTI
        ((1200, 1600), "resize", (378, 504)),  # the official README's example
        ((377, 504), "crop", (364, 504)),  # the official docstring's crop example
        ((504, 504), "resize", (504, 504)),
        ((30, 40), "resize", (378, 504)),  # enlarged
    ],
)
def test_da3_sizes_follow_the_official_rule(hw, mode, model_hw):
    assert da3_preprocess_geometry(*hw, mode).model_hw == model_hw


def test_da3_refuses_an_image_it_cannot_take():
    with pytest.raises(ValueError, match="too elongated for Depth Anything 3: it would become 504x0"):
        da3_preprocess_geometry(10, 5000)


def test_preprocess_da3_equals_opencv_steps_and_the_intrinsics_map():
    """The pixels are OpenCV's two resizes (area down, cubic up); a Gaussian blob at original
    pixel (u, v) lands where map_points / map_intrinsics say (to 0.05 px)."""
    import cv2

    from inference.preprocess import preprocess_da3

    H0, W0 = 376, 1241
    yy, xx = np.mgrid[0:H0, 0:W0]
    u, v = 400.3, 180.6
    img = (255 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 9.0**2))).astype(np.float64)
    rgb = np.repeat(np.clip(np.round(img), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
    ours = preprocess_da3([rgb])[0]
    step = cv2.resize(rgb, (504, 153), interpolation=cv2.INTER_AREA)
    step = cv2.resize(step, (504, 154), interpolation=cv2.INTER_CUBIC)
    np.testing.assert_array_equal(ours, step.transpose(2, 0, 1).astype(np.float32) / 255.0)
    geom = da3_preprocess_geometry(H0, W0)
    # blob centre from a float resize (no 8-bit rounding) against the map
    f = cv2.resize(
        cv2.resize(img.astype(np.float32), (504, 153), interpolation=cv2.INTER_AREA),
        (504, 154),
        interpolation=cv2.INTER_CUBIC,
    )
    w = np.clip(f, 0, None) ** 2
    ys, xs = np.mgrid[0:154, 0:504]
    centre = np.array([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])
    np.testing.assert_allclose(centre, map_points(np.array([u, v]), geom), atol=0.05)
    K = np.array([[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1]])
    Km = map_intrinsics(K, geom)
    x = np.linalg.solve(K, [u, v, 1.0])  # the same ray in both images
    np.testing.assert_allclose((Km @ x)[:2], map_points(np.array([u, v]), geom), atol=1e-9)


# ------------------------------------------------------------------------------ checkpoints


def _write_header_only(path, entries, body=b""):
    header = {}
    off = 0
    for name, shape in entries.items():
        n = int(np.prod(shape)) * 4
        header[name] = {"dtype": "F32", "shape": list(shape), "data_offsets": [off, off + n]}
        off += n
    data = json.dumps(header).encode()
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(data)) + data + (body if body else bytes(off)))
    return off


def test_header_reader_sees_family_and_truncation(tmp_path, da3_dir, golden_dir):
    assert describe_family(read_header(da3_dir / "tiny_weights.safetensors")) == "da3"
    assert describe_family(read_header(da3_dir / "tiny_nested_weights.safetensors")) == "da3-nested"
    assert describe_family(read_header(golden_dir / "tiny_weights.safetensors")) == "vggt"
    full = (da3_dir / "tiny_weights.safetensors").read_bytes()
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(full[: len(full) - 1000])
    with pytest.raises(HeaderError, match="cut.safetensors is truncated: tensor .* ends at byte"):
        read_header(cut)
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\xff" * 64)
    with pytest.raises(HeaderError, match="not a safetensors file"):
        read_header(junk)


def test_vggt_refuses_a_da3_checkpoint_and_a_wrong_shape(tmp_path, da3_dir, golden_dir):
    from inference.checkpoint import CheckpointError

    vggt = backbones.get("vggt-1b")
    config = vggt.impl.load_config(vggt, golden_dir / "tiny_config.json")
    vggt.impl.check_checkpoint(vggt, golden_dir / "tiny_weights.safetensors", config)  # the right one passes
    with pytest.raises(CheckpointError, match=r"is a Depth Anything 3 \(any-view\) checkpoint, not a VGGT one"):
        vggt.impl.check_checkpoint(vggt, da3_dir / "tiny_weights.safetensors", config)
    entries = {k: s for k, (_, s) in read_header(golden_dir / "tiny_weights.safetensors").items()}
    key = sorted(entries)[0]
    entries[key] = tuple(entries[key][:-1]) + (entries[key][-1] + 1,)
    bad = tmp_path / "shape.safetensors"
    _write_header_only(bad, entries)
    with pytest.raises(CheckpointError, match=f"shape mismatch 1 \\({key} "):
        vggt.impl.check_checkpoint(vggt, bad, config)


def test_drop_sky_with_the_nested_model_is_its_own_sky_map(golden):
    """--drop-sky with da3-nested-giant-large: the pixels whose confidence the nested model set
    to the floor 1 are exactly its metric branch's sky (sky >= 0.3), also after the chunk
    store's float16; the depth/confidence cue rule does not find them."""
    import jax.numpy as jnp

    from swiftjax import masks
    from swiftjax.pipeline import PipelineConfig
    from swiftjax.pipeline.user_camera import UserCamera

    conf, depth = golden["nested_depth_conf"][0], golden["nested_depth"][0]
    sky = golden["nested_metric_sky"][0] >= 0.3
    assert 0.2 < sky.mean() < 0.5
    np.testing.assert_array_equal(np.asarray(masks.network_sky_mask(conf)), sky)
    np.testing.assert_array_equal(np.asarray(masks.network_sky_mask(jnp.asarray(conf, jnp.float16))), sky)
    cues = np.asarray(masks.sky_mask(depth, conf))
    assert (cues & sky).sum() < 0.5 * sky.sum()
    cam = UserCamera.from_config(PipelineConfig(model="da3-nested-giant-large", drop_sky=True), predictor=None)
    assert cam.sky_rule == "network"
    np.testing.assert_array_equal(np.asarray(cam.keep(np.arange(4), depth, conf)), ~sky)
    assert UserCamera.from_config(PipelineConfig(model="da3-small", drop_sky=True), None).sky_rule == "cues"


def test_a_nan_in_da3_weights_is_named_by_the_model(da3_dir, golden):
    """Issue 25 item 15 for DA3: non-finite outputs are an error naming the model."""
    import torch

    from inference.runners import ModelOutputError

    b = backbones.get("da3-small")
    cfg = da3_backbone.load_config(b, da3_dir / "tiny_config.json")
    runner = da3_backbone.build_runner(b, str(da3_dir / "tiny_weights.safetensors"), "cpu", "float32", cfg)
    with torch.no_grad():
        runner.model.state_dict()[
            next(k for k in runner.model.state_dict() if k.startswith("head.") and k.endswith("weight"))
        ].fill_(float("nan"))
    with pytest.raises(
        ModelOutputError, match=r"da3-small \(.*tiny_weights.safetensors, float32\) predicted non-finite"
    ):
        runner.predict(golden["images_raw"][0])
