"""A small lidar-like synthetic scene (ground plane, boxes, poles) for tests and benchmarks.

Points are sampled from the exact surfaces, so normals are exact; no ray casting (the simulated
town with a lidar model is :mod:`icpbench.datasets.lidar_sim`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from icpbench.core.types import Sample


def _box_surface(rng: np.random.Generator, center, size, yaw, n) -> tuple[np.ndarray, np.ndarray]:
    """Uniform samples (n, 3) on the 4 walls and the roof of a yawed box, with outward normals."""
    sx, sy, sz = size
    areas = np.array([sy * sz, sy * sz, sx * sz, sx * sz, sx * sy])
    face = rng.choice(5, size=n, p=areas / areas.sum())
    u, v = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    p = np.zeros((n, 3))
    nrm = np.zeros((n, 3))
    for f, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1)]):
        k = face == f
        if axis == 0:
            p[k] = np.c_[np.full(k.sum(), sign * sx / 2), u[k] * sy, (v[k] + 0.5) * sz]
        elif axis == 1:
            p[k] = np.c_[u[k] * sx, np.full(k.sum(), sign * sy / 2), (v[k] + 0.5) * sz]
        else:
            p[k] = np.c_[u[k] * sx, v[k] * sy, np.full(k.sum(), sz)]
        nrm[k, axis] = sign
    Rz = Rotation.from_euler("z", yaw).as_matrix()
    return p @ Rz.T + np.asarray(center), nrm @ Rz.T


def _pole_surface(rng, center, radius, height, n) -> tuple[np.ndarray, np.ndarray]:
    a = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(0, height, n)
    nrm = np.c_[np.cos(a), np.sin(a), np.zeros(n)]
    return np.c_[center[0] + radius * nrm[:, 0], center[1] + radius * nrm[:, 1], z], nrm


def scene_points(n_points: int, seed: int = 0, extent_m: float = 40.0,
                 n_boxes: int = 10, n_poles: int = 16,
                 sampling_seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``n_points`` surface points (map frame, metres) and exact unit normals of a scene
    made of a ground square of side ``2 * extent_m``, yawed boxes and cylindrical poles.

    ``seed`` fixes the geometry; ``sampling_seed`` (default: ``seed``) the surface samples."""
    rng = np.random.default_rng(seed if sampling_seed is None else sampling_seed)
    scene = np.random.default_rng(10_000 + seed)  # geometry independent of the sample count
    boxes = []
    for _ in range(n_boxes):
        while True:
            c = scene.uniform(-extent_m * 0.8, extent_m * 0.8, 2)
            if np.linalg.norm(c) > 8:
                break
        boxes.append((np.r_[c, 0.0], scene.uniform([3, 3, 3], [10, 10, 12]),
                      scene.uniform(-0.4, 0.4)))
    poles = [(scene.uniform(-extent_m * 0.7, extent_m * 0.7, 2), scene.uniform(0.15, 0.3),
              scene.uniform(4, 8)) for _ in range(n_poles)]
    n_ground = n_points // 2
    n_box = (n_points - n_ground) * 3 // 4 // max(n_boxes, 1)
    n_pole = (n_points - n_ground - n_box * n_boxes) // max(n_poles, 1)
    pts = [np.c_[rng.uniform(-extent_m, extent_m, (n_ground, 2)), np.zeros(n_ground)]]
    nrm = [np.tile([0.0, 0.0, 1.0], (n_ground, 1))]
    for c, s, y in boxes:
        p, n = _box_surface(rng, c, s, y, n_box)
        pts.append(p)
        nrm.append(n)
    for c, r, h in poles:
        p, n = _pole_surface(rng, c, r, h, n_pole)
        pts.append(p)
        nrm.append(n)
    P, Nn = np.vstack(pts), np.vstack(nrm)
    k = n_points - P.shape[0]
    if k > 0:  # top up with ground points
        P = np.vstack([P, np.c_[rng.uniform(-extent_m, extent_m, (k, 2)), np.zeros(k)]])
        Nn = np.vstack([Nn, np.tile([0.0, 0.0, 1.0], (k, 1))])
    return P.astype(np.float32), Nn.astype(np.float32)


def random_transform(rng: np.random.Generator, trans_m: float, rot_deg: float,
                     yaw_only: bool = False) -> np.ndarray:
    """A (4, 4) transform with uniform translation in [-trans_m, trans_m]^3 and rotation angles in
    [-rot_deg, rot_deg] (yaw only, or roll/pitch/yaw)."""
    T = np.eye(4)
    if yaw_only:
        T[:3, :3] = Rotation.from_euler("z", rng.uniform(-rot_deg, rot_deg), degrees=True).as_matrix()
        T[:2, 3] = rng.uniform(-trans_m, trans_m, 2)
    else:
        T[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-rot_deg, rot_deg, 3),
                                        degrees=True).as_matrix()
        T[:3, 3] = rng.uniform(-trans_m, trans_m, 3)
    return T


def scene_sample(n_scan: int = 2_000, n_map: int = 20_000, seed: int = 0, noise_m: float = 0.0,
                 trans_m: float = 0.3, rot_deg: float = 5.0, scene_seed: int = 0,
                 scan_from_map: bool = False) -> Sample:
    """A registration problem on the synthetic scene.

    The scan is an independent set of surface samples of the same scene (or, with
    ``scan_from_map``, a subset of the map points, so exact alignment exists), expressed in a
    sensor frame offset by a random transform: ``scan = inv(T_gt) @ points`` so ``T_gt`` maps
    scan->map. ``T_init`` is the identity (as in the paper).
    """
    rng = np.random.default_rng(seed)
    map_pts, map_n = scene_points(n_map, seed=scene_seed)
    if scan_from_map:
        world = map_pts
    else:
        world, _ = scene_points(n_scan * 4, seed=scene_seed, sampling_seed=1_000 + seed)
    near = world[np.linalg.norm(world[:, :2], axis=1) < 30.0]
    pick = rng.choice(near.shape[0], size=n_scan, replace=near.shape[0] < n_scan)
    world = near[pick].astype(np.float64)
    if noise_m > 0:
        world = world + rng.normal(0, noise_m, world.shape)
    T_gt = random_transform(rng, trans_m, rot_deg)
    T_inv = np.linalg.inv(T_gt)
    scan = world @ T_inv[:3, :3].T + T_inv[:3, 3]
    return Sample(id=f"synthetic/{scene_seed}/{seed}", scan=scan.astype(np.float32), map=map_pts,
                  map_normals=map_n, T_gt=T_gt, T_init=np.eye(4),
                  meta={"scene_seed": scene_seed})
