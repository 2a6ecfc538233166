"""A generated closed driving route, so the demo needs no data file.

:func:`loop_route` drives a rounded rectangle ``laps`` times (default 1.25: the start of the
loop is revisited in the same direction after ~one lap, a loop closure) at ``spacing_m``
per frame, on a gently rolling road (height ``hill_m sin(2 pi s / L)``), with OpenCV
cameras (x right, y down, z forward) looking along the direction of travel, in a world
frame like KITTI's (y down, the route in the x-z plane, the first camera at the origin).
"""

from __future__ import annotations

import numpy as np

__all__ = ["loop_route"]


def _rounded_rectangle(width: float, length: float, radius: float, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``[M, 2]`` (x, z) and unit tangents at arc lengths ``s`` (counter-clockwise seen from above)."""
    a, b = width / 2 - radius, length / 2 - radius
    # right side (x = +w/2) heading +z, then corner, top, corner, left, corner, bottom, corner
    arc = 0.5 * np.pi * radius
    pieces = [
        ("line", 2 * b, np.array([width / 2, -b]), np.array([0.0, 1.0])),
        ("arc", arc, np.array([a, b]), 0.0),
        ("line", 2 * a, np.array([a, length / 2]), np.array([-1.0, 0.0])),
        ("arc", arc, np.array([-a, b]), 0.5 * np.pi),
        ("line", 2 * b, np.array([-width / 2, b]), np.array([0.0, -1.0])),
        ("arc", arc, np.array([-a, -b]), np.pi),
        ("line", 2 * a, np.array([-a, -length / 2]), np.array([1.0, 0.0])),
        ("arc", arc, np.array([a, -b]), 1.5 * np.pi),
    ]
    total = sum(p[1] for p in pieces)
    s = np.mod(s, total)
    pts = np.zeros((len(s), 2))
    tan = np.zeros((len(s), 2))
    start = 0.0
    for kind, L, p0, extra in pieces:
        m = (s >= start) & (s < start + L)
        u = s[m] - start
        if kind == "line":
            pts[m] = p0 + u[:, None] * extra
            tan[m] = extra
        else:
            ang = extra + u / radius
            pts[m] = p0 + radius * np.stack([np.cos(ang), np.sin(ang)], 1)
            tan[m] = np.stack([-np.sin(ang), np.cos(ang)], 1)
        start += L
    return pts, tan


def loop_route(
    width: float = 160.0,
    length: float = 100.0,
    corner_radius: float = 15.0,
    laps: float = 1.25,
    spacing_m: float = 1.0,
    hill_m: float = 1.5,
) -> np.ndarray:
    """Camera-to-world poses ``[N, 4, 4]`` float64 along a rounded-rectangle loop.

    Raises:
        ValueError: non-positive sizes, ``corner_radius`` larger than half a side, or fewer
            than 2 frames.
    """
    if min(width, length, corner_radius, laps, spacing_m) <= 0:
        raise ValueError("width, length, corner_radius, laps and spacing_m must be > 0")
    if 2 * corner_radius > min(width, length):
        raise ValueError(f"corner_radius {corner_radius} is more than half the shorter side")
    perimeter = 2 * (width + length) - (8 - 2 * np.pi) * corner_radius
    n = int(np.floor(laps * perimeter / spacing_m)) + 1
    if n < 2:
        raise ValueError("the route has fewer than 2 frames")
    s = np.arange(n) * spacing_m
    xz, tan = _rounded_rectangle(width, length, corner_radius, s)
    y = -hill_m * np.sin(2 * np.pi * s / perimeter)  # y is down: -height
    dy = -hill_m * 2 * np.pi / perimeter * np.cos(2 * np.pi * s / perimeter)
    fwd = np.stack([tan[:, 0], dy, tan[:, 1]], 1)
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    down = np.array([0.0, 1.0, 0.0])
    right = np.cross(down, fwd)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down_c = np.cross(fwd, right)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = right, down_c, fwd
    T[:, :3, 3] = np.stack([xz[:, 0], y, xz[:, 1]], 1)
    # express in the first camera's frame (KITTI convention: the first pose is the identity)
    T0inv = np.linalg.inv(T[0])
    return T0inv[None] @ T
