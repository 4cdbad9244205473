"""Write a drive through a ``lidar-sim`` town as a sequence in the KITTI odometry layout.

This is how "your own recordings" are tested end to end without real data: the files are exactly
what :class:`~icpbench.datasets.kitti.KittiDataset` reads from a user's folder::

    <root>/sequences/<seq>/velodyne/NNNNNN.bin   float32 x, y, z, reflectance (reflectance 0)
    <root>/sequences/<seq>/calib.txt             P0..P3 (a KITTI-like camera) and Tr (velo -> cam0)
    <root>/poses/<seq>.txt                       T_cam0(0)_cam0(i), 3x4 row-major per line

Frames: the scans are in the lidar (Velodyne) frame of each pose (x forward, y left, z up,
metres); poses follow the KITTI convention (left camera of frame 0; the loader recovers the lidar
poses as ``inv(Tr) @ P_i @ Tr``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.core.filenames import plain_name
from icpbench.datasets import submaps as sm
from icpbench.datasets.lidar_model import cast_scan
from icpbench.harness.outputs import write_file

#: T_cam0_velo of the writer: camera z forward = lidar x, camera x right = -lidar y, camera y down
#: = -lidar z, the camera 0.27 m ahead of and 0.08 m below the lidar (like KITTI's rig).
TR_CAM0_VELO = np.array([[0.0, -1.0, 0.0, 0.0],
                         [0.0, 0.0, -1.0, -0.08],
                         [1.0, 0.0, 0.0, -0.27],
                         [0.0, 0.0, 0.0, 1.0]])
_P = "7.18856e+02 0 6.071928e+02 {tx} 0 7.18856e+02 1.852157e+02 0 0 0 1 0"


def _row(T: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in np.asarray(T)[:3].ravel())


def write_kitti_sequence(ds: Any, root: str | Path, *, s_start_m: float, n_frames: int,
                         spacing_m: float, sequence: str = "00", seed: int = 0) -> Path:
    """Drive the lane centre of a single-town ``LidarSimDataset`` from arc length ``s_start_m``,
    one sweep every ``spacing_m`` metres (the teach pass's parked cars, no movers), and write the
    ``n_frames`` sweeps, calibration and poses under ``root`` in the KITTI layout.

    Returns:
        The sequence folder ``<root>/sequences/<sequence>``.
    Raises:
        InputError: fewer than 2 frames or a non-positive spacing.
    """
    if n_frames < 2 or not spacing_m > 0:
        raise InputError("need at least 2 frames and a positive spacing")
    root = Path(root)
    seq = root / "sequences" / plain_name(sequence, "sequence")
    (seq / "velodyne").mkdir(parents=True, exist_ok=True)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    scenes = [ds._static_scene(), ds._cars_scene(0)]
    T_w = [ds.sensor_pose(s_start_m + k * spacing_m) for k in range(n_frames)]
    Tr, Tr_inv = TR_CAM0_VELO, sm.inv(TR_CAM0_VELO)
    lines = []
    for k, T in enumerate(T_w):
        scan = cast_scan(scenes, T, ds.lidar, sm.sample_rng(seed, k, 911))
        rec = np.zeros((len(scan.points), 4), dtype="<f4")
        rec[:, :3] = scan.points
        rec.tofile(seq / "velodyne" / f"{k:06d}.bin")
        lines.append(_row(Tr @ sm.inv(T_w[0]) @ T @ Tr_inv))
    write_file(root / "poses" / f"{sequence}.txt", "\n".join(lines) + "\n")
    calib = [f"P{i}: " + _P.format(tx=tx) for i, tx in enumerate(("0", "-3.861448e+02", "4.538225e+01",
                                                                    "-3.372877e-01"))]
    write_file(seq / "calib.txt", "\n".join([*calib, "Tr: " + _row(Tr)]) + "\n")
    return seq
