"""The PLY format module (dss.ply) and the readers built on it: headers that miscount, doubles,
one bounding-box diagonal (fast)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from dss.pointcloud import PointCloud, PointCloudError, load_ply, save_ply


def _binary(path, points, declared: int | None = None, kind: str = "float"):
    rows = np.ascontiguousarray(points, "<f4" if kind == "float" else "<f8")
    n = len(rows) if declared is None else declared
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
              + "".join(f"property {kind} {c}\n" for c in "xyz") + "end_header\n")
    path.write_bytes(header.encode() + rows.tobytes())
    return path


def test_a_header_that_declares_fewer_vertices_than_the_file_holds_is_reported(tmp_path, caplog):
    """Binary and ASCII: the rows beyond the declared count are reported (nan_policy=drop reads the
    declared ones) and refused under nan_policy=raise."""
    p = np.random.default_rng(0).normal(size=(1000, 3))
    short = _binary(tmp_path / "under.ply", p, declared=600)
    with caplog.at_level(logging.WARNING):
        c = load_ply(short, compute_normals=False)
    assert len(c) == 600
    assert "under.ply: the file holds" in caplog.text and "400 vertex rows" in caplog.text
    with pytest.raises(PointCloudError, match=r"under\.ply: the file holds .*400 vertex rows.*after the 600 vertices "
                                              r"its header declares.*refusing \(nan_policy='raise'\)"):
        load_ply(short, nan_policy="raise", compute_normals=False)

    save_ply(tmp_path / "a.ply", PointCloud(torch.from_numpy(p).float()), ascii=True)
    text = (tmp_path / "a.ply").read_text().replace("element vertex 1000", "element vertex 990")
    (tmp_path / "under_ascii.ply").write_text(text)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert len(load_ply(tmp_path / "under_ascii.ply", compute_normals=False)) == 990
    assert "10 more rows" in caplog.text
    with pytest.raises(PointCloudError, match=r"under_ascii\.ply: the file holds 10 more rows"):
        load_ply(tmp_path / "under_ascii.ply", nan_policy="raise", compute_normals=False)
    # an exact file says nothing
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        load_ply(_binary(tmp_path / "exact.ply", p), nan_policy="raise", compute_normals=False)
    assert "holds" not in caplog.text


def test_the_ply_module_reads_and_writes_what_pointcloud_reexports(tmp_path):
    """dss.ply holds the format; dss.pointcloud keeps exporting the names other code imports."""
    import dss.ply as ply
    from dss import pointcloud

    for name in ("read_ply_header", "read_ply_vertices", "read_ply_triangles", "PlyHeader", "PointCloudError"):
        assert getattr(pointcloud, name) is getattr(ply, name)
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) + 1e7
    f = np.array([[0, 1, 2], [0, 1, 3]])
    path = ply.write_ply(tmp_path / "mesh.ply", v, faces=f, double=True)
    vv, ff = ply.read_ply_triangles(path)
    assert np.array_equal(vv, v) and np.array_equal(ff, f)  # doubles keep 1e7 + 1 exact
    arrays = ply.read_ply_arrays(path)
    assert arrays.coordinates == "double" and arrays.points.dtype == np.float64


def test_one_bbox_diagonal_refuses_an_empty_point_set():
    from dss import regularizers
    from dss.pointcloud import bbox_diagonal

    assert regularizers.bbox_diagonal is bbox_diagonal
    p = torch.tensor([[0.0, 0, 0], [3, 4, 0]])
    assert bbox_diagonal(p) == pytest.approx(5.0) and bbox_diagonal(p.numpy()) == pytest.approx(5.0)
    far = np.array([[1e8, 0, 0], [1e8 + 3, 4, 0]])  # float64 stays float64: 3 is not lost at 1e8
    assert bbox_diagonal(far) == 5.0
    for empty in (torch.zeros(0, 3), np.zeros((0, 3))):
        with pytest.raises(PointCloudError, match="bounding box of an empty point set"):
            bbox_diagonal(empty)
    with pytest.raises(ValueError, match="bounding box of an empty point set"):
        regularizers.bandwidth_for(torch.zeros(0, 3))
