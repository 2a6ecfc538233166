"""Strict loading of π³ / π³X checkpoints in the official layout (``model.safetensors``).

Only safetensors files are read (never pickles: nothing in a π³ file needs code to load).
Every model entry must be in the file with the same shape and the file may hold nothing else,
except that a π³X model built without its multimodal branches skips the file's
``depth_encoder.* / depth_emb / ray_embed.* / pose_inject_blk.*`` entries (what the official
``disable_multimodal()`` deletes).  The released π³X file may lack ``image_mean`` /
``image_std`` (the official examples load it with ``strict=False``): those two are the fixed
ImageNet constants, so only they may be missing, and they keep their built-in values.
Any other difference raises :class:`inference.checkpoint.CheckpointError` listing the keys.
"""

from __future__ import annotations

import os
from pathlib import Path

from torch import nn

from ..checkpoint import CheckpointError, LoadReport, key_differences, mismatch_error, read_state_dict

__all__ = ["load_pi3_checkpoint", "MULTIMODAL_PREFIXES", "OPTIONAL_KEYS"]

MULTIMODAL_PREFIXES: tuple[str, ...] = ("depth_encoder.", "depth_emb", "ray_embed.", "pose_inject_blk.")
OPTIONAL_KEYS: tuple[str, ...] = ("image_mean", "image_std")


def load_pi3_checkpoint(model: nn.Module, path: str | os.PathLike[str]) -> LoadReport:
    """Loads ``path`` (``.safetensors``) into a :class:`~inference.pi3.model.Pi3` or
    :class:`~inference.pi3.pi3x.Pi3X` with strict name and shape checking.

    A model on the ``meta`` device gets the file's tensors assigned.

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: not a safetensors file, unreadable, or not matching the model (the
            message lists the missing, unexpected and mismatched keys).
    """
    p = Path(path)
    if p.suffix.lower() != ".safetensors":
        raise CheckpointError(
            f"refused to load {p}: π³ checkpoints are read from .safetensors only (pickled "
            f"{p.suffix or 'files'} can run code when loaded; convert with safetensors.torch.save_file)"
        )
    state = read_state_dict(p)
    expected = model.state_dict()
    cfg = getattr(model, "config", None)
    skip_multimodal = getattr(cfg, "variant", "") == "pi3x" and not getattr(cfg, "multimodal", True)
    ignored = tuple(k for k in state if skip_multimodal and k.startswith(MULTIMODAL_PREFIXES))
    state = {k: v for k, v in state.items() if k not in ignored}
    missing, unexpected, mismatched = key_differences(state, expected, OPTIONAL_KEYS)
    if missing or unexpected or mismatched:
        raise mismatch_error(
            path,
            f"{type(model).__name__} model",
            missing,
            unexpected,
            mismatched,
            hint="the model config -- pi3 / pi3x, its sizes --",
        )
    on_meta = any(t.is_meta for t in expected.values())
    absent = [k for k in OPTIONAL_KEYS if k in expected and k not in state]
    result = model.load_state_dict(state, strict=False, assign=on_meta)
    leftover = [k for k in result.missing_keys if k not in absent] + list(result.unexpected_keys)
    if leftover:  # cannot happen after the checks above; kept as a guard against silent partial loads
        raise CheckpointError(f"checkpoint {os.fspath(path)}: unexpected load result {leftover}")
    if absent and on_meta:  # materialise the ImageNet constants the file does not hold
        model._register_normalisation()  # type: ignore[operator]
    return LoadReport(path=os.fspath(path), loaded=len(state), ignored=ignored)
