"""Shared machinery of the black-box ICP targets (Open3D, KISS-ICP, small_gicp).

:class:`BlackBoxTarget` implements :meth:`~icpbench.targets.base.Target.register` once for every
library that registers one scan at a time: it checks the batch, drops non-finite scan points,
calls the subclass's :meth:`BlackBoxTarget._register_one` per sample and assembles the
:class:`~icpbench.core.types.Registration`, with the same health statuses as our differentiable ICP
(:mod:`icpbench.targets.icp`).

This module imports no optional library (only NumPy, SciPy, torch and icpbench), so a missing
optional library still disables only its own plugin.

Frames: scans (B, N, 3) in the sensor frame, maps in their map frame, transforms ``T_map_scan``
(4, 4) as everywhere in icpbench. 6-vectors and 6x6 matrices are ordered ``[rho, phi]`` (metres,
radians) for left increments ``T <- exp(delta^) T``.
"""

from __future__ import annotations

import functools
import json
from abc import abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import fields
from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from icpbench.core.errors import InputError
from icpbench.core.types import Registration
from icpbench.targets import forward_cache
from icpbench.targets.base import Target
from icpbench.targets.icp import ICPConfig, icp_config

_ICP_FIELDS = frozenset(f.name for f in fields(ICPConfig))


class OneResult(NamedTuple):
    """Outcome of registering one scan, before the health check.

    Attributes:
        T: (4, 4) float64 ``T_map_scan`` returned by the library.
        converged: the library's stopping test (or the target's documented proxy) passed before
            the iteration cap.
        iterations: iterations used; ``-1`` when the library does not report them, ``0`` when it
            was not called.
        n_inliers: correspondences at the final pose.
        H: (6, 6) Gauss-Newton matrix ``[rho, phi]`` at ``T`` for the conditioning check, or
            ``None`` when the library was not run.
    """

    T: np.ndarray
    converged: bool
    iterations: int
    n_inliers: int
    H: np.ndarray | None


class BlackBoxTarget(Target):
    """A non-differentiable target that registers the scans of a batch one by one.

    Subclasses set ``map_type`` (the class of the handles their :meth:`prepare` returns) and
    ``min_correspondences`` (an int attribute, usually the preset's), and implement
    :meth:`_register_one`.
    """

    differentiable: ClassVar[bool] = False
    map_type: ClassVar[type]
    min_correspondences: int
    #: The library's registration is a function of the scan, the initial pose, the prepared map
    #: and the settings alone (one thread, no random draws), so a registration asked for again
    #: (the ensemble's best scan, queried during the attack, registered once more for its row)
    #: is taken from :mod:`icpbench.targets.forward_cache`; a subclass that draws at random sets
    #: it False.
    deterministic: ClassVar[bool] = True

    @functools.cached_property
    def _cache_settings(self) -> tuple[str, str]:
        """What identifies this target's registrations in the cache: its class and settings."""
        return (f"{type(self).__module__}.{type(self).__qualname__}",
                json.dumps(self.settings(), sort_keys=True, default=str))

    def register(self, scans: torch.Tensor, maps: Sequence[Any],
                 T_init: torch.Tensor) -> Registration:
        """Register each scan (N, 3), sensor frame, to its prepared map; returns float64 T (B, 4, 4).

        Non-finite scan points are dropped before the library sees them; with fewer than
        ``min_correspondences`` finite points the library is not called and the sample keeps
        ``T_init`` with status ``too_few_correspondences``. ``inlier_fraction`` is relative to all
        N points, so dropped points count as outliers.
        """
        S, T0 = batch_to_numpy(scans, maps, T_init, self.map_type, f"{type(self).__name__}.prepare")
        outs = []
        for b in range(S.shape[0]):
            pts = np.ascontiguousarray(S[b][np.isfinite(S[b]).all(axis=1)])
            if pts.shape[0] < self.min_correspondences:
                outs.append(OneResult(T0[b].copy(), False, 0, 0, None))
                continue
            key = (forward_cache.sample_key(self._cache_settings, S[b], T0[b], maps[b])
                   if self.deterministic else None)
            found = None if key is None else forward_cache.get(key)
            if found is None:
                found = OneResult(*self._register_one(pts, maps[b], T0[b]))
                if key is not None:
                    forward_cache.put(key, maps[b], found)
            outs.append(found)
        N = S.shape[1]
        status = [health_status(o.T, o.n_inliers, o.H, o.converged, self.min_correspondences)
                  for o in outs]
        return Registration(
            T=torch.as_tensor(np.stack([o.T for o in outs]), dtype=torch.float64),
            converged=torch.tensor([s == "ok" for s in status], dtype=torch.bool),
            iterations=torch.tensor([o.iterations for o in outs], dtype=torch.long),
            inlier_fraction=torch.tensor([o.n_inliers / max(N, 1) for o in outs],
                                         dtype=torch.float64),
            status=status,
        )

    @abstractmethod
    def _register_one(self, scan: np.ndarray, target: Any, T0: np.ndarray) -> OneResult:
        """Register one scan.

        Args:
            scan: (K, 3) float64, C-contiguous, finite points (sensor frame), K >= min_correspondences.
            target: the map handle from :meth:`prepare` (an instance of ``map_type``).
            T0: (4, 4) float64 initial ``T_map_scan``.

        Returns:
            ``(T, converged, iterations, n_inliers, H)`` as in :class:`OneResult`.
        """


def resolve_preset(preset: ICPConfig | str | None, overrides: Mapping[str, Any],
                   target: str) -> ICPConfig:
    """The ICP preset (name or ``ICPConfig``) with ``ICPConfig`` field overrides applied.

    Raises InputError for names that are neither the target's keywords nor ``ICPConfig`` fields,
    and for the smooth d_max gate (which no black-box library has).
    """
    unknown = sorted(set(overrides) - _ICP_FIELDS)
    if unknown:
        raise InputError(
            f"{target}: unknown setting(s) {', '.join(unknown)}; pass the target's own keywords or "
            f"ICPConfig fields ({', '.join(sorted(_ICP_FIELDS))})"
        )
    cfg = icp_config(preset, **overrides)
    if cfg.soft_dmax:
        raise InputError(f"{target} has no smooth d_max gate: use soft_dmax=False")
    return cfg


def batch_to_numpy(scans: torch.Tensor, maps: Sequence[Any], T_init: torch.Tensor, map_type: type,
                   prepare_name: str) -> tuple[np.ndarray, np.ndarray]:
    """Check a batch and return float64 scans (B, N, 3) and T_init (B, 4, 4) as NumPy arrays."""
    if not isinstance(scans, torch.Tensor) or scans.ndim != 3 or scans.shape[-1] != 3:
        raise InputError(f"scans must be a (B, N, 3) tensor, got {getattr(scans, 'shape', type(scans))}")
    B = scans.shape[0]
    if len(maps) != B:
        raise InputError(f"got {len(maps)} maps for a batch of {B} scans")
    if tuple(T_init.shape) != (B, 4, 4):
        raise InputError(f"T_init must have shape ({B}, 4, 4), got {tuple(T_init.shape)}")
    for m in maps:
        if not isinstance(m, map_type):
            raise InputError(f"maps must come from {prepare_name}(...), got {type(m).__name__}")
    T0 = T_init.detach().cpu().to(torch.float64).numpy()
    if not np.all(np.isfinite(T0)):
        raise InputError("T_init has NaN or Inf entries")
    return scans.detach().cpu().to(torch.float64).numpy(), T0


def increment_norm(T_from: np.ndarray, T_to: np.ndarray) -> float:
    """``||log(T_to T_from^-1)||`` of the left increment ``[rho, phi]`` (m and rad mixed), the
    quantity our ICP and KISS test against their tolerance (NumPy: ~40x cheaper than torch here)."""
    D = T_to @ np.linalg.inv(T_from)
    phi = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    th = float(np.linalg.norm(phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    # inverse left Jacobian of SO(3); series 1/12 + th^2/720 near 0
    c = 1 / 12 + th**2 / 720 if th < 1e-4 else 1 / th**2 - (1 + np.cos(th)) / (2 * th * np.sin(th))
    rho = (np.eye(3) - 0.5 * K + c * K @ K) @ D[:3, 3]
    return float(np.sqrt(rho @ rho + th**2))


def point_to_point_hessian(q: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """6x6 Gauss-Newton matrix ``sum_k w_k J_k^T J_k`` of point-to-point residuals, ``[rho, phi]``.

    Args:
        q: (K, 3) transformed scan points (map frame) that have a correspondence.
        w: (K,) weights, or ``None`` for 1.

    ``J_k = [I, -[q_k]x]`` is the Jacobian of ``exp(delta^) q_k`` at ``delta = 0``.
    """
    w = np.ones(q.shape[0]) if w is None else w
    H = np.zeros((6, 6))
    H[:3, :3] = w.sum() * np.eye(3)
    s = (w[:, None] * q).sum(0)
    Sx = np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]])
    H[:3, 3:] = -Sx
    H[3:, :3] = Sx
    H[3:, 3:] = (w * (q * q).sum(1)).sum() * np.eye(3) - (w[:, None] * q).T @ q
    return H


def health_status(T: np.ndarray, n_inliers: int, H: np.ndarray | None, converged: bool,
                  min_inliers: int) -> str:
    """ok / nonfinite / too_few_correspondences / singular / not_converged (as in targets/icp.py)."""
    if not np.all(np.isfinite(T)):
        return "nonfinite"
    if n_inliers < min_inliers or H is None:
        return "too_few_correspondences"
    ev = np.linalg.eigvalsh(np.nan_to_num(H))
    if ev[0] <= 1e-10 * max(ev[-1], 1e-300):
        return "singular"
    return "ok" if converged else "not_converged"
