"""VGGT's camera head: iterative refinement of the 9-number pose encoding per frame."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .layers import Block, Mlp

__all__ = ["CameraHead", "activate_pose"]

POSE_ENCODING_DIM = 9


def activate_pose(raw: Tensor) -> Tensor:
    """``absT_quaR_FoV`` activations on ``[..., 9]``: T and quaternion linear, FoV ReLU."""
    return torch.cat([raw[..., :7], F.relu(raw[..., 7:])], dim=-1)


class CameraHead(nn.Module):
    """Predicts ``[B, S, 9]`` pose encodings from the camera tokens of the last aggregator output.

    Each iteration embeds the previous raw (pre-activation) encoding — the learned
    ``empty_pose_tokens`` for the first — modulates the normalised camera tokens with it
    (adaLN: shift, scale, gate), runs the trunk (attention across frames) and adds the predicted
    delta to the raw encoding.  The activation is applied to the running sum each iteration.
    """

    def __init__(
        self, dim_in: int, trunk_depth: int, num_heads: int, mlp_ratio: float, init_values: float = 0.01
    ) -> None:
        super().__init__()
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, POSE_ENCODING_DIM))
        self.trunk = nn.Sequential(
            *(Block(dim_in, num_heads, mlp_ratio, init_values=init_values) for _ in range(trunk_depth))
        )
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.embed_pose = nn.Linear(POSE_ENCODING_DIM, dim_in)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim_in, 3 * dim_in))
        self.adaln_norm = nn.LayerNorm(dim_in, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim_in, dim_in // 2, POSE_ENCODING_DIM)

    def forward(self, last_tokens: Tensor, num_iterations: int = 4) -> list[Tensor]:
        """``last_tokens``: last aggregator output ``[B, S, T, 2C]``.

        Returns:
            ``num_iterations`` activated pose encodings ``[B, S, 9]``; the last is the prediction.
        """
        tokens = self.token_norm(last_tokens[:, :, 0])  # camera token, [B, S, 2C]
        b, s, _ = tokens.shape
        raw: Tensor | None = None
        outputs: list[Tensor] = []
        for _ in range(num_iterations):
            cond = self.empty_pose_tokens.expand(b, s, -1) if raw is None else raw.detach()
            shift, scale, gate = self.poseLN_modulation(self.embed_pose(cond)).chunk(3, dim=-1)
            x = gate * (self.adaln_norm(tokens) * (1 + scale) + shift) + tokens
            x = self.trunk(x)
            delta = self.pose_branch(self.trunk_norm(x))
            raw = delta if raw is None else raw + delta
            outputs.append(activate_pose(raw))
        return outputs
