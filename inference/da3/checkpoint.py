"""Strict loading of released Depth Anything 3 weights (``model.safetensors``).

The official layout: every key is ``"model." + <network state_dict key>`` (the network lives in
the ``model`` attribute of the API wrapper); the nested model's are ``model.da3.*`` and
``model.da3_metric.*``.  The DualDPT head holds ONE LayerNorm in all four
``head.scratch.output_conv2_aux.{0,1,2,3}.2`` slots; files written by safetensors keep one name
per shared tensor (the lexicographically first, ``...output_conv2_aux.0.2.*``) and drop the
other six.  Such aliases are filled from their kept name; if a file does carry them, they must
equal it.  Anything else — a missing, unexpected or wrongly-shaped key, another prefix — is
refused with one line naming the keys.  Only ``.safetensors`` is read (no pickles).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor, nn

from ..checkpoint import CheckpointError, LoadReport

__all__ = [
    "CHECKPOINT_PREFIX",
    "CheckpointError",
    "alias_groups",
    "expected_checkpoint_keys",
    "load_da3_checkpoint",
    "read_safetensors",
]

CHECKPOINT_PREFIX = "model."
_MAX_LISTED = 12


def read_safetensors(path: str | os.PathLike[str]) -> dict[str, Tensor]:
    """All tensors of a ``.safetensors`` file (CPU).  Raises CheckpointError (or FileNotFoundError)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"DA3 checkpoint not found: {p}")
    if p.suffix.lower() != ".safetensors":
        raise CheckpointError(f"DA3 checkpoint {p}: only .safetensors files are read (got {p.suffix or 'no suffix'!r})")
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        return dict(load_file(str(p), device="cpu"))
    except (SafetensorError, OSError, ValueError) as e:
        raise CheckpointError(f"cannot read safetensors file {p} (truncated or corrupt?): {e}") from e


def alias_groups(model: nn.Module) -> list[list[str]]:
    """Groups (sorted, size > 1) of state_dict names that share one parameter."""
    by_param: dict[int, list[str]] = {}
    for name, param in model.named_parameters(remove_duplicate=False):
        by_param.setdefault(id(param), []).append(name)
    return [sorted(names) for names in by_param.values() if len(names) > 1]


def expected_checkpoint_keys(model: nn.Module) -> list[str]:
    """Keys a released checkpoint holds for ``model``: prefixed, one name per shared tensor."""
    dropped = {n for group in alias_groups(model) for n in group[1:]}
    return [CHECKPOINT_PREFIX + k for k in model.state_dict() if k not in dropped]


def _listed(title: str, items: list[str]) -> str:
    more = f" ... (+{len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return f"{len(items)} {title}: {', '.join(items[:_MAX_LISTED])}{more}"


def load_da3_checkpoint(model: nn.Module, path: str | os.PathLike[str], strict: bool = True) -> LoadReport:
    """Loads official DA3 weights into ``model`` (:class:`DA3Net` or :class:`NestedDA3Net`).

    Every model tensor must be in the file under ``model.<name>`` with its shape (shared-tensor
    aliases may be absent), and the file may hold nothing else.  A model on the ``meta`` device
    gets the file's tensors assigned; otherwise values are copied (converted to the model dtype).

    Raises:
        CheckpointError: one line listing missing / unexpected / mismatched keys.
    """
    if not strict:
        raise ValueError("load_da3_checkpoint: only strict loading is supported")
    file = read_safetensors(path)
    expected = model.state_dict()
    state: dict[str, Tensor] = {}
    unexpected: list[str] = []
    for key, value in file.items():
        name = key[len(CHECKPOINT_PREFIX) :] if key.startswith(CHECKPOINT_PREFIX) else None
        if name is None or name not in expected:
            unexpected.append(key)
        else:
            state[name] = value
    mismatched = [
        f"{CHECKPOINT_PREFIX}{k} {tuple(v.shape)} vs model {tuple(expected[k].shape)}"
        for k, v in state.items()
        if tuple(v.shape) != tuple(expected[k].shape)
    ]
    conflicting: list[str] = []
    for group in alias_groups(model):
        kept = group[0]
        for alias in group[1:]:
            if alias not in state:
                if kept in state:
                    state[alias] = state[kept]
            elif kept in state and not mismatched and not torch.equal(state[alias], state[kept]):
                conflicting.append(f"{CHECKPOINT_PREFIX}{alias} != {CHECKPOINT_PREFIX}{kept}")
    missing = [CHECKPOINT_PREFIX + k for k in expected if k not in state]
    if missing or unexpected or mismatched or conflicting:
        name = type(model).__name__
        parts = [f"checkpoint {os.fspath(path)} does not match {name}"]
        if unexpected and not any(k.startswith(CHECKPOINT_PREFIX) for k in file):
            parts.append(
                f"no key starts with {CHECKPOINT_PREFIX!r} (not an official Depth Anything 3 file; "
                f"first key {next(iter(file), '<none>')!r})"
            )
        for title, items in (
            ("missing key(s)", missing),
            ("unexpected key(s)", unexpected),
            ("shape mismatch(es)", mismatched),
            ("shared-tensor alias(es) differing", conflicting),
        ):
            if items:
                parts.append(_listed(title, items))
        raise CheckpointError("; ".join(parts))
    on_meta = any(t.is_meta for t in expected.values())
    # The shared LayerNorm is one module object under four names, so it stays shared either way.
    model.load_state_dict(state, strict=True, assign=on_meta)
    return LoadReport(path=os.fspath(path), loaded=len(file), ignored=())
