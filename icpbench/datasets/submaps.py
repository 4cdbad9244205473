"""Shared pieces of the lidar datasets (``lidar-sim``, ``kitti``, ``boreas``).

* submap building: accumulate scans in a common frame, voxel-average, keep or estimate normals;
* the paper's sample protocol (Zhang et al., ICRA 2025, §IV-A): align the live scan with its
  submap using the true pose, then move the scan by a random transform (uniform +-0.3 m in x, y, z
  and +-10 deg in roll, pitch, yaw); ICP starts from the identity;
* a small on-disk cache of ``.npz`` files with atomic writes, keyed by a parameter hash.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from icpbench.core.errors import InputError
from icpbench.core.types import Sample

# ---------------------------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------------------------
#: Largest plausible coordinate of a lidar point (metres); beyond it a scan file is corrupt.
MAX_COORD_M = 1e5


def read_float32_records(path: str | Path, fields: int, what: str) -> np.ndarray:
    """Points (K, fields) float64 of a headerless little-endian float32 lidar file (KITTI: 4 fields,
    Boreas: 6). The first three fields are x, y, z.

    Raises:
        InputError: missing or empty file, a size that is not a whole number of records
            (truncated), or NaN/Inf coordinates or coordinates beyond :data:`MAX_COORD_M`
            (corrupt); the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing {what} {path}")
    size = path.stat().st_size
    if size % (4 * fields):
        raise InputError(f"{path} has {size} bytes, not a multiple of {4 * fields} ({fields} float32 "
                         f"per point): the file is truncated or not a {what}")
    if size == 0:
        raise InputError(f"{what} {path} is empty (0 bytes)")
    rec = np.fromfile(path, dtype="<f4").reshape(-1, fields).astype(np.float64)
    bad = int((~np.isfinite(rec[:, :3])).any(1).sum())
    if bad:
        raise InputError(f"{what} {path} is corrupt: {bad} point(s) have NaN or Inf coordinates")
    far = int((np.abs(rec[:, :3]) > MAX_COORD_M).any(1).sum())
    if far:
        raise InputError(f"{what} {path} is corrupt: {far} point(s) have a coordinate beyond "
                         f"{MAX_COORD_M:g} m")
    return rec


def file_digest(path: Path) -> str:
    """A hash of the bytes of ``path`` (BLAKE2b, 16 bytes, hex)."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points (K, 3); returns float64."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ np.ascontiguousarray(T[:3, :3].T) + T[:3, 3]


def rotate(T: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Apply the rotation of a (4, 4) transform to vectors (K, 3) (e.g. normals); float64."""
    R_t = np.ascontiguousarray(np.asarray(T, dtype=np.float64)[:3, :3].T)
    return np.asarray(vectors, dtype=np.float64) @ R_t


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform."""
    T = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def pose_2d(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """(4, 4) transform of a planar pose (metres, radians)."""
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def voxel_downsample(points: np.ndarray, voxel_m: float, normals: np.ndarray | None = None,
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """Average the points (K, 3) falling in each cubic voxel of side ``voxel_m`` (metres).

    With ``normals`` (K, 3), each voxel's normal is the mean of its points' normals after turning
    them all to the side of the voxel's first normal, so that the same thin surface seen from both
    sides (opposite signs) does not cancel. Signs are arbitrary; orient them with
    :func:`orient_normals`. Returns (points (V, 3), unit normals (V, 3) or None), float64.
    """
    if not voxel_m > 0:
        raise InputError(f"voxel size must be positive, got {voxel_m}")
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return pts.reshape(0, 3), None if normals is None else pts.reshape(0, 3)
    cell = np.floor(pts / voxel_m).astype(np.int64)
    cell -= cell.min(0)
    span = cell.max(0) + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        raise InputError("point cloud too large for the voxel size (coordinates out of range)")
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]  # one int64 per voxel
    _, first, inv_idx, counts = np.unique(key, return_index=True, return_inverse=True,
                                          return_counts=True)
    inv_idx = inv_idx.ravel()
    n_vox = len(counts)
    out = np.zeros((n_vox, 3))
    for j in range(3):
        out[:, j] = np.bincount(inv_idx, weights=pts[:, j], minlength=n_vox)
    out /= counts[:, None]
    if normals is None:
        return out, None
    n = np.asarray(normals, dtype=np.float64)
    ref = n[first][inv_idx]
    n = np.where(((n * ref).sum(1) < 0)[:, None], -n, n)
    acc = np.zeros((n_vox, 3))
    for j in range(3):
        acc[:, j] = np.bincount(inv_idx, weights=n[:, j], minlength=n_vox)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    acc = np.where(norm > 1e-9, acc / np.maximum(norm, 1e-12), n[first])
    return out, acc


def estimate_normals(points: np.ndarray, radius_m: float = 1.0, max_nn: int = 20) -> np.ndarray:
    """Unit normals (K, 3) of a point cloud (K, 3) by local PCA (Open3D hybrid radius/k-NN search).

    Points with too few neighbours get Open3D's default (an arbitrary unit vector)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=max_nn))
    n = np.asarray(pcd.normals)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    bad = norm[:, 0] < 1e-9
    n = np.where(bad[:, None], np.array([0.0, 0.0, 1.0]), n / np.maximum(norm, 1e-12))
    return n


def orient_normals(points: np.ndarray, normals: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """Flip normals (K, 3) so that they face ``viewpoint`` (3,) (e.g. the sensor)."""
    n = np.array(normals, dtype=np.float64, copy=True)
    flip = ((np.asarray(viewpoint) - np.asarray(points)) * n).sum(1) < 0
    n[flip] *= -1
    return n


def crop_radius(points: np.ndarray, centre_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """Boolean mask (K,) of points within a horizontal radius of centre_xy (2,)."""
    return np.linalg.norm(np.asarray(points)[:, :2] - np.asarray(centre_xy)[:2], axis=1) <= radius_m


def subsample(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` points drawn uniformly at random from ``len(points)`` (without replacement
    when there are enough, with replacement otherwise)."""
    k = len(points)
    if k == 0:
        raise InputError("cannot subsample an empty scan (no lidar returns)")
    return np.sort(rng.choice(k, size=n, replace=k < n))


def spatial_subsample(points: np.ndarray, n: int, voxel_m: float, rng: np.random.Generator
                      ) -> np.ndarray:
    """Indices of ``n`` points spread evenly in space: one random point per voxel, ``n`` of those
    drawn at random. The voxel side starts at ``voxel_m`` (metres) and shrinks by 25 % steps
    until there are at least ``n`` occupied voxels (below 1 cm, a plain uniform draw). Unlike a
    uniform draw over the returns, this keeps near objects (dense in a lidar sweep) from
    dominating the scan. ``voxel_m <= 0`` gives the uniform draw."""
    k = len(points)
    if k == 0:
        raise InputError("cannot subsample an empty scan (no lidar returns)")
    pts = np.asarray(points, dtype=np.float64)
    voxel = float(voxel_m)
    while 0.01 <= voxel and k >= n:
        perm = rng.permutation(k)
        cell = np.floor(pts[perm] / voxel).astype(np.int64)
        cell -= cell.min(0)
        span = cell.max(0) + 1
        key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
        _, first = np.unique(key, return_index=True)
        if len(first) >= n:
            return np.sort(rng.choice(perm[first], size=n, replace=False))
        voxel *= 0.75
    return subsample(pts, n, rng)


# ---------------------------------------------------------------------------------------------
# Sample protocol
# ---------------------------------------------------------------------------------------------
def random_offset(rng: np.random.Generator, trans_m: float = 0.3, rot_deg: float = 10.0) -> np.ndarray:
    """The paper's random transform (4, 4): translation uniform in [-trans_m, trans_m]^3, roll,
    pitch and yaw each uniform in [-rot_deg, rot_deg] (intrinsic x-y-z Euler angles)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-rot_deg, rot_deg, 3), degrees=True).as_matrix()
    T[:3, 3] = rng.uniform(-trans_m, trans_m, 3)
    return T


def make_sample(sample_id: str, scan_true: np.ndarray, map_points: np.ndarray,
                map_normals: np.ndarray, rng: np.random.Generator, meta: Mapping[str, Any],
                trans_m: float = 0.3, rot_deg: float = 10.0) -> Sample:
    """Build a :class:`Sample` from a live scan and a submap in the same (true vehicle) frame.

    ``scan_true`` (N, 3) and ``map_points`` (M, 3) must already be aligned. The scan is moved by
    ``T_off = random_offset(rng)``: ``scan = T_off * scan_true``, so the true scan->map transform is
    ``T_gt = inv(T_off)``; ``T_init`` is the identity.
    """
    T_off = random_offset(rng, trans_m, rot_deg)
    scan = transform(T_off, scan_true)
    return Sample(id=sample_id, scan=scan.astype(np.float32),
                  map=np.ascontiguousarray(map_points, dtype=np.float32),
                  map_normals=np.ascontiguousarray(map_normals, dtype=np.float32),
                  T_gt=inv(T_off), T_init=np.eye(4), meta=dict(meta))


def sample_rng(*keys: int) -> np.random.Generator:
    """A generator seeded from integer keys (e.g. seed, pass, frame, stream)."""
    return np.random.default_rng([int(k) & 0xFFFFFFFF for k in keys])


# ---------------------------------------------------------------------------------------------
# Cache
# ---------------------------------------------------------------------------------------------
class LRU:
    """A small in-memory least-recently-used cache (e.g. of scans shared by neighbouring submaps)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self._items: OrderedDict[Hashable, Any] = OrderedDict()

    def get(self, key: Hashable, build: Callable[[], Any]) -> Any:
        """The cached value of ``key``, built with ``build()`` on a miss."""
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = build()
        self._items[key] = value
        while len(self._items) > self.capacity:
            self._items.popitem(last=False)
        return value


def params_hash(params: Mapping[str, Any], version: int) -> str:
    """A 16-hex-digit key of JSON-serialisable parameters and a format version."""
    blob = json.dumps({"params": params, "format_version": version}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _atomic_write(path: Path, write: Any) -> None:
    """Call ``write(file)`` on a temporary file next to ``path``, then ``os.replace`` it into place,
    so that a reader (or a concurrent writer) never sees a partial file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    _atomic_write(path, lambda f: f.write(data))


def atomic_savez(path: Path, **arrays: Any) -> None:
    """``np.savez_compressed`` to ``path`` atomically."""
    _atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def load_npz(path: Path) -> dict[str, np.ndarray] | None:
    """Arrays of a cached ``.npz``; None if missing or unreadable (it is then regenerated)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError):
        return None


def write_params(folder: Path, params: Mapping[str, Any]) -> None:
    """Record the parameters of a cache folder in ``params.json`` (for people reading the cache)."""
    p = folder / "params.json"
    if not p.exists():
        atomic_write_bytes(p, json.dumps(params, indent=2, sort_keys=True, default=str).encode())


def window_indices(positions_s: np.ndarray, centre_s: float, half_window_m: float,
                   loop_length_m: float | None = None) -> np.ndarray:
    """Indices of 1-D positions (arc lengths, metres) within ``half_window_m`` of ``centre_s``;
    on a loop of length ``loop_length_m`` distances wrap around."""
    d = np.asarray(positions_s, dtype=np.float64) - centre_s
    if loop_length_m is not None:
        d = (d + loop_length_m / 2) % loop_length_m - loop_length_m / 2
    return np.flatnonzero(np.abs(d) <= half_window_m)


def build_submap(clouds: Sequence[tuple[np.ndarray, np.ndarray | None]], voxel_m: float,
                 centre: np.ndarray, radius_m: float, *, estimate: bool = False,
                 normal_radius_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Accumulate clouds already in one frame into a voxel-averaged submap with normals.

    Args:
        clouds: (points (K_i, 3), normals (K_i, 3) or None) in the submap frame (metres).
        voxel_m: voxel size (metres).
        centre: (3,) point the submap is centred on (its sensor position); points farther than
            ``radius_m`` horizontally are dropped, and normals are turned to face it.
        estimate: estimate normals by local PCA after downsampling instead of averaging the
            given ones (needed for real data without surface normals).
    Returns:
        (points (M, 3), unit normals (M, 3)), float64.
    """
    pts = np.vstack([c[0] for c in clouds]) if clouds else np.zeros((0, 3))
    have_normals = not estimate and all(c[1] is not None for c in clouds)
    nrm = np.vstack([c[1] for c in clouds]) if have_normals else None
    keep = crop_radius(pts, centre, radius_m)
    pts = pts[keep]
    nrm = nrm[keep] if nrm is not None else None
    if len(pts) < 6:
        raise InputError(f"submap has only {len(pts)} points within {radius_m} m of its centre; "
                         "check the poses and the window settings")
    pts, nrm = voxel_downsample(pts, voxel_m, nrm)
    if nrm is None:
        nrm = estimate_normals(pts, normal_radius_m)
    return pts, orient_normals(pts, nrm, centre)
