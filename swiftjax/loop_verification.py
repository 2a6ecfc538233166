"""Deprecated: geometric loop verification moved to :mod:`swiftjax.loops.verification`.

Every name is still reachable here for one release, with a :class:`DeprecationWarning`.
"""

from __future__ import annotations

import warnings
from typing import Any

from swiftjax.loops import verification as _verification

__all__ = list(_verification.__all__)


def __getattr__(name: str) -> Any:
    if hasattr(_verification, name):
        warnings.warn(
            f"swiftjax.loop_verification.{name} moved to swiftjax.loops.verification.{name}; "
            "the old module goes away in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(_verification, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
