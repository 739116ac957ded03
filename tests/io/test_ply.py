"""PLY writer/reader: binary round trips, ascii and big-endian reading, errors."""

from __future__ import annotations

import re

import numpy as np
import pytest

from runtime.io import PlyFormatError, read_ply, read_ply_faces, write_ply


def _cloud(n=100, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(scale=3, size=(n, 3)), rng.integers(0, 256, (n, 3), dtype=np.uint8)


def test_round_trip_xyz(tmp_path):
    xyz, _ = _cloud()
    p = write_ply(tmp_path / "d" / "map.ply", xyz)
    data = p.read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode()
    assert "format binary_little_endian 1.0" in header and "element vertex 100" in header
    assert "red" not in header
    assert len(data) - len(header) == 100 * 12  # float32 x, y, z
    got, rgb = read_ply(p)
    assert rgb is None and got.dtype == np.float64
    np.testing.assert_array_equal(got, xyz.astype(np.float32))


def test_round_trip_xyz_rgb(tmp_path):
    xyz, rgb = _cloud()
    p = write_ply(tmp_path / "map.ply", xyz, rgb)
    assert p.stat().st_size - p.read_bytes().index(b"end_header\n") - 11 == 100 * 15
    got, got_rgb = read_ply(p)
    np.testing.assert_array_equal(got, xyz.astype(np.float32))
    assert got_rgb.dtype == np.uint8
    np.testing.assert_array_equal(got_rgb, rgb)
    # first vertex bytes: little-endian float32 x, y, z then r, g, b
    raw = p.read_bytes()[p.read_bytes().index(b"end_header\n") + 11 :][:15]
    np.testing.assert_array_equal(np.frombuffer(raw[:12], "<f4"), xyz[0].astype(np.float32))
    assert tuple(raw[12:15]) == tuple(rgb[0])


def test_empty_cloud(tmp_path):
    got, rgb = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8)))
    assert got.shape == (0, 3) and rgb.shape == (0, 3)


def test_reads_ascii_with_faces(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text(
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float nx\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 1 255 0 0\n1.5 0 0 1 0 255 0\n0 -2 3e-1 1 0 0 255\n3 0 1 2\n"
    )
    xyz, rgb = read_ply(p)
    np.testing.assert_array_equal(xyz, [[0, 0, 0], [1.5, 0, 0], [0, -2, 0.3]])
    np.testing.assert_array_equal(rgb, [[255, 0, 0], [0, 255, 0], [0, 0, 255]])
    np.testing.assert_array_equal(read_ply_faces(p), [[0, 1, 2]])
    p.write_text(p.read_text().replace("3 0 1 2", "4 0 1 2 0"))  # a quad
    with pytest.raises(PlyFormatError, match="triangle"):
        read_ply_faces(p)


def test_faces_round_trip_binary_and_big_endian(tmp_path):
    xyz, rgb = _cloud(5)
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 0, 1]])
    p = write_ply(tmp_path / "m.ply", xyz, rgb, faces=faces)
    np.testing.assert_array_equal(read_ply_faces(p), faces)
    np.testing.assert_array_equal(read_ply(p)[1], rgb)  # the vertices read as before
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    )
    header += "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    rec = np.array([(3, [2, 1, 0])], dtype=[("n", "u1"), ("i", ">i4", (3,))])
    q = tmp_path / "be.ply"
    q.write_bytes(header.encode() + np.zeros((3, 3), ">f4").tobytes() + rec.tobytes())
    np.testing.assert_array_equal(read_ply_faces(q), [[2, 1, 0]])
    q.write_bytes(header.encode() + np.zeros((3, 3), ">f4").tobytes() + rec.tobytes()[:-2])
    with pytest.raises(PlyFormatError, match="truncated face data"):
        read_ply_faces(q)


def test_reads_big_endian_doubles_after_another_element(tmp_path):
    xyz, _ = _cloud(7, seed=2)
    p = tmp_path / "b.ply"
    header = (
        "ply\nformat binary_big_endian 1.0\nelement camera 2\nproperty float32 fx\nproperty int32 id\n"
        "element vertex 7\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
    )
    cams = np.zeros(2, dtype=[("fx", ">f4"), ("id", ">i4")])
    p.write_bytes(header.encode() + cams.tobytes() + xyz.astype(">f8").tobytes())
    got, rgb = read_ply(p)
    assert rgb is None
    np.testing.assert_array_equal(got, xyz)  # doubles kept exactly


def test_writer_checks_inputs(tmp_path):
    xyz, rgb = _cloud(5)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        write_ply(tmp_path / "x.ply", xyz[:, :2])
    bad = xyz.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="1 non-finite points .*index 3"):
        write_ply(tmp_path / "x.ply", bad)
    with pytest.raises(ValueError, match="uint8"):
        write_ply(tmp_path / "x.ply", xyz, rgb.astype(np.float32))
    with pytest.raises(ValueError, match="rgb must have shape"):
        write_ply(tmp_path / "x.ply", xyz, rgb[:4])


@pytest.mark.parametrize(
    "content,fragment",
    [
        (b"hello\n", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n", "no 'end_header'"),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no 'vertex' element"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n", "no property 'y'"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n" + b"\0" * 20,
            "truncated vertex data",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n0 0 0\n",
            "expected 2 vertex lines",
        ),
    ],
)
def test_bad_files_name_the_file(tmp_path, content, fragment):
    p = tmp_path / "bad.ply"
    p.write_bytes(content)
    with pytest.raises(PlyFormatError, match=re.escape(str(p)) + ".*" + re.escape(fragment)):
        read_ply(p)


def test_missing_file(tmp_path):
    with pytest.raises(PlyFormatError, match="missing file"):
        read_ply(tmp_path / "none.ply")


def test_round_trip_normals_and_scalars(tmp_path):
    from runtime.io import read_ply_normals, read_ply_vertex

    xyz, rgb = _cloud(50)
    nrm = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    count = np.arange(50, dtype=np.uint16)
    p = write_ply(tmp_path / "n.ply", xyz, rgb, normals=nrm, scalars={"keyframes": count})
    got, got_rgb = read_ply(p)
    np.testing.assert_array_equal(got, xyz.astype(np.float32))
    np.testing.assert_array_equal(got_rgb, rgb)
    np.testing.assert_array_equal(read_ply_normals(p), nrm.astype(np.float32))
    v = read_ply_vertex(p)
    assert v["keyframes"].dtype == np.uint16 and (v["keyframes"] == count).all()
    assert read_ply_normals(write_ply(tmp_path / "plain.ply", xyz)) is None
    with pytest.raises(ValueError, match="scalar 'k' must be"):
        write_ply(tmp_path / "bad.ply", xyz, scalars={"k": np.zeros(50, np.float64)})
    with pytest.raises(ValueError, match="normals has 1 non-finite rows"):
        bad = nrm.copy()
        bad[3, 0] = np.nan
        write_ply(tmp_path / "bad.ply", xyz, normals=bad)
