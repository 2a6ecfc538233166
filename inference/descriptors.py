"""Loop descriptors computed where the tokens are: on the model's device, in torch.

A chunk's DINO patch tokens are ``[S, P, C]`` (75 × 407 × 1024 floats, 125 MB, for VGGT-1B at
518 × 154); the loop stage needs one ``C``-vector per frame. On a GPU the reduction runs
before the copy to the host, which then moves 300 KB instead of 125 MB. The maths is
:func:`swiftjax.loops.frame_descriptor`'s (SwiftVGGT Sec. 3.3, before the power step):

    g⁰ = ℓ2( (1/P) Σ_k ℓ2(x_k) ),   ℓ2(v) = v / max(‖v‖, 1e-12)

accumulated in float32 whatever the token dtype.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["frame_descriptors"]

_NORM_EPS = 1e-12  # swiftjax.loops.descriptors._NORM_EPS


def frame_descriptors(tokens: Tensor) -> Tensor:
    """``[..., P, C]`` patch tokens -> ``[..., C]`` float32 descriptors ``g⁰`` (see module)."""
    import torch

    def l2(v: Tensor) -> Tensor:
        return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(_NORM_EPS)

    return l2(l2(tokens.float()).mean(dim=-2))
