"""Target ``kabsch-icp``: textbook point-to-point ICP with the closed-form SVD step.

Besl and McKay (1992) with the rotation of Arun, Huang and Blostein (1987); NumPy + SciPy, no
gradient. It shows the whole target contract: ``prepare`` once per map, ``register`` per batch.
"""

from typing import ClassVar

import numpy as np
import torch
from scipy.spatial import cKDTree

from icpbench.core.types import Registration
from icpbench.targets.base import Target
from icpbench.targets.icp import icp_config


class KabschICP(Target):
    """Point-to-point ICP, SVD update, hard max-distance gate (numpy, black box)."""

    name: ClassVar[str] = "kabsch-icp"
    description: ClassVar[str] = "Textbook point-to-point ICP with SVD steps (example plugin)"
    differentiable: ClassVar[bool] = False

    def __init__(self, preset="lidar", **overrides):
        self.config = icp_config(preset, **overrides)

    def prepare(self, map_points, map_normals):
        pts = np.asarray(map_points, dtype=np.float64)
        return pts, cKDTree(pts)

    def register(self, scans, maps, T_init):
        cfg = self.config
        Ts, conv, iters, inl = [], [], [], []
        for b, (pts, tree) in enumerate(maps):
            p = scans[b].detach().double().numpy()
            T = T_init[b].double().numpy().copy()
            done, k, ok = False, cfg.max_iterations, np.zeros(len(p), bool)
            for it in range(cfg.max_iterations):
                q = p @ T[:3, :3].T + T[:3, 3]
                d, idx = tree.query(q, distance_upper_bound=cfg.d_max or np.inf)
                ok = np.isfinite(d)
                if ok.sum() < 3:
                    break
                a, m = q[ok], pts[idx[ok]]
                ca, cm = a.mean(0), m.mean(0)
                U, _, Vt = np.linalg.svd((a - ca).T @ (m - cm))
                S = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
                R = Vt.T @ S @ U.T
                step = np.eye(4)
                step[:3, :3], step[:3, 3] = R, cm - R @ ca
                T = step @ T
                if np.linalg.norm(step[:3, 3]) + np.linalg.norm(R - np.eye(3)) < cfg.tol:
                    done, k = True, it + 1
                    break
            Ts.append(T)
            conv.append(done)
            iters.append(k)
            inl.append(ok.mean())
        return Registration(T=torch.as_tensor(np.stack(Ts)), converged=torch.tensor(conv),
                            iterations=torch.tensor(iters),
                            inlier_fraction=torch.tensor(inl, dtype=torch.float64),
                            status=["ok" if c else "not_converged" for c in conv])
