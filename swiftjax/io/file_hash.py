"""SHA-256 of whole files, hashed once and cached by file identity.

The run directory fingerprints the weights file and every input frame by content
(:mod:`swiftjax.pipeline.rundir`).  Hashing a 5 GB checkpoint on every run would cost
seconds, so each digest is cached under the file's identity ``(device, inode, size,
mtime_ns, ctime_ns)``: any write to the file changes its ``ctime``, which a user cannot set
back (``touch``/``os.utime`` restore ``mtime`` only and bump ``ctime`` themselves), so a file
edited with size and modification time restored is hashed again.

The cache is one JSON file, ``$SWIFTJAX_HASH_CACHE`` or ``~/.cache/swiftjax/sha256.json``
(``$XDG_CACHE_HOME`` respected), written atomically; concurrent runs may lose each other's
entries (then those files are hashed again), never read a wrong one.  It keeps the
:data:`MAX_ENTRIES` most recent digests.

    digests = sha256_files(paths)        # one hex digest per path
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
from collections.abc import Sequence

__all__ = ["sha256_files", "sha256_file", "cache_path", "MAX_ENTRIES"]

PathLike = str | os.PathLike[str]

#: Digests kept in the cache (least recently stored dropped first): ~100 bytes each.
MAX_ENTRIES = 200_000
_BLOCK = 8 << 20


def cache_path() -> pathlib.Path:
    """The cache file (module docstring)."""
    env = os.environ.get("SWIFTJAX_HASH_CACHE")
    if env:
        return pathlib.Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "swiftjax" / "sha256.json"


def _identity(st: os.stat_result) -> str:
    return f"{st.st_dev}:{st.st_ino}:{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}"


def _digest(path: PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def _load(path: pathlib.Path) -> dict[str, str]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return {k: v for k, v in data.items() if isinstance(v, str)} if isinstance(data, dict) else {}


def _store(path: pathlib.Path, cache: dict[str, str]) -> None:
    from swiftjax.io.atomic import atomic_write

    if len(cache) > MAX_ENTRIES:
        cache = dict(list(cache.items())[-MAX_ENTRIES:])
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            json.dump(cache, f)
    except OSError:  # a read-only home: no cache, every run hashes again
        pass


def sha256_files(paths: Sequence[PathLike]) -> list[str]:
    """The SHA-256 (hex) of each file's whole content, from the cache when its identity
    (device, inode, size, mtime, ctime) is cached, else read and cached."""
    where = cache_path()
    cache = _load(where)
    out, added = [], False
    for p in paths:
        key = _identity(os.stat(p))
        digest = cache.get(key)
        if digest is None:
            digest = _digest(p)
            if _identity(os.stat(p)) == key:  # not written to while being read
                cache[key] = digest
                added = True
        out.append(digest)
    if added:
        _store(where, cache)
    return out


def sha256_file(path: PathLike) -> str:
    """:func:`sha256_files` of one file."""
    return sha256_files([path])[0]
