"""``boreas``: teach-and-repeat localisation on drives in the Boreas layout.

Layout (Burnett et al., "Boreas: A Multi-Season Autonomous Driving Dataset", IJRR 2023; the
pyboreas devkit's ``DATA_REFERENCE.md``)::

    <root>/boreas-YYYY-MM-DD-HH-MM/lidar/<t_us>.bin          float32 x, y, z, intensity, ring, t
                                                             (24 bytes per point, lidar frame;
                                                             t in s relative to the file time)
    <root>/boreas-YYYY-MM-DD-HH-MM/applanix/lidar_poses.csv  header, then one row per lidar file:
        t_us, x, y, z, vx, vy, vz, roll, pitch, yaw, wz, wy, wx
        (position/velocity in the fixed ENU frame; rates in the sensor frame)
    <root>/boreas-YYYY-MM-DD-HH-MM/calib/T_applanix_lidar.txt  4x4 (applanix: x right, y forward)

Pose of a row, as in the devkit: ``T_enu_lidar = [[C, (x, y, z)], [0, 1]]`` with
``C = roll(r) @ pitch(p) @ yaw(y)`` built from the devkit's elementary rotations
(``yaw(y) = [[c, s, 0], [-s, c, 0], [0, 0, 1]]`` etc.).

Frames: samples use a *vehicle* frame V, the lidar frame turned about its z axis so that x points
forward (forward in the lidar frame is ``R_applanix_lidar^T e_y``), so pose errors are
longitudinal/lateral (docs/architecture.md, "Frames, units and pose error").

Protocol (Zhang et al., ICRA 2025, §IV-A): the *teach* drive gives keyframes every
``keyframe_spacing_m``; each *repeat* drive gives a live scan every ``sample_spacing_m`` travelled.
A live scan's submap accumulates the teach keyframes within ``submap_window_m`` (along the teach
trajectory) of the teach keyframe nearest to it, in the live scan's true vehicle frame (the
ground-truth poses play the part of the paper's GNSS alignment), voxel-averaged with PCA normals.
Then the random offset of :func:`~icpbench.datasets.submaps.make_sample`. Scans are deskewed
(``deskew=True``) with the constant body rate of their pose row, to the file time.
Train/test separation is by choosing repeat drives.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from scipy.spatial import cKDTree

from icpbench.core.errors import InputError
from icpbench.core.filenames import plain_name
from icpbench.core.registry import Range
from icpbench.core.se3 import se3_exp
from icpbench.core.types import Sample
from icpbench.datasets import submaps as sm
from icpbench.datasets.base import Dataset, Split, default_cache_dir

FORMAT_VERSION = 1
DEFAULT_TEACH = "boreas-2020-11-26-13-58"  # the map sequence of the Boreas localisation benchmark


def _rot_devkit(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``roll(r) @ pitch(p) @ yaw(y)`` with the devkit's elementary rotation matrices."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    R_r = np.array([[1, 0, 0], [0, cr, sr], [0, -sr, cr]])
    R_p = np.array([[cp, 0, -sp], [0, 1, 0], [sp, 0, cp]])
    R_y = np.array([[cy, sy, 0], [-sy, cy, 0], [0, 0, 1]])
    return R_r @ R_p @ R_y


def pose_from_row(row: np.ndarray) -> np.ndarray:
    """T_enu_sensor (4, 4) of one pose row ``t_us, x, y, z, vx, vy, vz, roll, pitch, yaw, ...``."""
    T = np.eye(4)
    T[:3, :3] = _rot_devkit(row[7], row[8], row[9])
    T[:3, 3] = row[1:4]
    return T


def read_boreas_bin(path: Path) -> np.ndarray:
    """Points (K, 6) float64 ``x, y, z, intensity, ring, t`` of a Boreas lidar ``.bin``."""
    return sm.read_float32_records(path, 6, "Boreas lidar scan")


def read_pose_csv(path: Path) -> np.ndarray:
    """Rows (F, 13) of an applanix pose CSV (header skipped; columns read by position)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing Boreas pose file {path}")
    rows = []
    lines = path.read_text().splitlines()
    for n, line in enumerate(lines[1:], 2):
        if not line.strip():
            continue
        parts = line.split(",")
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise InputError(f"{path}:{n}: pose row has non-numeric values") from None
        if len(vals) < 13 or not np.all(np.isfinite(vals[:13])):
            raise InputError(f"{path}:{n}: a pose row needs 13 finite numbers (t_us, x, y, z, vx, vy, "
                             f"vz, roll, pitch, yaw, wz, wy, wx), got {len(vals)}")
        rows.append(vals[:13])
    if not rows:
        raise InputError(f"{path} holds no pose rows (after the header line)")
    return np.array(rows, dtype=np.float64)  # microsecond times < 2^53 are exact in float64


def read_matrix4(path: Path) -> np.ndarray:
    """A 4x4 matrix from a text file (16 numbers)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing calibration file {path}")
    try:
        M = np.loadtxt(path, dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: not a 4x4 matrix of numbers") from None
    if M.size != 16:
        raise InputError(f"{path}: expected a 4x4 matrix, got {M.size} numbers")
    return M.reshape(4, 4)


def deskew(points: np.ndarray, times_s: np.ndarray, body_rate: np.ndarray) -> np.ndarray:
    """Remove motion distortion: ``p_ref = exp(t * varpi^) p`` with ``varpi = [v (3), w (3)]`` the
    body rate in the sensor frame (m/s, rad/s) and ``t`` the time of each point relative to the
    reference time (s). points (K, 3), times (K,) -> (K, 3)."""
    xi = torch.as_tensor(np.asarray(times_s, dtype=np.float64)[:, None] * np.asarray(body_rate)[None, :])
    T = se3_exp(xi).numpy()  # (K, 4, 4)
    return np.einsum("kij,kj->ki", T[:, :3, :3], points) + T[:, :3, 3]


class _Drive:
    """One Boreas sequence: lidar files, their poses (T_enu_V) and body rates."""

    def __init__(self, folder: Path) -> None:
        if not folder.is_dir():
            raise InputError(f"missing Boreas sequence folder {folder}")
        lidar = folder / "lidar"
        if not lidar.is_dir():
            raise InputError(f"missing lidar folder {lidar}")
        self.name = folder.name
        self.bins = sorted(lidar.glob("*.bin"), key=lambda p: int(p.stem) if p.stem.isdigit() else -1)
        if not self.bins:
            raise InputError(f"{lidar} holds no .bin scans")
        if any(not p.stem.isdigit() for p in self.bins):
            raise InputError(f"{lidar}: scan names must be microsecond timestamps like 1606417230036848.bin")
        rows = read_pose_csv(folder / "applanix" / "lidar_poses.csv")
        by_t = {int(round(r[0])): r for r in rows}
        missing = [p.name for p in self.bins if int(p.stem) not in by_t]
        if missing:
            raise InputError(f"{folder / 'applanix' / 'lidar_poses.csv'} has no row for "
                             f"{len(missing)} lidar file(s), e.g. {missing[0]}")
        self.rows = np.stack([by_t[int(p.stem)] for p in self.bins])
        self.t_us = np.array([int(p.stem) for p in self.bins], dtype=np.int64)
        T_al = read_matrix4(folder / "calib" / "T_applanix_lidar.txt")
        fwd = T_al[:3, :3].T @ np.array([0.0, 1.0, 0.0])  # vehicle forward in the lidar frame
        self.T_lidar_V = sm.pose_2d(0.0, 0.0, float(np.arctan2(fwd[1], fwd[0])))
        T_enu_lidar = np.stack([pose_from_row(r) for r in self.rows])
        self.T_enu_V = T_enu_lidar @ self.T_lidar_V
        # body rate in the lidar frame: v = C^T v_enu, w = (wx, wy, wz)
        v_s = np.einsum("kji,kj->ki", T_enu_lidar[:, :3, :3], self.rows[:, 4:7])
        self.body_rate = np.hstack([v_s, self.rows[:, [12, 11, 10]]])
        steps = np.linalg.norm(np.diff(self.T_enu_V[:, :3, 3], axis=0), axis=1)
        self.dist = np.r_[0.0, np.cumsum(steps)]  # distance travelled (m)

    def spaced(self, spacing_m: float) -> np.ndarray:
        """Indices of frames about ``spacing_m`` apart along the drive (first frame included)."""
        out, last = [0], 0.0
        for k in range(1, len(self.dist)):
            if self.dist[k] - last >= spacing_m:
                out.append(k)
                last = self.dist[k]
        return np.array(out)

    def scan_V(self, k: int, min_range_m: float, do_deskew: bool) -> np.ndarray:
        """Scan k (K, 3) in the vehicle frame V (deskewed, ego returns removed)."""
        raw = read_boreas_bin(self.bins[k])
        pts = raw[:, :3]
        if do_deskew:
            pts = deskew(pts, raw[:, 5], self.body_rate[k])
        pts = pts[np.linalg.norm(pts, axis=1) >= min_range_m]
        if len(pts) < 6:
            raise InputError(f"Boreas lidar scan {self.bins[k]} has {len(pts)} point(s) farther than "
                             f"min_range_m = {min_range_m:g} m (an all-zero or empty scan); at least "
                             "6 are needed")
        return sm.transform(sm.inv(self.T_lidar_V), pts)


class BoreasDataset(Dataset):
    """Boreas teach-and-repeat: repeat-drive scans vs submaps of a teach drive.

    Args:
        root: folder holding the ``boreas-*`` sequence folders.
        teach: the map sequence (default: the localisation benchmark's ``boreas-2020-11-26-13-58``).
        repeats: repeat sequences (default: every other ``boreas-*`` folder in ``root``).
        sample_spacing_m: distance travelled between samples of a repeat drive.
        keyframe_spacing_m: distance between teach keyframes used in submaps.
        submap_window_m: teach keyframes within this distance along the teach drive of the
            nearest keyframe form the submap.
        max_teach_dist_m: live scans farther than this from every teach keyframe are skipped.
        n_points, scan_voxel_m, min_range_m: scan size, spreading voxel, ego-vehicle crop (m).
        map_voxel_m, map_radius_m, normal_radius_m: submap voxel, crop radius, normal PCA radius.
        deskew: remove motion distortion with the pose row's body rate.
        offset_trans_m, offset_rot_deg: the random initial offset (paper: 0.3 m, 10 deg).
        cache_dir: cache root.
        split: recorded only; choose repeat drives for training and testing.
    """

    name: ClassVar[str] = "boreas"
    param_ranges: ClassVar[dict[str, Range]] = {
        "sample_spacing_m": Range(0.0, lo_open=True), "keyframe_spacing_m": Range(0.0, lo_open=True),
        "submap_window_m": Range(0.0), "max_teach_dist_m": Range(0.0, lo_open=True),
        "n_points": Range(6, 10_000_000), "scan_voxel_m": Range(0.0, lo_open=True),
        "min_range_m": Range(0.0), "map_voxel_m": Range(0.0, lo_open=True),
        "map_radius_m": Range(0.0, lo_open=True), "normal_radius_m": Range(0.0, lo_open=True),
        "offset_trans_m": Range(0.0, 100.0), "offset_rot_deg": Range(0.0, 180.0)}
    description: ClassVar[str] = "Boreas layout: repeat-drive scans vs submaps of a teach drive"
    icp_preset: ClassVar[str] = "lidar"

    def __init__(self, root: str | Path, teach: str = DEFAULT_TEACH,
                 repeats: list[str] | tuple[str, ...] | str | None = None, *, seed: int = 0,
                 split: Split = "all", sample_spacing_m: float = 10.0, keyframe_spacing_m: float = 2.0,
                 submap_window_m: float = 20.0, max_teach_dist_m: float = 5.0, n_points: int = 10_000,
                 scan_voxel_m: float = 0.3, min_range_m: float = 3.0, map_voxel_m: float = 0.25,
                 map_radius_m: float = 50.0, normal_radius_m: float = 1.0, deskew: bool = True,
                 offset_trans_m: float = 0.3, offset_rot_deg: float = 10.0,
                 cache_dir: str | Path | None = None) -> None:
        root = Path(root)
        if not root.is_dir():
            raise InputError(f"Boreas root {root} is not a folder")
        if isinstance(repeats, str):
            repeats = [repeats]
        if repeats is None:
            repeats = sorted(p.name for p in root.glob("boreas-*") if p.is_dir() and p.name != teach)
        repeats = [plain_name(r, "Boreas setting repeats") for r in repeats]
        teach = plain_name(teach, "Boreas setting teach")
        if not repeats:
            raise InputError(f"no repeat sequences: {root} holds no boreas-* folder besides {teach}")
        if teach in repeats:
            raise InputError(f"the teach sequence {teach} cannot also be a repeat")
        if not (sample_spacing_m > 0 and keyframe_spacing_m > 0 and submap_window_m > 0):
            raise InputError("sample_spacing_m, keyframe_spacing_m and submap_window_m must be positive")
        self.teach = _Drive(root / teach)
        self.repeats = {name: _Drive(root / name) for name in repeats}
        self._gen = {"teach": teach, "keyframe_spacing_m": float(keyframe_spacing_m),
                     "submap_window_m": float(submap_window_m), "n_points": int(n_points),
                     "scan_voxel_m": float(scan_voxel_m), "min_range_m": float(min_range_m),
                     "map_voxel_m": float(map_voxel_m), "map_radius_m": float(map_radius_m),
                     "normal_radius_m": float(normal_radius_m), "deskew": bool(deskew),
                     "seed": int(seed)}
        super().__init__(seed=seed, split=split, root=str(root), repeats=repeats,
                         sample_spacing_m=float(sample_spacing_m), max_teach_dist_m=float(max_teach_dist_m),
                         offset_trans_m=float(offset_trans_m), offset_rot_deg=float(offset_rot_deg),
                         **{k: v for k, v in self._gen.items() if k != "seed"})
        self.offset = (float(offset_trans_m), float(offset_rot_deg))
        self._teach_scans = sm.LRU(64)  # keyframes shared by neighbouring submaps
        self.keyframes = self.teach.spaced(keyframe_spacing_m)
        self._kf_tree = cKDTree(self.teach.T_enu_V[self.keyframes, :2, 3])
        self._index: list[tuple[str, int, int]] = []  # (repeat, frame, nearest keyframe position)
        for name, drive in self.repeats.items():
            for k in drive.spaced(sample_spacing_m):
                dist, j = self._kf_tree.query(drive.T_enu_V[k, :2, 3])
                if dist <= max_teach_dist_m:
                    self._index.append((name, int(k), int(j)))
        root_id = {"root": str(root.resolve()),
                   "drives": {d.name: [len(d.bins), int(d.t_us[0]), int(d.t_us[-1])]
                              for d in [self.teach, *self.repeats.values()]}}
        self.cache_root = ((Path(cache_dir) if cache_dir is not None else default_cache_dir()) / "boreas"
                           / sm.params_hash({**self._gen, **root_id}, FORMAT_VERSION))

    def __len__(self) -> int:
        return len(self._index)

    def sample_id(self, i: int) -> str:
        """The id of sample ``i`` without reading its files."""
        name, k, _ = self._index[i]
        return f"boreas/{name}/{int(self.repeats[name].t_us[k])}"

    def _submap_keyframes(self, j: int) -> np.ndarray:
        """Teach frames whose scans form the submap around keyframe position j."""
        d_kf = self.teach.dist[self.keyframes]
        return self.keyframes[np.abs(d_kf - d_kf[j]) <= self._gen["submap_window_m"]]

    def _inputs_key(self, drive: _Drive, k: int, j: int) -> str:
        """A key of every lidar file a sample reads (name and a hash of its bytes): a rewritten
        file is never served from a stale cache entry, whatever its modification time."""
        files = [drive.bins[k], *(self.teach.bins[int(m)] for m in self._submap_keyframes(j))]
        try:
            stats = [[f.name, sm.file_digest(f)] for f in files]
        except OSError as exc:
            raise InputError(f"Boreas lidar scan {exc.filename} cannot be read ({exc.strerror})") from exc
        return sm.params_hash({"files": stats}, FORMAT_VERSION)

    def __getitem__(self, i: int) -> Sample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample index {i} out of range for {len(self)} samples")
        name, k, j = self._index[i]
        drive = self.repeats[name]
        t_us = int(drive.t_us[k])
        path = self.cache_root / name / f"{t_us}-{self._inputs_key(drive, k, j)}.npz"
        rec = sm.load_npz(path)
        if rec is None:
            rec = self._build(drive, k, j)
            sm.atomic_savez(path, **rec)
        T = drive.T_enu_V[k]
        meta = {"x": float(T[0, 3]), "y": float(T[1, 3]), "sequence": name, "pass": name,
                "frame": int(k), "t_us": t_us, "teach_frame": int(self.keyframes[j]),
                "n_map_frames": int(rec["n_map_frames"])}
        rng = sm.sample_rng(self.seed, t_us & 0xFFFFFFFF, t_us >> 32, 4)
        return sm.make_sample(f"boreas/{name}/{t_us}", rec["scan"], rec["map"], rec["normals"], rng,
                              meta, *self.offset)

    def _teach_scan(self, m: int) -> np.ndarray:
        """Teach scan m in its vehicle frame, voxel-averaged at the submap voxel size, cached."""
        g = self._gen
        return self._teach_scans.get(m, lambda: sm.voxel_downsample(
            self.teach.scan_V(m, g["min_range_m"], g["deskew"]), g["map_voxel_m"])[0])

    def _build(self, drive: _Drive, k: int, j: int) -> dict[str, Any]:
        g = self._gen
        scan = drive.scan_V(k, g["min_range_m"], g["deskew"])
        t_us = int(drive.t_us[k])
        idx = sm.spatial_subsample(scan, g["n_points"], g["scan_voxel_m"],
                                   sm.sample_rng(self.seed, t_us & 0xFFFFFFFF, t_us >> 32, 3))
        teach = self.teach
        use = self._submap_keyframes(j)
        T_live_enu = sm.inv(drive.T_enu_V[k])
        clouds = [(sm.transform(T_live_enu @ teach.T_enu_V[m], self._teach_scan(int(m))), None)
                  for m in use]
        centre = (T_live_enu @ teach.T_enu_V[self.keyframes[j]])[:3, 3]
        pts, nrm = sm.build_submap(clouds, g["map_voxel_m"], centre, g["map_radius_m"], estimate=True,
                                   normal_radius_m=g["normal_radius_m"])
        return {"scan": scan[idx].astype(np.float32), "map": pts.astype(np.float32),
                "normals": nrm.astype(np.float32), "n_map_frames": np.array(len(use))}
