"""The notebooks in ``notebooks/`` are executable documentation: each one must run top to bottom.

Every notebook asserts its key facts in its own cells (errors against closed forms, recovered
transforms against the synthetic truth, loop-closure gains), so a notebook whose API or
numbers rot fails here.  One test per notebook; a cell error fails it with the cell's
traceback.

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
def kernel_env(tmp_path_factory):
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
    mp.setenv(
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(jax.config.jax_persistent_cache_min_compile_time_secs)
    )
    mp.setenv("PYDEVD_DISABLE_FILE_VALIDATION", "1")  # silence the debugger warning on kernel start
    spec = KernelSpecManager().get_kernel_spec("python3")
    assert pathlib.Path(spec.argv[0]).resolve() == pathlib.Path(sys.executable).resolve(), spec.argv
    yield
    mp.undo()


def test_notebooks_exist_and_are_committed_without_outputs():
    names = [p.name for p in NOTEBOOKS]
    assert names == [
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


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, kernel_env, tmp_path):
    nb = nbformat.read(path, as_version=4)
    check = nbformat.v4.new_code_cell(
        CHECK_KERNEL.format(
            exe=sys.executable, pkg=str(REPO / "swiftjax"), cache=str(jax.config.jax_compilation_cache_dir)
        )
    )
    nb.cells.insert(0, check)
    client = nbclient.NotebookClient(
        nb,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},  # the kernel's working directory
    )
    t0 = time.perf_counter()
    client.execute()  # raises CellExecutionError (with the traceback) on the first failing cell
    print(f"{path.name}: executed in {time.perf_counter() - t0:.1f} s; slowest cells: {_slowest(nb)}")


def _slowest(nb, n: int = 3) -> str:
    """The ``n`` slowest code cells as ``"#index seconds"`` (from nbclient's execution timing)."""
    from datetime import datetime

    def seconds(cell) -> float:
        t = cell.get("metadata", {}).get("execution", {})
        try:
            start, end = t["iopub.execute_input"], t["shell.execute_reply"]
        except KeyError:
            return 0.0
        parse = lambda s: datetime.fromisoformat(s.replace("Z", "+00:00"))  # noqa: E731
        return (parse(end) - parse(start)).total_seconds()

    # Index 0 is the injected kernel check; notebook cell k is nb.cells[k + 1].
    timed = sorted(((seconds(c), k - 1) for k, c in enumerate(nb.cells) if c.cell_type == "code"), reverse=True)
    return ", ".join(f"#{k} {s:.1f} s" for s, k in timed[:n])
