"""Cameras from Depth Anything 3's ray map (the official ``use_ray_pose=True`` path).

The aux head predicts per cell of an ``8h × 8w`` grid a ray direction ``d`` (channels 0:3) and
origin ``o`` (3:6) in the reference camera's frame, with confidence ``c``.  Per view:

1. Canonical points: cell centres of a grid spanning ``[0, 2]²`` seen by an identity camera
   (focal 1, centre (1, 1)): ``p = (u - 1, v - 1, 1)``.  Directions with ``|d_z| <= 1e-4`` get
   weight 0; the others are divided by ``d_z``.
2. Weighted RANSAC for the homography ``A`` with ``d ~ A p``: candidates = the
   ``max(8, int(0.3 N))`` most confident cells; 100 hypotheses of 8 candidates (indices from the
   global torch RNG, shared by all views, or injected), each a ``sqrt(c)``-weighted DLT solved
   by SVD; score = summed confidence of cells reprojected closer than 0.2; the best inliers are
   refitted (a random 8000 of the 95 % most confident if there are more).
3. ``A`` is negated if ``det A < 0`` and split ``A = Q L`` (QL via QR of the column-reversed
   matrix, signs making ``diag L > 0``), ``L /= L[2,2]``: rotation camera-to-world ``Q``, focal
   ``1 / (L00, L11)`` and principal point ``(L20, L21) + 1`` in half-image units.  (A
   rotation times a lower-triangular matrix: an off-centre principal point is not recovered
   exactly; that is the official behaviour.)
4. Camera centre = confidence-weighted mean of the origins.  ``w2c = inverse([Q | t])``;
   ``fx = f_x W / 2``, ``fy = f_y H / 2``, ``cx = pp_x W / 2``, ``cy = pp_y H / 2``.

Data-dependent (RANSAC, SVD, boolean inlier sets): runs in eager torch, outside any ONNX graph.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ..device import without_autocast
from .camera import affine_inverse

__all__ = ["RayPose", "ransac_sample_indices", "cameras_from_rays"]

N_ITER = 100
N_PER_SAMPLE = 8
SAMPLE_RATIO = 0.3
REPROJ_THRESHOLD = 0.2
Z_THRESHOLD = 1e-4
MAX_INLIERS = 8000


@dataclasses.dataclass
class RayPose:
    """``extrinsics [B,S,3,4]`` (w2c), ``intrinsics [B,S,3,3]`` (pixels), ``c2w [B,S,4,4]``,
    ``focal [B,S,2]`` (normalised), ``pp [B,S,2]`` (in [0, 2] units), ``homography [B*S,3,3]``
    (after the inlier refit, before the det < 0 flip), ``sample_idx [100, 8]``."""

    extrinsics: Tensor
    intrinsics: Tensor
    c2w: Tensor
    focal: Tensor
    pp: Tensor
    homography: Tensor
    sample_idx: Tensor


def n_candidates(n_cells: int) -> int:
    return max(N_PER_SAMPLE, int(n_cells * SAMPLE_RATIO))


def ransac_sample_indices(n_cells: int, device: torch.device | None = None) -> Tensor:
    """``[100, 8]`` candidate indices drawn like the official code (global torch RNG)."""
    n = n_candidates(n_cells)
    return torch.stack([torch.randperm(n, device=device)[:N_PER_SAMPLE] for _ in range(N_ITER)])


def _dlt(src: Tensor, dst: Tensor, weight: Tensor) -> Tensor:
    """Weighted DLT homographies ``[..., 3, 3]`` (``H[2,2] = 1``) from ``src, dst [..., K, 2]``, ``weight [..., K]``."""
    w = weight.sqrt()[..., None]
    x, y, u, v = src[..., 0:1], src[..., 1:2], dst[..., 0:1], dst[..., 1:2]
    z = torch.zeros_like(x)
    a1 = torch.cat([-x * w, -y * w, -w, z, z, z, x * u * w, y * u * w, u * w], dim=-1)
    a2 = torch.cat([z, z, z, -x * w, -y * w, -w, x * v * w, y * v * w, v * w], dim=-1)
    _, _, vh = torch.linalg.svd(torch.cat([a1, a2], dim=-2))
    h = vh[..., -1, :].reshape(*src.shape[:-2], 3, 3)
    return h / h[..., 2:3, 2:3]


def _ransac(src: Tensor, dst: Tensor, weight: Tensor, sample_idx: Tensor) -> Tensor:
    """Per view ``[V, 3, 3]`` homography from ``src, dst [V, N, 2]`` and ``weight [V, N]``."""
    v, n, _ = src.shape
    cand = torch.argsort(weight, dim=1, descending=True)[:, : n_candidates(n)]
    idx = cand[:, sample_idx]  # [V, iters, 8]
    batch = torch.arange(v, device=src.device)[:, None, None]
    hyp = _dlt(src[batch, idx], dst[batch, idx], weight[batch, idx])  # [V, iters, 3, 3]
    src_h = torch.cat([src, torch.ones_like(src[..., :1])], dim=-1)  # [V, N, 3]
    proj = torch.einsum("vnj,vtij->vtni", src_h, hyp)  # [V, iters, N, 3]
    err = ((proj[..., :2] / proj[..., 2:3] - dst[:, None]) ** 2).sum(-1).sqrt()
    inliers = err < REPROJ_THRESHOLD
    best = (inliers * weight[:, None]).sum(-1).argmax(dim=1)
    out = []
    for k in range(v):
        mask = inliers[k, best[k]]
        s, d, w = src[k][mask], dst[k][mask], weight[k][mask]
        order = torch.argsort(w, descending=True)
        if order.numel() > MAX_INLIERS:
            order = order[: max(int(order.numel() * 0.95), MAX_INLIERS)]
            order = order[torch.randperm(order.numel(), device=order.device)[:MAX_INLIERS]]
        out.append(_dlt(s[order], d[order], w[order]))
    return torch.stack(out)


def _ql(a: Tensor) -> tuple[Tensor, Tensor]:
    """``a = q @ l`` with ``q`` orthogonal, ``l`` lower-triangular with a positive diagonal."""
    p = torch.tensor([[0.0, 0, 1], [0, 1, 0], [1, 0, 0]], dtype=a.dtype, device=a.device)
    q_t, r_t = torch.linalg.qr(a @ p)
    q, l = q_t @ p, p @ r_t @ p
    sign = torch.sign(torch.diagonal(l, dim1=-2, dim2=-1))
    return q * sign[..., None, :], l * sign[..., :, None]


def _canonical_points(ny: int, nx: int, device: torch.device) -> Tensor:
    """``[ny*nx, 2]`` cell centres of the identity camera, ``(u - 1, v - 1)`` (z = 1)."""
    dx, dy = 1 / nx, 1 / ny
    ys = torch.linspace(-(1 - dy) + 1.0, (1 - dy) + 1.0, ny, dtype=torch.float32, device=device)
    xs = torch.linspace(-(1 - dx) + 1.0, (1 - dx) + 1.0, nx, dtype=torch.float32, device=device)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx - 1.0, gy - 1.0], dim=-1).reshape(-1, 2)


def cameras_from_rays(
    ray: Tensor, ray_conf: Tensor, image_hw: tuple[int, int], sample_idx: Tensor | None = None
) -> RayPose:
    """Decodes cameras from ``ray [B, S, ny, nx, 6]`` and ``ray_conf [B, S, ny, nx]`` (see module doc).

    ``sample_idx [100, 8]``: RANSAC candidate indices; drawn from the global RNG when None.
    Runs in float32 outside autocast (a bf16 forward's ``det`` has no CUDA kernel).
    """
    with without_autocast(ray.device):
        return _cameras_from_rays(ray, ray_conf, image_hw, sample_idx)


def _cameras_from_rays(ray: Tensor, ray_conf: Tensor, image_hw: tuple[int, int], sample_idx: Tensor | None) -> RayPose:
    b, s, ny, nx, _ = ray.shape
    n = ny * nx
    rays = ray.reshape(b * s, n, 6).float()
    weight = ray_conf.reshape(b * s, n).float().clone()
    if sample_idx is None:
        sample_idx = ransac_sample_indices(n, ray.device)
    src = _canonical_points(ny, nx, ray.device).expand(b * s, n, 2)
    d = rays[..., :3]
    valid = d[..., 2].abs() > Z_THRESHOLD
    dst = torch.where(
        valid[..., None], d[..., :2] / torch.where(valid, d[..., 2], torch.ones_like(d[..., 2]))[..., None], d[..., :2]
    )
    weight = torch.where(valid, weight, torch.zeros_like(weight))
    homography = _ransac(src, dst, weight, sample_idx.to(ray.device))
    a = torch.where((torch.linalg.det(homography) < 0)[:, None, None], -homography, homography)
    q, l = _ql(a)
    l = l / l[:, 2:3, 2:3]
    focal = 1.0 / torch.stack([l[:, 0, 0], l[:, 1, 1]], -1)
    pp = torch.stack([l[:, 2, 0], l[:, 2, 1]], -1) + 1.0
    centre = (rays[..., 3:] * weight[..., None]).sum(1) / weight.sum(-1, keepdim=True)
    bottom = torch.tensor([0.0, 0, 0, 1], dtype=q.dtype, device=q.device).expand(b * s, 1, 4)
    c2w = torch.cat([torch.cat([q, centre[..., None]], -1), bottom], -2).reshape(b, s, 4, 4)
    height, width = image_hw
    focal, pp = focal.reshape(b, s, 2), pp.reshape(b, s, 2)
    k = torch.zeros(b, s, 3, 3, dtype=q.dtype, device=q.device)
    k[..., 0, 0], k[..., 1, 1] = focal[..., 0] / 2 * width, focal[..., 1] / 2 * height
    k[..., 0, 2], k[..., 1, 2], k[..., 2, 2] = pp[..., 0] * width * 0.5, pp[..., 1] * height * 0.5, 1.0
    return RayPose(affine_inverse(c2w)[..., :3, :], k, c2w, focal, pp, homography, sample_idx)
