"""The real-image path end to end: image files -> preprocessing -> a (tiny) VGGT -> pipeline.

The tiny golden VGGT has random weights, so the geometry is meaningless; what is checked is
that every stage runs on real runner outputs (shapes, dtypes, patch tokens reduced to
descriptors, alignment fallbacks never produce a non-finite pose) and that the outputs are
consistent with the input frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax import pipeline
from swiftjax.io import images, trajectory

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")


def test_reconstruct_from_image_files_with_tiny_vggt(tmp_path, golden_dir):
    from inference import VGGT, VGGTConfig, load_checkpoint
    from inference.predictor import ImagePredictor
    from inference.runners import TorchRunner

    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (60, 220, 3), np.uint8)
    for k in range(14):
        cv2.imwrite(str(folder / f"{k:04d}.png"), np.roll(base, 3 * k, axis=1))

    model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json"))
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    source = images.validate(images.list_frames(folder))
    predictor = ImagePredictor(source, TorchRunner(model))
    config = pipeline.PipelineConfig(chunk_size=8, overlap=3, min_points=10, loop_closure=False)
    result = pipeline.reconstruct(predictor, tmp_path / "run", config, progress=False)

    assert result.num_frames == 14 and result.num_chunks == 3
    poses = trajectory.read_kitti(tmp_path / "run" / "poses_kitti.txt")
    assert poses.shape == (14, 4, 4) and np.all(np.isfinite(poses))
    # Preprocessed as VGGT's loader does: width 518, height a multiple of 14.
    import pycolmap
    from PIL import Image

    rec = pycolmap.Reconstruction(str(tmp_path / "run" / "colmap" / "sparse" / "0"))
    assert "0013.png" in {im.name for im in rec.images.values()}
    (cam,) = rec.cameras.values()
    assert cam.width == 518 and cam.height % 14 == 0
    # The frames VGGT saw, at its resolution, beside the model.
    assert Image.open(tmp_path / "run" / "colmap" / "images" / "0013.png").size == (cam.width, cam.height)
