"""g2o reader/writer: the shared benchmark graphs, round trips, malformed lines, unknown records."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax.io.g2o import G2oError, read_g2o, write_g2o


def test_reads_shared_graphs_with_documented_sizes(shared_dir):
    sizes = {
        "tinyGrid3D": (9, 11),
        "smallGrid3D": (125, 297),
        "sphere2500": (2500, 4949),
        "parking-garage": (1661, 6275),
    }
    for name, (n, e) in sizes.items():
        g = read_g2o(shared_dir / "data" / "posegraphs" / f"{name}.g2o")
        assert g.poses.shape == (n, 8) and g.edges.shape == (e, 2)
        assert g.information.shape == (e, 7, 7)
        np.testing.assert_allclose(np.linalg.norm(g.poses[:, 3:7], axis=1), 1.0, atol=1e-12)
        assert np.all(g.poses[:, 7] == 1.0) and np.all(g.measurements[:, 7] == 1.0)
        assert g.fixed.sum() == 1 and g.fixed[0]
        assert np.all(np.linalg.eigvalsh(g.information)[:, 0] > 0)


def test_information_upper_triangle_order(tmp_path):
    tri = np.arange(1, 22, dtype=float)
    path = tmp_path / "g.g2o"
    path.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + " ".join(str(v) for v in tri) + "\n"
    )
    g = read_g2o(path, scale_information=7.5)
    info = g.information[0]
    assert info[0, 0] == 1 and info[0, 5] == 6 and info[1, 1] == 7 and info[5, 5] == 21
    np.testing.assert_array_equal(info, info.T)
    assert info[6, 6] == 7.5 and np.all(info[6, :6] == 0)


def test_round_trip_and_ids(tmp_path):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = np.c_[rng.normal(size=(5, 3)), q, np.ones(5)]
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [0, 4]])
    meas = poses[[1, 2, 3, 4, 4]]
    a = rng.normal(size=(5, 7, 7))
    info = a @ np.swapaxes(a, 1, 2) + np.eye(7)
    path = tmp_path / "rt.g2o"
    write_g2o(path, poses, edges, meas, info, node_ids=[10, 11, 12, 20, 30], fixed=[False, True, False, False, False])
    g = read_g2o(path)
    np.testing.assert_array_equal(g.node_ids, [10, 11, 12, 20, 30])
    np.testing.assert_allclose(g.poses, poses, atol=1e-15)
    np.testing.assert_array_equal(g.edges, edges)
    np.testing.assert_allclose(g.measurements, meas, atol=1e-15)
    np.testing.assert_allclose(g.information[:, :6, :6], info[:, :6, :6], rtol=1e-15)
    np.testing.assert_array_equal(g.fixed, [False, True, False, False, False])


def test_write_refuses_scale(tmp_path):
    poses = np.array([[0, 0, 0, 0, 0, 0, 1, 2.0]])
    with pytest.raises(ValueError, match="scale != 1"):
        write_g2o(tmp_path / "s.g2o", poses, np.zeros((0, 2), int), np.zeros((0, 8)))
    write_g2o(tmp_path / "s.g2o", poses, np.zeros((0, 2), int), np.zeros((0, 8)), drop_scale=True)
    assert read_g2o(tmp_path / "s.g2o").poses[0, 7] == 1.0


@pytest.mark.parametrize(
    "line, match",
    [
        ("VERTEX_SE3:QUAT 2 0 0 0 0 0 1", r":3: VERTEX_SE3:QUAT: expected id \+ 7 numbers"),
        ("VERTEX_SE3:QUAT 2 0 0 x 0 0 0 1", r":3: VERTEX_SE3:QUAT: not a number"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", r":3: VERTEX_SE3:QUAT: vertex id 0 defined twice"),
        ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1 0 0", r":3: EDGE_SE3:QUAT: expected 2 ids"),
        ("EDGE_SE3:QUAT 0 9 0 0 0 0 0 0 1 " + " ".join(["1"] * 21), r"undefined vertex 9"),
        ("VERTEX_SE3:QUAT 2 0 0 0 0 0 0 0", r":3: VERTEX_SE3:QUAT: zero quaternion"),
        ("VERTEX_SE3:QUAT 2 0 0 nan 0 0 0 1", r":3: VERTEX_SE3:QUAT: non-finite"),
    ],
)
def test_malformed_lines_name_the_line(tmp_path, line, match):
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n# comment\n" + line + "\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n")
    with pytest.raises(G2oError, match=match):
        read_g2o(path)


def test_unknown_records_warn_and_skip(tmp_path, logged_warning):
    path = tmp_path / "u.g2o"
    path.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_XY 1 0 0\nVERTEX_XY 2 0 0\nPARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n"
    )
    with logged_warning(r"skipped 2 record\(s\) of unknown type 'VERTEX_XY'"):
        g = read_g2o(path)
    assert g.poses.shape == (1, 8)
