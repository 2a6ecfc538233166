"""PNGs without a browser: the top-view trajectory (estimate vs reference, loop closures drawn as
segments) and a bird's-eye view of the coloured point cloud with the cameras (``points.png``).

Uses matplotlib's object API with the Agg canvas (no pyplot global state, no display) and
writes the file atomically (:func:`swiftjax.io.atomic.atomic_path`).
"""

from __future__ import annotations

import os

import numpy as np

from swiftjax.io.atomic import atomic_path

__all__ = ["plot_points", "plot_trajectory", "top_view_axes"]

_AXIS = "xyz"


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
) -> None:
    """Write a top-view PNG of ``estimate`` (and ``reference``) to ``path``.

    Args:
        path: output ``.png`` file (written atomically; the folder must exist).
        estimate: ``[N, 4, 4]`` poses or ``[N, 3]`` positions (already aligned to the reference
            if one is given, e.g. ``evaluation.ate(...).aligned``).
        reference: optional ground truth, same forms.
        loops: optional ``[M, 2]`` frame-index pairs; each is drawn as a segment between the
            two estimated positions.
        title: figure title.
        rejected: optional ``[R, 2]`` rejected loop candidates, drawn as dotted grey segments.
        axes: the two coordinate axes to plot (default: :func:`top_view_axes` of the reference,
            or of the estimate).
        dpi: resolution.

    Raises:
        ValueError: bad shapes or loop indices outside the estimate.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    est = _positions(estimate, "estimate")
    ref = None if reference is None else _positions(reference, "reference")
    pairs = lambda x: np.zeros((0, 2), np.int64) if x is None else np.asarray(x, np.int64).reshape(-1, 2)  # noqa: E731
    lp, rj = pairs(loops), pairs(rejected)
    for name, p in (("loops", lp), ("rejected", rj)):
        if p.size and (p.min() < 0 or p.max() >= len(est)):
            raise ValueError(f"{name} index frames outside [0, {len(est)})")
    a, b = axes if axes is not None else top_view_axes(ref if ref is not None else est)
    fig = Figure(figsize=(7, 7))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if ref is not None:
        ax.plot(ref[:, a], ref[:, b], "-", color="0.55", lw=1.5, label="reference")
    ax.plot(est[:, a], est[:, b], "-", color="tab:blue", lw=1.0, label="estimate")
    ax.plot(est[:1, a], est[:1, b], "o", color="tab:green", ms=6, label="start")
    for k, (i, j) in enumerate(rj):
        ax.plot(est[[i, j], a], est[[i, j], b], ":", color="0.35", lw=0.9,
                label="rejected loop candidates" if k == 0 else None)
    for k, (i, j) in enumerate(lp):
        ax.plot(est[[i, j], a], est[[i, j], b], "-", color="tab:red", lw=0.8,
                label="loop closures" if k == 0 else None)
    ax.set_xlabel(f"{_AXIS[a]} [m]")
    ax.set_ylabel(f"{_AXIS[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")


def plot_points(
    path: str | os.PathLike,
    points: np.ndarray,
    colors: np.ndarray,
    cameras: np.ndarray,
    loops: np.ndarray | None = None,
    title: str | None = None,
    max_points: int = 100_000,
    dpi: int = 120,
) -> None:
    """Write a bird's-eye PNG of a coloured point cloud with the camera trajectory.

    The view looks down the vertical axis: the coordinate axis outside the two of largest
    trajectory extent (:func:`top_view_axes`), "up" being the cameras' mean up direction
    (``-y`` of OpenCV cameras).  Points are drawn lowest first, so roofs and tree tops cover
    the ground as seen from above; at most ``max_points`` (an evenly spaced subset).

    Args:
        path: output ``.png`` (written atomically; the folder must exist).
        points: ``[M, 3]`` world points; colors: ``[M, 3]`` uint8 RGB.
        cameras: ``[N, 4, 4]`` camera-to-world poses (OpenCV axes) -- the trajectory.
        loops: optional ``[L, 2]`` frame pairs drawn as segments.
        title: figure title.
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
    # Mirror so that the picture is a view from above (right-handed: a x b = up).
    flip = sign * np.cross(np.eye(3)[a], np.eye(3)[b])[vertical] < 0
    x = lambda p: -p[..., a] if flip else p[..., a]  # noqa: E731

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
    ax.scatter(x(pts[order]), pts[order, b], c=rgb[order] / 255.0, s=0.6, marker="s", linewidths=0,
               rasterized=True)
    ax.plot(x(est), est[:, b], "-", color="tab:blue", lw=1.2, label="cameras")
    ax.plot(x(est[:1]), est[:1, b], "o", color="tab:green", ms=6, label="start")
    for k, (i, j) in enumerate(lp):
        ax.plot(x(est[[i, j]]), est[[i, j], b], "-", color="tab:red", lw=1.0,
                label="loop closures" if k == 0 else None)
    ax.set_xlabel(f"{'-' if flip else ''}{_AXIS[a]}")
    ax.set_ylabel(_AXIS[b])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight")
