"""Top-view trajectory plot (PNG): estimate vs reference, loop closures drawn as segments.

Uses matplotlib's object API with the Agg canvas (no pyplot global state, no display) and
writes the file atomically (:func:`swiftjax.io.atomic.atomic_path`).
"""

from __future__ import annotations

import os

import numpy as np

from swiftjax.io.atomic import atomic_path

__all__ = ["plot_trajectory", "top_view_axes"]

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
    lp = np.zeros((0, 2), np.int64) if loops is None else np.asarray(loops, np.int64).reshape(-1, 2)
    if lp.size and (lp.min() < 0 or lp.max() >= len(est)):
        raise ValueError(f"loops index frames outside [0, {len(est)})")
    a, b = axes if axes is not None else top_view_axes(ref if ref is not None else est)
    fig = Figure(figsize=(7, 7))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if ref is not None:
        ax.plot(ref[:, a], ref[:, b], "-", color="0.55", lw=1.5, label="reference")
    ax.plot(est[:, a], est[:, b], "-", color="tab:blue", lw=1.0, label="estimate")
    ax.plot(est[:1, a], est[:1, b], "o", color="tab:green", ms=6, label="start")
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
