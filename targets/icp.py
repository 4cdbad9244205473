"""Differentiable multi-iteration ICP (point-to-plane and point-to-point) in PyTorch.

A re-implementation of the algorithm of dICP (Lisus et al., "Pointing the Way: Refining Radar-Lidar
Localization Using Learned ICP Weights", 2023) used by Zhang et al. (ICRA 2025), with the nearest
neighbour search moved to a KD-tree outside autograd:

* correspondences are re-computed every iteration (nearest map point of each transformed scan
  point); the *choice* of neighbour carries no gradient, gradients flow through the residuals,
  the weights and the Gauss-Newton solve, unrolled over all iterations (``backprop="unrolled"``)
  or, with ``backprop="implicit"``, by the implicit function theorem at the final pose (the
  iterations themselves build no graph);
* Cauchy robust weight ``1 / (1 + (r / c)^2)`` on the point-to-plane residual ``r = n.(q - m)``
  (point-to-point: on ``||q - m||``), not detached (IRLS is differentiated through);
* maximum correspondence distance ``d_max``: a hard gate, or optionally a smooth
  ``0.5 + 0.5 tanh(k (d_max - d) / d_max)`` gate for training;
* left-perturbation update ``T <- exp(delta^) T`` with ``delta = [rho, phi]``;
* per-sample convergence when ``||delta|| < tol``; a converged sample is frozen, so a batch gives
  the same result as its samples one by one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import numpy as np
import torch

from icpbench.errors import InputError
from icpbench.mapindex import MapIndex
from icpbench.se3 import hat, se3_exp
from icpbench.types import Registration

Mode = Literal["plane", "point"]
Backprop = Literal["unrolled", "implicit"]


@dataclass(frozen=True)
class ICPConfig:
    """Settings of the differentiable ICP.

    Attributes:
        max_iterations: cap on Gauss-Newton iterations.
        tol: convergence threshold on ``||delta||_2`` of the 6-vector increment (m and rad mixed,
            as in dICP).
        cauchy_c: Cauchy parameter c (metres); ``None`` disables the robust kernel.
        d_max: maximum correspondence distance (metres); ``None`` disables the filter.
        soft_dmax: use the smooth gate instead of the hard one (training only).
        soft_steepness: k of the smooth gate (dimensionless; the gate falls from 0.88 to 0.12
            over about ``2 / k * d_max``).
        damping: relative Levenberg damping added to the 6x6 normal equations
            (``damping * trace(H) / 6``); keeps degenerate (planar/collinear) scans finite.
        min_correspondences: fewer inliers than this marks the sample ``too_few_correspondences``.
        kdtree_workers: threads of the KD-tree query.
        backprop: how gradients reach the scan: ``"unrolled"`` (dICP, through every iteration)
            or ``"implicit"`` (the iterations run without a graph; the gradient is the
            implicit-function derivative of the final pose, exact at a converged pose; the pose
            value is unchanged and training can use the evaluation's iteration cap).
    """

    max_iterations: int = 100
    tol: float = 1e-4
    cauchy_c: float | None = 1.0
    d_max: float | None = 5.0
    soft_dmax: bool = False
    soft_steepness: float = 10.0
    damping: float = 1e-9
    min_correspondences: int = 6
    kdtree_workers: int = 1
    backprop: Backprop = "unrolled"

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise InputError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if not self.tol > 0:
            raise InputError(f"tol must be > 0, got {self.tol}")
        if self.backprop not in ("unrolled", "implicit"):
            raise InputError(f"backprop must be 'unrolled' or 'implicit', got {self.backprop!r}")
        for name in ("cauchy_c", "d_max"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive number or None, got {v}")

    def with_(self, **kw: Any) -> ICPConfig:
        """A copy with some fields replaced."""
        return replace(self, **kw)


#: The paper's settings (Zhang et al. 2025, §IV-C and §IV-D).
PRESETS: dict[str, ICPConfig] = {
    "objects": ICPConfig(max_iterations=150, tol=1e-4, cauchy_c=0.15, d_max=0.3),
    "objects-train": ICPConfig(max_iterations=25, tol=1e-4, cauchy_c=0.15, d_max=0.3),
    "lidar": ICPConfig(max_iterations=100, tol=1e-4, cauchy_c=1.0, d_max=5.0),
    "lidar-train": ICPConfig(max_iterations=25, tol=1e-4, cauchy_c=1.0, d_max=5.0),
}


def icp_config(preset: str | ICPConfig | None = "lidar", **overrides: Any) -> ICPConfig:
    """Resolve a preset name (``objects``, ``lidar``, ``*-train``) plus overrides."""
    if isinstance(preset, ICPConfig):
        base = preset
    elif preset is None:
        base = ICPConfig()
    else:
        if preset not in PRESETS:
            raise InputError(f"unknown ICP preset {preset!r}; valid: {', '.join(PRESETS)}")
        base = PRESETS[preset]
    unknown = sorted(set(overrides) - set(ICPConfig.__dataclass_fields__))
    if unknown:
        raise InputError(f"unknown ICP setting(s) {', '.join(map(repr, unknown))}; valid: "
                         f"{', '.join(ICPConfig.__dataclass_fields__)}")
    return base.with_(**overrides) if overrides else base


def _gate(d: torch.Tensor, cfg: ICPConfig) -> torch.Tensor:
    """Max-distance weight for 3-D correspondence distances d (B, N)."""
    if cfg.d_max is None:
        return torch.ones_like(d)
    if cfg.soft_dmax:
        return 0.5 + 0.5 * torch.tanh(cfg.soft_steepness * (cfg.d_max - d) / cfg.d_max)
    return (d < cfg.d_max).to(d.dtype)


def _cauchy(r2: torch.Tensor, cfg: ICPConfig) -> torch.Tensor:
    if cfg.cauchy_c is None:
        return torch.ones_like(r2)
    return 1.0 / (1.0 + r2 / (cfg.cauchy_c**2))


def icp(
    scans: torch.Tensor,
    maps: Sequence[MapIndex],
    T_init: torch.Tensor,
    cfg: ICPConfig,
    mode: Mode = "plane",
) -> Registration:
    """Run batched differentiable ICP.

    Args:
        scans: (B, N, 3) scan points, sensor frame, metres (float32 or float64; may require grad).
        maps: B prepared maps (``MapIndex``); point-to-plane needs their normals.
        T_init: (B, 4, 4) initial scan->map transforms.
        cfg: ICP settings.
        mode: ``"plane"`` (point-to-plane) or ``"point"`` (point-to-point).

    Returns:
        Registration with differentiable T (B, 4, 4) in ``scans``' dtype.
    """
    if scans.ndim != 3 or scans.shape[-1] != 3:
        raise InputError(f"scans must have shape (B, N, 3), got {tuple(scans.shape)}")
    B, N, _ = scans.shape
    if len(maps) != B:
        raise InputError(f"got {len(maps)} maps for a batch of {B} scans")
    if T_init.shape != (B, 4, 4):
        raise InputError(f"T_init must have shape ({B}, 4, 4), got {tuple(T_init.shape)}")
    if not scans.is_floating_point():
        raise InputError(f"scans must be floating point, got {scans.dtype}")
    dtype = scans.dtype
    if mode == "plane" and any(m.normals is None for m in maps):
        raise InputError("point-to-plane ICP needs map normals")

    finite = torch.isfinite(scans).all(-1)  # (B, N)
    p = torch.where(finite[..., None], scans, torch.zeros((), dtype=dtype))
    T = T_init.to(dtype)
    R, t = T[:, :3, :3], T[:, :3, 3]
    map_t = [m.tensors(dtype) for m in maps]
    active = torch.ones(B, dtype=torch.bool)
    iterations = torch.full((B,), cfg.max_iterations, dtype=torch.long)
    converged = torch.zeros(B, dtype=torch.bool)
    n_inliers = torch.zeros(B, dtype=torch.long)
    query_bound = np.inf if cfg.d_max is None else (cfg.d_max * (3.0 if cfg.soft_dmax else 1.0))

    H_last = torch.zeros(B, 6, 6, dtype=dtype)
    # Query the KD-tree in a spatially coherent order (1 m voxels of the scan, fixed for the run):
    # measured ~25% faster queries; the result does not depend on the order.
    p_np = p.detach().to(torch.float64).numpy()
    orders = [np.lexsort(np.floor(p_np[b] / 1.0).T[::-1]) for b in range(B)]
    implicit = cfg.backprop == "implicit" and scans.requires_grad and torch.is_grad_enabled()
    src = p.detach() if implicit else p
    with torch.set_grad_enabled(torch.is_grad_enabled() and not implicit):
        for it in range(cfg.max_iterations):
            H, g, w = _linearise(src, R, t, maps, map_t, finite, orders, active, query_bound, cfg,
                                 mode)
            n_inliers = torch.where(active, (w.detach() > 0).sum(1), n_inliers)
            H_last = torch.where(active[:, None, None], H.detach(), H_last)
            delta = _solve(H, g, cfg)
            delta = torch.where(active[:, None], delta, torch.zeros((), dtype=dtype))
            R, t = _left_update(delta, R, t)
            step = torch.linalg.norm(delta.detach(), dim=-1)
            newly = active & (step < cfg.tol)
            iterations = torch.where(newly, torch.full_like(iterations, it + 1), iterations)
            converged = converged | newly
            active = active & ~newly
            if not bool(active.any()):
                break

    if implicit:
        R, t = _implicit_pose(p, R.detach(), t.detach(), maps, map_t, finite, orders, query_bound,
                              cfg, mode)

    T_out = torch.cat([torch.cat([R, t[..., None]], -1),
                       T_init[:, 3:4, :].to(dtype)], 1)
    status = _health(H_last, n_inliers, converged, T_out.detach(), cfg)
    converged = converged & torch.tensor([s == "ok" for s in status])
    return Registration(
        T=T_out,
        converged=converged,
        iterations=iterations,
        inlier_fraction=n_inliers.to(torch.float64) / max(N, 1),
        status=status,
    )


def _linearise(p: torch.Tensor, R: torch.Tensor, t: torch.Tensor, maps: Sequence[MapIndex],
               map_t: list, finite: torch.Tensor, orders: list[np.ndarray], active: torch.Tensor,
               query_bound: float, cfg: ICPConfig, mode: Mode
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Gauss-Newton linearisation at the pose (R (B, 3, 3), t (B, 3)) of scan points p (B, N, 3).

    Correspondences (KD-tree, no gradient) for the ``active`` samples only (the others get none).
    Returns H (B, 6, 6), g (B, 6) of the IRLS normal equations ``H delta = -g`` and the weights
    w (B, N) (0 for points without a correspondence)."""
    B, N, _ = p.shape
    dtype = p.dtype
    q = p @ R.transpose(1, 2) + t[:, None, :]  # (B, N, 3), map frame
    q_np = q.detach().to(torch.float64).numpy()
    m_list, n_list, ok_list = [], [], []
    for b in range(B):
        if not bool(active[b]):
            idx = np.full(N, len(maps[b]), dtype=np.int64)
        else:
            qb = np.where(finite[b].numpy()[:, None], q_np[b], np.nan)[orders[b]]
            idx = np.empty(N, dtype=np.int64)
            idx[orders[b]] = maps[b].query(qb, query_bound)[1]
        idx_t = torch.from_numpy(idx)
        pts, nrm = map_t[b]
        m_list.append(torch.index_select(pts, 0, idx_t))
        if nrm is not None:
            n_list.append(torch.index_select(nrm, 0, idx_t))
        ok_list.append(idx_t < len(maps[b]))
    m = torch.stack(m_list)
    ok = torch.stack(ok_list) & finite
    diff = q - m
    d = torch.linalg.norm(torch.where(ok[..., None], diff, torch.ones((), dtype=dtype)), dim=-1)
    if mode == "plane":
        nn = torch.stack(n_list)
        r = (diff * nn).sum(-1)  # (B, N)
        w = _gate(d, cfg) * _cauchy(r * r, cfg)
        w = torch.where(ok, w, torch.zeros((), dtype=dtype))
        r = torch.where(ok, r, torch.zeros((), dtype=dtype))
        qx, qy, qz = q.unbind(-1)
        nx, ny, nz = nn.unbind(-1)
        qxn = torch.stack([qy * nz - qz * ny, qz * nx - qx * nz, qx * ny - qy * nx], -1)
        J = torch.cat([nn, qxn], -1)  # (B, N, 6): [d/drho, d/dphi]
        Jw = J * w[..., None]
        H = Jw.transpose(1, 2) @ J
        g = (Jw * r[..., None]).sum(1)
    else:
        e = torch.where(ok[..., None], diff, torch.zeros((), dtype=dtype))  # (B, N, 3)
        w = _gate(d, cfg) * _cauchy((e * e).sum(-1), cfg)
        w = torch.where(ok, w, torch.zeros((), dtype=dtype))
        # de/drho = I, de/dphi = -[q]x
        Jphi = -hat(q)  # (B, N, 3, 3)
        sw = w.sum(1)
        Hrr = sw[:, None, None] * torch.eye(3, dtype=dtype)
        Hrp = (w[..., None, None] * Jphi).sum(1)
        Hpp = (w[..., None, None] * (Jphi.transpose(-1, -2) @ Jphi)).sum(1)
        H = torch.cat([torch.cat([Hrr, Hrp], 2), torch.cat([Hrp.transpose(1, 2), Hpp], 2)], 1)
        g = torch.cat([(w[..., None] * e).sum(1),
                       (w[..., None, None] * Jphi.transpose(-1, -2) @ e[..., None])[..., 0]
                       .sum(1)], -1)
    return H, g, w


def _implicit_pose(p: torch.Tensor, R0: torch.Tensor, t0: torch.Tensor, maps: Sequence[MapIndex],
                   map_t: list, finite: torch.Tensor, orders: list[np.ndarray], query_bound: float,
                   cfg: ICPConfig, mode: Mode) -> tuple[torch.Tensor, torch.Tensor]:
    """The final pose (R0 (B, 3, 3), t0 (B, 3), no graph) with the implicit-function gradient.

    At the converged pose the IRLS gradient ``g(T, X)`` (B, 6) vanishes, so
    ``dT/dX = -(dg/d delta)^-1 dg/dX`` (implicit function theorem; Blondel et al., "Efficient and
    Modular Implicit Differentiation", NeurIPS 2022), correspondences held fixed as in the unrolled
    mode. ``dg/d delta`` (B, 6, 6) is the exact Jacobian (Cauchy weights and rotation included, by
    autograd at ``delta = 0``), not the Gauss-Newton ``H``. The returned pose has the value of
    (R0, t0): the increment ``delta - delta.detach()`` is zero, only its gradient is kept.
    """
    B = p.shape[0]
    on = torch.ones(B, dtype=torch.bool)
    x = p.detach()

    def g_of(dl: torch.Tensor) -> torch.Tensor:
        return _linearise(x, *_left_update(dl, R0, t0), maps, map_t, finite, orders, on,
                          query_bound, cfg, mode)[1]

    with torch.enable_grad():
        A = torch.autograd.functional.jacobian(g_of, torch.zeros(B, 6, dtype=p.dtype))  # (B,6,B,6)
    A = A[torch.arange(B), :, torch.arange(B), :]  # per-sample blocks (B, 6, 6)
    _, g, _ = _linearise(p, R0, t0, maps, map_t, finite, orders, on, query_bound, cfg, mode)
    delta = _solve(A, g, cfg)
    return _left_update(delta - delta.detach(), R0, t0)


def _left_update(delta: torch.Tensor, R: torch.Tensor, t: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The pose ``exp(delta) T`` for twists delta (B, 6) and T = (R (B, 3, 3), t (B, 3))."""
    dT = se3_exp(delta)
    return dT[:, :3, :3] @ R, (dT[:, :3, :3] @ t[..., None])[..., 0] + dT[:, :3, 3]


def _solve(H: torch.Tensor, g: torch.Tensor, cfg: ICPConfig) -> torch.Tensor:
    """Damped Newton-type increment delta (B, 6) = -(H + damping)^-1 g for H (B, 6, 6), g (B, 6)."""
    lam = cfg.damping * torch.diagonal(H, dim1=1, dim2=2).sum(-1) / 6.0 + 1e-12
    eye6 = torch.eye(6, dtype=H.dtype)
    return -torch.linalg.solve(H + lam[:, None, None] * eye6, g[..., None])[..., 0]


def _health(H: torch.Tensor, n_inliers: torch.Tensor, converged: torch.Tensor,
            T: torch.Tensor, cfg: ICPConfig) -> list[str]:
    """Per-sample status: ok / nonfinite / too_few_correspondences / singular / not_converged."""
    out = []
    ev = torch.linalg.eigvalsh(torch.nan_to_num(H.to(torch.float64)))  # ascending
    for b in range(H.shape[0]):
        if not bool(torch.isfinite(T[b]).all()):
            out.append("nonfinite")
        elif int(n_inliers[b]) < cfg.min_correspondences:
            out.append("too_few_correspondences")
        elif float(ev[b, 0]) <= 1e-10 * max(float(ev[b, -1]), 1e-300):
            out.append("singular")
        elif not bool(converged[b]):
            out.append("not_converged")
        else:
            out.append("ok")
    return out


def config_dict(cfg: ICPConfig) -> dict[str, Any]:
    """The config as a plain dict (for manifests)."""
    return asdict(cfg)
