"""Localisability per direction, in the manner of X-ICP (Tuna et al., "X-ICP: Localizability-Aware
LiDAR Registration for Robust Localization in Extreme Environments", IEEE T-RO 2024, arXiv
2211.16335).

The idea of the paper, as used here: a direction of the pose is constrained by the correspondences
whose constraint *points along it*. The point-to-plane Hessian is split into its translation block
``H_tt = sum_i w_i n_i n_i^T`` and its rotation block ``H_rr = sum_i w_i c_i c_i^T`` with
``c_i = q_i x n_i``; the eigenvectors of each block are the principal directions of that part of the
problem. For each principal direction ``v_k`` and each correspondence i, the *alignment*
``a_ik = |u_i . v_k|`` in [0, 1] measures how much the correspondence's unit constraint direction
``u_i`` (``n_i`` for translation, ``c_i / |c_i|`` for rotation) pushes along ``v_k``. The
localisability of direction k is the weighted sum of the alignments that are strong enough to
matter:

``L_k = sum_i w_i a_ik [a_ik >= kappa]``

(units: correspondences; a direction no correspondence faces has ``L_k = 0``). The paper filters
weak contributions in the same spirit before summing and then sorts directions into fully,
partially and not localisable with thresholds; this module reports the sums and leaves thresholds to
the caller. Choices made here (not the paper's constants): ``kappa = 0.3`` by default, weights
``w_i`` from the caller (the ICP's Cauchy weights at the true pose in
:mod:`icpbench.analysis.predictors`), and the rotation directions normalised per correspondence so
that a far point does not count more than a near one (the lever arm enters the Hessian, not the
localisability).

Frames and units: points and normals (K, 3) in one frame (the map frame for the harness's pose
error); directions are unit vectors in that frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icpbench.core.errors import InputError

#: Smallest alignment that counts towards a direction's localisability (default).
KAPPA = 0.3
#: Cross products shorter than this (metres) have no rotation direction (a point on its own normal
#: line through the origin constrains no rotation).
MIN_LEVER_M = 1e-9


@dataclass(frozen=True)
class Localisability:
    """Localisability of the principal directions of translation and rotation.

    Attributes:
        trans_dirs: (3, 3) unit eigenvectors of ``H_tt`` as columns, ascending eigenvalue.
        trans: (3,) localisability L_k of each translation direction (correspondences).
        rot_dirs: (3, 3) unit eigenvectors of ``H_rr`` as columns, ascending eigenvalue.
        rot: (3,) localisability of each rotation direction (correspondences).
        kappa: the alignment threshold used.
    """

    trans_dirs: np.ndarray
    trans: np.ndarray
    rot_dirs: np.ndarray
    rot: np.ndarray
    kappa: float

    @property
    def trans_min(self) -> float:
        """Localisability of the weakest translation direction."""
        return float(self.trans.min())

    @property
    def rot_min(self) -> float:
        """Localisability of the weakest rotation direction."""
        return float(self.rot.min())

    def weakest_translation(self) -> np.ndarray:
        """(3,) unit direction of the least localisable translation."""
        return self.trans_dirs[:, int(np.argmin(self.trans))]

    def along(self, direction: np.ndarray) -> float:
        """Localisability of translation along a unit ``direction`` (3,): the L of the principal
        direction best aligned with it."""
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        return float(self.trans[int(np.argmax(np.abs(self.trans_dirs.T @ d)))])


def _directions(block: np.ndarray) -> np.ndarray:
    _, vecs = np.linalg.eigh(block)
    return vecs


def _filtered_sum(u: np.ndarray, w: np.ndarray, dirs: np.ndarray, kappa: float) -> np.ndarray:
    a = np.abs(u @ dirs)  # (K, 3) alignment of each correspondence with each direction
    return ((a >= kappa) * a * w[:, None]).sum(axis=0)


def localisability(points: np.ndarray, normals: np.ndarray, weights: np.ndarray | None = None,
                   kappa: float = KAPPA) -> Localisability:
    """Localisability of the translation and rotation directions (see the module doc).

    Args:
        points: (K, 3) associated scan points ``q_i``, metres (map frame: at the true pose).
        normals: (K, 3) unit normals ``n_i`` of their map points.
        weights: (K,) non-negative weights (default 1).
        kappa: alignment threshold in [0, 1].

    Raises:
        InputError: shapes that differ or are not (K, 3), non-finite values, bad weights or kappa.
    """
    q = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3 or q.shape != n.shape:
        raise InputError(f"points and normals must both be (K, 3), got {q.shape} and {n.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(n))):
        raise InputError("points or normals have NaN or Inf entries")
    w = np.ones(q.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (q.shape[0],) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError(f"weights must be {q.shape[0]} finite non-negative numbers")
    if not 0.0 <= kappa <= 1.0:
        raise InputError(f"kappa must lie in [0, 1], got {kappa}")
    c = np.cross(q, n)
    lever = np.linalg.norm(c, axis=1)
    has_rot = lever > MIN_LEVER_M
    u_rot = np.zeros_like(c)
    u_rot[has_rot] = c[has_rot] / lever[has_rot, None]
    t_dirs = _directions((n * w[:, None]).T @ n)
    r_dirs = _directions((c * w[:, None]).T @ c)
    return Localisability(trans_dirs=t_dirs, trans=_filtered_sum(n, w, t_dirs, kappa),
                          rot_dirs=r_dirs, rot=_filtered_sum(u_rot, w, r_dirs, kappa),
                          kappa=float(kappa))
