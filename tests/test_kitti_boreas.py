"""KITTI and Boreas loaders: tiny datasets written in each layout inside the test, read back.

The "world" is the synthetic scene of :mod:`icpbench.datasets.synthetic_scene` (ground, boxes, poles, exact
surface samples); each frame is a fresh set of surface samples within 30 m of the sensor,
written in the sensor frame with the layout's pose conventions.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from icpbench.core.errors import InputError
from icpbench.datasets import submaps as sm
from icpbench.datasets.boreas import BoreasDataset, pose_from_row
from icpbench.datasets.kitti import KittiDataset
from icpbench.datasets.synthetic_scene import scene_points

torch.set_num_threads(1)

N_FRAMES = 10
SENSOR_Z = 1.7
MARKER_W = np.array([10.0, 4.0, 16.0])  # a blob (above every object) seen only in KITTI frame 4


def _world(frame_seed: int, n: int = 30_000) -> np.ndarray:
    pts, _ = scene_points(n, seed=0, extent_m=60.0, sampling_seed=100 + frame_seed)
    return pts.astype(np.float64)


def _sensor_poses(heading: float, lateral: float = 0.0, spacing: float = 1.5) -> np.ndarray:
    """(F, 4, 4) world poses of a sensor driving straight along ``heading`` (rad)."""
    f = np.array([np.cos(heading), np.sin(heading)])
    left = np.array([-f[1], f[0]])
    out = []
    for k in range(N_FRAMES):
        xy = np.array([-8.0, -3.0]) + k * spacing * f + lateral * left
        out.append(sm.pose_2d(xy[0], xy[1], heading, SENSOR_Z))
    return np.stack(out)


def _scan(T_w_s: np.ndarray, frame_seed: int) -> np.ndarray:
    pw = _world(frame_seed)
    pw = pw[np.linalg.norm(pw[:, :2] - T_w_s[:2, 3], axis=1) < 30.0]
    return sm.transform(sm.inv(T_w_s), pw)


def _aligned_residual(sample) -> tuple[float, float]:
    """Median nearest-neighbour distance and median |point-to-plane residual| at T_gt."""
    q = sm.transform(sample.T_gt, sample.scan)
    d, i = cKDTree(sample.map).query(q)
    r = np.abs(((q - sample.map[i]) * sample.map_normals[i]).sum(1))
    return float(np.median(d)), float(np.median(r[d < 1.0]))


# ---------------------------------------------------------------------------------------------
# KITTI
# ---------------------------------------------------------------------------------------------
# A KITTI-like velodyne-to-camera transform: x_cam = -y_velo, y_cam = -z_velo, z_cam = x_velo.
TR = np.array([[0.0, -1.0, 0.0, 0.02], [0.0, 0.0, -1.0, -0.07], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1]])


def _write_kitti(root, T_w_s):
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    (root / "poses").mkdir()
    for k, T in enumerate(T_w_s):
        pts = _scan(T, k)
        if k == 4:
            blob = MARKER_W + np.random.default_rng(0).normal(0, 0.1, (300, 3))
            pts = np.vstack([pts, sm.transform(sm.inv(T), blob)])
        arr = np.c_[pts, np.full(len(pts), 0.5)].astype("<f4")
        arr.tofile(seq / "velodyne" / f"{k:06d}.bin")
    lines = [f"P{i}: " + " ".join(["0.0"] * 12) for i in range(4)]
    lines.append("Tr: " + " ".join(f"{v:.12e}" for v in TR[:3].ravel()))
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    T_v0 = sm.inv(T_w_s[0]) @ T_w_s  # T_velo0_velo(i)
    P = TR @ T_v0 @ np.linalg.inv(TR)  # camera-0 poses, as KITTI stores them
    (root / "poses" / "00.txt").write_text(
        "\n".join(" ".join(f"{v:.12e}" for v in T[:3].ravel()) for T in P) + "\n")
    return seq, T_v0


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti")
    T_w_s = _sensor_poses(0.3)
    seq, T_v0 = _write_kitti(root, T_w_s)
    ds = KittiDataset(root, "00", stride=2, window=3, n_points=4000,
                      cache_dir=tmp_path_factory.mktemp("kitti-cache"))
    return root, seq, T_v0, ds


def test_kitti_poses_round_trip(kitti):
    _, _, T_v0, ds = kitti
    assert len(ds) == N_FRAMES // 2
    assert np.allclose(ds.T_velo, T_v0, atol=1e-9)  # inv(Tr) @ P @ Tr undoes the camera frame


def test_kitti_samples_align_and_exclude_their_own_frame(kitti):
    _, _, T_v0, ds = kitti
    s = ds[2]  # frame 4, the one with the marker blob
    s.validate()
    assert s.id == "kitti/00/000004" and s.scan.shape == (4000, 3)
    assert s.meta["frame"] == 4 and s.meta["n_map_frames"] == 6
    assert np.allclose([s.meta["x"], s.meta["y"]], T_v0[4][:2, 3])
    med_d, med_r = _aligned_residual(s)
    assert med_d < 0.5 and med_r < 0.02
    # the submap is in frame 4's lidar frame and does not contain frame 4's own points
    marker = sm.transform(sm.inv(T_v0[4]) @ sm.inv(_sensor_poses(0.3)[0]), MARKER_W[None])[0]
    d_marker, _ = cKDTree(s.map).query(marker)
    assert d_marker > 1.0
    # offset protocol: |t| <= 0.3 m per axis, |angles| <= 10 deg, T_init = identity
    off = np.linalg.inv(s.T_gt)
    assert np.all(np.abs(off[:3, 3]) <= 0.3 + 1e-9) and np.array_equal(s.T_init, np.eye(4))
    assert np.all(np.abs(Rotation.from_matrix(off[:3, :3]).as_euler("xyz", degrees=True)) <= 10 + 1e-6)


def test_kitti_cache_and_icp(kitti, tmp_path):
    from icpbench.core.se3 import pose_error_components
    from icpbench.core.types import Batch
    from icpbench.targets.p2plane import PointToPlaneICP

    _, _, _, ds = kitti
    a = ds[1]
    assert list(ds.cache_root.glob("*.npz"))
    b = KittiDataset(kitti[0], "00", stride=2, window=3, n_points=4000, cache_dir=ds.cache_root.parents[1])[1]
    assert np.array_equal(a.scan, b.scan) and np.array_equal(a.map, b.map)
    batch = Batch.from_samples([ds[0], ds[1], ds[3]])
    reg = PointToPlaneICP("lidar").register(batch.scans, batch.maps, batch.T_init)
    err = pose_error_components(reg.T, batch.T_gt)
    assert bool(reg.converged.all()) and float(err["trans_err"].max()) < 0.05


def test_kitti_input_errors(kitti, tmp_path):
    root, seq, _, _ = kitti
    with pytest.raises(InputError, match="velodyne"):
        KittiDataset(tmp_path, "00")
    # malformed pose line
    bad = tmp_path / "bad"
    (bad / "sequences" / "00" / "velodyne").mkdir(parents=True)
    (bad / "poses").mkdir()
    for f in (seq / "velodyne").glob("*.bin"):
        (bad / "sequences" / "00" / "velodyne" / f.name).write_bytes(f.read_bytes())
    (bad / "sequences" / "00" / "calib.txt").write_text((seq / "calib.txt").read_text())
    lines = (root / "poses" / "00.txt").read_text().splitlines()
    (bad / "poses" / "00.txt").write_text("\n".join(lines[:3] + [" ".join(lines[3].split()[:11])]
                                                    + lines[4:]))
    with pytest.raises(InputError, match=r"00.txt:4: a pose line needs 12"):
        KittiDataset(bad, "00")
    (bad / "poses" / "00.txt").write_text("\n".join(lines))
    (bad / "sequences" / "00" / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match="no 'Tr:' line"):
        KittiDataset(bad, "00")
    # a truncated scan is reported when it is read
    (bad / "sequences" / "00" / "calib.txt").write_text((seq / "calib.txt").read_text())
    f0 = bad / "sequences" / "00" / "velodyne" / "000000.bin"
    f0.write_bytes(f0.read_bytes()[:-6])
    ds = KittiDataset(bad, "00", stride=5, window=2, cache_dir=tmp_path / "c")
    with pytest.raises(InputError, match="not a multiple of 16"):
        ds[0]


def test_show_dataset_for_a_loaded_dataset(kitti, tmp_path):
    from icpbench.analysis.dataset_figures import show_dataset

    paths = show_dataset(kitti[3], tmp_path)
    assert [p.name for p in paths] == ["kitti_route.png", "kitti_scan_on_submap.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)


# ---------------------------------------------------------------------------------------------
# Boreas
# ---------------------------------------------------------------------------------------------
GAMMA = -np.pi / 2  # the lidar is mounted turned: its +y axis points forward
SPEED = 10.0  # m/s


def _devkit_yaw_for(rot_z: float) -> float:
    """The ``yaw`` column giving ``R_enu_lidar = Rz(rot_z)`` under the devkit formula
    ``roll(r) @ pitch(p) @ yaw(y)`` with roll = pitch = 0 (``yaw(y) = Rz(-y)``)."""
    return -rot_z


def _write_boreas_drive(root, name, heading, lateral, t0_us, frame_offset, skew=True):
    folder = root / name
    (folder / "lidar").mkdir(parents=True)
    (folder / "applanix").mkdir()
    (folder / "calib").mkdir()
    T_al = np.eye(4)
    T_al[:3, :3] = Rotation.from_euler("z", np.pi / 2 + GAMMA).as_matrix()
    np.savetxt(folder / "calib" / "T_applanix_lidar.txt", T_al)
    T_w_V = _sensor_poses(heading, lateral, spacing=1.0)  # 10 Hz at 10 m/s
    T_V_L = sm.pose_2d(0, 0, GAMMA)
    rows = ["GPSTime,easting,northing,altitude,vel_east,vel_north,vel_up,roll,pitch,heading,"
            "angvel_z,angvel_y,angvel_x"]
    rng = np.random.default_rng(frame_offset)
    for k, T in enumerate(T_w_V):
        t_us = t0_us + k * 100_000
        T_w_L = T @ T_V_L
        pw = _world(frame_offset + k)
        pw = pw[np.linalg.norm(pw[:, :2] - T[:2, 3], axis=1) < 30.0]
        t = rng.uniform(-0.05, 0.05, len(pw)) if skew else np.zeros(len(pw))
        v_enu = SPEED * np.array([np.cos(heading), np.sin(heading), 0.0])
        v_L = T_w_L[:3, :3].T @ v_enu
        # a point measured at time t by the sensor at pose T_w_L(t) = T_w_L @ [I, v_L t]
        pl = sm.transform(sm.inv(T_w_L), pw) - t[:, None] * v_L
        arr = np.c_[pl, np.full(len(pl), 10.0), np.zeros(len(pl)), t].astype("<f4")
        arr.tofile(folder / "lidar" / f"{t_us}.bin")
        yaw = _devkit_yaw_for(heading + GAMMA)
        rows.append(",".join(str(v) for v in [t_us, *T_w_L[:3, 3], *v_enu, 0.0, 0.0, yaw, 0.0, 0.0, 0.0]))
    (folder / "applanix" / "lidar_poses.csv").write_text("\n".join(rows) + "\n")
    return T_w_V


@pytest.fixture(scope="module")
def boreas(tmp_path_factory):
    root = tmp_path_factory.mktemp("boreas")
    teach = _write_boreas_drive(root, "boreas-2020-11-26-13-58", 0.4, 0.0, 1_606_417_230_000_000, 0)
    rep = _write_boreas_drive(root, "boreas-2021-01-26-10-59", 0.4, 0.4, 1_611_676_000_000_000, 50)
    cache = tmp_path_factory.mktemp("boreas-cache")
    ds = BoreasDataset(root, sample_spacing_m=1.9, keyframe_spacing_m=0.9, submap_window_m=4.0,
                       n_points=4000, cache_dir=cache)
    return root, teach, rep, ds, cache


def test_boreas_pose_row_follows_the_devkit():
    row = np.zeros(13)
    row[1:4] = [1.0, 2.0, 3.0]
    row[9] = 0.3
    T = pose_from_row(row)
    assert np.allclose(T[:3, :3], Rotation.from_euler("z", -0.3).as_matrix())
    assert np.allclose(T[:3, 3], [1, 2, 3])
    row[7:10] = [0.1, -0.2, 0.3]
    R = pose_from_row(row)[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)


def test_boreas_samples_in_the_vehicle_frame(boreas):
    _, teach, rep, ds, _ = boreas
    assert len(ds) == N_FRAMES // 2
    s = ds[1]
    s.validate()
    assert s.id.startswith("boreas/boreas-2021-01-26-10-59/") and s.meta["pass"] == "boreas-2021-01-26-10-59"
    k = s.meta["frame"]
    assert np.allclose(ds.repeats[s.meta["pass"]].T_enu_V, rep, atol=1e-4)
    assert np.allclose([s.meta["x"], s.meta["y"]], rep[k][:2, 3], atol=1e-4)
    # x forward: the next repeat position lies ahead on the x axis of the vehicle frame
    ahead = sm.transform(sm.inv(rep[k]), rep[k + 1][:3, 3][None])[0]
    assert ahead[0] > 0.9 and abs(ahead[1]) < 1e-3
    med_d, med_r = _aligned_residual(s)
    assert med_d < 0.5 and med_r < 0.02
    # the submap comes from the teach drive, 0.4 m to the right of the repeat drive
    assert s.meta["n_map_frames"] >= 5


def test_boreas_deskew_matters(boreas, tmp_path):
    root, _, _, ds, _ = boreas
    raw = BoreasDataset(root, sample_spacing_m=1.9, keyframe_spacing_m=0.9, submap_window_m=4.0,
                        n_points=4000, deskew=False, cache_dir=tmp_path)
    _, r_deskewed = _aligned_residual(ds[2])
    _, r_raw = _aligned_residual(raw[2])
    assert r_deskewed < 0.02 and r_raw > 2 * r_deskewed


def test_boreas_input_errors(boreas, tmp_path):
    root, *_ = boreas
    with pytest.raises(InputError, match="missing Boreas sequence folder"):
        BoreasDataset(root, teach="boreas-1999-01-01-00-00", repeats=["boreas-2021-01-26-10-59"])
    bad = tmp_path / "b"
    for name in ("boreas-2020-11-26-13-58", "boreas-2021-01-26-10-59"):
        for f in (root / name).rglob("*"):
            if f.is_file():
                dst = bad / name / f.relative_to(root / name)
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.write_bytes(f.read_bytes())
    csv = bad / "boreas-2021-01-26-10-59" / "applanix" / "lidar_poses.csv"
    good = csv.read_text()
    lines = good.splitlines()
    csv.write_text("\n".join(lines[:2] + [",".join(lines[2].split(",")[:10])] + lines[3:]))
    with pytest.raises(InputError, match=r"lidar_poses.csv:3: a pose row needs 13"):
        BoreasDataset(bad)
    csv.write_text("\n".join(lines[:2] + [lines[2].replace(",", ",x", 1)] + lines[3:]))
    with pytest.raises(InputError, match="non-numeric"):
        BoreasDataset(bad)
    csv.write_text(good)
    (bad / "boreas-2020-11-26-13-58" / "calib" / "T_applanix_lidar.txt").unlink()
    with pytest.raises(InputError, match="T_applanix_lidar"):
        BoreasDataset(bad)
    np.savetxt(bad / "boreas-2020-11-26-13-58" / "calib" / "T_applanix_lidar.txt", np.eye(4))
    scan = sorted((bad / "boreas-2021-01-26-10-59" / "lidar").glob("*.bin"))[0]
    scan.write_bytes(scan.read_bytes()[:-10])
    ds = BoreasDataset(bad, sample_spacing_m=1.9, cache_dir=tmp_path / "c")
    with pytest.raises(InputError, match="not a multiple of 24"):
        ds[0]
    (bad / "boreas-2021-01-26-10-59" / "applanix" / "lidar_poses.csv").unlink()
    with pytest.raises(InputError, match="missing Boreas pose file"):
        BoreasDataset(bad)


@pytest.mark.parametrize("content, needle", [(b"", r"is empty \(0 bytes\)"),
                                             ("nan", r"corrupt: 1 point\(s\) have NaN")])
def test_boreas_empty_or_nan_scan_is_named(tmp_path, content, needle):
    from icpbench.datasets.boreas import read_boreas_bin

    path = tmp_path / "1600000000000000.bin"
    if content == "nan":
        rec = np.ones((5, 6), dtype="<f4")
        rec[2, 1] = np.nan
        rec.tofile(path)
    else:
        path.write_bytes(content)
    with pytest.raises(InputError, match=needle):
        read_boreas_bin(path)
