"""``kitti``: scan-to-submap localisation on a sequence in the KITTI odometry layout.

Layout (see the KITTI odometry devkit; SemanticKITTI adds ``sequences/XX/poses.txt``)::

    <root>/sequences/XX/velodyne/NNNNNN.bin   float32 x, y, z, reflectance per point (16 bytes)
    <root>/sequences/XX/calib.txt             lines "KEY: 12 floats"; Tr = T_cam0_velo (3x4)
    <root>/poses/XX.txt                       line i: 3x4 row-major T_cam0(0)_cam0(i), 12 floats
                                              (or <root>/sequences/XX/poses.txt)

``root`` may also be the sequence folder itself (the one holding ``velodyne/``). Lidar poses in the
frame of the first lidar frame are ``T_velo0_velo(i) = inv(Tr) @ T_cam0(0)_cam0(i) @ Tr``.

Sample ``i`` (every ``stride``-th frame): the scan of frame ``i`` (returns nearer than
``min_range_m`` dropped, then ``n_points`` spread by :func:`~icpbench.datasets.submaps.spatial_subsample`)
against a submap accumulated from frames ``i - window .. i + window`` *excluding* ``i`` (every
``map_stride``-th), expressed in the lidar frame of frame ``i`` (x forward, so pose errors are
longitudinal/lateral), voxel-averaged and with PCA normals. The paper's random offset is then
applied (:func:`~icpbench.datasets.submaps.make_sample`). KITTI has no repeat drives, so this is
the odometry-style variant of the protocol; train/test separation is by choosing sequences.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from icpbench.core.errors import InputError
from icpbench.core.filenames import plain_name
from icpbench.core.registry import Range, check_ranges
from icpbench.core.types import Sample
from icpbench.datasets import submaps as sm
from icpbench.datasets.base import Dataset, Split, default_cache_dir

FORMAT_VERSION = 1


def read_kitti_bin(path: Path) -> np.ndarray:
    """Points (K, 3) float64 (x, y, z in the Velodyne frame) of a KITTI ``.bin`` scan."""
    return sm.read_float32_records(path, 4, "KITTI scan")[:, :3]


#: Largest deviation of ``R^T R`` from the identity (and of ``det R`` from 1) accepted in a pose or
#: calibration read from a text file (KITTI writes 6-7 significant digits).
RIGID_TOL = 1e-3


def check_rigid(T: np.ndarray, where: str, what: str) -> None:
    """Raise :class:`InputError` naming ``where`` (file:line) unless the 4x4 ``T`` is a rigid
    transform: finite, rotation block orthonormal with determinant +1 (to :data:`RIGID_TOL`)."""
    if not np.all(np.isfinite(T)):
        raise InputError(f"{where}: {what} has NaN or Inf values")
    R = T[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if dev > RIGID_TOL or abs(det - 1.0) > RIGID_TOL:
        raise InputError(f"{where}: {what} is not a rigid transform (its rotation block has "
                         f"max |R^T R - I| = {dev:.3g} and det {det:.3g}; a rotation has 0 and 1): "
                         "the file is corrupt or not in the KITTI format")


def read_calib_tr(path: Path) -> np.ndarray:
    """``Tr`` (T_cam0_velo, 4x4) from a KITTI ``calib.txt`` (parsed by key)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing KITTI calibration file {path} (it must contain a 'Tr:' line)")
    for n, line in enumerate(path.read_text().splitlines(), 1):
        key, _, rest = line.partition(":")
        if key.strip() in ("Tr", "Tr_velo_to_cam"):
            vals = rest.split()
            try:
                M = np.array([float(v) for v in vals])
            except ValueError:
                raise InputError(f"{path}:{n}: Tr has non-numeric values") from None
            if M.size != 12:
                raise InputError(f"{path}:{n}: Tr needs 12 numbers (3x4), got {M.size}")
            T = np.eye(4)
            T[:3] = M.reshape(3, 4)
            check_rigid(T, f"{path}:{n}", "Tr")
            return T
    raise InputError(f"{path} has no 'Tr:' line (the Velodyne-to-camera-0 transform)")


def read_kitti_poses(path: Path) -> np.ndarray:
    """Poses (F, 4, 4) from a KITTI pose file (12 numbers per line, 3x4 row-major)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing KITTI pose file {path}")
    poses = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = np.array([float(v) for v in line.split()])
        except ValueError:
            raise InputError(f"{path}:{n}: pose line has non-numeric values") from None
        if vals.size != 12:
            raise InputError(f"{path}:{n}: a pose line needs 12 numbers (3x4 row-major), "
                             f"got {vals.size}")
        if not np.all(np.isfinite(vals)):
            raise InputError(f"{path}:{n}: the pose line has {int((~np.isfinite(vals)).sum())} "
                             "NaN or Inf value(s); a pose needs 12 finite numbers")
        T = np.eye(4)
        T[:3] = vals.reshape(3, 4)
        check_rigid(T, f"{path}:{n}", "pose")
        poses.append(T)
    if not poses:
        raise InputError(f"{path} holds no poses")
    return np.stack(poses)


class KittiDataset(Dataset):
    """KITTI odometry sequence: scan ``i`` vs a submap of its neighbouring frames.

    Args:
        root: dataset root (holding ``sequences/`` and ``poses/``) or the sequence folder.
        sequence: sequence name, e.g. ``"00"``.
        poses: explicit pose file (default: ``poses/XX.txt``, else ``sequences/XX/poses.txt``).
        stride: every ``stride``-th frame is a sample.
        window: neighbours on each side used for the submap; ``map_stride`` thins them.
        n_points, scan_voxel_m, min_range_m: scan size, spreading voxel, ego-vehicle crop (m).
        map_voxel_m, map_radius_m, normal_radius_m: submap voxel, crop radius, normal PCA radius.
        offset_trans_m, offset_rot_deg: the random initial offset (paper: 0.3 m, 10 deg).
        cache_dir: cache root (built submaps are cached, keyed by the parameters, the pose and
            calibration files and the name and contents of every scan file a sample reads).
        split: recorded only; KITTI has no split, choose sequences for training and testing.
    """

    name: ClassVar[str] = "kitti"
    param_ranges: ClassVar[dict[str, Range]] = {
        "stride": Range(1), "window": Range(1), "map_stride": Range(1),
        "n_points": Range(6), "scan_voxel_m": Range(0.0, lo_open=True),
        "min_range_m": Range(0.0), "map_voxel_m": Range(0.0, lo_open=True),
        "map_radius_m": Range(0.0, lo_open=True), "normal_radius_m": Range(0.0, lo_open=True),
        "offset_trans_m": Range(0.0, 100.0), "offset_rot_deg": Range(0.0, 180.0),
    }
    description: ClassVar[str] = "KITTI odometry layout: scan i vs a submap of neighbouring frames"
    icp_preset: ClassVar[str] = "lidar"

    def __init__(self, root: str | Path, sequence: str = "00", *, seed: int = 0, split: Split = "all",
                 poses: str | Path | None = None, stride: int = 10, window: int = 10,
                 map_stride: int = 1, n_points: int = 10_000, scan_voxel_m: float = 0.3,
                 min_range_m: float = 2.5, map_voxel_m: float = 0.25, map_radius_m: float = 50.0,
                 normal_radius_m: float = 1.0, offset_trans_m: float = 0.3,
                 offset_rot_deg: float = 10.0, cache_dir: str | Path | None = None) -> None:
        check_ranges("dataset 'kitti'", locals(), self.param_ranges)
        root = Path(root)
        sequence = plain_name(sequence, "KITTI setting sequence")
        if not root.is_dir():
            raise InputError(f"KITTI root {root} is not a folder")
        seq_dir = root if (root / "velodyne").is_dir() else root / "sequences" / str(sequence)
        vel = seq_dir / "velodyne"
        if not vel.is_dir():
            raise InputError(f"no velodyne folder at {vel}; expected <root>/sequences/{sequence}/velodyne")
        if poses is None:
            cands = [root / "poses" / f"{sequence}.txt", seq_dir / "poses.txt"]
            found = [c for c in cands if c.is_file()]
            if not found:
                raise InputError(f"no pose file for sequence {sequence}: looked for "
                                 f"{', '.join(str(c) for c in cands)}")
            poses = found[0]
        if stride < 1 or window < 1 or map_stride < 1:
            raise InputError("stride, window and map_stride must be >= 1")
        self.bins = sorted(vel.glob("*.bin"), key=lambda p: int(p.stem) if p.stem.isdigit() else -1)
        if not self.bins:
            raise InputError(f"{vel} holds no .bin scans")
        if any(not p.stem.isdigit() for p in self.bins):
            raise InputError(f"{vel}: scan names must be frame numbers like 000000.bin")
        Tr = read_calib_tr(seq_dir / "calib.txt")
        P = read_kitti_poses(Path(poses))
        if len(P) < len(self.bins):
            raise InputError(f"{poses} has {len(P)} poses but {vel} has {len(self.bins)} scans")
        frame_ids = np.array([int(p.stem) for p in self.bins])
        if frame_ids.max() >= len(P):
            raise InputError(f"scan {frame_ids.max():06d}.bin has no pose in {poses}")
        self.T_velo = np.linalg.inv(Tr) @ P[frame_ids] @ Tr  # T_velo0_velo(i)
        self.frame_ids = frame_ids
        self.sequence = str(sequence)
        fingerprint = {"seq_dir": str(seq_dir.resolve()), "poses": str(Path(poses).resolve()),
                       "n_scans": len(self.bins), "poses_digest": sm.file_digest(Path(poses)),
                       "calib_digest": sm.file_digest(seq_dir / "calib.txt")}
        self._gen = {"window": int(window), "map_stride": int(map_stride), "n_points": int(n_points),
                     "scan_voxel_m": float(scan_voxel_m), "min_range_m": float(min_range_m),
                     "map_voxel_m": float(map_voxel_m), "map_radius_m": float(map_radius_m),
                     "normal_radius_m": float(normal_radius_m), "seed": int(seed)}
        super().__init__(seed=seed, split=split, root=str(root), sequence=self.sequence,
                         stride=int(stride), offset_trans_m=float(offset_trans_m),
                         offset_rot_deg=float(offset_rot_deg),
                         **{k: v for k, v in self._gen.items() if k != "seed"})
        self.offset = (float(offset_trans_m), float(offset_rot_deg))
        self.cache_root = ((Path(cache_dir) if cache_dir is not None else default_cache_dir()) / "kitti"
                           / sm.params_hash({**self._gen, **fingerprint}, FORMAT_VERSION))
        self._index = list(range(0, len(self.bins), int(stride)))
        self._scans = sm.LRU(4 * int(window) + 4)  # neighbours shared by consecutive samples

    def __len__(self) -> int:
        return len(self._index)

    def sample_id(self, i: int) -> str:
        """The id of sample ``i`` without reading its files."""
        return f"kitti/{self.sequence}/{self.frame_ids[self._index[i]]:06d}"

    def _neighbours(self, k: int) -> list[int]:
        """Frames (indices into ``bins``) whose scans form the submap of frame k."""
        g = self._gen
        lo, hi = max(0, k - g["window"]), min(len(self.bins), k + g["window"] + 1)
        return [j for j in range(lo, hi, g["map_stride"]) if j != k]

    def _inputs_key(self, k: int) -> str:
        """A key of the contents of every scan file sample k reads (name and a hash of the bytes),
        so that a rewritten file is never served from a stale cache entry, even one rewritten
        with the same size and its old modification time (``cp -p``, ``rsync -a``)."""
        return sm.params_hash({"files": [[self.bins[j].name, sm.file_digest(self.bins[j])]
                                         for j in [k, *self._neighbours(k)]]}, FORMAT_VERSION)

    def __getitem__(self, i: int) -> Sample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample index {i} out of range for {len(self)} samples")
        k = self._index[i]
        try:
            key = self._inputs_key(k)
        except OSError as exc:
            raise InputError(f"KITTI scan {exc.filename} cannot be read ({exc.strerror})") from exc
        path = self.cache_root / f"{self.frame_ids[k]:06d}-{key}.npz"
        rec = sm.load_npz(path)
        if rec is None:
            rec = self._build(k)
            sm.atomic_savez(path, **rec)
        T = self.T_velo[k]
        meta = {"x": float(T[0, 3]), "y": float(T[1, 3]), "sequence": self.sequence,
                "pass": self.sequence, "frame": int(self.frame_ids[k]),
                "n_map_frames": int(rec["n_map_frames"])}
        rng = sm.sample_rng(self.seed, int(self.frame_ids[k]), 4, _seq_key(self.sequence))
        return sm.make_sample(self.sample_id(i), rec["scan"], rec["map"],
                              rec["normals"], rng, meta, *self.offset)

    def _scan(self, k: int) -> np.ndarray:
        """Scan k (K, 3), Velodyne frame, returns nearer than ``min_range_m`` removed."""
        pts = read_kitti_bin(self.bins[k])
        pts = pts[np.linalg.norm(pts, axis=1) >= self._gen["min_range_m"]]
        if len(pts) < 6:
            raise InputError(f"KITTI scan {self.bins[k]} has {len(pts)} point(s) farther than "
                             f"min_range_m = {self._gen['min_range_m']:g} m (an all-zero or "
                             "empty scan); at least 6 are needed")
        return pts

    def _map_scan(self, k: int) -> np.ndarray:
        """Scan k voxel-averaged at the submap voxel size (what submaps accumulate), cached."""
        return self._scans.get(k, lambda: sm.voxel_downsample(self._scan(k), self._gen["map_voxel_m"])[0])

    def _build(self, k: int) -> dict[str, Any]:
        g = self._gen
        scan = self._scan(k)
        idx = sm.spatial_subsample(scan, g["n_points"], g["scan_voxel_m"],
                                   sm.sample_rng(self.seed, int(self.frame_ids[k]), 3))
        nbrs = self._neighbours(k)
        if not nbrs:
            raise InputError(f"frame {self.frame_ids[k]} has no neighbouring frames for a submap")
        T_k_inv = sm.inv(self.T_velo[k])
        clouds = [(sm.transform(T_k_inv @ self.T_velo[j], self._map_scan(j)), None) for j in nbrs]
        pts, nrm = sm.build_submap(clouds, g["map_voxel_m"], np.zeros(3), g["map_radius_m"],
                                   estimate=True, normal_radius_m=g["normal_radius_m"])
        return {"scan": scan[idx].astype(np.float32), "map": pts.astype(np.float32),
                "normals": nrm.astype(np.float32), "n_map_frames": np.array(len(nbrs))}


def _seq_key(name: str) -> int:
    """A stable integer from a sequence name (for seeding)."""
    return int(sm.params_hash({"name": name}, 0)[:8], 16)
