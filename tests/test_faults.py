"""Fault injection through the real CLI: a user's run killed anywhere resumes to the same bytes.

Each test runs ``swiftjax demo`` (a small synthetic loop route: 155 frames, 8 chunks, one
loop) in subprocesses.  ``SWIFTJAX_FAULT=NAME:INDEX:SIGNAL`` (only tests set it; see
:mod:`swiftjax._faults`) makes the process signal itself at a named point: SIGKILL (no
cleanup at all), SIGINT (a Ctrl-C) or SIGSTOP (frozen, holding the lock).  Checked:

* killed at every stage boundary and in the middle of chunk writes, one kill after another
  (each resume runs until the next fault point), the final resume's outputs equal an
  uninterrupted run's, file by file (every output, the manifest, the chunk store member by
  member), and no chunk recorded as finished is ever predicted (written) again;
* bytes flipped in every kind of stored array (dense maps, poses, descriptors, export points,
  a checksum table, a truncated file): each is reported naming the file and field, that chunk
  alone is predicted again, and the outputs equal the uninterrupted run's;
* a second writer on a running run directory is refused in one line naming the holder's pid;
  the lock of the killed holder is taken over.

One uninterrupted reference run per session (fixture); about 25 short processes in all.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest
from test_pipeline_stages import assert_same_outputs

from swiftjax import chunks
from swiftjax.io.atomic import temp_files

pytestmark = pytest.mark.slow

REPO = pathlib.Path(__file__).resolve().parents[1]
DEMO = [
    "demo",
    "--image-size",
    "28x98",
    "--frame-spacing",
    "4",
    "--chunk-size",
    "30",
    "--overlap",
    "10",
    "--loop-min-separation",
    "50",
    "--loop-nms-radius",
    "10",
    "--loop-half-window",
    "8",
    "--point-stride",
    "3",
    "--colmap-max-points",
    "2000",
    "--loop-threshold-rule",
    "fixed",
    "--no-progress",
]
N_FRAMES, CHUNK, OVERLAP = 155, 30, 10


def _env(fault: str | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("SWIFTJAX_FAULT", None)
    if fault:
        env["SWIFTJAX_FAULT"] = fault
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    # The test session's persistent compilation cache (tests/conftest.py) serves the CLI too.
    env.setdefault(
        "SWIFTJAX_CACHE_DIR",
        os.environ.get("JAX_COMPILATION_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax-tests")),
    )
    env["OPENBLAS_NUM_THREADS"] = "1"
    return env


def _default_sigint() -> None:
    """In the child before exec: SIGINT back to its default action.  A test session started in
    the background by a non-interactive shell (``pytest &``) inherits SIGINT ignored, and
    Python installs its Ctrl-C handler only where SIGINT is not ignored: the injected SIGINT
    would then be dropped and the run would finish (exit 0) instead of stopping (exit 130)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def swiftjax(
    out: pathlib.Path, *extra: str, fault: str | None = None, timeout: float = 600
) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "swiftjax.cli", *DEMO, "--out", str(out), *extra],
        env=_env(fault),
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=_default_sigint,
    )


def _manifest(run_dir: pathlib.Path) -> dict:
    return json.loads((run_dir / "manifest.json").read_text())


def _finished_chunk_files(run_dir: pathlib.Path) -> dict[str, tuple[int, int]]:
    """``{file name: (inode, mtime_ns)}`` of the chunks the manifest records as finished
    (chunk and its edge recorded): a re-prediction would replace the file (new inode)."""
    m = _manifest(run_dir)
    out = {}
    for key in m["chunks"]:
        t = int(key)
        if t == 0 or str(t - 1) in m["edges"]:
            st = (run_dir / "chunks" / f"chunk_{t:05d}.npz").stat()
            out[f"chunk_{t:05d}.npz"] = (st.st_ino, st.st_mtime_ns)
    return out


@pytest.fixture(scope="session")
def reference(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("faults") / "reference"
    proc = swiftjax(out)
    assert proc.returncode == 0, proc.stderr
    m = _manifest(out)
    schedule = chunks.chunk_schedule(N_FRAMES, CHUNK, OVERLAP)
    assert len(m["chunks"]) == schedule.num_chunks == 8 and len(m["loop_edges"]) >= 1
    return out


# (point, index) in the order a run reaches them; each resume runs to the next one.
CHAIN = [
    ("chunk-write", 2),
    ("chunk-predicted", 3),
    ("chunk-recorded", 4),
    ("chunk-write", 6),
    ("temporal-done", None),
    ("loop-recorded", 0),
    ("loops-done", None),
    ("graph-done", None),
    ("export-chunk", 3),
    ("export-done", None),
]
INT_CHAIN = [
    ("chunk-write", 2),
    ("chunk-recorded", 4),
    ("temporal-done", None),
    ("loop-recorded", 0),
    ("graph-done", None),
    ("export-chunk", 3),
]


@pytest.mark.parametrize("sig, chain", [("KILL", CHAIN), ("INT", INT_CHAIN)], ids=["SIGKILL", "SIGINT"])
def test_killed_at_every_point_then_resumed_equals_the_uninterrupted_run(reference, tmp_path, sig, chain):
    out = tmp_path / "run"
    finished: dict[str, tuple[int, int]] = {}
    for name, index in chain:
        proc = swiftjax(out, fault=f"{name}:{'' if index is None else index}:{sig}")
        want = -signal.SIGKILL if sig == "KILL" else 130
        assert proc.returncode == want, (name, index, proc.returncode, proc.stderr[-2000:])
        if sig == "INT":
            assert "interrupted (finished chunks are kept" in proc.stderr
        now = _finished_chunk_files(out)
        for f, ident in finished.items():  # recorded once: never predicted (written) again
            assert now.get(f) == ident, (name, index, f)
        finished = now
    proc = swiftjax(out)
    assert proc.returncode == 0, proc.stderr
    for f, ident in finished.items():
        assert _finished_chunk_files(out).get(f) == ident, f
    assert not any(temp_files(d) for d in (out, out / "chunks", out / "colmap"))
    assert not list((out / "chunks").glob("tail_*"))
    assert_same_outputs(out, reference)


def _member_span(path: pathlib.Path, member: str) -> tuple[int, int]:
    """(data offset, size) of an uncompressed .npz member's bytes (its .npy header included)."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member + ".npy")
    raw = path.read_bytes()
    local = raw[info.header_offset : info.header_offset + 30]
    start = info.header_offset + 30 + int.from_bytes(local[26:28], "little") + int.from_bytes(local[28:30], "little")
    return start, info.compress_size


def _flip_every_frame(path: pathlib.Path, member: str, frames: int) -> None:
    start, size = _member_span(path, member)
    raw = bytearray(path.read_bytes())
    row = (size - 128) // frames  # the .npy header is at most 128 bytes here
    for k in range(frames):
        raw[start + size - 1 - k * row] ^= 0x04
    path.write_bytes(bytes(raw))


def _flip_one(path: pathlib.Path, member: str) -> None:
    start, size = _member_span(path, member)
    raw = bytearray(path.read_bytes())
    raw[start + size - 2] ^= 0x40
    path.write_bytes(bytes(raw))


def test_flipped_bytes_in_each_stored_array_are_named_and_repredicted(reference, tmp_path):
    """Defect 4: flipped depth bytes were read back silently by the memory-mapped reads, and
    flipped point bytes ended in a BadZipFile traceback."""
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    m = _manifest(out)
    m["loop_edges"] = {}  # as if killed after the temporal stage: the loop stage reads the dense maps
    (out / "manifest.json").write_text(json.dumps(m))
    loop = next(iter(_manifest(reference)["loop_edges"].values()))
    ci, cj = loop["chunk_i"], loop["chunk_j"]
    others = [t for t in range(8) if t not in (ci, cj)]
    damage = {  # chunk -> (field, how)
        ci: ("depth", "frames"),
        cj: ("conf", "frames"),
        others[0]: ("descriptors", "one"),
        others[1]: ("intrinsic", "frames"),
        others[2]: ("extrinsic", "one"),
        others[3]: ("extra__points_xyz", "one"),
        others[4]: ("crc32__points_conf", "one"),
        others[5]: (None, "truncate"),
    }
    chunk_dir = out / "chunks"
    for t, (field, how) in damage.items():
        path = chunk_dir / f"chunk_{t:05d}.npz"
        n = CHUNK if t < 7 else N_FRAMES - chunks.chunk_schedule(N_FRAMES, CHUNK, OVERLAP).starts[7]
        if how == "frames":
            _flip_every_frame(path, field, int(n))
        elif how == "one":
            _flip_one(path, field.replace("crc32__", "crc32__extra__") if field.startswith("crc32__") else field)
        else:
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    intact = {p.name: p.stat().st_ino for p in chunk_dir.glob("chunk_*") if int(p.stem[6:]) not in damage}
    proc = swiftjax(out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = proc.stdout + proc.stderr
    for t, (field, _) in damage.items():
        name = f"chunk_{t:05d}.npz: corrupt chunk file"
        assert name in text, (t, field, text[-3000:])
        line = next(ln for ln in text.splitlines() if name in ln)
        assert f"predicting chunk {t} again" in line
        if field is not None:
            shown = field.replace("crc32__", "extra__")  # a bad checksum table fails its array
            assert shown in line, line
    assert {p.name: p.stat().st_ino for p in chunk_dir.glob("chunk_*") if int(p.stem[6:]) not in damage} == intact
    assert_same_outputs(out, reference)


def test_second_writer_is_refused_and_a_dead_holders_lock_is_taken_over(reference, tmp_path):
    """Defect 2: two runs on one directory both exited 0 with mixed-up results."""
    out = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-m", "swiftjax.cli", *DEMO, "--out", str(out)],
        env=_env("chunk-recorded:1:STOP"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:  # frozen at the fault point, holding the lock
            if holder.poll() is not None:
                pytest.fail(f"the holder exited early ({holder.returncode})")
            try:
                stat = pathlib.Path(f"/proc/{holder.pid}/stat").read_text().split()[2]
            except OSError:
                stat = "?"
            if stat == "T":
                break
            time.sleep(0.2)
        else:
            pytest.fail("the holder never reached its fault point")
        second = swiftjax(out, "--overlap", "12", "--overwrite")
        assert second.returncode == 2
        errors = [ln for ln in second.stderr.splitlines() if ln.startswith("swiftjax: error:")]
        assert (
            len(errors) == 1 and f"pid {holder.pid} on " in errors[0] and "in use by another swiftjax run" in errors[0]
        )
        assert "Traceback" not in second.stderr
    finally:
        holder.kill()
        holder.wait()
    third = swiftjax(out)
    assert third.returncode == 0, third.stderr
    assert f"taking over the lock of an interrupted run (pid {holder.pid}" in third.stdout + third.stderr
    assert (out / ".swiftjax.lock").read_text() == ""
    assert_same_outputs(out, reference)


def test_options_are_refused_before_work_and_an_export_fix_reruns_only_the_export(reference, tmp_path):
    """Defect 5 through the CLI: the bad value never starts a prediction, the fixed export
    option re-runs the export alone (every chunk file untouched)."""
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    before = {p.name: p.stat().st_ino for p in (out / "chunks").iterdir()}
    bad = swiftjax(out, "--colmap-max-points", "-1")
    assert bad.returncode == 2 and "--colmap-max-points" in bad.stderr
    good = swiftjax(out, "--colmap-max-points", "500")
    assert good.returncode == 0, good.stderr
    assert {p.name: p.stat().st_ino for p in (out / "chunks").iterdir()} == before
    assert (out / "poses_kitti.txt").read_bytes() == (reference / "poses_kitti.txt").read_bytes()
    refused = swiftjax(out, "--depth-threshold", "0.3")
    assert refused.returncode == 2 and "different options depth_threshold" in refused.stderr
    assert "--overwrite" in refused.stderr


def test_a_user_folder_as_out_is_refused_and_left_as_it_was(tmp_path):
    """Issue 25 item 1: --out at a user's folder replaced 4 of its 5 files (and --overwrite
    deleted its chunks/*.npz)."""
    user = tmp_path / "mine"
    files = {
        "points.ply": b"ply",
        "metrics.json": b"{}",
        "colmap/images/00000.png": b"png",
        "colmap/sparse/0/cameras.bin": b"bin",
        "chunks/chunk_00007.npz": b"npz",
        "chunks/loop_00001.npz": b"npz",
    }
    for rel, data in files.items():
        (user / rel).parent.mkdir(parents=True, exist_ok=True)
        (user / rel).write_bytes(data)
    for extra in ((), ("--overwrite",)):
        proc = swiftjax(user, *extra)
        errors = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert proc.returncode == 2 and len(errors) == 1, proc.stderr
        assert f"--out {user} is not empty and holds no swiftjax run" in errors[0]
    assert sorted(str(p.relative_to(user)) for p in user.rglob("*") if p.is_file()) == sorted(files)
    assert all((user / rel).read_bytes() == data for rel, data in files.items())


def test_swapped_and_foreign_chunks_an_edited_record_and_damaged_frames_are_named_and_repaired(reference, tmp_path):
    """Issue 25 items 5, 6, 7: a chunk file copied over another, another run's chunk, one
    changed digit of an edge record, COLMAP frames deleted or damaged after the run: each was
    used (or left) silently.  Now each is named, repaired, and the outputs equal the
    uninterrupted run's."""
    from swiftjax.io.chunk_store import ChunkStore

    out = tmp_path / "run"
    shutil.copytree(reference, out)
    chunk_dir = out / "chunks"
    shutil.copy(chunk_dir / "chunk_00002.npz", chunk_dir / "chunk_00001.npz")
    store = ChunkStore(out)  # chunk 6 as another run (another fingerprint) wrote it: a sound file
    extra = store.load_extra("chunk", 6)
    extra["fingerprint"] = np.asarray("0" * 64)
    store.save("chunk", 6, store.load("chunk", 6), extra)
    m = _manifest(out)
    m["edges"]["4"]["S"][3] += 1e-3  # edge (4, 5): one digit
    (out / "manifest.json").write_text(json.dumps(m))
    images = out / "colmap" / "images"
    (images / "000007.png").unlink()
    raw = bytearray((images / "000065.png").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (images / "000065.png").write_bytes(bytes(raw))
    proc = swiftjax(out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = proc.stdout + proc.stderr
    assert "chunk_00001.npz: not this run's chunk file: it holds chunk 2, not chunk 1; predicting chunk 1 again" in text
    assert (
        "chunk_00006.npz: not this run's chunk file: it was predicted from another input, model or configuration"
        in text
    )
    assert (
        "the record of edge (chunks 4/5) fails its checksum (edited or damaged): predicting chunks 4 and 5 again"
        in text
    )
    assert "000007.png (missing)" in text and "000065.png (damaged: fails its CRC32)" in text
    assert "Traceback" not in text
    assert_same_outputs(out, reference)


@pytest.mark.parametrize("k", [0, 3, 7])
def test_ctrl_c_during_the_export_exits_cleanly(reference, tmp_path, k):
    """Issue 25 item 21: a Ctrl-C during the export once ended in 'Fatal Python error:
    PyThreadState_Get ... finalizing' (SIGABRT): the writer threads and JAX's work are now
    waited for before the interpreter exits."""
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    (out / "colmap" / "images" / "000003.png").unlink()  # the export has frames to write too
    proc = swiftjax(out, "--colmap-max-points", "500", fault=f"export-chunk:{k}:INT")
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert "Fatal Python error" not in proc.stderr and "Traceback" not in proc.stderr
    assert "interrupted (finished chunks are kept" in proc.stderr
    assert (out / "poses_kitti.txt").read_bytes() == (reference / "poses_kitti.txt").read_bytes()


def test_weights_changed_after_the_first_mib_are_refused_and_every_export_option_predicts_nothing(tmp_path, golden_dir):
    """Issue 25 item 3 (weights edited after their first MiB, size and mtime kept, were
    reused) and issue 26 item 3 through the real CLI with the tiny VGGT: adding
    --colmap-original-resolution (or any export option) to a finished run re-runs the export
    alone (no chunk file rewritten), and turning it off draws the model-resolution frames
    from the input again."""
    from PIL import Image

    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (60, 90, 3), np.uint8)
    for k in range(6):
        Image.fromarray(np.roll(base, 3 * k, axis=1)).save(folder / f"img_{k}.png")
    weights = tmp_path / "tiny.safetensors"
    shutil.copy(golden_dir / "tiny_weights.safetensors", weights)
    out = tmp_path / "run"
    env = {**_env(), "SWIFTJAX_HASH_CACHE": str(tmp_path / "hashes.json")}

    def run(*extra):
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "swiftjax.cli",
                "reconstruct",
                str(folder),
                "--weights",
                str(weights),
                "--model-config",
                str(golden_dir / "tiny_config.json"),
                "--out",
                str(out),
                "--chunk-size",
                "4",
                "--overlap",
                "2",
                "--min-points",
                "10",
                "--no-loop-closure",
                "--point-stride",
                "2",
                "--no-progress",
                *extra,
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )

    first = run()
    assert first.returncode == 0, first.stderr[-3000:]
    frames_before = {p.name: p.read_bytes() for p in (out / "colmap" / "images").iterdir()}
    chunks_before = {p.name: p.stat().st_ino for p in (out / "chunks").iterdir()}
    for extra in (
        ("--colmap-original-resolution",),
        ("--colmap-text", "--voxel-size", "0.05"),
        ("--colmap-max-points", "50"),
        ("--no-colmap",),
        (),
    ):
        proc = run(*extra)
        assert proc.returncode == 0, (extra, proc.stderr[-3000:])
        assert {p.name: p.stat().st_ino for p in (out / "chunks").iterdir()} == chunks_before, extra
        names = sorted(p.name for p in (out / "colmap" / "images").iterdir()) if (out / "colmap").exists() else []
        if extra == ("--colmap-original-resolution",):
            assert names == [f"img_{k}.png" for k in range(6)]
            assert (out / "colmap" / "images" / "img_2.png").read_bytes() == (folder / "img_2.png").read_bytes()
        elif extra == ("--no-colmap",):
            assert names == []
        else:
            assert {n: (out / "colmap" / "images" / n).read_bytes() for n in names} == frames_before, extra
    st = weights.stat()
    raw = bytearray(weights.read_bytes())
    raw[(4 << 20) + 11] ^= 0x01  # after the first MiB, inside the tensors
    weights.write_bytes(bytes(raw))
    os.utime(weights, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (weights.stat().st_size, weights.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    refused = run()
    assert refused.returncode == 2 and "holds a run with a different model (weights)" in refused.stderr, refused.stderr
