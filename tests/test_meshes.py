"""Mesh utilities and the ``meshes`` dataset: sampling, normalisation, OBJ/OFF/PLY/STL round trips,
the ShapeNetCore layout, deterministic splits, and clear errors for bad folders and files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from icpbench.core.errors import InputError
from icpbench.core.registry import datasets
from icpbench.datasets.meshes import (
    MeshFolderDataset,
    ObjectSampling,
    find_mesh_files,
    mesh_sample,
    model_key,
    normalize_vertices,
    read_mesh,
    sample_surface,
    split_of,
)

SMALL = dict(n_map_points=2000, n_scan_points=256)


def _box(sx: float = 1.0, sy: float = 0.5, sz: float = 0.25) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    m.compute_triangle_normals()  # the STL writer needs them
    return m


def _write(path: Path, mesh: o3d.geometry.TriangleMesh, ascii_: bool = True) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=ascii_ and path.suffix != ".stl")
    return path


def _truncate(path: Path, frac: float = 0.5) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * frac)])
    return path


# ---------------------------------------------------------------------------------------------
def test_registered():
    assert datasets.get("meshes") is MeshFolderDataset
    assert MeshFolderDataset.icp_preset == "objects"


def test_sample_surface_is_uniform_on_triangles_with_face_normals():
    # two triangles in z=0 (areas 0.5 and 1.5) and their normals (+z and -z by winding)
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0], [5, 0, 0]], float)
    F = np.array([[0, 1, 2], [3, 4, 5]])
    pts, nrm = sample_surface(V, F, 20_000, np.random.default_rng(0))
    in_first = pts[:, 0] <= 1.0
    assert abs(in_first.mean() - 0.25) < 0.015  # area weighting
    np.testing.assert_array_equal(nrm[in_first], np.tile([0.0, 0.0, 1.0], (in_first.sum(), 1)))
    np.testing.assert_array_equal(nrm[~in_first], np.tile([0.0, 0.0, -1.0], ((~in_first).sum(), 1)))
    a = pts[in_first]
    assert np.all(a[:, :2] >= 0) and np.all(a[:, 0] + a[:, 1] <= 1 + 1e-12)  # inside the triangle
    assert abs(a[:, 0].mean() - 1 / 3) < 0.01  # uniform: centroid of the triangle
    with pytest.raises(InputError, match="zero surface area"):
        sample_surface(V, np.array([[0, 1, 1]]), 10, np.random.default_rng(0))


@pytest.mark.parametrize("radius", ["3d", "xy"])
def test_normalize_vertices(radius):
    V = np.array([[1, 1, 1], [3, 1, 1], [1, 5, 1], [1, 1, 2], [100, 100, 100]], float)  # last unused
    F = np.array([[0, 1, 2], [0, 1, 3]])
    W = normalize_vertices(V, F, radius)
    used = W[:4]
    np.testing.assert_allclose(0.5 * (used.min(0) + used.max(0)), 0.0, atol=1e-12)
    r = np.linalg.norm(used if radius == "3d" else used[:, :2], axis=1)
    assert abs(r.max() - 1.0) < 1e-12
    with pytest.raises(InputError, match="zero"):
        normalize_vertices(np.zeros((3, 3)), np.array([[0, 1, 2]]))


def test_mesh_sample_of_a_box_lies_on_the_box():
    """noise 0: T_gt @ scan lies on the faces of the normalised box (analytic check of frames)."""
    m = _box(1.0, 0.6, 0.3)
    V, F = np.asarray(m.vertices), np.asarray(m.triangles)
    s = mesh_sample(V, F, sample_id="box", seed=[0, 1], sampling=ObjectSampling(noise_std=0.0, **SMALL))
    half = np.array([1.0, 0.6, 0.3]) / 2 / np.linalg.norm([0.5, 0.3, 0.15])
    q = s.scan.astype(np.float64) @ s.T_gt[:3, :3].T + s.T_gt[:3, 3]
    np.testing.assert_allclose(np.max(np.abs(q) / half, axis=1), 1.0, atol=1e-5)
    # and the map normals point out of the face the point lies on
    k = np.argmax(np.abs(s.map) / half, axis=1)
    expected = np.zeros_like(s.map)
    expected[np.arange(len(k)), k] = np.sign(s.map[np.arange(len(k)), k])
    np.testing.assert_allclose(s.map_normals, expected, atol=1e-6)
    s2 = mesh_sample(V, F, sample_id="box", seed=[0, 1], sampling=ObjectSampling(noise_std=0.0, **SMALL))
    np.testing.assert_array_equal(s.scan, s2.scan)


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply", ".stl"])
def test_round_trip_each_format(tmp_path, suffix):
    m = _box(1.0, 0.5, 0.25)
    V, F = read_mesh(_write(tmp_path / f"box{suffix}", m))
    assert F.shape == (12, 3)
    np.testing.assert_allclose(V.min(0), [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(V.max(0), [1.0, 0.5, 0.25], atol=1e-6)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    assert abs(area - 2 * (0.5 + 0.25 + 0.125)) < 1e-5
    if suffix == ".ply":  # binary PLY too
        V2, F2 = read_mesh(_write(tmp_path / "bin.ply", m, ascii_=False))
        assert F2.shape == (12, 3)


def _shapenet_tree(root: Path) -> None:
    tall_y = _box(0.2, 1.0, 0.3)  # y-up model: tall along y
    _write(root / "03001627" / "1a2b3c" / "models" / "model_normalized.obj", tall_y)
    _write(root / "03001627" / "0fff00" / "models" / "model_normalized.obj", _box(0.5, 0.5, 0.5))
    _write(root / "02691156" / "9d8e7f" / "model.obj", _box(1.0, 0.2, 0.1))  # ShapeNetCore v1
    _write(root / "loose.stl", _box(0.3, 0.2, 0.1))
    (root / "02691156" / "9d8e7f" / "notes.txt").write_text("not a mesh")


def test_shapenet_layout(tmp_path):
    _shapenet_tree(tmp_path)
    ds = MeshFolderDataset(tmp_path, split="all", seed=0, **SMALL)
    assert len(ds) == 4
    assert [e.key for e in ds.entries] == ["02691156/9d8e7f", "03001627/0fff00", "03001627/1a2b3c", "loose"]
    assert [e.category for e in ds.entries] == ["02691156", "03001627", "03001627", "uncategorized"]
    s = ds[2]
    assert s.id == "meshes/03001627/1a2b3c" and s.meta["category"] == "03001627"
    assert s.meta["up_axis"] == "y" and ds[3].meta["up_axis"] == "z"
    ext = s.map.max(0) - s.map.min(0)
    assert np.argmax(ext) == 2  # the y-up model now stands along z
    assert np.linalg.norm(s.map, axis=1).max() <= 1 + 1e-5
    raw = MeshFolderDataset(tmp_path, split="all", up_axis="z", **SMALL)[2]
    assert np.argmax(raw.map.max(0) - raw.map.min(0)) == 1
    assert {e.split for e in ds.entries} <= {"train", "test"}


def test_model_key_and_sorted_recursive_search(tmp_path):
    _shapenet_tree(tmp_path)
    files = find_mesh_files(tmp_path)
    rel = [f.relative_to(tmp_path).as_posix() for f in files]
    assert rel == sorted(rel) and len(rel) == 4
    assert model_key(tmp_path, files[0]) == "02691156/9d8e7f"
    assert model_key(tmp_path, tmp_path / "a" / "chair.OBJ") == "a/chair"


def test_split_is_a_deterministic_hash_of_the_model_id(tmp_path):
    keys = [f"0300{i % 7}/model{i:04d}" for i in range(2000)]
    splits = [split_of(k, 0.2) for k in keys]
    assert splits == [split_of(k, 0.2) for k in keys]
    assert abs(splits.count("test") / len(keys) - 0.2) < 0.03
    assert all(split_of(k, 0.0) == "train" for k in keys[:50])
    assert all(split_of(k, 1.0) == "test" for k in keys[:50])
    for i in range(12):
        _write(tmp_path / "cat" / f"m{i:02d}.off", _box(1.0 + i * 0.1, 0.5, 0.3))
    test = MeshFolderDataset(tmp_path, split="test", test_fraction=0.5, seed=0, **SMALL)
    train = MeshFolderDataset(tmp_path, split="train", test_fraction=0.5, seed=9, **SMALL)
    k_test, k_train = {e.key for e in test.entries}, {e.key for e in train.entries}
    assert not k_test & k_train and len(k_test | k_train) == 12
    assert len(test) > 0 and len(train) > 0
    assert len(MeshFolderDataset(tmp_path, split="test", test_fraction=0.0, **SMALL)) == 0
    assert len(MeshFolderDataset(tmp_path, split="train", n_samples=3, **SMALL)) == 3


def test_samples_are_deterministic_and_stable_when_files_are_added(tmp_path):
    _write(tmp_path / "b.ply", _box(0.4, 0.3, 0.2))
    a1 = MeshFolderDataset(tmp_path, split="all", seed=3, **SMALL)[0]
    a2 = MeshFolderDataset(tmp_path, split="all", seed=3, **SMALL)[0]
    np.testing.assert_array_equal(a1.scan, a2.scan)
    np.testing.assert_array_equal(a1.T_gt, a2.T_gt)
    _write(tmp_path / "a.ply", _box(0.4, 0.6, 0.2))  # sorts before b.ply
    ds = MeshFolderDataset(tmp_path, split="all", seed=3, **SMALL)
    assert ds[1].id == a1.id
    np.testing.assert_array_equal(ds[1].scan, a1.scan)
    other_seed = MeshFolderDataset(tmp_path, split="all", seed=4, **SMALL)[1]
    assert not np.allclose(other_seed.scan, a1.scan)


def test_folder_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        MeshFolderDataset(tmp_path / "nope")
    with pytest.raises(InputError, match="no mesh files"):
        MeshFolderDataset(tmp_path)
    (tmp_path / "readme.txt").write_text("hello")
    with pytest.raises(InputError, match="no mesh files"):
        MeshFolderDataset(tmp_path)
    with pytest.raises(InputError, match="not a folder"):
        MeshFolderDataset(tmp_path / "readme.txt")
    with pytest.raises(InputError, match="root"):
        MeshFolderDataset()
    (tmp_path / "empty.obj").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty\.obj is empty"):  # when its sample is read
        MeshFolderDataset(tmp_path, split="all")[0]
    with pytest.raises(InputError, match="test_fraction"):
        MeshFolderDataset(tmp_path, test_fraction=2.0)


@pytest.mark.parametrize("name", ["t.off", "t.ply", "t.stl", "t.obj"])
def test_truncated_files_raise_naming_the_file(tmp_path, name):
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, 10)
    sphere.compute_triangle_normals()
    path = _write(tmp_path / name, sphere)
    assert read_mesh(path)[1].shape == (360, 3)
    # cut in the face section (OBJ: in the middle of a face line)
    data = path.read_bytes()
    cut = data.rfind(b"\nf ") + 5 if name.endswith(".obj") else int(len(data) * 0.8)
    path.write_bytes(data[:cut])
    with pytest.raises(InputError, match=rf"{name}.*(truncated|no triangles)"):
        read_mesh(path)


def test_corrupt_files_raise(tmp_path):
    garbage = tmp_path / "junk.obj"
    garbage.write_bytes(b"\x00\x01binary junk\xff" * 10)
    with pytest.raises(InputError, match="junk.obj gave no triangles"):
        read_mesh(garbage)
    cloud = tmp_path / "cloud.ply"
    cloud.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match="no triangles"):
        read_mesh(cloud)
    bad_off = tmp_path / "bad.off"
    bad_off.write_text("NOT AN OFF\n")
    with pytest.raises(InputError, match="OFF keyword"):
        read_mesh(bad_off)
    with pytest.raises(InputError, match="does not exist"):
        read_mesh(tmp_path / "missing.stl")
    with pytest.raises(InputError, match="unsupported"):
        read_mesh(tmp_path / "model.fbx")


def test_dataset_reports_the_bad_file_on_access(tmp_path):
    _write(tmp_path / "good.off", _box())
    _truncate(_write(tmp_path / "zz_bad.ply", _box(), ascii_=False), 0.6)
    ds = MeshFolderDataset(tmp_path, split="all", **SMALL)
    assert len(ds) == 2 and ds[0].scan.shape == (256, 3)
    with pytest.raises(InputError, match=r"zz_bad\.ply"):
        ds[1]
