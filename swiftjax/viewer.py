"""``swiftjax view``: a web viewer (viser) of a finished or still-running run directory.

What it shows, all read from the run directory (nothing is recomputed but the placement of
chunks):

* the point cloud: each chunk file's export points (chunk frame, already confidence
  filtered), read **one chunk at a time** and merged into a uniform reservoir sample of at
  most ``max_points`` points (:class:`Reservoir`), so memory is bounded by the budget plus
  one chunk, whatever the run's size; a confidence-percentile slider hides the least
  confident share; colours from the images or one colour per chunk;
* the cameras as frustums (the frame as texture where ``colmap/images/`` holds it), the
  trajectory, loop-closure candidates as segments between the two frames (accepted green,
  rejected red; records without an ``accepted`` key count as accepted, as every loop edge
  was before loop verification), the ground truth (Sim(3)-aligned to the estimate) when the
  run had one;
* a toggle between the chunk poses with and without loop closure.

Placement: a finished run has ``chunk_poses.json`` (the optimised ``S_t`` and the chained
ones, written by the export); while a run is going, the viewer chains the temporal edges
``S_{t-1 -> t}`` recorded in ``manifest.json`` over the longest prefix of finished chunks
(no loop closure yet).  :func:`serve` polls the directory (``manifest.json``'s and
``chunk_poses.json``'s modification times) and adds chunks as they arrive: ``swiftjax view``
on a running reconstruction, or ``swiftjax reconstruct ... --view``.

The server binds ``127.0.0.1`` unless told otherwise (a map is private).  A web page on
another site open in the same browser could still reach ``ws://127.0.0.1:8080`` (cross-site
WebSocket hijacking) or rename itself to that address (DNS rebinding), so every request is
checked before viser sees it (:func:`request_refusal`): the ``Host`` header must name this
server (an IP address, ``localhost``, this machine's name, or the ``--host`` given), and a
WebSocket's ``Origin``, when a browser sends one, must be the page's own address.  A
refused request gets ``403`` and no scene.  ``import swiftjax`` never imports viser: this
module imports it inside :class:`Viewer` only.
"""

from __future__ import annotations

import contextlib
import dataclasses
import ipaddress
import logging
import pathlib
import socket
import threading
import urllib.parse
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from swiftjax.errors import SwiftjaxError
from swiftjax.sampling import Reservoir

__all__ = ["ViewerError", "RunView", "Reservoir", "Viewer", "serve", "read_run", "check_port", "request_refusal"]

logger = logging.getLogger(__name__)


#: Distinct colours for per-chunk colouring (matplotlib's tab10, as uint8).
_CHUNK_COLOURS = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    np.uint8,
)
_ACCEPTED = (40, 170, 60)
_REJECTED = (220, 30, 30)
_TRAJECTORY = (30, 90, 220)
_GROUND_TRUTH = (255, 127, 14)  # orange, drawn wider than the trajectory: visible where they agree
#: The GUI's legend: each colour as the scene draws it (emoji squares render in any browser).
LEGEND = (
    "**legend**  \n"
    "🟦 trajectory (camera centres)  \n"
    "🟧 ground truth (Sim(3)-aligned, wide band)  \n"
    "🟩 accepted loop closure  \n"
    "🟥 rejected loop candidate  \n"
    "cameras and *chunk* colouring: one colour per chunk"
)


class ViewerError(SwiftjaxError, RuntimeError):
    """The run directory cannot be shown (missing, not a swiftjax run) or the port is taken."""


# ------------------------------------------------------------------------------ reading


@dataclasses.dataclass
class RunView:
    """What the viewer draws, in world coordinates, for one pose set at a time.

    ``chunks`` are the placed chunk indices (a prefix ``0..k-1`` of the run's chunks);
    ``poses[name]`` ``[k, 8]`` chunk-to-world Sim(3) for each name in ``POSE_SETS`` that is
    known (a live run has only ``"no loop closure"``); ``frames [F]`` the global indices of
    the cameras the placed chunks own, ``frame_chunk [F]`` their chunk, ``extrinsic [F, 3,
    4]`` their chunk-frame world-to-camera; ``K [3, 3]`` and ``image_hw`` of the model's
    resolution; ``loops``: ``(i, j, accepted)`` frame pairs; ``ground_truth [N, 4, 4]`` or
    None; ``names``: a file name per frame if known; ``final``: the run has finished its export.
    """

    run_dir: pathlib.Path
    chunks: list[int]
    poses: dict[str, np.ndarray]
    frames: np.ndarray
    frame_chunk: np.ndarray
    extrinsic: np.ndarray
    K: np.ndarray
    image_hw: tuple[int, int]
    loops: list[tuple[int, int, bool]]
    ground_truth: np.ndarray | None
    names: list[str] | None
    final: bool

    def cam_to_world(self, pose_set: str) -> np.ndarray:
        """``[F, 4, 4]`` camera-to-world of the placed frames under ``pose_set``."""
        import jax
        import jax.numpy as jnp

        from swiftjax.camera import world_cameras

        poses = self.poses[pose_set][np.searchsorted(self.chunks, self.frame_chunk)]
        with jax.enable_x64(True):
            return np.asarray(world_cameras(jnp.asarray(poses), jnp.asarray(self.extrinsic, jnp.float64)))


def open_manifest(run_dir: pathlib.Path) -> dict[str, Any]:
    """The run's manifest, or :class:`ViewerError` naming what is wrong with ``run_dir``."""
    from swiftjax.pipeline import reader

    try:
        return reader.read_manifest(run_dir)
    except reader.RunReadError as err:
        raise ViewerError(str(err)) from None


@dataclasses.dataclass
class _Chunk:
    """What the viewer keeps of one chunk file: its frames and chunk-frame extrinsics."""

    frames: np.ndarray  # [S] global frame indices
    extrinsic: np.ndarray  # [S, 3, 4]
    K: np.ndarray  # [3, 3] of its first frame
    image_hw: tuple[int, int]


def read_run(
    run_dir: str | pathlib.Path, reservoir: Reservoir | None = None, cache: dict[int, _Chunk] | None = None
) -> RunView:
    """Read the run's placement; chunk files not in ``cache`` are read once each (their points
    merged into ``reservoir``, their frames and extrinsics kept in ``cache``)."""
    from swiftjax.io import trajectory
    from swiftjax.io.chunk_store import ChunkStore
    from swiftjax.pipeline import chain_poses, reader

    run_dir = pathlib.Path(run_dir)
    manifest = open_manifest(run_dir)
    cache = {} if cache is None else cache
    store = ChunkStore(run_dir)
    done = {int(c) for c, ok in manifest["chunks"].items() if ok}
    try:
        poses = reader.read_chunk_poses(run_dir)
    except reader.RunReadError as err:
        raise ViewerError(str(err)) from None
    if poses is not None:
        count = min(len(p) for p in poses.values()) if poses else 0
        if not all(c in done for c in range(count)):
            raise ViewerError(
                f"{run_dir / 'chunk_poses.json'} has {count} chunk poses but the chunk store lacks some of them"
            )
        chunk_ids = list(range(count))
        final = True
    else:
        # Live: the longest prefix 0..k-1 of finished chunks whose edges are all recorded.
        k, rel = reader.chained_prefix(manifest)
        chunk_ids = list(range(k))
        poses = {"no loop closure": chain_poses(rel)} if k else {}
        final = False

    for t in chunk_ids:
        if t in cache:
            continue
        extra = store.load_extra("chunk", t)
        extrinsic = store.load_array("chunk", t, "extrinsic")
        K = np.asarray(store.load_array("chunk", t, "intrinsic", frames=slice(0, 1))[0], np.float64)
        hw = (int(extra["image_hw"][0]), int(extra["image_hw"][1]))
        cache[t] = _Chunk(np.asarray(extra["frames"], np.int64), extrinsic, K, hw)
        if reservoir is not None:
            xyz = extra["points_xyz"]
            rgb = extra["points_rgb"] if "points_rgb" in extra else np.full((len(xyz), 3), 200, np.uint8)
            reservoir.add(t, xyz, rgb, extra["points_conf"])
        del extra

    frames, owner, extrinsic = [], [], []
    for t in chunk_ids:
        c, nxt = cache[t], cache.get(t + 1) if (t + 1) in chunk_ids else None
        own = c.frames < nxt.frames[0] if nxt is not None else np.ones(len(c.frames), bool)  # later chunk wins
        frames.append(c.frames[own])
        owner.append(np.full(int(own.sum()), t))
        extrinsic.append(c.extrinsic[own])

    gt_path = run_dir / "ground_truth_kitti.txt"
    gt = trajectory.read_kitti(gt_path) if gt_path.is_file() else None
    first = cache.get(0)
    return RunView(
        run_dir=run_dir,
        chunks=chunk_ids,
        poses=poses,
        frames=np.concatenate(frames) if frames else np.zeros(0, np.int64),
        frame_chunk=np.concatenate(owner) if owner else np.zeros(0, np.int64),
        extrinsic=np.concatenate(extrinsic) if extrinsic else np.zeros((0, 3, 4), np.float32),
        K=first.K if first else np.eye(3),
        image_hw=first.image_hw if first else (1, 1),
        loops=reader.loop_candidates(manifest),
        ground_truth=gt,
        names=reader.frame_names(run_dir),
        final=final,
    )


def world_points(view: RunView, reservoir: Reservoir, pose_set: str) -> tuple[np.ndarray, np.ndarray]:
    """The reservoir's points of the placed chunks in world coordinates ``[k, 3]`` float32
    (``S_t`` of each point's chunk applied: ``s R x + t``) and the mask of placed points."""
    from swiftjax.io.trajectory import quaternion_to_matrix

    placed = np.isin(reservoir.chunk, view.chunks)
    P = view.poses[pose_set]
    idx = np.searchsorted(view.chunks, reservoir.chunk[placed])
    R = quaternion_to_matrix(P[:, 3:7]) * P[:, 7, None, None]  # [k, 3, 3] s R
    xyz = np.einsum("nij,nj->ni", R[idx].astype(np.float32), reservoir.xyz[placed]) + P[idx, :3].astype(np.float32)
    return xyz.astype(np.float32), placed


def check_port(host: str, port: int) -> None:
    """:class:`ViewerError` if ``host:port`` cannot be bound (in use, or not an address here)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as err:
            what = "is already in use" if err.errno in (98, 48) else f"cannot be bound ({err.strerror})"
            raise ViewerError(f"port {port} on {host} {what}; choose another with --port") from None


# ------------------------------------------------------------------------------ request guard


def _split_host(value: str) -> str | None:
    """The host name of a ``Host`` header or an origin's netloc, lower case, without port or
    IPv6 brackets; None if it does not parse."""
    try:
        parsed = urllib.parse.urlsplit("//" + value.strip())
        return (parsed.hostname or "").lower() or None
    except ValueError:
        return None


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def allowed_host_names(bind_host: str) -> frozenset[str]:
    """Names a ``Host`` header may carry besides an IP address: ``localhost``, this machine's
    names, and the ``--host`` the server was started with (an IP literal cannot be rebound
    by DNS, a name can)."""
    names = {"localhost", "localhost.localdomain", bind_host.strip("[]").lower()}
    with contextlib.suppress(OSError):
        names.update({socket.gethostname().lower(), socket.getfqdn().lower()})
    return frozenset(n for n in names if n)


def request_refusal(headers: Any, allowed: frozenset[str]) -> str | None:
    """Why a request (its HTTP headers) must be refused, or None to serve it.

    * ``Host`` must be an IP address or one of ``allowed`` (:func:`allowed_host_names`):
      a page of ``evil.example`` rebound by DNS to 127.0.0.1 sends ``Host: evil.example``;
    * ``Origin``, when present (browsers always send it on a WebSocket), must be
      ``http(s)://`` + the ``Host`` header: the page that opens the socket was served here.
      A client that is not a browser (a script) sends none and is let through.
    """
    host_header = headers.get("Host")
    host = _split_host(host_header) if host_header else None
    if host is None:
        return "no valid Host header"
    if not _is_ip(host) and host not in allowed:
        return f"Host {host_header!r} is not this viewer's address"
    origin = headers.get("Origin")
    if origin is not None:
        parsed = urllib.parse.urlsplit(origin.strip())
        if parsed.scheme not in ("http", "https") or parsed.netloc.lower() != host_header.strip().lower():
            return f"Origin {origin!r} is not this viewer's page ({host_header})"
    return None


@contextlib.contextmanager
def _guarded_websockets(allowed: frozenset[str]) -> Iterator[None]:
    """While viser starts its server, make websockets' ``serve`` run :func:`request_refusal`
    before viser's own request hook (viser offers no hook of its own).  viser's constructor
    returns only once the socket is bound, so the patch is in place exactly as long as it
    is read; a lock keeps two viewers of one process from interleaving."""
    import http

    import websockets.asyncio.server as ws_server

    original = ws_server.serve

    class GuardedServe(original):  # type: ignore[misc, valid-type]
        def __init__(self, *args: Any, process_request: Any = None, **kwargs: Any) -> None:
            def guard(connection: Any, request: Any) -> Any:
                reason = request_refusal(request.headers, allowed)
                if reason is not None:
                    return connection.respond(http.HTTPStatus.FORBIDDEN, f"swiftjax view: refused: {reason}\n")
                return process_request(connection, request) if process_request is not None else None

            super().__init__(*args, process_request=guard, **kwargs)

    with _GUARD_LOCK:
        ws_server.serve = GuardedServe
        try:
            yield
        finally:
            ws_server.serve = original


_GUARD_LOCK = threading.Lock()


# ------------------------------------------------------------------------------ serving


class Viewer:
    """A viser server showing one run directory; :meth:`refresh` re-reads what changed.

    Scene nodes: ``/cloud``, ``/trajectory``, ``/frustums/<frame>``, ``/loops/accepted``,
    ``/loops/rejected``, ``/ground_truth``.  GUI: confidence percentile slider, colour
    dropdown (``image`` / ``chunk``), loop-closure toggle, frustum / loop / ground-truth
    checkboxes, a status line.
    """

    def __init__(
        self,
        run_dir: str | pathlib.Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        max_points: int = 1_000_000,
        max_frustums: int = 200,
        point_size: float | None = None,
        log: Callable[[str], None] = logger.info,
    ) -> None:
        self.run_dir = pathlib.Path(run_dir)
        open_manifest(self.run_dir)  # a clear error before the server starts
        check_port(host, port)
        import viser

        self.log = log
        self.max_frustums = max_frustums
        self.reservoir = Reservoir(max_points)
        self.cache: dict[int, _Chunk] = {}
        self._thumbs: dict[int, np.ndarray | None] = {}
        self._signature: tuple[Any, ...] | None = None
        self._lock = threading.RLock()
        self.view: RunView | None = None
        self._point_size = point_size
        with _guarded_websockets(allowed_host_names(host)):
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        if port and self.server.get_port() != port:  # viser moves on to a free port silently
            self.server.stop()
            raise ViewerError(f"port {port} on {host} is already in use; choose another with --port")
        self.server.scene.set_up_direction("-y")  # OpenCV world: y down
        gui = self.server.gui
        self.status = gui.add_markdown("reading the run ...")
        self.legend = gui.add_markdown(LEGEND)
        self.conf_slider = gui.add_slider(
            "confidence percentile",
            min=0,
            max=99,
            step=1,
            initial_value=0,
            hint="hide the least confident points (percentile of the shown sample)",
        )
        self.colour = gui.add_dropdown("colour", ("image", "chunk"), initial_value="image")
        self.loop_toggle = gui.add_checkbox("loop closure", True, hint="chunk poses after the pose graph")
        self.show_frustums = gui.add_checkbox("cameras", True)
        self.show_loops = gui.add_checkbox("loop candidates", True)
        self.show_gt = gui.add_checkbox("ground truth", True)
        for handle in (self.conf_slider, self.colour):
            handle.on_update(lambda _: self._draw_cloud())
        self.loop_toggle.on_update(lambda _: self._draw_all())
        for handle in (self.show_frustums, self.show_loops, self.show_gt):
            handle.on_update(lambda _: self._draw_all())
        self.refresh()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}/"

    def _state_signature(self) -> tuple[Any, ...]:
        sig = []
        for name in ("manifest.json", "chunk_poses.json"):
            try:
                st = (self.run_dir / name).stat()
                sig.append((st.st_mtime_ns, st.st_size))
            except FileNotFoundError:
                sig.append(None)
        return tuple(sig)

    def refresh(self) -> bool:
        """Re-read the run if ``manifest.json`` or ``chunk_poses.json`` changed; True if it did."""
        with self._lock:
            sig = self._state_signature()
            if sig == self._signature:
                return False
            self._signature = sig
            self.view = read_run(self.run_dir, self.reservoir, self.cache)
            self._draw_all()
            return True

    def pose_set(self) -> str | None:
        view = self.view
        if view is None or not view.poses:
            return None
        if self.loop_toggle.value and "loop closure" in view.poses:
            return "loop closure"
        return "no loop closure" if "no loop closure" in view.poses else next(iter(view.poses))

    def _scale(self, centres: np.ndarray) -> float:
        if len(centres) < 2:
            return 1.0
        return float(np.linalg.norm(np.ptp(centres, axis=0))) or 1.0

    def _draw_all(self) -> None:
        with self._lock:
            view, name = self.view, self.pose_set()
            if view is None or name is None:
                self.status.content = f"**{self.run_dir}**: no finished chunk yet"
                return
            self.loop_toggle.disabled = "loop closure" not in view.poses
            c2w = view.cam_to_world(name)
            scene = self.server.scene
            centres = c2w[:, :3, 3]
            extent = self._scale(centres)
            if not getattr(self, "_camera_set", False) and len(centres):
                # First in the message log, so that a connecting page applies it before it
                # has replayed the (large) cloud.
                self._initial_camera(centres, extent)
            self._draw_cloud()
            if len(centres) >= 2:
                seg = np.stack([centres[:-1], centres[1:]], axis=1)
                scene.add_line_segments("/trajectory", seg, _TRAJECTORY, thickness=3.0, thickness_units="screen")
            self._draw_frustums(view, c2w, extent)
            self._draw_loops(view, centres)
            self._draw_ground_truth(view, centres)
            n_acc = sum(a for _, _, a in view.loops)
            state = "finished" if view.final else "running (poses chained, no loop closure yet)"
            self.status.content = (
                f"**{self.run_dir.name}** ({state})  \n{len(view.chunks)} chunks, {len(view.frames)} cameras, "
                f"{len(self.reservoir):,} of {self.reservoir.seen:,} points shown  \n"
                f"loop candidates: {n_acc} accepted, {len(view.loops) - n_acc} rejected  \nposes: {name}"
            )

    def _initial_camera(self, centres: np.ndarray, extent: float) -> None:
        """Look at the trajectory's centre from above and behind (y is down in the world)."""
        centre = centres.mean(axis=0)
        self.server.initial_camera.look_at = tuple(centre)
        self.server.initial_camera.up = (0.0, -1.0, 0.0)
        self.server.initial_camera.position = tuple(centre + np.array([0.0, -0.8, -0.6]) * extent)
        self._camera_set = True

    def _draw_cloud(self) -> None:
        with self._lock:
            view, name = self.view, self.pose_set()
            if view is None or name is None or len(self.reservoir) == 0:
                return
            xyz, placed = world_points(view, self.reservoir, name)
            conf = self.reservoir.conf[placed]
            if self.colour.value == "chunk":
                rgb = _CHUNK_COLOURS[self.reservoir.chunk[placed] % len(_CHUNK_COLOURS)]
            else:
                rgb = self.reservoir.rgb[placed]
            pct = float(self.conf_slider.value)
            if pct > 0 and len(conf):
                keep = conf >= np.percentile(conf, pct)
                xyz, rgb = xyz[keep], rgb[keep]
            size = self._point_size or 0.002 * self._scale(xyz if len(xyz) else np.zeros((1, 3)))
            # float32: float16 would quantise a 500-unit route to 0.25-unit steps.
            self.server.scene.add_point_cloud(
                "/cloud", xyz, rgb, point_size=size, point_shape="circle", precision="float32"
            )

    def _draw_frustums(self, view: RunView, c2w: np.ndarray, extent: float) -> None:
        from swiftjax.io.trajectory import matrix_to_quaternion

        scene = self.server.scene
        scene.remove_by_name("/frustums")
        if not self.show_frustums.value or not len(c2w):
            return
        h, w = view.image_hw
        fy = float(view.K[1, 1])
        fov = 2.0 * np.arctan2(h / 2.0, fy)
        step = max(1, -(-len(c2w) // self.max_frustums))
        q = matrix_to_quaternion(c2w[:, :3, :3])[:, [3, 0, 1, 2]]  # wxyz
        for k in range(0, len(c2w), step):
            frame = int(view.frames[k])
            scene.add_camera_frustum(
                f"/frustums/{frame:06d}",
                fov=fov,
                aspect=w / h,
                scale=0.015 * extent,
                color=_CHUNK_COLOURS[view.frame_chunk[k] % len(_CHUNK_COLOURS)],
                image=self._thumbnail(view, frame),
                wxyz=q[k],
                position=c2w[k, :3, 3],
                thickness=1.5,
                thickness_units="screen",
            )

    def _thumbnail(self, view: RunView, frame: int) -> np.ndarray | None:
        """The frame from ``colmap/images/`` (written when COLMAP export is on), 160 pixels wide."""
        if view.names is None or frame >= len(view.names):
            return None
        if frame in self._thumbs:
            return self._thumbs[frame]
        path = view.run_dir / "colmap" / "images" / view.names[frame]
        thumb = None
        if path.is_file():
            from PIL import Image

            try:
                with Image.open(path) as img:
                    rgb = img.convert("RGB")
                height = max(1, round(rgb.height * 160.0 / rgb.width))
                thumb = np.asarray(rgb.resize((160, height), Image.Resampling.BOX))
            except OSError:
                thumb = None
        if thumb is not None or view.final:  # a running run may write the frame later
            self._thumbs[frame] = thumb
        return thumb

    def _draw_loops(self, view: RunView, centres: np.ndarray) -> None:
        scene = self.server.scene
        scene.remove_by_name("/loops")
        if not self.show_loops.value:
            return
        index = {int(f): k for k, f in enumerate(view.frames)}
        for accepted, node, colour in ((True, "accepted", _ACCEPTED), (False, "rejected", _REJECTED)):
            pairs = [(index[i], index[j]) for i, j, a in view.loops if a == accepted and i in index and j in index]
            if pairs:
                p = np.asarray(pairs)
                seg = np.stack([centres[p[:, 0]], centres[p[:, 1]]], axis=1)
                scene.add_line_segments(
                    f"/loops/{node}", seg, colour, thickness=4.0 if accepted else 2.0, thickness_units="screen"
                )

    def _draw_ground_truth(self, view: RunView, centres: np.ndarray) -> None:
        from swiftjax.evaluation import umeyama_alignment

        scene = self.server.scene
        scene.remove_by_name("/ground_truth")
        if view.ground_truth is None or not self.show_gt.value or len(centres) < 3:
            return
        gt = view.ground_truth[view.frames, :3, 3]
        R, t, s = umeyama_alignment(gt, centres, "sim3")  # ground truth onto the estimate
        aligned = s * gt @ R.T + t
        seg = np.stack([aligned[:-1], aligned[1:]], axis=1)
        scene.add_line_segments("/ground_truth", seg, _GROUND_TRUTH, thickness=8.0, thickness_units="screen")

    def watch(self, interval: float = 1.0, stop: threading.Event | None = None) -> None:
        """Poll the run directory every ``interval`` seconds until ``stop`` is set."""
        stop = stop or threading.Event()
        while not stop.wait(interval):
            try:
                self.refresh()
            except (ViewerError, OSError, ValueError) as err:  # a file mid-replacement: retry
                self.log(f"swiftjax view: {err}")

    def close(self) -> None:
        self.server.stop()


def serve(
    run_dir: str | pathlib.Path,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    max_points: int = 1_000_000,
    log: Callable[[str], None] = logger.info,
) -> Viewer:
    """Start a :class:`Viewer` on ``run_dir`` (returns at once; the server runs in threads)."""
    viewer = Viewer(run_dir, host=host, port=port, max_points=max_points, log=log)
    if host not in ("127.0.0.1", "localhost", "::1"):
        warning = f"serving on {host}: anyone who can reach this machine can see the map"
        if log == logger.info:  # the default: a warning of the swiftjax logger
            logger.warning(warning)
        else:
            log(f"swiftjax view: warning: {warning}")
    log(f"swiftjax view: {viewer.url} ({run_dir}; Ctrl-C to stop)")
    return viewer


class LiveViewer:
    """A :class:`Viewer` started once the run directory has a manifest, polling in a thread
    (``swiftjax reconstruct ... --view``)."""

    def __init__(
        self,
        run_dir: str | pathlib.Path,
        *,
        host: str,
        port: int,
        max_points: int,
        log: Callable[[str], None] = logger.info,
        interval: float = 1.0,
    ) -> None:
        self.run_dir = pathlib.Path(run_dir)
        self.viewer: Viewer | None = None
        self._args = dict(host=host, port=port, max_points=max_points, log=log)
        self._stop = threading.Event()
        check_port(host, port)
        self._thread = threading.Thread(target=self._run, args=(interval,), daemon=True, name="swiftjax-view")
        self._thread.start()

    def _run(self, interval: float) -> None:
        while not self._stop.is_set() and self.viewer is None:
            if (self.run_dir / "manifest.json").is_file():
                try:
                    self.viewer = serve(self.run_dir, **self._args)
                except Exception as err:
                    self._args["log"](f"swiftjax view: error: {err}")
                    return
                break
            self._stop.wait(0.2)
        if self.viewer is not None:
            self.viewer.watch(interval, self._stop)

    def refresh_now(self) -> None:
        """Show the finished run at once (without waiting for the next poll)."""
        if self.viewer is not None:
            self.viewer.refresh()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        if self.viewer is not None:
            self.viewer.close()
