"""PNGs without a browser: the top-view trajectory (estimate vs reference, loop closures drawn as
segments) and a bird's-eye view of the coloured point cloud with the cameras (``points.png``).

Both pictures share one convention: the two coordinate axes of largest extent of the camera
positions (:func:`top_view_axes`), the lower-numbered one to the right, never mirrored (in
an OpenCV world, y down, x right and z up on the page is the view from above), each axis
labelled with the world's unit (``[m]`` only when the run is metric, else ``[up to
scale]``).

Uses matplotlib's object API with the Agg canvas (no pyplot global state, no display) and
writes the file atomically (:func:`swiftjax.io.atomic.atomic_path`).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from swiftjax.io.atomic import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["plot_points", "plot_trajectory", "top_view_axes", "axis_label"]

_AXIS = "xyz"
#: Colours shared by both pictures (and named in their legends).
_ESTIMATE, _NO_LOOPS, _REFERENCE, _LOOP, _REJECTED = "tab:blue", "tab:purple", "tab:orange", "tab:red", "0.35"


def axis_label(axis: int, unit: str | None) -> str:
    """``"x [m]"`` for a metric world (``unit`` ``"m"`` / ``"metres"``), ``"x [up to scale]"``
    when the unit is unknown (``None``) or up to scale, else ``"x [<unit>]"``."""
    name = _AXIS[axis]
    if unit in ("m", "metres", "meters"):
        return f"{name} [m]"
    if unit is None or "scale" in unit:
        return f"{name} [up to scale]"
    return f"{name} [{unit}]"


def _positions(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.ndim == 3 and a.shape[1:] in ((4, 4), (3, 4)):
        return a[:, :3, 3]
    if a.ndim == 2 and a.shape[1] == 3:
        return a
    raise ValueError(f"{name} must be poses [N, 4, 4] / [N, 3, 4] or positions [N, 3], got shape {a.shape}")


def top_view_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two coordinate axes with the largest extent (KITTI / OpenCV worlds: x and z)."""
    extent = np.ptp(np.asarray(positions, np.float64), axis=0)
    a, b = sorted(np.argsort(extent)[-2:])
    return int(a), int(b)


def plot_trajectory(
    path: str | os.PathLike,
    estimate: np.ndarray,
    reference: np.ndarray | None = None,
    loops: np.ndarray | None = None,
    title: str | None = None,
    axes: tuple[int, int] | None = None,
    dpi: int = 120,
    rejected: np.ndarray | None = None,
    no_loops: np.ndarray | None = None,
    unit: str | None = None,
) -> Figure:
    """Write a top-view PNG of ``estimate`` (and ``reference``) to ``path``.

    The reference is drawn first as a wide light band and the estimate on it as a thin line,
    so both stay visible where they agree; accepted loop closures are red segments with
    their two frames marked, rejected candidates dotted grey.

    Args:
        path: output ``.png`` file (written atomically; the folder must exist).
        estimate: ``[N, 4, 4]`` poses or ``[N, 3]`` positions (already aligned to the reference
            if one is given, e.g. ``evaluation.ate(...).aligned``).
        reference: optional ground truth, same forms.
        loops: optional ``[M, 2]`` frame-index pairs; each is drawn as a segment between the
            two estimated positions.
        title: figure title.
        rejected: optional ``[R, 2]`` rejected loop candidates, drawn as dotted grey segments.
        no_loops: optional trajectory without loop closure (same forms and frame as
            ``estimate``), drawn dashed.
        unit: the world's unit for the axis labels (:func:`axis_label`; None: up to scale).
        axes: the two coordinate axes to plot (default: :func:`top_view_axes` of the reference,
            or of the estimate).
        dpi: resolution.

    Returns:
        the matplotlib figure (written already; its axes can be inspected).

    Raises:
        ValueError: bad shapes or loop indices outside the estimate.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    est = _positions(estimate, "estimate")
    ref = None if reference is None else _positions(reference, "reference")
    free = None if no_loops is None else _positions(no_loops, "no_loops")
    pairs = lambda x: np.zeros((0, 2), np.int64) if x is None else np.asarray(x, np.int64).reshape(-1, 2)
    lp, rj = pairs(loops), pairs(rejected)
    for name, p in (("loops", lp), ("rejected", rj)):
        if p.size and (p.min() < 0 or p.max() >= len(est)):
            raise ValueError(f"{name} index frames outside [0, {len(est)})")
    a, b = axes if axes is not None else top_view_axes(est)
    fig = Figure(figsize=(7, 7))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if ref is not None:
        ax.plot(
            ref[:, a],
            ref[:, b],
            "-",
            color=_REFERENCE,
            lw=5.0,
            alpha=0.45,
            solid_capstyle="round",
            label="ground truth",
            zorder=1,
        )
    if free is not None:
        ax.plot(free[:, a], free[:, b], "--", color=_NO_LOOPS, lw=1.0, label="without loop closure", zorder=2)
    ax.plot(
        est[:, a],
        est[:, b],
        "-",
        color=_ESTIMATE,
        lw=1.2,
        label="estimate" if free is None else "with loop closure",
        zorder=3,
    )
    ax.plot(est[:1, a], est[:1, b], "o", color="tab:green", ms=6, label="start", zorder=5)
    for k, (i, j) in enumerate(rj):
        ax.plot(
            est[[i, j], a],
            est[[i, j], b],
            ":",
            color=_REJECTED,
            lw=0.9,
            label="rejected loop candidates" if k == 0 else None,
            zorder=4,
        )
    for k, (i, j) in enumerate(lp):
        ax.plot(
            est[[i, j], a],
            est[[i, j], b],
            "-",
            color=_LOOP,
            lw=1.5,
            marker="o",
            ms=3.5,
            label=f"loop closures ({len(lp)})" if k == 0 else None,
            zorder=4,
        )
    ax.set_xlabel(axis_label(a, unit))
    ax.set_ylabel(axis_label(b, unit))
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return fig


def plot_points(
    path: str | os.PathLike,
    points: np.ndarray,
    colors: np.ndarray,
    cameras: np.ndarray,
    loops: np.ndarray | None = None,
    title: str | None = None,
    max_points: int = 100_000,
    dpi: int = 120,
    unit: str | None = None,
) -> Figure:
    """Write a bird's-eye PNG of a coloured point cloud with the camera trajectory.

    The axes are those of :func:`plot_trajectory` (:func:`top_view_axes` of the cameras,
    never mirrored), so the two pictures overlay.  Points are drawn lowest first along the
    third axis, "up" being the cameras' mean up direction (``-y`` of OpenCV cameras), so
    roofs and tree tops cover the ground; at most ``max_points`` (an evenly spaced subset).

    Args:
        path: output ``.png`` (written atomically; the folder must exist).
        points: ``[M, 3]`` world points; colors: ``[M, 3]`` uint8 RGB.
        cameras: ``[N, 4, 4]`` camera-to-world poses (OpenCV axes) -- the trajectory.
        loops: optional ``[L, 2]`` frame pairs drawn as segments.
        title: figure title.
        unit: the world's unit for the axis labels (:func:`axis_label`; None: up to scale).

    Returns:
        the matplotlib figure (written already).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    rgb = np.asarray(colors).reshape(-1, 3)
    if rgb.shape != pts.shape or rgb.dtype != np.uint8:
        raise ValueError(f"colors must be uint8 [{len(pts)}, 3] like the points, got {rgb.dtype} {rgb.shape}")
    c2w = np.asarray(cameras, np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)) or len(c2w) == 0:
        raise ValueError(f"cameras must be camera-to-world poses [N, 4, 4], got shape {c2w.shape}")
    est = c2w[:, :3, 3]
    lp = np.zeros((0, 2), np.int64) if loops is None else np.asarray(loops, np.int64).reshape(-1, 2)
    if lp.size and (lp.min() < 0 or lp.max() >= len(est)):
        raise ValueError(f"loops index frames outside [0, {len(est)})")
    a, b = top_view_axes(est) if len(est) > 1 else (0, 2)
    vertical = 3 - a - b
    up = -c2w[:, :3, 1].mean(axis=0)  # OpenCV: the camera's y axis points down
    sign = 1.0 if up[vertical] >= 0 else -1.0
    if len(pts) > max_points:
        pts, rgb = pts[:: -(-len(pts) // max_points)], rgb[:: -(-len(pts) // max_points)]
    order = np.argsort(sign * pts[:, vertical], kind="stable")
    x = lambda p: p[..., a]

    # Frame the cloud without its farthest 0.5 % (sky, stray depth) and the whole trajectory.
    uv_cam = np.stack([x(est), est[:, b]], axis=1)
    uv = np.stack([x(pts), pts[:, b]], axis=1) if len(pts) else uv_cam
    lo = np.minimum(np.percentile(uv, 0.5, axis=0), uv_cam.min(axis=0))
    hi = np.maximum(np.percentile(uv, 99.5, axis=0), uv_cam.max(axis=0))
    pad = 0.03 * (hi - lo).max()
    aspect = (hi[1] - lo[1] + 2 * pad) / max(hi[0] - lo[0] + 2 * pad, 1e-12)
    fig = Figure(figsize=(8, float(np.clip(8 * aspect, 3, 12))))  # the figure takes the map's shape
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(x(pts[order]), pts[order, b], c=rgb[order] / 255.0, s=0.6, marker="s", linewidths=0, rasterized=True)
    ax.plot(x(est), est[:, b], "-", color=_ESTIMATE, lw=1.2, label="cameras")
    ax.plot(x(est[:1]), est[:1, b], "o", color="tab:green", ms=6, label="start")
    for k, (i, j) in enumerate(lp):
        ax.plot(
            x(est[[i, j]]),
            est[[i, j], b],
            "-",
            color=_LOOP,
            lw=1.5,
            marker="o",
            ms=3.5,
            label=f"loop closures ({len(lp)})" if k == 0 else None,
        )
    ax.set_xlabel(axis_label(a, unit))
    ax.set_ylabel(axis_label(b, unit))
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight")
    return fig
