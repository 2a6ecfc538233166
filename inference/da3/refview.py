"""Choice of the reference view of Depth Anything 3 (the view whose camera frames the outputs).

Right before block ``alt_start - 1`` the network picks one view from the (un-normalised) token 0
of every view and moves it to the front; the others keep their order.  Strategies:

* ``first``: view 0.  ``middle``: view ``S // 2``.
* ``saddle_balanced`` (the official default): with ``u_i = t_i / |t_i|`` the unit cls tokens,
  ``sim_i = mean_{j != i} u_i . u_j``, ``norm_i = |t_i|`` and ``var_i = var(u_i)`` (unbiased over
  channels), each min-max normalised over the views (``(m - min) / (max - min + 1e-8)``), pick
  ``argmin_i sum |m_i - 0.5|``.
* ``saddle_sim_range``: ``argmax_i (max_j sim_ij - min_j sim_ij)`` over ``j != i`` (with the
  diagonal set to 0 as in the official code).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "STRATEGIES",
    "MIN_VIEWS_FOR_SELECTION",
    "balance_scores",
    "select_reference_view",
    "reference_order",
    "restore_order",
    "gather_views",
]

STRATEGIES = ("first", "middle", "saddle_balanced", "saddle_sim_range")
# The official THRESH_FOR_REF_SELECTION: with fewer views nothing is chosen or reordered.
MIN_VIEWS_FOR_SELECTION = 3


def _unit_similarity(cls_tokens: Tensor) -> tuple[Tensor, Tensor]:
    unit = cls_tokens / cls_tokens.norm(dim=-1, keepdim=True)
    s = cls_tokens.shape[1]
    sim = unit @ unit.transpose(1, 2) - torch.eye(s, device=cls_tokens.device, dtype=cls_tokens.dtype)
    return unit, sim


def balance_scores(cls_tokens: Tensor) -> Tensor:
    """The saddle-balanced criterion: ``[4, B, S]`` rows sim_score, feat_norm, feat_var, balance.

    Args:
        cls_tokens: ``[B, S, C]`` token 0 of every view.
    """
    s = cls_tokens.shape[1]
    unit, sim = _unit_similarity(cls_tokens)
    sim_score = sim.sum(dim=-1) / (s - 1)
    feat_norm = cls_tokens.norm(dim=-1)
    feat_var = unit.var(dim=-1)

    def minmax(m: Tensor) -> Tensor:
        lo, hi = m.min(dim=1, keepdim=True).values, m.max(dim=1, keepdim=True).values
        return (m - lo) / (hi - lo + 1e-8)

    balance = (minmax(sim_score) - 0.5).abs() + (minmax(feat_norm) - 0.5).abs() + (minmax(feat_var) - 0.5).abs()
    return torch.stack([sim_score, feat_norm, feat_var, balance])


def select_reference_view(cls_tokens: Tensor, strategy: str) -> Tensor:
    """Index ``[B]`` (int64) of the reference view per scene from ``cls_tokens [B, S, C]``."""
    b, s, _ = cls_tokens.shape
    if strategy not in STRATEGIES:
        raise ValueError(f"ref_view_strategy: {strategy!r} is not one of {', '.join(STRATEGIES)}")
    if strategy == "first" or s <= 1:
        return torch.zeros(b, dtype=torch.long, device=cls_tokens.device)
    if strategy == "middle":
        return torch.full((b,), s // 2, dtype=torch.long, device=cls_tokens.device)
    if strategy == "saddle_balanced":
        return balance_scores(cls_tokens)[3].argmin(dim=1)
    _, sim = _unit_similarity(cls_tokens)
    return (sim.max(dim=-1).values - sim.min(dim=-1).values).argmax(dim=1)


def reference_order(ref: Tensor, s: int) -> Tensor:
    """``[B, S]`` original view index at each internal slot: ``ref`` first, the others in order."""
    pos = torch.arange(s, device=ref.device).expand(ref.shape[0], s)
    r = ref[:, None]
    order = torch.where((pos > 0) & (pos <= r), pos - 1, pos)
    return torch.where(pos == 0, r.expand_as(pos), order)


def restore_order(ref: Tensor, s: int) -> Tensor:
    """``[B, S]`` internal slot of each original view (the inverse of :func:`reference_order`)."""
    pos = torch.arange(s, device=ref.device).expand(ref.shape[0], s)
    r = ref[:, None]
    return torch.where(pos < r, pos + 1, torch.where(pos == r, torch.zeros_like(pos), pos))


def gather_views(x: Tensor, index: Tensor) -> Tensor:
    """``x [B, S, ...]`` with its views taken in the order ``index [B, S]``."""
    idx = index.reshape(*index.shape, *([1] * (x.dim() - 2))).expand(*index.shape, *x.shape[2:])
    return torch.gather(x, 1, idx)
