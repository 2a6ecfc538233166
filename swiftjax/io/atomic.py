"""Atomic file writes: a temp file in the target's directory, fsync, then ``os.replace``.

A reader (or a crashed run being resumed) sees either the old file or the complete new one,
never a half-written file.  On any exception the temp file is removed and the old file is
left untouched.

    with atomic_write("poses.txt") as f:          # text, or mode="wb" for bytes
        f.write("...")
    with atomic_path("plot.png") as tmp:          # for tools that want a path (savefig, cv2)
        fig.savefig(tmp)
    atomic_save_npz("chunk_0003.npz", depth=d, conf=c)

A set of files that belong together (a run's outputs) is written with :func:`output_set`:
inside it every atomic write of this thread's context is fsynced but not yet renamed; the
renames all happen when the block ends without an error.  An error (a full disk) or a kill
before that leaves every previous file as it was (the temp files are removed, or cleaned
later with :func:`temp_files`), so the set on disk is always one complete set.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import pathlib
import tempfile
from collections.abc import Callable, Iterator, Sequence
from typing import IO, Any

import numpy as np

__all__ = ["atomic_path", "atomic_paths", "atomic_write", "atomic_save_npz", "output_set", "temp_files", "TEMP_MARK"]

#: Temp files are ``.<name>.<random>.tmp<suffix>`` beside their target (see :func:`temp_files`).
TEMP_MARK = ".tmp"

_UMASK: int | None = None


def _file_mode() -> int:
    """``0o666 & ~umask``: the permissions ``open(path, "w")`` would give (mkstemp gives 0600)."""
    global _UMASK
    if _UMASK is None:
        _UMASK = os.umask(0)
        os.umask(_UMASK)
    return 0o666 & ~_UMASK


def _fsync_dir(directory: pathlib.Path) -> None:
    """Persist the rename itself (POSIX); silently skipped where directories can't be opened."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: The open :func:`output_set`'s pending renames ``[(temp, target)]`` (None: rename at once).
_PENDING: contextvars.ContextVar[list[tuple[pathlib.Path, pathlib.Path]] | None] = contextvars.ContextVar(
    "swiftjax_output_set", default=None
)


def _replace(tmp: pathlib.Path, target: pathlib.Path) -> bool:
    """Rename now (True), or queue the rename in the open :func:`output_set` (False)."""
    pending = _PENDING.get()
    if pending is None:
        os.replace(tmp, target)
        return True
    for old in [t for t, g in pending if g == target]:  # rewritten in the set: the last version wins
        old.unlink(missing_ok=True)
    pending[:] = [(t, g) for t, g in pending if g != target]
    pending.append((tmp, target))
    return False


@contextlib.contextmanager
def output_set(before_rename: Callable[[list[pathlib.Path]], None] | None = None) -> Iterator[None]:
    """Write the atomic files of the block as one set (module docstring): renamed together at
    the end, none of them on an exception.  Nested sets join the outer one.

    ``before_rename(targets)``, if given, is called with the set's files once the block has
    succeeded, before the renames (its own atomic writes happen at once); an exception from
    it cancels the set."""
    if _PENDING.get() is not None:
        yield
        return
    pending: list[tuple[pathlib.Path, pathlib.Path]] = []
    token = _PENDING.set(pending)
    try:
        yield
    except BaseException:
        for tmp, _ in pending:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise
    finally:
        _PENDING.reset(token)
    if before_rename is not None:
        try:
            before_rename([target for _, target in pending])
        except BaseException:
            for tmp, _ in pending:
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
            raise
    for tmp, target in pending:
        os.replace(tmp, target)
    for directory in dict.fromkeys(t.parent for _, t in pending):
        _fsync_dir(directory)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[pathlib.Path]:
    """Yield a temp path beside ``path``; on success it is fsynced and renamed onto ``path``.

    The temp name keeps ``path``'s suffix (``.name.XXXX.tmp.png``) so that tools which pick
    a format from the extension still work.  The parent directory must exist.  On an
    exception inside the block the temp file is deleted and ``path`` is left as it was.
    """
    target = pathlib.Path(path)
    parent = target.parent
    if not parent.is_dir():
        raise FileNotFoundError(f"cannot write {target}: directory {parent} does not exist")
    fd, tmp_name = tempfile.mkstemp(dir=parent, prefix=f".{target.name}.", suffix=f"{TEMP_MARK}{target.suffix}")
    os.close(fd)
    tmp = pathlib.Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _file_mode())
        renamed = _replace(tmp, target)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:
            # e.g. ENOSPC from a write: name the file being written (the temp file is gone).
            raise OSError(e.errno, f"{e.strerror or e} (writing {target})", os.fspath(target)) from e
        raise
    if renamed:
        _fsync_dir(parent)


@contextlib.contextmanager
def atomic_paths(paths: Sequence[str | os.PathLike[str]]) -> Iterator[list[pathlib.Path]]:
    """:func:`atomic_path` for many files at once: yields one temp path per target; on success
    every temp file is fsynced, then all are renamed, then each directory is fsynced once.

    Batching the syncs is cheaper per file than one :func:`atomic_path` each
    (docs/performance/io.md).  Each file is still replaced atomically; on an exception every
    temp file is deleted and no target is touched.
    """
    targets = [pathlib.Path(p) for p in paths]
    tmps: list[pathlib.Path] = []
    try:
        for target in targets:
            if not target.parent.is_dir():
                raise FileNotFoundError(f"cannot write {target}: directory {target.parent} does not exist")
            fd, name = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=f".tmp{target.suffix}")
            os.close(fd)
            tmps.append(pathlib.Path(name))
        yield list(tmps)
        for tmp in tmps:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.chmod(tmp, _file_mode())
        renamed = [_replace(tmp, target) for tmp, target in zip(tmps, targets)]
    except BaseException:
        for tmp in tmps:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise
    if all(renamed):
        for directory in dict.fromkeys(t.parent for t in targets):
            _fsync_dir(directory)


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str], mode: str = "w", encoding: str | None = "utf-8", newline: str | None = None
) -> Iterator[IO[Any]]:
    """Open a temp file beside ``path`` for writing; atomically replace ``path`` on success.

    Args:
        path: the final file.
        mode: ``"w"`` (text) or ``"wb"`` (bytes).
        encoding, newline: as for :func:`open` (text mode only).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write mode must be 'w' or 'wb', got {mode!r}")
    with atomic_path(path) as tmp:
        if mode == "w":
            f = open(tmp, "w", encoding=encoding, newline=newline)
        else:
            f = open(tmp, "wb")
        with f:
            yield f


def atomic_save_npz(path: str | os.PathLike[str], compress: bool = False, **arrays: Any) -> None:
    """Write ``arrays`` to the ``.npz`` file ``path`` atomically (exact name, no suffix added).

    ``compress=True`` uses ``np.savez_compressed`` (zlib; slower, smaller).
    """
    save = np.savez_compressed if compress else np.savez
    with atomic_write(path, "wb") as f:
        save(f, **arrays)


def temp_files(directory: str | os.PathLike[str]) -> list[pathlib.Path]:
    """The temp files :func:`atomic_path` leaves behind when its process is killed, in ``directory``
    (not recursive): ``.<target name>.<8 random characters>.tmp<target suffix>``."""
    import re

    pattern = re.compile(r"^\..+\.[A-Za-z0-9_]{8}" + re.escape(TEMP_MARK) + r"(\.[^.]*)?$")
    d = pathlib.Path(directory)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if p.is_file() and pattern.match(p.name))
