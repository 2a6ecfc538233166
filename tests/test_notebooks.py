"""The notebooks in ``notebooks/`` are executable documentation: each one must run top to bottom.

Notebooks 1-5 assert their key facts in their own cells (errors against closed forms,
recovered transforms against the synthetic truth, loop-closure gains), so a notebook whose API
or numbers rot fails here.  One test per notebook; a cell error fails it with the cell's
traceback.  Every notebook runs with its own empty ``TMPDIR`` and must leave it empty.

Notebook 0 (*your images*) is a tutorial: it asserts nothing itself; its checks are here
(:func:`test_tutorial_does_the_job`): the run it makes is complete and its pictures show inline.

The kernel is this interpreter (``sys.executable``): a ``python3`` kernelspec pointing at it is
written to a temporary ``JUPYTER_PATH`` entry, and a first cell injected into the in-memory
copy of each notebook checks ``sys.executable`` and that ``swiftjax`` is imported from this
repository.  The kernel inherits JAX's persistent compilation cache settings through the
environment (the directory and threshold ``tests/conftest.py`` set in this process), so a notebook shares compiled
executables with the tests that run the same shapes (e.g. ``tests/test_pipeline.py``).

The committed notebooks carry no outputs; executing never writes them back.
"""

from __future__ import annotations

import os
import pathlib
import sys
import time

import jax
import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

REPO = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"))

CHECK_KERNEL = """
import pathlib, sys
assert pathlib.Path(sys.executable).resolve() == pathlib.Path({exe!r}).resolve(), sys.executable
import swiftjax
assert pathlib.Path(swiftjax.__file__).resolve().parent == pathlib.Path({pkg!r}).resolve(), swiftjax.__file__
import jax
assert jax.config.jax_compilation_cache_dir == {cache!r}, jax.config.jax_compilation_cache_dir
"""


@pytest.fixture(scope="module")
def kernel_env(tmp_path_factory, shared_dir):
    """A ``python3`` kernelspec running ``sys.executable``, first on ``JUPYTER_PATH``."""
    from ipykernel.kernelspec import install
    from jupyter_client.kernelspec import KernelSpecManager

    prefix = tmp_path_factory.mktemp("kernel")
    install(kernel_name="python3", prefix=str(prefix))
    mp = pytest.MonkeyPatch()
    jupyter_path = str(prefix / "share" / "jupyter")
    mp.setenv("JUPYTER_PATH", os.pathsep.join(filter(None, [jupyter_path, os.environ.get("JUPYTER_PATH")])))
    # JAX's persistent compilation cache, exactly as tests/conftest.py configured this process.
    mp.setenv("JAX_COMPILATION_CACHE_DIR", str(jax.config.jax_compilation_cache_dir))
    mp.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(jax.config.jax_persistent_cache_min_compile_time_secs))
    mp.setenv("SWIFTJAX_SHARED", str(shared_dir))  # notebook 0's tiny VGGT
    mp.setenv("PYDEVD_DISABLE_FILE_VALIDATION", "1")  # silence the debugger warning on kernel start
    spec = KernelSpecManager().get_kernel_spec("python3")
    assert pathlib.Path(spec.argv[0]).resolve() == pathlib.Path(sys.executable).resolve(), spec.argv
    yield
    mp.undo()


def test_notebooks_exist_and_are_committed_without_outputs():
    names = [p.name for p in NOTEBOOKS]
    assert names == [
        "00_your_images.ipynb",
        "01_sim3.ipynb",
        "02_chunk_alignment.ipynb",
        "03_loop_descriptors.ipynb",
        "04_pose_graph.ipynb",
        "05_full_pipeline.ipynb",
    ]
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"{path.name}: outputs not cleared"


def _execute(path, tmp_path, monkeypatch):
    """Execute a notebook (kernel in ``tmp_path/cwd``, ``TMPDIR`` = ``tmp_path/tmp``); returns
    the executed notebook.  Fails if the notebook leaves anything in its ``TMPDIR``."""
    nb = nbformat.read(path, as_version=4)
    check = nbformat.v4.new_code_cell(
        CHECK_KERNEL.format(
            exe=sys.executable, pkg=str(REPO / "swiftjax"), cache=str(jax.config.jax_compilation_cache_dir)
        )
    )
    nb.cells.insert(0, check)
    cwd, tmp = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))  # the kernel's tempfile.gettempdir()
    client = nbclient.NotebookClient(
        nb,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(cwd)}},  # the kernel's working directory
    )
    t0 = time.perf_counter()
    client.execute()  # raises CellExecutionError (with the traceback) on the first failing cell
    print(f"{path.name}: executed in {time.perf_counter() - t0:.1f} s; slowest cells: {_slowest(nb)}")
    left = sorted(p.name for p in tmp.iterdir())
    assert not left, f"{path.name} left {left} in its temporary folder"
    return nb


@pytest.mark.parametrize("path", NOTEBOOKS[1:], ids=[p.stem for p in NOTEBOOKS[1:]])
def test_notebook_runs(path, kernel_env, tmp_path, monkeypatch):
    _execute(path, tmp_path, monkeypatch)


def test_tutorial_does_the_job(kernel_env, tmp_path, monkeypatch):
    """Notebook 0: frames -> ImagePredictor (tiny VGGT) -> reconstruct -> pictures inline; it
    teaches (no asserts of its own) and shows the lines to change for VGGT-1B."""
    path = REPO / "notebooks" / "00_your_images.ipynb"
    source = "\n".join(c.source for c in nbformat.read(path, as_version=4).cells if c.cell_type == "code")
    assert "assert " not in source, "the tutorial teaches; its checks belong here"
    markdown = "\n".join(c.source for c in nbformat.read(path, as_version=4).cells if c.cell_type == "markdown")
    assert 'build_runner("model.pt", device="cuda", dtype="bfloat16")' in markdown and "facebook/VGGT-1B" in markdown
    nb = _execute(path, tmp_path, monkeypatch)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    pngs = [o for o in outputs if o.get("output_type") == "display_data" and "image/png" in o.get("data", {})]
    assert len(pngs) == 3, len(pngs)  # trajectory.png, points.png, the side view
    assert "10 frames of 400 x 120 pixels" in text and "next:    swiftjax view " in text
    rows = {
        ln.rsplit(None, 1)[0].strip(): ln.rsplit(None, 1)[1]
        for ln in text.splitlines()
        if ln.startswith("  ") and len(ln.split()) >= 2
    }
    assert rows["frames"] == "10" and rows["chunks"] == "2", rows
    points = int(rows["points written"].replace(",", ""))
    assert points > 1000 and f"{points:,} points, 10 cameras" in text
    assert "'points.ply'" in text and "'colmap'" in text and "'trajectory.png'" in text


def _slowest(nb, n: int = 3) -> str:
    """The ``n`` slowest code cells as ``"#index seconds"`` (from nbclient's execution timing)."""
    from datetime import datetime

    def seconds(cell) -> float:
        t = cell.get("metadata", {}).get("execution", {})
        try:
            start, end = t["iopub.execute_input"], t["shell.execute_reply"]
        except KeyError:
            return 0.0
        parse = lambda s: datetime.fromisoformat(s.replace("Z", "+00:00"))
        return (parse(end) - parse(start)).total_seconds()

    # Index 0 is the injected kernel check; notebook cell k is nb.cells[k + 1].
    timed = sorted(((seconds(c), k - 1) for k, c in enumerate(nb.cells) if c.cell_type == "code"), reverse=True)
    return ", ".join(f"#{k} {s:.1f} s" for s, k in timed[:n])
