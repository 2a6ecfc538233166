"""swiftjax.viewer: reading a run directory (live and finished), and the page in a real browser.

The browser test starts the viewer on a small demo run, takes screenshots with headless
Chromium (software WebGL) and checks what a person would: the page connected, the canvas
shows the cloud's colours, the scene tree has the cloud / frustum / trajectory nodes, and
moving the confidence slider (server side) changes the picture.  In CI it must run: a
missing Chromium or viser fails there (``.ci/run`` installs Chromium).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time

import numpy as np
import pytest

from swiftjax import viewer
from swiftjax.pipeline import reader

CI = bool(os.environ.get("CI"))


def _need(what: str, ok: bool, how: str) -> None:
    if ok:
        return
    if CI:
        pytest.fail(f"{what} is missing in CI ({how})")
    pytest.skip(f"{what} is not installed ({how})")


@pytest.fixture(scope="module")
def demo_run(small_loop_run):
    return small_loop_run


def test_reservoir_is_uniform_and_bounded():
    """Each of 100 points (5 chunks) is kept with probability k / N = 0.2 (400 seeds)."""
    counts = np.zeros(100)
    for seed in range(400):
        r = viewer.Reservoir(20, seed=seed)
        for c in range(5):
            ids = np.arange(20 * c, 20 * c + 20)
            r.add(c, np.c_[ids, ids, ids].astype(np.float32), np.zeros((20, 3), np.uint8), ids.astype(np.float32))
            assert len(r) == min(20, 20 * (c + 1))
        counts[r.conf.astype(int)] += 1
        assert len(np.unique(r.conf)) == 20 and np.all(r.xyz[:, 0] == r.conf)  # rows stay together
    freq = counts / 400
    assert np.all(np.abs(freq - 0.2) < 0.09), freq  # 4.5 sigma
    r.add(4, np.zeros((3, 3), np.float32), np.zeros((3, 3), np.uint8), np.full(3, -1, np.float32))
    assert np.sum(r.chunk == 4) <= 3 and not np.any((r.chunk == 4) & (r.conf >= 0))  # chunk 4 replaced


def test_loop_candidates_accepted_and_rejected():
    manifest = {  # before verification: every loop edge was used
        "loop_edges": {"5-300": {"i": 5, "j": 300}, "9-400": {"i": 9, "j": 400, "accepted": False}},
    }
    assert reader.loop_candidates(manifest) == [(5, 300, True), (9, 400, False)]
    manifest["loops"] = [  # verified: the candidates' list has the verdicts
        {"i": 5, "j": 300, "accepted": False},
        {"i": 7, "j": 350},
        {"i": 8, "j": 390, "accepted": True},
    ]
    assert reader.loop_candidates(manifest) == [(5, 300, False), (7, 350, False), (8, 390, True), (9, 400, False)]
    assert reader.loop_candidates({"loops": None, "loop_edges": {}}) == []


def test_errors_name_the_problem(tmp_path):
    with pytest.raises(viewer.ViewerError, match="does not exist"):
        viewer.open_manifest(tmp_path / "nope")
    with pytest.raises(viewer.ViewerError, match="not a swiftjax run directory"):
        viewer.open_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({"something": 1}))
    with pytest.raises(viewer.ViewerError, match="not a swiftjax manifest"):
        viewer.open_manifest(tmp_path)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(viewer.ViewerError, match=f"port {s.getsockname()[1]} .* already in use"):
            viewer.check_port("127.0.0.1", s.getsockname()[1])


def test_finished_run_matches_the_pipeline(demo_run):
    """Cameras equal the pipeline's (with and without loop closure); every shown point is a
    point of points.ply."""
    from scipy.spatial import cKDTree

    from swiftjax.io.ply import read_ply

    out, result = demo_run
    res = viewer.Reservoir(5_000)
    view = viewer.read_run(out, res)
    assert view.final and view.chunks == list(range(result.num_chunks))
    np.testing.assert_array_equal(view.frames, np.arange(result.num_frames))
    np.testing.assert_allclose(view.cam_to_world("loop closure"), result.cam_to_world, atol=1e-9)
    np.testing.assert_allclose(view.cam_to_world("no loop closure"), result.cam_to_world_no_loops, atol=1e-9)
    assert len(res) == 5_000 and res.seen == result.metrics["points"]
    xyz, placed = viewer.world_points(view, res, "loop closure")
    assert placed.all()
    cloud = read_ply(out / "points.ply")
    dist, _ = cKDTree(cloud.points).query(xyz)
    assert dist.max() < 1e-4 * np.abs(cloud.points).max()
    assert view.ground_truth is not None and view.ground_truth.shape == (result.num_frames, 4, 4)


def test_live_run_grows_as_chunks_arrive(demo_run, tmp_path):
    """A run directory mid-run (2 chunks recorded, no chunk poses yet): chained placement;
    when the manifest records more chunks, refresh() adds them."""
    from swiftjax import chunks
    from swiftjax.pipeline import chain_poses

    out, result = demo_run
    live = tmp_path / "live"
    shutil.copytree(out / "chunks", live / "chunks")
    manifest = json.loads((out / "manifest.json").read_text())
    full = json.loads(json.dumps(manifest))
    manifest["chunks"] = {"0": True, "1": True}
    manifest["edges"] = {"0": manifest["edges"]["0"]}
    (live / "manifest.json").write_text(json.dumps(manifest))
    res = viewer.Reservoir(10**7)
    cache: dict = {}
    view = viewer.read_run(live, res, cache)
    assert not view.final and view.chunks == [0, 1] and list(view.poses) == ["no loop closure"]
    np.testing.assert_allclose(view.poses["no loop closure"], chain_poses(np.array([full["edges"]["0"]["S"]])))
    schedule = chunks.chunk_schedule(result.num_frames, 40, 15)
    np.testing.assert_array_equal(view.frames, np.arange(schedule.ends[1]))  # chunk 1 owns all its frames
    own = view.frames < schedule.starts[2]  # frames that chunk 1 still owns once chunk 2 is in
    c2w = view.cam_to_world("no loop closure")
    np.testing.assert_allclose(c2w[own], result.cam_to_world_no_loops[view.frames[own]], atol=1e-9)
    n2 = len(res)
    (live / "manifest.json").write_text(json.dumps(full))
    view = viewer.read_run(live, res, cache)
    assert view.chunks == list(range(result.num_chunks)) and len(res) > n2 and len(cache) == result.num_chunks


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _live_group_members(pgid: int) -> list[int]:
    """Processes of group ``pgid`` that are not zombies (zombies wait for init to reap them)."""
    alive = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        if int(fields[2]) == pgid and fields[0] != "Z":
            alive.append(int(entry))
    return alive


def _run_chromium(flags: list[str], url: str, timeout: float) -> tuple[int, bytes, bytes]:
    """Headless Chromium (software WebGL) with ``flags`` on ``url``: (exit status, stdout,
    stderr). The browser's whole process group is killed afterwards, and checked gone."""
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            _chromium(),
            "--headless=new",
            "--no-sandbox",
            "--use-gl=angle",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--user-data-dir={profile}",
            *flags,
            url,
        ]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        try:
            out, err = proc.communicate(timeout=timeout)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
        deadline = time.monotonic() + 10
        while _live_group_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _live_group_members(proc.pid), "browser processes were left behind"
    return proc.returncode, out, err


def _screenshot(url: str, path: str) -> np.ndarray:
    """A 1200 x 800 screenshot of ``url``, as ``[H, W, 3]`` uint8."""
    from PIL import Image

    rc, _, err = _run_chromium(
        ["--window-size=1200,800", "--virtual-time-budget=15000", f"--screenshot={path}"], url, timeout=120
    )
    assert rc == 0 and os.path.isfile(path), err.decode(errors="replace")[-2000:]
    return np.asarray(Image.open(path).convert("RGB"))


def _canvas(img: np.ndarray) -> np.ndarray:
    """The 3-D canvas without the control panel (top right) and the notification (top left)."""
    out = img.astype(np.int32).copy()
    out[:400, 850:] = 255
    out[:160, :330] = 255
    return out


def test_browser_shows_the_run(demo_run, tmp_path):
    _need("viser", __import__("importlib").util.find_spec("viser") is not None, "pip install 'swiftjax[view]'")
    _need("chromium", _chromium() is not None, "apt-get install chromium")
    out, _ = demo_run
    v = viewer.Viewer(out, port=0, max_points=100_000, log=lambda _: None)
    connected = []
    v.server.on_client_connect(lambda client: connected.append(client.client_id))
    try:
        for name in ("/cloud", "/trajectory", "/ground_truth", "/loops/accepted"):
            assert v.server.scene.get_handle_by_name(name) is not None, name
        frustums = [n for n in v.server.scene._handle_from_node_name if n.startswith("/frustums/")]
        assert len(frustums) >= 20
        palette = v.reservoir.rgb[:: max(1, len(v.reservoir) // 3000)].astype(np.int32)

        def look(name: str) -> tuple[np.ndarray, np.ndarray, float]:
            """Screenshot, drawn-pixel mask, share of drawn pixels near a colour of the cloud.
            Software WebGL on a loaded machine can capture before the scene has arrived: up
            to 3 tries until the cloud's colours are on the canvas (stated in the failure)."""
            for attempt in range(3):
                img = _screenshot(v.url, str(tmp_path / f"{name}{attempt}.png"))
                canvas = _canvas(img)
                drawn = np.abs(canvas - 255).max(axis=-1) > 40  # not background
                pixels = canvas[drawn][:: max(1, int(drawn.sum()) // 4000)]
                near = np.min(np.abs(pixels[:, None, :] - palette[None]).max(-1), axis=1) if len(pixels) else [0]
                share = float(np.mean(np.asarray(near) < 30))
                if drawn.mean() > 0.003 and share > 0.5:
                    break
            return img, drawn, share

        first, drawn, share = look("first")
        assert connected, "the page never connected to the viewer's websocket"
        assert drawn.mean() > 0.03 and _canvas(first).std() > 20, (drawn.mean(), _canvas(first).std())
        assert share > 0.5, share  # most drawn pixels have a colour of the cloud's sample

        v.conf_slider.value = 95  # server-side GUI handle: the cloud keeps its top 5 %
        second, drawn2, share2 = look("second")
        assert share2 > 0.5, share2  # the cloud is still drawn, thinner
        assert np.abs(second.astype(int) - first.astype(int)).max(-1).astype(bool).mean() > 0.02
        assert drawn2.mean() < 0.8 * drawn.mean(), (drawn.mean(), drawn2.mean())
    finally:
        v.close()


def test_cli_view_errors_are_one_line(tmp_path, capsys):
    from swiftjax import cli

    assert cli.main(["view", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not exist" in err
    assert cli.main(["view", str(tmp_path)]) == 2
    assert "not a swiftjax run directory" in capsys.readouterr().err


def test_import_swiftjax_does_not_import_viser():
    import subprocess
    import sys

    code = "import sys, swiftjax, swiftjax.viewer, swiftjax.cli; print('viser' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_live_viewer_and_host_warning(demo_run):
    """``--view``'s LiveViewer serves once the manifest is there and stops cleanly; binding
    anything but loopback prints a warning."""
    import threading
    import time as _time

    _need("viser", __import__("importlib").util.find_spec("viser") is not None, "pip install 'swiftjax[view]'")
    out, _ = demo_run
    lines: list[str] = []
    live = viewer.LiveViewer(out, host="127.0.0.1", port=0, max_points=1000, log=lines.append, interval=0.1)
    deadline = _time.monotonic() + 60
    while live.viewer is None and _time.monotonic() < deadline:
        _time.sleep(0.1)
    assert live.viewer is not None and live.viewer.view.final
    live.refresh_now()
    assert any("127.0.0.1" in ln for ln in lines) and not any("warning" in ln for ln in lines)
    v = live.viewer
    cloud = lambda: v.server.scene.get_handle_by_name("/cloud")
    with_loops = np.asarray(cloud().points, np.float64)
    v.loop_toggle.value = False  # the chained poses: the same points, placed without loop closure
    assert v.pose_set() == "no loop closure"
    xyz, _ = viewer.world_points(v.view, v.reservoir, "no loop closure")
    np.testing.assert_allclose(np.asarray(cloud().points, np.float64), xyz, rtol=1e-6, atol=1e-6)
    assert np.abs(with_loops - xyz).max() > 1e-2
    v.colour.value = "chunk"
    assert len(np.unique(np.asarray(cloud().colors).reshape(-1, 3), axis=0)) == min(10, len(v.view.chunks))
    live.close()
    assert not any(t.name == "swiftjax-view" and t.is_alive() for t in threading.enumerate())
    shared = viewer.serve(out, host="0.0.0.0", port=0, max_points=1000, log=lines.append)
    try:
        assert any("warning: serving on 0.0.0.0" in ln for ln in lines)
    finally:
        shared.close()


def _raw_request(port: int, host: str, origin: str | None, websocket: bool) -> bytes:
    """One HTTP request over a plain socket (a browser's headers, set by hand: Python's
    clients will not send a foreign Host); everything the server sends within 3 s."""
    lines = ["GET / HTTP/1.1", f"Host: {host}"]
    if websocket:
        lines += [
            "Upgrade: websocket",
            "Connection: Upgrade",
            "Sec-WebSocket-Version: 13",
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
            f"Sec-WebSocket-Protocol: viser-v{__import__('viser').__version__}",
        ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    received = b""
    with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline and len(received) < 200_000:
            try:
                chunk = s.recv(65536)
            except TimeoutError:
                break
            if not chunk:
                break
            received += chunk
    return received


def test_foreign_origin_and_host_get_no_scene(demo_run):
    """Cross-site WebSocket hijacking and DNS rebinding (issue 25 item 16): a page of
    another site (``Origin: http://evil.example``) or a rebound name (``Host:
    evil.example``) gets 403 and no scene; the viewer's own page (same Origin as Host) and a
    script without Origin get the scene."""
    _need("viser", __import__("importlib").util.find_spec("viser") is not None, "pip install 'swiftjax[view]'")
    out, _ = demo_run
    v = viewer.Viewer(out, port=0, max_points=2000, log=lambda _: None)
    try:
        port = v.server.get_port()
        own = f"127.0.0.1:{port}"
        refused = [
            (own, "http://evil.example", True),
            (own, f"http://evil.example:{port}", True),
            (own, "null", True),
            (f"evil.example:{port}", f"http://evil.example:{port}", True),  # DNS rebinding: same-origin
            (f"evil.example:{port}", None, True),
            (f"evil.example:{port}", None, False),  # the page itself
        ]
        for host, origin, ws in refused:
            reply = _raw_request(port, host, origin, ws)
            assert reply.startswith(b"HTTP/1.1 403"), (host, origin, ws, reply[:200])
            assert len(reply) < 1000 and b"/cloud" not in reply, (host, origin, ws, len(reply))
        for host, origin in ((own, f"http://{own}"), (f"localhost:{port}", f"http://localhost:{port}"), (own, None)):
            reply = _raw_request(port, host, origin, True)
            assert reply.startswith(b"HTTP/1.1 101"), (host, origin, reply[:200])
            assert len(reply) > 10_000, (host, origin, len(reply))  # the scene's messages follow
        assert _raw_request(port, own, None, False).startswith(b"HTTP/1.1 200")
    finally:
        v.close()


def test_request_refusal_rules():
    allowed = viewer.allowed_host_names("127.0.0.1")
    ok = [
        {"Host": "127.0.0.1:8080"},
        {"Host": "[::1]:8080", "Origin": "http://[::1]:8080"},
        {"Host": "localhost:8080", "Origin": "http://localhost:8080"},
        {"Host": "10.1.2.3:8080"},
    ]
    for headers in ok:
        assert viewer.request_refusal(headers, allowed) is None, headers
    bad = [
        {},
        {"Host": "evil.example:8080"},
        {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:9999"},
        {"Host": "127.0.0.1:8080", "Origin": "file://"},
        {"Host": "localhost.evil.example"},
    ]
    for headers in bad:
        assert viewer.request_refusal(headers, allowed) is not None, headers
    assert viewer.request_refusal({"Host": "my-box:8080"}, viewer.allowed_host_names("my-box")) is None


def test_legend_and_ground_truth_visible(demo_run):
    """The GUI names every colour the scene uses; the ground truth, when ticked, is drawn in
    its own colour and wider than the trajectory (visible where the two agree), and gone
    when unticked."""
    _need("viser", __import__("importlib").util.find_spec("viser") is not None, "pip install 'swiftjax[view]'")
    out, _ = demo_run
    v = viewer.Viewer(out, port=0, max_points=2000, log=lambda _: None)
    try:
        for words in ("trajectory", "ground truth", "accepted loop closure", "rejected loop candidate", "chunk"):
            assert words in v.legend.content, words
        scene = v.server.scene
        gt, traj = scene.get_handle_by_name("/ground_truth"), scene.get_handle_by_name("/trajectory")
        assert gt is not None and traj is not None
        assert gt.thickness >= 2 * traj.thickness
        gt_rgb, traj_rgb = np.asarray(gt.colors).reshape(-1, 3)[0], np.asarray(traj.colors).reshape(-1, 3)[0]
        assert np.abs(gt_rgb.astype(int) - traj_rgb.astype(int)).max() > 100  # told apart at a glance
        v.show_gt.value = False
        assert scene.get_handle_by_name("/ground_truth") is None
        v.show_gt.value = True
        assert scene.get_handle_by_name("/ground_truth") is not None
    finally:
        v.close()


# ------------------------------------------------------------------ the docs' maths, offline


def _docs_site(tmp_path_factory) -> "os.PathLike[str]":
    """A built docs site: ``$SWIFTJAX_DOCS_SITE`` (``.ci/run`` points it at the site its
    ``mkdocs build --strict`` wrote), else built here without executing the notebooks."""
    import importlib.util
    import sys

    site = os.environ.get("SWIFTJAX_DOCS_SITE")
    if site:
        assert os.path.isfile(os.path.join(site, "index.html")), f"SWIFTJAX_DOCS_SITE={site} holds no site"
        return site
    if importlib.util.find_spec("mkdocs") is None:
        assert os.environ.get("CI") != "true", "CI builds the docs first and sets SWIFTJAX_DOCS_SITE (.ci/run)"
        pytest.skip("mkdocs is not installed (pip install -e '.[docs]'), nor SWIFTJAX_DOCS_SITE set")
    out = tmp_path_factory.mktemp("site")
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, SWIFTJAX_DOCS_EXECUTE="false", NO_MKDOCS_2_WARNING="1")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(out)],
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def _dump_dom(url: str) -> str:
    """The page's DOM after its scripts ran, in headless Chromium that can resolve no host
    but 127.0.0.1 (a renderer fetched from a CDN cannot load)."""
    _, out, err = _run_chromium(
        ["--virtual-time-budget=20000", "--dump-dom", "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1"],
        url,
        timeout=180,
    )
    assert out, err.decode(errors="replace")[-2000:]
    return out.decode()


def test_docs_maths_render_offline(tmp_path_factory):
    """Issue 26 item 5: a built page's equations are typeset in the browser with no network
    (MathJax served by the site): every arithmatex element of ``method/`` holds an SVG
    formula and no TeX error; a notebook page's ``$...$`` maths is typeset too."""
    import functools
    import http.server
    import re
    import threading

    _need("chromium", _chromium() is not None, "apt-get install chromium")
    site = _docs_site(tmp_path_factory)
    for page in ("method/index.html", "conventions/index.html"):
        html = open(os.path.join(site, page), encoding="utf-8").read()
        assert not re.search(r"<script[^>]+src=\"https?://", html), f"{page} loads a script from the network"

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    handler = functools.partial(Quiet, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}/"
        source = open(os.path.join(site, "method", "index.html"), encoding="utf-8").read()
        n_maths = len(re.findall(r'class="arithmatex"', source))
        assert n_maths >= 20, n_maths
        dom = _dump_dom(base + "method/")
        formulas = re.findall(r"<mjx-container[^>]*>\s*<svg", dom)
        assert len(formulas) >= n_maths, (len(formulas), n_maths)
        assert '<g data-mml-node="merror"' not in dom  # an unknown macro would render as an error box
        assert not re.search(r'class="arithmatex">\\[(\[]', dom)  # no raw TeX left
        dom = _dump_dom(base + "notebooks/05_full_pipeline/")
        assert re.search(r"<mjx-container[^>]*>\s*<svg", dom) and "$S_{i\\to j}" not in dom  # typeset, not raw
    finally:
        server.shutdown()
