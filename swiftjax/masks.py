"""Pixels to leave out: the user's mask images and sky from VGGT's own cues.

A keep-mask is bool ``[S, H, W]`` at the model's resolution, ``True`` = use the pixel.  The
pipeline ANDs it into the reliable points of every alignment (temporal and loop chunks,
:class:`swiftjax.align.ChunkFrames` ``mask``) and into the exported points; descriptors are
untouched (the DINO tokens stay whole-image).

* :class:`MaskDirectory` (``--mask-dir DIR``): one image per frame, matched by file stem
  (``000123.png`` for ``000123.jpg``), at the original image size, white (> 127) = keep;
  a box or a segmentation both work.  Mapped to the model's resolution by exactly the
  resize + crop/pad the images went through (:func:`swiftjax.intrinsics.map_mask`; padding is
  not kept).
* :func:`sky_mask` (``--drop-sky``): VGGT has no sky class, but it predicts sky as very far
  and unsure.  A pixel is sky when its depth exceeds ``depth_ratio`` times the frame's
  median depth AND its confidence is below ``conf_ratio`` times the frame's median
  confidence.  Measured against the synthetic world's sky label: docs/performance/index.md,
  "The user's camera".
  :func:`network_sky_mask` (``--drop-sky`` with the nested DA3 model): that network has a sky
  head and marks its sky pixels itself, with confidence exactly 1 (the floor of ``1 + exp``).
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int

from swiftjax.errors import SwiftjaxError
from swiftjax.intrinsics import PreprocessGeometry, map_mask

__all__ = ["MaskError", "MaskDirectory", "sky_mask", "network_sky_mask", "keep_mask", "SKY_RULES"]

#: How ``--drop-sky`` finds sky: ``cues`` (:func:`sky_mask`) or ``network`` (:func:`network_sky_mask`).
SKY_RULES = ("cues", "network")

_EXTENSIONS = (".png", ".PNG")


class MaskError(SwiftjaxError, ValueError):
    """A mask folder that does not fit the frames (names the folder / file and the problem)."""


class MaskDirectory:
    """Per-frame keep-masks read from ``directory`` (module docstring).

    Args:
        directory: folder of PNG masks.
        frame_names: the frames' names (``FrameSource.names``); the mask of frame ``k`` is
            ``directory / (stem of frame_names[k]) + ".png"``.
        geometry: the images' :class:`~swiftjax.intrinsics.PreprocessGeometry` (original size
            -> model size).

    Every mask's existence is checked at construction (before any work); sizes are checked
    when read (:class:`MaskError` naming the file).
    """

    def __init__(
        self, directory: str | os.PathLike[str], frame_names: Sequence[str], geometry: PreprocessGeometry
    ) -> None:
        self.directory = pathlib.Path(directory)
        if self.directory.exists() and not self.directory.is_dir():
            raise MaskError(f"--mask-dir {self.directory} is a file: give the folder of masks (one PNG per frame)")
        if not self.directory.is_dir():
            raise MaskError(f"mask directory {self.directory} does not exist")
        self.geometry = geometry
        self.paths: list[pathlib.Path] = []
        missing = []
        for name in frame_names:
            stem = pathlib.PurePath(name).with_suffix("")
            found = None
            for ext in _EXTENSIONS:
                p = self.directory / (str(stem) + ext)
                if p.is_file():
                    found = p
                    break
            if found is None:
                missing.append(str(stem) + ".png")
            self.paths.append(found)  # type: ignore[arg-type]
        if missing:
            raise MaskError(
                f"mask directory {self.directory} lacks {len(missing)} of {len(frame_names)} masks "
                f"(first: {missing[0]}); give one PNG per frame, named like the frame"
            )

    def __len__(self) -> int:
        return len(self.paths)

    def fingerprint(self) -> list[list[str | int]]:
        """``[name, bytes, mtime_ns]`` per mask file (a changed mask changes the run)."""
        out: list[list[str | int]] = []
        for p in self.paths:
            st = p.stat()
            out.append([p.name, int(st.st_size), int(st.st_mtime_ns)])
        return out

    def check(self) -> None:
        """Before any work: every mask's size (from its header) is the images', and not every
        mask is black (white = keep; an all-black folder kept no pixel: the run wrote "0
        points" and exit 0).  Masks are decoded only until one keeps a pixel."""
        from PIL import Image

        h, w = self.geometry.original_hw
        for p in self.paths:
            try:
                with Image.open(p) as im:
                    size = im.size
            except Exception as err:  # any decoder failure names the file
                raise MaskError(f"mask {p} cannot be read: {err}") from None
            if size != (w, h):
                raise MaskError(f"mask {p} is {size[0]}x{size[1]} but the images are {w}x{h}")
        if not any(bool(self.read_original(k).any()) for k in range(len(self.paths))):
            raise MaskError(
                f"every mask in {self.directory} is black ({len(self.paths)} masks keep no pixel; white = keep): "
                "nothing would be reconstructed"
            )

    def read_original(self, k: int) -> np.ndarray:
        """Frame ``k``'s mask at the original size: bool ``[H0, W0]``."""
        from PIL import Image

        p = self.paths[k]
        try:
            with Image.open(p) as im:
                a = np.asarray(im)
        except Exception as err:  # any decoder failure names the file
            raise MaskError(f"mask {p} cannot be read: {err}") from None
        if a.ndim == 3:
            a = a[..., :3].max(axis=-1) if a.shape[2] >= 3 else a[..., 0]
        if a.dtype == bool:
            keep = a
        else:
            hi = 32767 if a.dtype == np.uint16 else 127
            keep = a > hi
        if keep.shape != self.geometry.original_hw:
            h, w = self.geometry.original_hw
            raise MaskError(f"mask {p} is {keep.shape[1]}x{keep.shape[0]} but the images are {w}x{h}")
        return keep

    def read(self, frames: Sequence[int] | Int[ArrayLike, " S"]) -> Bool[np.ndarray, "S H W"]:
        """Keep-masks of global ``frames [S]`` at the model's resolution: bool ``[S, H, W]``."""
        return np.stack([map_mask(self.read_original(int(k)), self.geometry) for k in np.asarray(frames).reshape(-1)])


@jax.jit
def sky_mask(
    depth: Float[ArrayLike, "*s H W"],
    conf: Float[ArrayLike, "*s H W"],
    depth_ratio: float | Float[ArrayLike, ""] = 5.0,
    conf_ratio: float | Float[ArrayLike, ""] = 0.3,
) -> Bool[Array, "*s H W"]:
    """Sky pixels from depth and confidence alone: bool ``[..., H, W]`` (True = sky).

    ``sky = D > depth_ratio * median(D) and conf < conf_ratio * median(conf)``, medians per
    frame over the finite pixels of a 4 x 4-strided subsample (fixed shape).  Non-finite
    depths count as sky.  Recompiles per shape and dtype; the ratios are traced.
    """
    depth = jnp.asarray(depth)
    conf = jnp.asarray(conf, depth.dtype)
    sub = (Ellipsis, slice(None, None, 4), slice(None, None, 4))
    flat_d = depth[sub].reshape(*depth.shape[:-2], -1)
    flat_c = conf[sub].reshape(*conf.shape[:-2], -1)
    fin = jnp.isfinite(flat_d) & jnp.isfinite(flat_c)
    med_d = jnp.nanmedian(jnp.where(fin, flat_d, jnp.nan), axis=-1)
    med_c = jnp.nanmedian(jnp.where(fin, flat_c, jnp.nan), axis=-1)
    e = (Ellipsis, None, None)
    far = depth > jnp.asarray(depth_ratio, depth.dtype) * med_d[e]
    unsure = conf < jnp.asarray(conf_ratio, depth.dtype) * med_c[e]
    return (far & unsure) | ~jnp.isfinite(depth)


def network_sky_mask(conf: Float[ArrayLike, "*s H W"]) -> Bool[Array, "*s H W"]:
    """Sky as a network with a sky head marks it: bool ``[..., H, W]``, ``conf <= 1``.

    The nested Depth Anything 3 model sets the confidence of the pixels its metric branch calls
    sky (``sky >= 0.3``) to exactly 1, the lowest value ``1 + exp(.)`` takes; every other
    pixel keeps ``1 + exp(logit) > 1``.  Stored as float16 (the chunk store), a pixel with
    ``logit < -7.6`` also rounds to 1: those are unreliable pixels the point filter drops anyway.
    """
    return jnp.asarray(conf) <= 1


def keep_mask(
    depth: Float[ArrayLike, "S H W"],
    conf: Float[ArrayLike, "S H W"],
    user: Bool[ArrayLike, "S H W"] | None = None,
    drop_sky: bool = False,
    sky_rule: str = "cues",
    **sky_options: float,
) -> Bool[Array, "S H W"] | None:
    """The combined keep-mask ``[S, H, W]`` (user mask AND not sky), or ``None`` when neither
    is asked for (the caller then uses every pixel, with no extra compile).  ``sky_rule``:
    :data:`SKY_RULES` (``network`` for a backbone that marks sky, see :func:`network_sky_mask`)."""
    keep = None if user is None else jnp.asarray(user, bool)
    if drop_sky:
        not_sky = ~(network_sky_mask(conf) if sky_rule == "network" else sky_mask(depth, conf, **sky_options))
        keep = not_sky if keep is None else keep & not_sky
    return keep
