"""Load the previous synthetic oracle (renderer + oracle modules at a pinned commit) for A/B runs.

``load_previous_oracle()`` reads ``swiftjax/synthetic/render.py`` and ``oracle.py`` from git at
:data:`PREVIOUS_COMMIT` (the implementation before the per-tile renderer), imports them as
private modules (the old oracle is pointed at the old renderer) and returns the old module
``oracle``, or ``None`` when git or the commit is unavailable.  Benchmark use only.
"""

from __future__ import annotations

import importlib.util
import pathlib
import subprocess
import sys
import types

PREVIOUS_COMMIT = "61e4a9d"  # before "synthetic.render: per-column-tile candidate lists ..."
ROOT = pathlib.Path(__file__).resolve().parents[1]


def _source(path: str) -> str | None:
    try:
        return subprocess.run(
            ["git", "-C", str(ROOT), "show", f"{PREVIOUS_COMMIT}:{path}"], check=True, capture_output=True, text=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None


def _module(name: str, source: str) -> types.ModuleType:
    spec = importlib.util.spec_from_loader(name, loader=None)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up here
    exec(compile(source, f"<{PREVIOUS_COMMIT}:{name}>", "exec"), mod.__dict__)
    return mod


def load_previous_oracle() -> types.ModuleType | None:
    render_src = _source("swiftjax/synthetic/render.py")
    oracle_src = _source("swiftjax/synthetic/oracle.py")
    if render_src is None or oracle_src is None:
        return None
    _module("_previous_render", render_src)
    old_import = "from swiftjax.synthetic.render import"
    if old_import not in oracle_src:
        return None
    return _module("_previous_oracle", oracle_src.replace(old_import, "from _previous_render import"))
