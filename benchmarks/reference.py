"""The fixed reference of every benchmark: one Open3D point-to-plane ICP of the same scan and map.

Every case in ``bench_generator.py`` and ``bench_training.py`` is printed as a ratio to this
reference measured in the same run, so that numbers taken on different (or differently loaded)
machines compare: Open3D's legacy ``registration_icp``, point-to-plane with a Cauchy kernel
(k = 1 m), correspondences within 5 m (the lidar preset), exactly 30 iterations (relative fitness
and RMSE criteria 0), 1 thread; its time includes its KD-tree build of the map, as in every call.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import open3d as o3d

from icpbench.core.types import Sample

ITERS = 30
THREADS = 1
reg = o3d.pipelines.registration


def open3d_icp(sample: Sample) -> Callable[[], object]:
    """A callable running the reference ICP of ``sample``'s scan against its map."""
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample.map.astype(np.float64)))
    tgt.normals = o3d.utility.Vector3dVector(sample.map_normals.astype(np.float64))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample.scan.astype(np.float64)))
    est = reg.TransformationEstimationPointToPlane(reg.CauchyLoss(k=1.0))
    crit = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=ITERS)
    T0 = np.asarray(sample.T_init, dtype=np.float64)

    def run():
        o3d.utility.set_max_threads(THREADS)
        return reg.registration_icp(src, tgt, 5.0, T0, est, crit)

    return run
