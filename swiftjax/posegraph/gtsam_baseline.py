"""Deprecated: the GTSAM baseline moved to ``bench/_gtsam_baseline.py`` (benchmarks and tests only).

This shim loads it from the source checkout (the bench folder is not part of an installed wheel).
"""

import importlib.util
import pathlib
import warnings

warnings.warn(
    "swiftjax.posegraph.gtsam_baseline is deprecated; it lives in bench/_gtsam_baseline.py",
    DeprecationWarning,
    stacklevel=2,
)

_PATH = pathlib.Path(__file__).resolve().parents[2] / "bench" / "_gtsam_baseline.py"
if not _PATH.is_file():
    raise ImportError(f"the GTSAM baseline is part of the source checkout's bench/ folder ({_PATH} not found)")
_spec = importlib.util.spec_from_file_location("_gtsam_baseline", _PATH)
_module = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_module)
globals().update({name: getattr(_module, name) for name in _module.__all__})
__all__ = list(_module.__all__)
