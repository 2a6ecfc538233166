"""The user's camera in a run: known intrinsics, keep-masks, metric scale (host glue).

:func:`UserCamera.from_config` resolves ``--intrinsics``, ``--mask-dir``, ``--drop-sky`` and
``--metric`` once, before any work, against the predictor's image geometry (the original
image size and the preprocessing's resize + crop/pad, :mod:`swiftjax.intrinsics`):

* ``K_ref``: the file's intrinsics mapped to the model's resolution.  They replace the first
  frame's predicted intrinsics as the reference of eq. 1, of every unprojection (alignment,
  ground planes, exported points) and of the COLMAP camera; VGGT's predicted focal length
  only enters eq. 1's ratio ``f_ref / f_pred``.  (The COLMAP model pairs its camera ``K_ref``
  with the frames at the model's resolution, ``colmap/images/``.)
* :meth:`UserCamera.keep`: a frame's keep-mask (the mask folder's, AND not sky), computed
  from the global frame indices and that chunk's depth/confidence wherever the frames are
  used, so temporal chunks, loop chunks and resumed runs see the same pixels.

A predictor describes its images with ``preprocess_geometry()`` (a
:class:`~swiftjax.intrinsics.PreprocessGeometry`); the synthetic oracle's images ARE the
model's images (identity).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import intrinsics as _intrinsics
from swiftjax import masks as _masks
from swiftjax import metric_scale
from swiftjax.options import OptionError

__all__ = ["UserCamera"]


@dataclasses.dataclass
class UserCamera:
    """The resolved camera options of a run (see the module docstring).

    Attributes:
        geometry: the images' original size -> model size map (``None`` if the predictor does
            not describe it and no option needs it).
        intrinsics: the file's :class:`~swiftjax.intrinsics.CameraIntrinsics` or ``None``.
        K_ref: ``[3, 3]`` float64 at the model's resolution, or ``None`` (use the prediction's).
        masks: the :class:`~swiftjax.masks.MaskDirectory` or ``None``.
        drop_sky: drop sky pixels: :func:`~swiftjax.masks.sky_mask`, or the network's own
            (:func:`~swiftjax.masks.network_sky_mask`, ``sky_rule == "network"``: a backbone of
            :data:`~swiftjax.pipeline.config.METRIC_BACKBONES`, which has a sky head).
        metric: ``None``, ``("camera-height", H)`` or ``("gt", None)``.
    """

    geometry: _intrinsics.PreprocessGeometry | None = None
    intrinsics: _intrinsics.CameraIntrinsics | None = None
    K_ref: np.ndarray | None = None
    masks: _masks.MaskDirectory | None = None
    drop_sky: bool = False
    metric: tuple[str, float | None] | None = None
    sky_rule: str = "cues"

    @classmethod
    def from_config(cls, config: Any, predictor: Any) -> UserCamera:
        """Validate and load every camera option (errors name the file and the problem)."""
        metric = metric_scale.parse_metric(config.metric)
        needs_geometry = config.intrinsics is not None or config.mask_dir is not None
        geometry = None
        describe = getattr(predictor, "preprocess_geometry", None)
        if describe is not None:
            geometry = describe()
        elif needs_geometry:
            raise OptionError(
                f"--intrinsics / --mask-dir need the images' size and preprocessing, which "
                f"{type(predictor).__name__} does not describe (no preprocess_geometry())"
            )
        intr = K_ref = None
        if config.intrinsics is not None:
            intr = _intrinsics.read_intrinsics(config.intrinsics)
            intr.check_image_size(*geometry.original_hw)
            K_ref = _intrinsics.map_intrinsics(intr.K, geometry)
        mask_dir = None
        if config.mask_dir is not None:
            mask_dir = _masks.MaskDirectory(config.mask_dir, predictor.frame_names(), geometry)
            mask_dir.check()
        from swiftjax.pipeline.config import METRIC_BACKBONES

        sky_rule = "network" if getattr(config, "model", None) in METRIC_BACKBONES else "cues"
        return cls(geometry, intr, K_ref, mask_dir, bool(config.drop_sky), metric, sky_rule)

    @property
    def masked(self) -> bool:
        """Whether any pixel can be masked (a mask folder or ``drop_sky``)."""
        return self.masks is not None or self.drop_sky

    def fingerprint(self) -> list[Any]:
        """What the run's results depend on beyond the configuration's paths: the intrinsics
        values and every mask file's size and time (empty when no such option is given)."""
        out: list[Any] = []
        if self.intrinsics is not None:
            out.append(["intrinsics", self.intrinsics.to_dict()])
        if self.masks is not None:
            out.append(["masks", self.masks.fingerprint()])
        return out

    def keep(self, frames: np.ndarray, depth: Any, conf: Any) -> jax.Array | None:
        """Keep-mask ``[S, H, W]`` bool of global ``frames [S]`` whose depth and confidence
        (``[S, H, W]``, this chunk's) are given, or ``None`` when nothing is masked."""
        if not self.masked:
            return None
        user = None if self.masks is None else jnp.asarray(self.masks.read(frames))
        return _masks.keep_mask(
            jnp.asarray(depth, jnp.float32),
            jnp.asarray(conf, jnp.float32),
            user,
            drop_sky=self.drop_sky,
            sky_rule=self.sky_rule,
        )
