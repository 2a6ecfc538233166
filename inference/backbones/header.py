"""A safetensors file's header, read without torch and without reading the tensors.

The header (8-byte little-endian length, then JSON ``name -> {dtype, shape, data_offsets}``)
says which network a checkpoint is for and whether the file is whole: the CLI refuses a
checkpoint of another family, of other shapes, or a truncated one before any model is built.
"""

from __future__ import annotations

import json
import math
import os
import struct
from typing import Any

from swiftjax.errors import SwiftjaxError

__all__ = ["read_header", "checkpoint_header", "compare_shapes", "describe_family", "HeaderError", "FAMILY_TEXT"]

_ITEMSIZE = {
    "F64": 8,
    "F32": 4,
    "F16": 2,
    "BF16": 2,
    "I64": 8,
    "I32": 4,
    "I16": 2,
    "I8": 1,
    "U8": 1,
    "BOOL": 1,
    "F8_E4M3": 1,
    "F8_E5M2": 1,
    "U16": 2,
    "U32": 4,
    "U64": 8,
}
_MAX_HEADER = 100 << 20


class HeaderError(SwiftjaxError, ValueError):
    """Not a readable, complete safetensors file (one line naming the file)."""


def read_header(path: str | os.PathLike[str]) -> dict[str, tuple[str, tuple[int, ...]]]:
    """``name -> (dtype, shape)`` of every tensor in a ``.safetensors`` file.

    Raises :class:`HeaderError` when the header is unreadable, a tensor's byte range does not
    match its dtype and shape, or the file is shorter than the header says (truncated).
    """
    p = os.fspath(path)
    size = os.path.getsize(p)
    with open(p, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            raise HeaderError(f"{p} is not a safetensors file ({size} bytes, no header)")
        (n,) = struct.unpack("<Q", head)
        if n > min(size - 8, _MAX_HEADER):
            raise HeaderError(
                f"{p} is not a safetensors file or is truncated (header of {n} bytes in a {size}-byte file)"
            )
        try:
            meta = json.loads(f.read(n))
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise HeaderError(f"{p}: unreadable safetensors header ({err})") from None
    if not isinstance(meta, dict):
        raise HeaderError(f"{p}: the safetensors header is not a JSON object")
    body = size - 8 - n
    out: dict[str, tuple[str, tuple[int, ...]]] = {}
    for name, info in meta.items():
        if name == "__metadata__":
            continue
        try:
            dtype, shape, (start, stop) = info["dtype"], tuple(int(v) for v in info["shape"]), info["data_offsets"]
        except (KeyError, TypeError, ValueError):
            raise HeaderError(f"{p}: malformed header entry for {name!r}") from None
        want = math.prod(shape) * _ITEMSIZE.get(dtype, 0)
        if _ITEMSIZE.get(dtype) is not None and stop - start != want:
            raise HeaderError(
                f"{p}: tensor {name} claims {stop - start} bytes for {dtype} {list(shape)} ({want} needed)"
            )
        if stop > body:
            raise HeaderError(f"{p} is truncated: tensor {name} ends at byte {stop} of a {body}-byte data section")
        out[str(name)] = (str(dtype), shape)
    return out


def describe_family(names: Any) -> str:
    """Which network a checkpoint's key names belong to: ``vggt``, ``da3``, ``da3-nested`` or ``unknown``."""
    names = list(names)
    if any(k.startswith("model.da3.") or k.startswith("model.da3_metric.") for k in names):
        return "da3-nested"
    if any(k.startswith("model.backbone.") for k in names):
        return "da3"
    if any(k.startswith("aggregator.") for k in names):
        return "vggt"
    return "unknown"


FAMILY_TEXT = {
    "vggt": "a VGGT checkpoint",
    "da3": "a Depth Anything 3 (any-view) checkpoint",
    "da3-nested": "a Depth Anything 3 nested (metric) checkpoint",
    "unknown": "not a checkpoint of a known network",
}


def checkpoint_header(path: str | os.PathLike[str]) -> dict[str, tuple[str, tuple[int, ...]]]:
    """:func:`read_header`, its failure as the loaders' one-line ``CheckpointError``."""
    from inference.checkpoint import CheckpointError

    try:
        return read_header(path)
    except HeaderError as err:
        raise CheckpointError(str(err)) from None


def compare_shapes(
    path: str | os.PathLike[str],
    got: dict[str, tuple[int, ...]],
    want: dict[str, tuple[int, ...]],
    what: str,
    optional: tuple[str, ...] = (),
) -> None:
    """One-line ``CheckpointError`` naming the first differing keys (missing, unexpected, shape)
    between a file's tensor shapes ``got`` and the model's ``want``; ``optional`` keys may be absent."""
    from inference.checkpoint import CheckpointError

    missing = [k for k in want if k not in got and k not in optional]
    unexpected = [k for k in got if k not in want]
    shapes = [f"{k} {list(got[k])} vs {list(want[k])}" for k in want if k in got and tuple(got[k]) != tuple(want[k])]
    if missing or unexpected or shapes:
        parts = [
            f"{title} {len(items)} ({', '.join(items[:3])}{', ...' if len(items) > 3 else ''})"
            for title, items in (("missing", missing), ("unexpected", unexpected), ("shape mismatch", shapes))
            if items
        ]
        raise CheckpointError(
            f"checkpoint {os.fspath(path)} does not match the {what}: {'; '.join(parts)} "
            f"(is --model / --model-config the one it was trained with?)"
        )
