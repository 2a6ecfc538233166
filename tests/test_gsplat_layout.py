"""The README's gsplat command line works with gsplat's own defaults (issue 26 item 2).

gsplat is not installable here (it builds CUDA kernels), so this test replays, on the small
run's ``colmap/`` folder, the steps of gsplat's ``examples/datasets/colmap.py`` ``Parser``
that depend on the files (read from gsplat's source, commit 0714fc6): ``sparse/0`` (else
``sparse``) read by pycolmap; with ``factor > 1`` the images are read from
``images_<factor>/`` and both that folder and ``images/`` must exist (``ValueError: Image
folder ... does not exist``); the two sorted file lists are zipped, so each model image
needs a file; ``K`` is scaled by (actual size of the first image) / (camera size //
factor).  The command's flags are taken from the README itself, with
``simple_trainer.py``'s defaults (``data_factor = 4``) for the ones it leaves out.
"""

from __future__ import annotations

import os
import pathlib
import re
import shlex

import numpy as np
import pytest
from _extras import require_extra

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
#: simple_trainer.py's Config defaults for the flags the Parser reads.
GSPLAT_DEFAULTS = {"data_dir": "data/360_v2/garden", "data_factor": 4}


def readme_gsplat_command() -> list[str]:
    text = " ".join(README.read_text().split())
    m = re.search(r"gsplat: `(python examples/simple_trainer\.py [^`]*)`", text)
    assert m, "the README has no gsplat command line"
    return shlex.split(m.group(1))


def gsplat_flags(argv: list[str]) -> dict[str, object]:
    """``--name value`` / ``--name=value`` pairs after the subcommand (tyro accepts ``-`` or
    ``_`` in names), over the defaults."""
    assert argv[:3] == ["python", "examples/simple_trainer.py", "default"], argv
    flags = dict(GSPLAT_DEFAULTS)
    args = iter(argv[3:])
    for a in args:
        assert a.startswith("--"), a
        name, _, value = a[2:].partition("=")
        flags[name.replace("-", "_")] = value or next(args)
    flags["data_factor"] = int(flags["data_factor"])
    return flags


def gsplat_parser_steps(data_dir: pathlib.Path, factor: int) -> tuple[list[str], np.ndarray, tuple[int, int]]:
    """gsplat's Parser, the file-dependent steps: (image paths, scaled K, image size)."""
    import pycolmap
    from PIL import Image

    colmap_dir = data_dir / "sparse" / "0"
    if not colmap_dir.exists():
        colmap_dir = data_dir / "sparse"
    assert colmap_dir.exists(), f"COLMAP directory {colmap_dir} does not exist."
    rec = pycolmap.Reconstruction(str(colmap_dir))
    (cam,) = rec.cameras.values()
    K = cam.calibration_matrix()
    K[:2, :] /= factor
    imsize = (cam.width // factor, cam.height // factor)
    names = sorted(im.name for im in rec.images.values())
    suffix = f"_{factor}" if factor > 1 else ""
    colmap_image_dir, image_dir = data_dir / "images", data_dir / f"images{suffix}"
    for d in (image_dir, colmap_image_dir):
        if not d.exists():
            raise ValueError(f"Image folder {d} does not exist.")

    def rel(d):  # gsplat's _get_rel_paths, sorted
        return sorted(os.path.relpath(os.path.join(dp, f), d) for dp, _, fs in os.walk(d) for f in fs)

    colmap_to_image = dict(zip(rel(colmap_image_dir), rel(image_dir)))
    paths = [str(image_dir / colmap_to_image[n]) for n in names]
    with Image.open(paths[0]) as im:
        w, h = im.size
    s_w, s_h = w / imsize[0], h / imsize[1]
    K[0, :] *= s_w
    K[1, :] *= s_h
    return paths, K, (int(imsize[0] * s_w), int(imsize[1] * s_h))


def test_readme_gsplat_command_loads_the_run(small_loop_run):
    require_extra("pycolmap")
    out, result = small_loop_run
    flags = gsplat_flags(readme_gsplat_command())
    assert flags["data_dir"] == "runs/demo/colmap"  # the README's own demo run
    paths, K, size = gsplat_parser_steps(out / "colmap", flags["data_factor"])
    assert len(paths) == result.num_frames and all(os.path.isfile(p) for p in paths)
    K_ref = result.intrinsics[0]
    # gsplat trains at the model's own camera: the K and size the run wrote, no rescale
    np.testing.assert_allclose(
        K[[0, 1, 0, 1], [0, 1, 2, 2]], [K_ref[0, 0], K_ref[1, 1], K_ref[0, 2] + 0.5, K_ref[1, 2] + 0.5], rtol=1e-6
    )
    import pycolmap

    (cam,) = pycolmap.Reconstruction(str(out / "colmap" / "sparse" / "0")).cameras.values()
    assert size == (cam.width, cam.height)


def test_gsplat_default_factor_needs_the_flag(small_loop_run):
    """Without ``--data_factor 1`` gsplat's default looks for ``images_4/``: the error the
    issue reported, reproduced by the replayed steps (so they are faithful to it)."""
    require_extra("pycolmap")
    out, _ = small_loop_run
    flags = gsplat_flags(["python", "examples/simple_trainer.py", "default", "--data_dir", str(out / "colmap")])
    assert flags["data_factor"] == 4
    with pytest.raises(ValueError, match=r"Image folder .*images_4 does not exist"):
        gsplat_parser_steps(out / "colmap", flags["data_factor"])
