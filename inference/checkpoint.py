"""Loading the official VGGT checkpoint (``model.pt``) or a safetensors copy into :class:`VGGT`.

Loading is strict: every model parameter must be in the file with the same shape, and the file
may hold nothing else except the point and track heads (``point_head.*``, ``track_head.*``),
which SwiftVGGT does not use and which are skipped on purpose.  Floating-point tensors of
another precision are cast to float32 with a warning; integer or boolean tensors and NaN/inf
values are refused, naming the tensors.  Pickled checkpoints are read
with ``torch.load(weights_only=True)``, which refuses pickles that would run code.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pickle
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor, nn

from swiftjax.errors import SwiftjaxError

__all__ = [
    "CheckpointError",
    "LoadReport",
    "key_differences",
    "mismatch_error",
    "IGNORED_PREFIXES",
    "load_checkpoint",
    "read_state_dict",
]

logger = logging.getLogger("swiftjax." + __name__)

IGNORED_PREFIXES: tuple[str, ...] = ("point_head.", "track_head.")
_PICKLE_SUFFIXES = (".pt", ".pth", ".bin", ".ckpt")
_MAX_LISTED = 15


class CheckpointError(SwiftjaxError, RuntimeError):
    """A checkpoint could not be read or does not fit the model."""


@dataclasses.dataclass(frozen=True)
class LoadReport:
    """What :func:`load_checkpoint` did."""

    path: str
    loaded: int
    ignored: tuple[str, ...]
    cast: str = ""  # e.g. "385 float16 tensor(s) cast to float32" (also warned)


def read_state_dict(path: str | os.PathLike[str]) -> dict[str, Tensor]:
    """Reads a flat ``name -> tensor`` mapping from ``.safetensors`` or a torch pickle.

    Torch files are opened with ``weights_only=True`` and memory-mapped when they are in the
    zip format; a ``{"model": ...}`` or ``{"state_dict": ...}`` wrapper is unwrapped.

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: unreadable, truncated, unsafe, or not a mapping of tensors.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"VGGT checkpoint not found: {p}")
    suffix = p.suffix.lower()
    if suffix == ".safetensors":
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            obj: object = load_file(str(p), device="cpu")
        except (SafetensorError, OSError, ValueError) as e:
            raise CheckpointError(f"cannot read safetensors file {p} (truncated or corrupt?): {e}") from e
    elif suffix in _PICKLE_SUFFIXES:
        obj = _torch_load(p)
    else:
        raise CheckpointError(f"unknown checkpoint format {p.suffix!r} for {p}: use .safetensors, .pt or .pth")

    for wrapper in ("state_dict", "model"):
        if isinstance(obj, Mapping) and wrapper in obj and isinstance(obj[wrapper], Mapping):
            obj = obj[wrapper]
    if not isinstance(obj, Mapping) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise CheckpointError(f"{p} does not hold a state_dict (a mapping of parameter names to tensors)")
    return {str(k): v for k, v in obj.items()}


def _pickle_reason(e: Exception) -> str:
    """The informative line of torch's weights-only error (e.g. 'unsupported GLOBAL posix.system')."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    for ln in lines:
        if "GLOBAL" in ln or "Unsupported" in ln:
            return ln.rstrip(".")
    return lines[0] if lines else type(e).__name__


def _is_unsafe(e: Exception) -> bool:
    """Whether torch's weights-only unpickler refused a global (code that would run), as
    opposed to bytes that are not a valid pickle at all (e.g. 'Unsupported operand 64')."""
    return "global" in str(e).lower()


def _torch_load(p: Path) -> object:
    with open(p, "rb") as f:
        head = f.read(4)
    if head[:4] != b"PK\x03\x04" and head[:1] != b"\x80":
        raise CheckpointError(
            f"cannot read torch checkpoint {p}: not a torch file (neither the zip format nor a pickle; "
            f"starts with {head!r}; corrupt or another format?)"
        )
    try:
        return torch.load(p, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError as e:
        if not _is_unsafe(e):
            raise CheckpointError(
                f"cannot read torch checkpoint {p} (truncated or corrupt?): {_pickle_reason(e)}"
            ) from e
        raise CheckpointError(
            f"refused to load {p}: torch.load(weights_only=True) found something other than tensors "
            f"in the pickle, which could run code when unpickled ({_pickle_reason(e)}). VGGT "
            f"checkpoints hold tensors only: this file is not one, or has been tampered with."
        ) from e
    except RuntimeError as e:
        if "mmap" in str(e) and "zip" in str(e):  # torch's pre-1.6 (non-zip) serialisation cannot be mmapped
            try:
                return torch.load(p, map_location="cpu", weights_only=True)
            except pickle.UnpicklingError as e2:
                if not _is_unsafe(e2):
                    raise CheckpointError(
                        f"cannot read torch checkpoint {p} (truncated or corrupt?): {_pickle_reason(e2)}"
                    ) from e2
                raise CheckpointError(f"refused to load {p} (unsafe pickle: {_pickle_reason(e2)})") from e2
            except Exception as e2:  # report any reader failure uniformly
                raise CheckpointError(f"cannot read torch checkpoint {p}: {e2}") from e2
        raise CheckpointError(f"cannot read torch checkpoint {p} (truncated or corrupt?): {e}") from e
    except (EOFError, OSError, ValueError) as e:
        raise CheckpointError(f"cannot read torch checkpoint {p} (truncated or corrupt?): {e}") from e


def key_differences(
    state: Mapping[str, Tensor], expected: Mapping[str, Tensor], optional: tuple[str, ...] = ()
) -> tuple[list[str], list[str], list[str]]:
    """``(missing, unexpected, shape mismatches)`` of a checkpoint against a model's state_dict;
    keys in ``optional`` may be missing."""
    missing = [k for k in expected if k not in state and k not in optional]
    unexpected = [k for k in state if k not in expected]
    mismatched = [
        f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in expected
        if k in state and tuple(state[k].shape) != tuple(expected[k].shape)
    ]
    return missing, unexpected, mismatched


def mismatch_error(
    path: str | os.PathLike[str],
    what: str,
    missing: list[str],
    unexpected: list[str],
    mismatched: list[str],
    hint: str = "the model config",
) -> CheckpointError:
    """The error listing a checkpoint's missing, unexpected and shape-mismatched keys (up to
    15 of each)."""
    parts = [f"checkpoint {os.fspath(path)} does not match the {what}:"]
    for title, items in (("missing", missing), ("unexpected", unexpected), ("shape mismatch", mismatched)):
        if items:
            shown = "\n    ".join(items[:_MAX_LISTED])
            more = f"\n    ... and {len(items) - _MAX_LISTED} more" if len(items) > _MAX_LISTED else ""
            parts.append(f"  {len(items)} {title} key(s):\n    {shown}{more}")
    parts.append(f"  (is {hint} the one the checkpoint was trained with?)")
    return CheckpointError("\n".join(parts))


def load_checkpoint(model: nn.Module, path: str | os.PathLike[str]) -> LoadReport:
    """Loads official VGGT weights into ``model`` with strict name and shape checking.

    Keys starting with ``point_head.`` or ``track_head.`` are ignored on purpose.  Any other
    difference fails with one error that lists the missing, unexpected and shape-mismatched
    keys.  Values are copied into the model's parameters (converted to their dtype); a model
    built on the ``meta`` device gets the checkpoint's tensors assigned instead.

    Returns:
        a :class:`LoadReport` (number of loaded tensors, ignored keys).
    """
    state = read_state_dict(path)
    ignored = tuple(k for k in state if k.startswith(IGNORED_PREFIXES))
    state = {k: v for k, v in state.items() if not k.startswith(IGNORED_PREFIXES)}
    expected = model.state_dict()
    missing, unexpected, mismatched = key_differences(state, expected)
    if missing or unexpected or mismatched:
        raise mismatch_error(path, "VGGT model", missing, unexpected, mismatched)
    state, cast = _check_values(state, expected, os.fspath(path))
    if cast:
        logger.warning(f"checkpoint {os.fspath(path)}: {cast}")
    on_meta = any(t.is_meta for t in expected.values())
    model.load_state_dict(state, strict=True, assign=on_meta)
    return LoadReport(path=os.fspath(path), loaded=len(state), ignored=ignored, cast=cast)


def _listed(names: list[str]) -> str:
    shown = ", ".join(names[:_MAX_LISTED])
    return shown + (f" and {len(names) - _MAX_LISTED} more" if len(names) > _MAX_LISTED else "")


def _check_values(state: dict[str, Tensor], expected: Mapping[str, Tensor], path: str) -> tuple[dict[str, Tensor], str]:
    """Dtypes and values of a checkpoint whose names and shapes fit the model.

    A floating-point tensor of another precision (float16, bfloat16, float64 copies of the
    weights) is cast to the model's dtype, and said (``(state, "N tensors cast ...")``): it
    used to pass the checks and fail at the first prediction.  Integer, boolean or complex
    tensors where the model has floating-point parameters, and NaN/inf values, are a
    :class:`CheckpointError` naming the tensors (they failed inside ``load_state_dict``, or
    came out much later as non-finite poses)."""
    wrong: list[str] = []
    cast: dict[str, list[str]] = {}
    for k, v in state.items():
        want = expected[k].dtype
        if v.dtype == want:
            continue
        if want.is_floating_point and v.dtype.is_floating_point:
            cast.setdefault(str(v.dtype).removeprefix("torch."), []).append(k)
        else:
            wrong.append(f"{k} ({str(v.dtype).removeprefix('torch.')})")
    if wrong:
        raise CheckpointError(
            f"checkpoint {path} holds {len(wrong)} tensor(s) of a non-floating-point dtype where VGGT has "
            f"float32 parameters: {_listed(wrong)} (not a VGGT checkpoint, or a quantised one)"
        )
    if cast:
        state = {k: (v.to(expected[k].dtype) if v.dtype != expected[k].dtype else v) for k, v in state.items()}
    bad = [k for k, v in state.items() if v.dtype.is_floating_point and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(
            f"checkpoint {path}: {len(bad)} tensor(s) hold NaN/inf values: {_listed(bad)} (a damaged or diverged "
            "checkpoint: VGGT's outputs would be non-finite)"
        )
    text = "; ".join(f"{len(names)} {dt} tensor(s) cast to float32" for dt, names in sorted(cast.items()))
    return state, text
