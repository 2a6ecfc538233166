"""The demo's outputs are the ones recorded before the pipeline was re-shaped into stages.

``tests/data/demo_outputs.json`` was written from a run of main (commit c404600; re-recorded when
the manifest and ``metrics.json`` gained the pairwise-consistency and null-test fields, every
pose, point and loop verdict unchanged) by
``python tests/test_demo_outputs.py RUN_DIR > tests/data/demo_outputs.json`` after
``swiftjax <DEMO args> --out RUN_DIR``.  It holds, per output file, a small summary instead of
the file: the text with its numbers taken out (a SHA-256, exact) and the numbers (compared with
a relative tolerance of 1e-6 of the file's largest magnitude); PLY, chunk ``.npz`` members and
images as counts, shapes and float64 sums; binary COLMAP files by size.  Timings are dropped.

The run is not bit-identical across processors: XLA compiles for the host's vector width and
FMA, and the fused alignment kernels sum in 16 or 8 lanes.  Poses, points, images and chunk
files agree to 1e-6 between the AMD EPYC the recording was made on and an Intel Xeon.  The
statistics of thresholded tests do not: a pixel on a threshold's edge flips with the last bit
of a float32 sum.  These are the loop verification's dense-agreement counts, in ``loops.txt``,
``manifest.json`` and ``metrics.json`` (1297 vs 1298 agreeing pixels, 523 vs 522 in front).
Those three files are compared to 1 % relative (:data:`_STATISTICS`).  Left out entirely are
the records' CRC32 columns and the pose graph's ``status``, which names the LM stopping test
that fired first (``relative cost decrease`` or ``gradient``).  Re-recorded on the Xeon (commit
2c8b1b4); the EPYC recording agreed with it under these rules.  Re-recorded for issue 28 when
the manifest gained ``loop_geometry_neighbours`` (0) and ``loop_null_sided`` (false); every other number equal
to the previous recording.  Re-recorded when ``loop_null_sided`` became ``loop_null_model``
(default ``trend``): the one loop's null numbers changed (bound 0.422 → 0.327, mean 0.183 →
0.287, κ 0.709 → 0.667; still accepted), every other number equal.  The manifest's skeleton
re-hashed when ``loop_siblings`` became false by default (issue 28, fourteenth pass): its text
only, every number equal.
"""

from __future__ import annotations

import hashlib
import io
import json
import pathlib
import re
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from test_faults import DEMO  # the demo run the recording was made of (155 frames, 8 chunks, one loop)

pytestmark = pytest.mark.slow

REPO = pathlib.Path(__file__).resolve().parents[1]
RECORDING = REPO / "tests" / "data" / "demo_outputs.json"
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)\b")
#: Left out: timings, the CRC32s of records (they follow the exact bits of the floats beside them)
#: and the LM stopping test that fired first (module docstring).
_SKIPPED_KEYS = {"timings_seconds", "compile_seconds", "solve_seconds", "crc32", "status"}
#: Files of thresholded-test statistics and their relative tolerance (module docstring).
_STATISTICS = {"loops.txt": 1e-2, "manifest.json": 1e-2, "metrics.json": 1e-2}


def _sha(data: bytes | str) -> str:
    return hashlib.sha256(data.encode() if isinstance(data, str) else data).hexdigest()[:16]


def _round(values: list[float]) -> list[float]:
    return [float(f"{v:.8g}") for v in values]  # 8 digits: far inside the 1e-6 tolerance


def _without_columns(text: str, names: set[str]) -> str:
    """``text`` without the columns ``names`` of its table: the last ``# `` comment line names
    the columns of the lines after it (``loops.txt``'s layout); other text is returned as is."""
    lines = text.splitlines()
    header = max((k for k, line in enumerate(lines) if line.startswith("# ")), default=None)
    if header is None:
        return text
    columns = lines[header][2:].split()
    drop = [k for k, name in enumerate(columns) if name in names]
    if not drop:
        return text

    def cut(line: str) -> str:
        fields = line.split(" ", len(columns) - 1)  # the last column holds spaces
        return " ".join(f for k, f in enumerate(fields) if k not in drop)

    return "\n".join([*lines[: header + 1], *(cut(line) for line in lines[header + 1 :])])


def _text(text: str) -> dict:
    text = _without_columns(text, {"crc32"})
    numbers = [float(m) for m in _NUMBER.findall(text)]
    return {"skeleton": _sha(_NUMBER.sub("#", text)), "numbers": _round(numbers)}


def _json(value: object) -> dict:
    strings: list[str] = []
    numbers: list[float] = []

    def walk(x: object, path: str) -> None:
        if isinstance(x, dict):
            for k in sorted(x):
                if k not in _SKIPPED_KEYS:
                    walk(x[k], f"{path}/{k}")
        elif isinstance(x, list):
            for k, v in enumerate(x):
                walk(v, f"{path}/{k}")
        elif isinstance(x, bool) or x is None or isinstance(x, str):
            strings.append(f"{path}={x}")
        else:
            strings.append(f"{path}=#")
            numbers.append(float(x))

    walk(value, "")
    return {"skeleton": _sha("\n".join(strings)), "numbers": _round(numbers)}


def _array(a: np.ndarray) -> dict:
    a = np.asarray(a)
    out: dict = {"shape": list(a.shape), "dtype": str(a.dtype)}
    if a.dtype.kind in "fiub" and a.size:
        x = a.astype(np.float64)
        finite = np.isfinite(x)
        out["numbers"] = _round([float(np.sum(x[finite])), float(np.sum(np.abs(x[finite]))), float(np.sum(~finite))])
    return out


def summarise(run_dir: pathlib.Path) -> dict[str, dict]:
    """``{relative path: summary}`` of every file of a run directory (see the module docstring)."""
    from PIL import Image

    from swiftjax.io import ply

    out: dict[str, dict] = {}
    for path in sorted(p for p in run_dir.rglob("*") if p.is_file() and not p.name.startswith(".")):
        rel = path.relative_to(run_dir).as_posix()
        if path.suffix == ".json":
            out[rel] = _json(json.loads(path.read_text()))
        elif path.suffix == ".txt":
            out[rel] = _text(path.read_text())
        elif path.suffix == ".ply":
            cloud = ply.read_ply(path)
            out[rel] = {name: _array(value) for name, value in cloud._asdict().items() if value is not None}
        elif path.suffix == ".npz":
            with zipfile.ZipFile(path) as z:
                out[rel] = {
                    name: _array(np.load(io.BytesIO(z.read(name)), allow_pickle=False))
                    for name in sorted(z.namelist())
                    if not name.startswith("crc32__")
                }
        elif path.suffix == ".png":
            image = np.asarray(Image.open(path))
            out[rel] = _array(image) if rel.startswith("colmap/") else {"shape": list(image.shape)}
        else:
            out[rel] = {"size": path.stat().st_size}
    return out


def assert_matches(got: dict, want: dict, where: str = "", rtol: float = 1e-6) -> None:
    """Every key equal, ``numbers`` lists within 1e-6 relative to their largest magnitude (and
    ``rtol`` relative to each number: the statistics files' tolerance)."""
    assert sorted(got) == sorted(want), where
    for key in want:
        g, w = got[key], want[key]
        if key == "numbers":
            g, w = np.asarray(g, np.float64), np.asarray(w, np.float64)
            assert g.shape == w.shape, where
            scale = max(float(np.max(np.abs(w[np.isfinite(w)]), initial=0.0)), 1e-12)
            np.testing.assert_allclose(g, w, rtol=rtol, atol=1e-6 * scale, equal_nan=True, err_msg=where)
        elif isinstance(w, dict):
            assert_matches(g, w, f"{where}/{key}", rtol)
        else:
            assert g == w, f"{where}/{key}: {g!r} != {w!r}"


def run_demo(out: pathlib.Path) -> None:
    from test_faults import _env

    proc = subprocess.run(
        [sys.executable, "-m", "swiftjax.cli", *DEMO, "--out", str(out)],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_demo_outputs_equal_the_recording(tmp_path):
    run_demo(tmp_path / "demo")
    want = json.loads(RECORDING.read_text())
    got = summarise(tmp_path / "demo")
    assert sorted(got) == sorted(want)
    for rel in want:
        assert_matches(got[rel], want[rel], rel, _STATISTICS.get(rel, 1e-6))


def test_the_crc32_column_is_left_out_of_a_table():
    text = "# a\n# i crc32 score reason\n1 6db4c5f2 0.5 kept, the best\n2 00000012 0.25 rejected\n"
    assert _without_columns(text, {"crc32"}).splitlines()[2:] == ["1 0.5 kept, the best", "2 0.25 rejected"]
    assert _without_columns("no table here\n", {"crc32"}) == "no table here\n"


if __name__ == "__main__":
    summary = summarise(pathlib.Path(sys.argv[1]))  # one file a line
    print("{\n" + ",\n".join(f"{json.dumps(k)}: {json.dumps(v, sort_keys=True)}" for k, v in summary.items()) + "\n}")
