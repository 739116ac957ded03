"""dit-slam's dense outputs are written atomically like the others: ``dense_map.ply`` under a temporary name then
renamed, ``keyframe_depth/`` filled as a temporary folder then renamed into place. A writer that fails mid-way
leaves nothing under the final name, and an earlier complete output stays whole until the new one is."""

import numpy as np
import pytest

from runtime.dense import fusion
from runtime.dense import map as dense_map
from runtime.io.ply import read_ply, read_ply_normals, read_ply_vertex
from tests.reliability.fakes import fail_on_call


def _listing(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def _maps(n, offset=0.0):
    shape = (4, 6)
    return [
        (f"kf{k:05d}", np.full(shape, 1.0 + k + offset, np.float32), np.full(shape, 0.1, np.float32)) for k in range(n)
    ]


def test_dense_map_ply_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    xyz, rgb = rng.normal(size=(50, 3)), rng.integers(0, 255, (50, 3), dtype=np.uint8)
    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    count = rng.integers(1, 5, 50)
    real = fusion.write_ply

    def half(path, *args):  # the header and some points, then Ctrl-C
        path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 50\n")
        raise KeyboardInterrupt

    final = tmp_path / "dense_map.ply"
    monkeypatch.setattr(fusion, "write_ply", half)
    with pytest.raises(KeyboardInterrupt):
        fusion.write_fused_map(final, xyz, rgb, nrm, count)
    assert _listing(tmp_path) == []  # neither a truncated dense_map.ply nor a temporary file
    monkeypatch.setattr(fusion, "write_ply", real)
    fusion.write_fused_map(final, xyz, rgb, nrm, count)
    whole = final.read_bytes()
    monkeypatch.setattr(fusion, "write_ply", half)
    with pytest.raises(KeyboardInterrupt):
        fusion.write_fused_map(tmp_path, xyz[:10], rgb[:10], nrm[:10], count[:10])  # into the folder: fails
    assert _listing(tmp_path) == ["dense_map.ply"] and final.read_bytes() == whole  # the earlier map is whole
    got, got_rgb = read_ply(final)
    np.testing.assert_allclose(got, xyz.astype(np.float32))
    assert (got_rgb == rgb).all()
    np.testing.assert_array_equal(read_ply_normals(final), nrm.astype(np.float32))
    np.testing.assert_array_equal(read_ply_vertex(final)["keyframes"], count)


def test_keyframe_depth_folder_is_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    real, calls = dense_map.save_keyframe_maps, []
    fails_at_the_second = fail_on_call(real, 2, calls, OSError("disk full"))
    folder = tmp_path / "keyframe_depth"
    monkeypatch.setattr(dense_map, "save_keyframe_maps", fails_at_the_second)
    with pytest.raises(OSError, match="disk full"):
        dense_map.write_keyframe_maps(folder, _maps(3))
    assert _listing(tmp_path) == []  # no folder with one keyframe's maps presented as the whole set
    monkeypatch.setattr(dense_map, "save_keyframe_maps", real)
    dense_map.write_keyframe_maps(folder, _maps(2))
    before = {name: (folder / name).read_bytes() for name in _listing(folder)}
    assert sorted(before) == [f"kf{k:05d}{s}" for k in range(2) for s in (".npz", "_depth.png", "_uncertainty.png")]
    calls.clear()
    monkeypatch.setattr(dense_map, "save_keyframe_maps", fails_at_the_second)
    with pytest.raises(OSError, match="disk full"):
        dense_map.write_keyframe_maps(folder, _maps(3, offset=5.0))
    assert _listing(tmp_path) == ["keyframe_depth", *(f"keyframe_depth/{n}" for n in sorted(before))]
    assert {name: (folder / name).read_bytes() for name in before} == before  # the earlier set is whole
    monkeypatch.setattr(dense_map, "save_keyframe_maps", real)
    dense_map.write_keyframe_maps(folder, _maps(3, offset=5.0)[1:])  # replaced as a whole: kf00000 is gone
    assert _listing(tmp_path) == ["keyframe_depth", *(f"keyframe_depth/{n}" for n in _listing(folder))]
    assert sorted({n.split(".")[0].split("_")[0] for n in _listing(folder)}) == ["kf00001", "kf00002"]
    with np.load(folder / "kf00002.npz") as z:
        assert float(z["depth"][0, 0]) == 8.0


def test_a_dense_run_whose_keyframe_maps_fail_leaves_no_dense_output(tiny_seq, tmp_path, monkeypatch):
    from runtime.dense import DenseConfig
    from runtime.io.euroc import read_euroc
    from runtime.run import run_sequence
    from tests.reliability.fakes import write_model

    calls = []
    monkeypatch.setattr(dense_map, "save_keyframe_maps", fail_on_call(dense_map.save_keyframe_maps, 3, calls))
    out = tmp_path / "o"
    cfg = DenseConfig(start_after_s=0.0)
    with pytest.raises(KeyboardInterrupt):
        run_sequence(read_euroc(tiny_seq), out, dense=cfg, model_dir=write_model(tmp_path / "m"), progress=False)
    assert len(calls) == 3
    names = _listing(out)
    assert "keyframe_depth" not in names and "dense_map.ply" not in names
    assert not [n for n in names if ".partial-" in n]  # no temporary file or folder left either


def test_a_new_run_clears_the_temporary_dense_outputs_of_a_killed_run(tmp_path):
    from runtime.outputs import prepare_run_dir

    out = tmp_path / "o"
    (out / ".keyframe_depth.partial-123-abcdef").mkdir(parents=True)  # what SIGKILL while writing leaves
    (out / ".keyframe_depth.partial-123-abcdef" / "kf00000.npz").write_bytes(b"half")
    (out / ".dense_map.partial-123-abcdef.ply").write_bytes(b"ply\n")
    (out / "notes.txt").write_text("mine")
    prepare_run_dir(out)
    assert _listing(out) == ["metrics.json", "notes.txt"]
