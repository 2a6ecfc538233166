"""Optional test dependencies (the ``test`` extra): skipped with the reason outside CI, required in CI.

``CI`` set in the environment (as CI services set it) turns a missing package into a failure
naming it, so that a comparison against evo or pycolmap never silently stops running there.
"""

from __future__ import annotations

import importlib
import os
import types

import pytest


def require_extra(name: str) -> types.ModuleType:
    """``import name``; outside CI a missing package skips the test, in CI it fails it."""
    try:
        return importlib.import_module(name)
    except ImportError as err:
        reason = f"{name} is not installed (pip install -e '.[test]'): {err}"
        if os.environ.get("CI"):
            pytest.fail(f"CI needs the test extra: {reason}", pytrace=False)
        pytest.skip(reason, allow_module_level=True)
