"""Uniform sampling of a point stream read chunk by chunk (the viewer's cloud, ``points.png``)."""

from __future__ import annotations

import numpy as np

__all__ = ["Reservoir"]


class Reservoir:
    """A uniform sample of at most ``capacity`` points of a stream of chunks.

    Every point gets an independent uniform key; the sample is the ``capacity`` points with
    the smallest keys seen so far (a bottom-k sketch), which is a uniform sample without
    replacement of the stream, kept in ``O(capacity + chunk)`` memory: :meth:`add` merges
    one chunk and cuts back with ``argpartition`` (no Python loop over points).  A chunk
    added again replaces its previous points (live runs re-read nothing, but resume does).

    Arrays: ``xyz [k, 3]`` float32 (chunk frame), ``rgb [k, 3]`` uint8, ``conf [k]``
    float32, ``chunk [k]`` int32, ``key [k]`` float64.
    """

    def __init__(self, capacity: int, seed: int = 0) -> None:
        if capacity < 1:
            raise ValueError(f"the point budget must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.rng = np.random.default_rng(seed)
        self.xyz = np.zeros((0, 3), np.float32)
        self.rgb = np.zeros((0, 3), np.uint8)
        self.conf = np.zeros(0, np.float32)
        self.chunk = np.zeros(0, np.int32)
        self.key = np.zeros(0, np.float64)
        self.seen = 0  # points offered so far

    def __len__(self) -> int:
        return len(self.key)

    def add(self, chunk: int, xyz: np.ndarray, rgb: np.ndarray, conf: np.ndarray) -> None:
        """Merge one chunk's points (``[P, 3]``, ``[P, 3]`` uint8, ``[P]``)."""
        keep = self.chunk != chunk
        key = self.rng.random(len(xyz))
        self.seen += len(xyz)
        xyz_all = np.concatenate([self.xyz[keep], np.asarray(xyz, np.float32)])
        rgb_all = np.concatenate([self.rgb[keep], np.asarray(rgb, np.uint8)])
        conf_all = np.concatenate([self.conf[keep], np.asarray(conf, np.float32)])
        chunk_all = np.concatenate([self.chunk[keep], np.full(len(xyz), chunk, np.int32)])
        key_all = np.concatenate([self.key[keep], key])
        if len(key_all) > self.capacity:
            sel = np.argpartition(key_all, self.capacity - 1)[: self.capacity]
            sel.sort()
            xyz_all, rgb_all, conf_all = xyz_all[sel], rgb_all[sel], conf_all[sel]
            chunk_all, key_all = chunk_all[sel], key_all[sel]
        self.xyz, self.rgb, self.conf, self.chunk, self.key = xyz_all, rgb_all, conf_all, chunk_all, key_all
