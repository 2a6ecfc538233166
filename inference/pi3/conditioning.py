"""π³X's optional conditions: known intrinsics (as rays), depth, and camera poses.

Everything here runs before the network and equals the official ``Pi3X.encode`` preamble:

* **rays** (the intrinsics condition): ``K^-1 (u + 1/2, v + 1/2, 1)`` for pixel ``(u, v)``,
  first two components, NOT normalised (upstream's pixel grid puts pixel centres at
  ``+ 1/2``, i.e. it reads ``K`` with the origin at the top-left CORNER).
  :func:`official_intrinsics` converts swiftjax's integer-pixel-centre ``K``
  (``--intrinsics``) so that each pixel gets the ray swiftjax means; given ray directions are
  reduced to ``(x/(z + 1e-6), y/(z + 1e-6))``.
* **depth**: divided by the mean of the valid (``> 0``) depths of the whole batch element (1 if
  none); the validity mask is the second input channel.
* **poses** (camera-to-world, OpenCV): made relative to view 0 (``P_0^-1 P_i``), translations
  divided by that depth mean; a batch element that uses no depth and moves (some translation
  ``>= 0.02``) has its translations and depths divided by the mean translation norm of views
  ``1..N-1`` instead (and the factor multiplied by it).
* **masks** ``[B, N]`` bool say which views get which condition.  Upstream draws them at
  random with probability 1 (condition given) or 0 (not given) when they are not passed;
  here the defaults are that limit, deterministic: all True when the condition is given,
  else all False.  A batch element with exactly one posed view gets none (a single absolute
  pose constrains nothing).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .decoders import se3_inverse

__all__ = [
    "Conditions",
    "PreparedConditions",
    "prepare_conditions",
    "rays_from_intrinsics",
    "official_intrinsics",
    "intrinsics_condition",
    "overlap_pose_conditions",
    "normalize_depth",
]

_STATIC_THRESHOLD = 2e-2


@dataclasses.dataclass
class Conditions:
    """Optional inputs of :class:`~inference.pi3.pi3x.Pi3X` (all torch tensors).

    Attributes:
        intrinsics: ``[B, N, 3, 3]`` pixel intrinsics in the OFFICIAL convention (pixel
            centres at ``u + 1/2``), or ``None``.
        rays: ``[B, N, H, W, 3]`` ray directions (replace ``intrinsics``), or ``None``.
        depths: ``[B, N, H, W]`` depth, ``<= 0`` where unknown, or ``None``.
        poses: ``[B, N, 4, 4]`` camera-to-world (OpenCV), or ``None``.
        mask_depth, mask_ray, mask_pose: ``[B, N]`` bool, or ``None`` for the default.
        with_prior: ``False`` makes the default masks all False (upstream ``with_prior``).
    """

    intrinsics: Tensor | None = None
    rays: Tensor | None = None
    depths: Tensor | None = None
    poses: Tensor | None = None
    mask_depth: Tensor | None = None
    mask_ray: Tensor | None = None
    mask_pose: Tensor | None = None
    with_prior: bool = True


@dataclasses.dataclass
class PreparedConditions:
    """What the network consumes (``V = B N`` views).

    ``depth_input [V, 2, H, W]`` (normalised depth, validity), ``rays_xy [V, 2, H, W]``,
    ``poses [B, N, 4, 4]`` (normalised, relative to view 0), ``norm_factor [B]``, and the
    three masks ``[B, N]`` bool.
    """

    depth_input: Tensor
    rays_xy: Tensor
    poses: Tensor
    norm_factor: Tensor
    mask_depth: Tensor
    mask_ray: Tensor
    mask_pose: Tensor


def rays_from_intrinsics(K: Tensor, height: int, width: int) -> Tensor:
    """``K [B, N, 3, 3]`` (official convention) -> ``[B, N, H, W, 2]``: ``(K^-1 (u+½, v+½, 1))_{xy}``."""
    v, u = torch.meshgrid(
        torch.arange(height, device=K.device, dtype=torch.float32) + 0.5,
        torch.arange(width, device=K.device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # [H, W, 3]
    return torch.einsum("bnij,hwj->bnhwi", torch.inverse(K.float()), pix)[..., :2]


def official_intrinsics(K: Any) -> Tensor:
    """swiftjax's ``K`` (integer pixel centres, ``--intrinsics`` mapped to the model size) ->
    upstream's convention (pixel centres at ``+ 1/2``): ``c_x + 1/2, c_y + 1/2``, so that
    :func:`rays_from_intrinsics` gives pixel ``(u, v)`` the ray ``K^-1 (u, v, 1)``."""
    out = torch.as_tensor(np.asarray(K, dtype=np.float32)).clone()
    out[..., 0, 2] += 0.5
    out[..., 1, 2] += 0.5
    return out


def intrinsics_condition(K: Any, views: int) -> Conditions:
    """``--intrinsics`` as π³X's ray condition for a chunk of ``views`` frames.

    ``K``: ``[3, 3]`` or ``[views, 3, 3]`` swiftjax intrinsics at the model resolution
    (:func:`swiftjax.intrinsics.map_intrinsics` with :func:`inference.pi3.preprocess.geometry`).
    """
    k = official_intrinsics(K)
    if k.dim() == 2:
        k = k.expand(views, 3, 3)
    if k.shape != (views, 3, 3):
        raise ValueError(f"intrinsics must be [3, 3] or [{views}, 3, 3], got {tuple(k.shape)}")
    return Conditions(intrinsics=k[None])


def overlap_pose_conditions(prev_extrinsic: Any, views: int, base: Conditions | None = None) -> Conditions:
    """Condition a chunk on the poses of its first ``O`` views known from the previous chunk.

    As Pi3's ``example_vo.py`` (``Pi3XVO`` with ``inject_condition=['pose']``): the first ``O``
    views get those poses and a True pose mask, the others identity poses and False.  The
    ``[O, 3, 4]`` (or ``[O, 4, 4]``) world-to-camera ``prev_extrinsic`` (the previous chunk's
    ``ChunkPrediction.extrinsic`` of the overlap frames) are inverted and re-based on the first
    overlap view, which makes the condition independent of the previous chunk's world frame
    and scale (π³X normalises poses relative to view 0 and by the mean translation); upstream
    passes the globally aligned poses, the same when its first overlap pose is the identity.
    ``base``: other conditions (e.g. :func:`intrinsics_condition`) to keep.
    """
    E = np.asarray(prev_extrinsic, dtype=np.float64)
    if E.ndim != 3 or E.shape[1:] not in ((3, 4), (4, 4)) or not 2 <= E.shape[0] <= views:
        raise ValueError(f"prev_extrinsic must be [O, 3, 4] with 2 <= O <= {views}, got shape {E.shape}")
    o = E.shape[0]
    W2C = np.tile(np.eye(4), (o, 1, 1))
    W2C[:, :3, :] = E[:, :3, :]
    c2w = np.linalg.inv(W2C)
    rel = np.linalg.inv(c2w[0]) @ c2w
    poses = np.tile(np.eye(4), (views, 1, 1))
    poses[:o] = rel
    mask = np.zeros(views, dtype=bool)
    mask[:o] = True
    out = dataclasses.replace(base) if base is not None else Conditions()
    out.poses = torch.from_numpy(poses.astype(np.float32))[None]
    out.mask_pose = torch.from_numpy(mask)[None]
    return out


def normalize_depth(depths: Tensor) -> tuple[Tensor, Tensor]:
    """``[B, N, H, W]`` -> (``depths / (mean + 1e-8)``, ``mean [B]``), mean over valid (> 0)
    pixels of each batch element, 1 where none is valid."""
    b = depths.shape[0]
    valid = torch.where(depths > 0, depths, torch.nan).reshape(b, -1)
    factor = torch.nan_to_num(torch.nanmean(valid, dim=1), nan=1.0)
    return depths / (factor.view(b, 1, 1, 1) + 1e-8), factor


def _divide_translation(T: Tensor, divisor: Tensor) -> Tensor:
    """``T [B, N, 4, 4]`` with its translations divided by ``divisor [B]``."""
    out = T.clone()
    out[..., :3, 3] = T[..., :3, 3] / divisor.view(-1, 1, 1)
    return out


def _default_mask(
    given: Tensor | None, present: bool, with_prior: bool, shape: tuple[int, int], device: torch.device
) -> Tensor:
    if given is not None:
        return given.to(device=device, dtype=torch.bool).clone()
    return torch.full(shape, present and with_prior, dtype=torch.bool, device=device)


def prepare_conditions(
    cond: Conditions, batch: int, views: int, height: int, width: int, device: torch.device
) -> PreparedConditions:
    """The official ``encode`` preamble (see the module docstring), in float32."""
    shape = (batch, views)
    depths = cond.depths.float() if cond.depths is not None else torch.zeros(batch, views, height, width, device=device)
    if cond.rays is not None:
        rays = cond.rays[..., :2] / (cond.rays[..., 2:3] + 1e-6)
    elif cond.intrinsics is not None:
        rays = rays_from_intrinsics(cond.intrinsics, height, width)
    else:
        rays = torch.zeros(batch, views, height, width, 2, device=device)
    poses = cond.poses.float() if cond.poses is not None else torch.eye(4, device=device).expand(batch, views, 4, 4)
    mask_depth = _default_mask(cond.mask_depth, cond.depths is not None, cond.with_prior, shape, device)
    mask_ray = _default_mask(
        cond.mask_ray, cond.rays is not None or cond.intrinsics is not None, cond.with_prior, shape, device
    )
    mask_pose = _default_mask(cond.mask_pose, cond.poses is not None, cond.with_prior, shape, device)
    mask_pose[mask_pose.sum(dim=1) == 1] = False

    normalized, factor = normalize_depth(depths)
    valid = (normalized > 0).float()
    rel = _divide_translation(se3_inverse(poses[:, :1]) @ poses, factor)
    uses_depth = mask_depth.sum(dim=1) > 0
    if views > 1 and bool((~uses_depth).any()):
        norms = rel[:, 1:, :3, 3].norm(dim=-1)  # [B, N-1]
        moving = ~uses_depth & ~(norms.max(dim=1).values < _STATIC_THRESHOLD)
        mean_norm = norms.mean(dim=1)
        divisor = torch.where(moving, mean_norm + 1e-8, torch.ones_like(mean_norm))
        rel = _divide_translation(rel, divisor)
        normalized = normalized / divisor.view(batch, 1, 1, 1)
        factor = torch.where(moving, factor * mean_norm, factor)
    return PreparedConditions(
        depth_input=torch.cat([normalized.reshape(-1, 1, height, width), valid.reshape(-1, 1, height, width)], dim=1),
        rays_xy=rays.reshape(-1, height, width, 2).permute(0, 3, 1, 2),
        poses=rel,
        norm_factor=factor,
        mask_depth=mask_depth,
        mask_ray=mask_ray,
        mask_pose=mask_pose,
    )
