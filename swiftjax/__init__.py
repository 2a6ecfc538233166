"""swiftjax: SwiftVGGT large-scale reconstruction with a pure, jit-compiled JAX core.

Submodules are imported lazily so that ``import swiftjax`` stays cheap and never pulls in
torch (the inference shim lives in the separate ``inference`` package).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_SUBMODULES = (
    "align",
    "camera",
    "chunks",
    "evaluation",
    "io",
    "loops",
    "pipeline",
    "posegraph",
    "prediction",
    "sim3",
    "so3",
    "synthetic",
)

__all__ = list(_SUBMODULES) + ["__version__"]


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
