"""Host-boundary input checks shared by the loop functions (concrete arrays only)."""

from __future__ import annotations

import jax
import numpy as np


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _check_finite(x, name: str) -> None:
    a = np.asarray(x)
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a.reshape(a.shape[0], -1) if a.ndim > 1 else a[:, None]))
        rows = np.unique(bad[:, 0])
        raise ValueError(f"{name} contains NaN or Inf in {len(rows)} row(s), first at row {int(rows[0])}")
