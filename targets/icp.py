"""Differentiable multi-iteration ICP (point-to-plane and point-to-point) in PyTorch.

A re-implementation of the algorithm of dICP (Lisus et al., "Pointing the Way: Refining Radar-Lidar
Localization Using Learned ICP Weights", 2023) used by Zhang et al. (ICRA 2025), with the nearest
neighbour search moved to a KD-tree outside autograd:

* correspondences are re-computed every iteration (nearest map point of each transformed scan
  point); the *choice* of neighbour carries no gradient, gradients flow through the residuals,
  the weights and the Gauss-Newton solve, unrolled over all iterations (``backprop="unrolled"``)
  or, with ``backprop="implicit"``, by the implicit function theorem at the final pose (the
  iterations themselves build no graph);
* robust weight on the point-to-plane residual ``r = n.(q - m)`` (point-to-point: on
  ``||q - m||``), not detached (IRLS is differentiated through): Cauchy ``1 / (1 + (r / c)^2)``
  (dICP's, the default), Huber ``min(1, c / |r|)`` or Geman-McClure ``1 / (1 + (r / c)^2)^2``
  (KISS-ICP's weight ``kappa^2 / (kappa + r^2)^2`` with ``kappa = c^2``; Vizzo et al., RA-L
  2023), or none (``ICPConfig.kernel``, scale ``ICPConfig.cauchy_c``);
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

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.registry import Range, check_ranges
from icpbench.core.se3 import hat, se3_exp
from icpbench.core.types import Registration
from icpbench.targets import forward_cache

Mode = Literal["plane", "point", "gicp"]
Backprop = Literal["unrolled", "implicit"]
Kernel = Literal["cauchy", "huber", "geman_mcclure", "none"]
#: The robust kernels of :class:`ICPConfig` (``kernel``).
KERNELS: tuple[str, ...] = ("cauchy", "huber", "geman_mcclure", "none")


#: Valid values of the numeric :class:`ICPConfig` fields (None, where allowed, disables a feature).
ICP_RANGES: dict[str, Range] = {
    "max_iterations": Range(1, 1_000_000),
    # the pose-increment threshold (m and rad mixed): at 0.1 and above every ICP stops after one
    # step and reports converged (measured on the synthetic scene: 0.19-0.26 m off the tol=1e-8
    # pose); up to 1e-3, 10x the paper's 1e-4, the pose moves by < 2 cm
    "tol": Range(0.0, 1e-3, lo_open=True),
    "cauchy_c": Range(0.0, lo_open=True),
    "d_max": Range(0.0, lo_open=True),
    "soft_steepness": Range(0.0, lo_open=True),
    "damping": Range(0.0, 1.0),
    "min_correspondences": Range(1),
    "kdtree_workers": Range(1, 1024),
    "nn_reuse_m": Range(0.0),
}


@dataclass(frozen=True)
class ICPConfig:
    """Settings of the differentiable ICP.

    Attributes:
        max_iterations: cap on Gauss-Newton iterations.
        tol: convergence threshold on ``||delta||_2`` of the 6-vector increment (m and rad mixed,
            as in dICP).
        cauchy_c: scale c (metres) of the robust kernel named by ``kernel`` (the field keeps its
            first name, from when Cauchy was the only kernel, so saved configurations still
            load); ``None`` disables the robust kernel (weights 1, whatever ``kernel`` says).
        d_max: maximum correspondence distance (metres); ``None`` disables the filter.
        soft_dmax: use the smooth gate instead of the hard one (training only).
        soft_steepness: k of the smooth gate (dimensionless; the gate falls from 0.88 to 0.12
            over about ``2 / k * d_max``).
        damping: relative Levenberg damping added to the 6x6 normal equations
            (``damping * trace(H) / 6``); keeps degenerate (planar/collinear) scans finite.
        min_correspondences: fewer inliers than this marks the sample ``too_few_correspondences``.
        kdtree_workers: threads of the KD-tree query.
        nn_reuse_m: beyond dICP, an *approximate* correspondence search: a point keeps its map
            row (point and normal) while it stays within this distance (metres) of where it was
            last queried, even where the exact cache would re-query it. 0 (default): exact nearest
            neighbours. On a planar wall the row's plane is the same either way, so the
            point-to-plane residual barely changes; it saves the KD-tree queries of points
            that slide a few millimetres per iteration (attacked scans, docs/performance.md).
        backprop: how gradients reach the scan: ``"unrolled"`` (dICP, through every iteration)
            or ``"implicit"`` (the iterations run without a graph; the gradient is the
            implicit-function derivative of the final pose, exact at a converged pose; the pose
            value is unchanged and training can use the evaluation's iteration cap).
        kernel: the robust weight ``w(r)`` of a residual r (point-to-plane distance, or
            point-to-point distance) with scale ``c = cauchy_c``: ``"cauchy"`` (default, dICP's)
            ``1 / (1 + r^2 / c^2)``; ``"huber"`` ``min(1, c / |r|)`` (the IRLS weight of Huber's
            loss); ``"geman_mcclure"`` ``1 / (1 + r^2 / c^2)^2``, KISS-ICP's weight
            ``kappa^2 / (kappa + r^2)^2`` with ``kappa = c^2`` (Vizzo et al., RA-L 2023, eq. 11);
            ``"none"``: weights 1, as ``cauchy_c=None`` (a name a command line can pass).
            Weights are differentiated (unrolled and implicit gradients alike).
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
    nn_reuse_m: float = 0.0
    backprop: Backprop = "unrolled"
    kernel: Kernel = "cauchy"

    def __post_init__(self) -> None:
        check_ranges("the ICP settings", asdict(self), ICP_RANGES)
        if self.max_iterations < 1:
            raise InputError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if not self.tol > 0:
            raise InputError(f"tol must be > 0, got {self.tol}")
        if self.backprop not in ("unrolled", "implicit"):
            raise InputError(f"backprop must be 'unrolled' or 'implicit', got {self.backprop!r}")
        if self.kernel not in KERNELS:
            raise InputError(f"kernel must be one of {', '.join(KERNELS)}, got {self.kernel!r}")
        if not (np.isfinite(self.nn_reuse_m) and self.nn_reuse_m >= 0):
            raise InputError(f"nn_reuse_m must be a finite number >= 0 (metres), got {self.nn_reuse_m}")
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


def _robust(r2: torch.Tensor, cfg: ICPConfig) -> torch.Tensor:
    """Robust weight (differentiable) of squared residuals r2 (B, N) (``ICPConfig.kernel``)."""
    if cfg.cauchy_c is None or cfg.kernel == "none":
        return torch.ones_like(r2)
    return kernel_weight(r2, cfg.kernel, cfg.cauchy_c**2)[0]


def kernel_weight(r2: torch.Tensor, kernel: str, c2: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust weight w and its slope ``dw / d(r^2)`` for squared residuals r2 (any shape, units of
    c2), kernel scale ``c2 = c^2`` (``inf``: no kernel, w = 1, slope 0).

    The weight is built from differentiable operations, so autograd of ``w`` is the slope too; the
    slope is returned for hand-written backward passes. Huber's weight is 1 for ``r^2 <= c^2`` and
    ``c / |r|`` beyond (continuous, its slope jumps at ``|r| = c``)."""
    if not np.isfinite(c2) or kernel == "none":
        return torch.ones_like(r2), torch.zeros_like(r2)
    if kernel == "cauchy":
        w = 1.0 / (1.0 + r2 / c2)
        return w, -w * w / c2
    if kernel == "geman_mcclure":
        u = 1.0 / (1.0 + r2 / c2)
        return u * u, -2.0 * u * u * u / c2
    if kernel == "huber":
        out = r2 > c2
        big = torch.clamp(r2, min=c2)
        w = torch.where(out, np.sqrt(c2) * torch.rsqrt(big), torch.ones((), dtype=r2.dtype))
        return w, torch.where(out, -0.5 * w / big, torch.zeros((), dtype=r2.dtype))
    raise InputError(f"unknown kernel {kernel!r}; valid: {', '.join(KERNELS)}")


def icp(
    scans: torch.Tensor,
    maps: Sequence[MapIndex],
    T_init: torch.Tensor,
    cfg: ICPConfig,
    mode: Mode = "plane",
    scan_cov: torch.Tensor | None = None,
) -> Registration:
    """Run batched differentiable ICP.

    Args:
        scans: (B, N, 3) scan points, sensor frame, metres (float32 or float64; may require grad).
        maps: B prepared maps (``MapIndex``); point-to-plane needs their normals.
        T_init: (B, 4, 4) initial scan->map transforms.
        cfg: ICP settings.
        mode: ``"plane"`` (point-to-plane), ``"point"`` (point-to-point) or ``"gicp"``
            (Generalized-ICP: the maps' ``table`` rows carry covariances instead of normals,
            :class:`icpbench.targets.gicp_replica.CovarianceMap`, and ``scan_cov`` is required).
        scan_cov: GICP only: (B, 6, N) covariances of the scan points (sensor frame, entries
            ``xx yy zz xy xz yz``); may carry a graph to the scans.

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
    if mode not in ("plane", "point", "gicp"):
        raise InputError(f"mode must be 'plane', 'point' or 'gicp', got {mode!r}")
    if mode == "plane" and any(m.normals is None for m in maps):
        raise InputError("point-to-plane ICP needs map normals")
    if mode == "gicp" and (scan_cov is None or tuple(scan_cov.shape) != (B, 6, N)):
        raise InputError(f"GICP needs scan covariances of shape ({B}, 6, {N})")

    finite = torch.isfinite(scans).all(-1)  # (B, N)
    p = torch.where(finite[..., None], scans, torch.zeros((), dtype=dtype))
    query_bound = np.inf if cfg.d_max is None else (cfg.d_max * (3.0 if cfg.soft_dmax else 1.0))
    implicit = cfg.backprop == "implicit" and scans.requires_grad and torch.is_grad_enabled()
    graph = scans.requires_grad and torch.is_grad_enabled() and not implicit
    # a forward pass without an unrolled graph is taken from the per-sample cache when the same
    # scan was registered with the same settings before (icpbench.targets.forward_cache)
    cacheable = not graph and cfg.nn_reuse_m == 0 and scan_cov is None
    nn = None
    if not cacheable:  # the whole batch, possibly with its unrolled graph
        R, t, converged, iterations, n_inliers, H_last, nn = _iterate(
            p, finite, list(maps), T_init, cfg, mode, implicit, query_bound, scan_cov)
    else:
        compiled = implicit and _compiled_forward(cfg, mode, dtype)
        # the compiled pass's results are kept apart, so a forward pass asked for without a
        # gradient (a row) is always this module's own
        settings = (tuple(sorted(asdict(replace(cfg, backprop="unrolled")).items())),
                    mode + ("-compiled" if compiled else ""))
        keys = [forward_cache.sample_key(settings, scans[b], T_init[b], maps[b]) for b in range(B)]
        found = [forward_cache.get(k) for k in keys]
        miss = [b for b in range(B) if found[b] is None]
        if miss:
            sel = torch.as_tensor(miss)
            iterate = _iterate_compiled if compiled else _iterate
            R_m, t_m, conv_m, it_m, inl_m, H_m, _ = iterate(
                p[sel], finite[sel], [maps[b] for b in miss], T_init[sel], cfg, mode, implicit,
                query_bound)
            for j, b in enumerate(miss):
                found[b] = forward_cache.SampleResult(
                    R_m[j].detach(), t_m[j].detach(), bool(conv_m[j]), int(it_m[j]),
                    int(inl_m[j]), H_m[j].detach())
                forward_cache.put(keys[b], maps[b], found[b])
        R = torch.stack([f.R for f in found]).to(dtype)
        t = torch.stack([f.t for f in found]).to(dtype)
        converged = torch.tensor([f.converged for f in found])
        iterations = torch.tensor([f.iterations for f in found], dtype=torch.long)
        n_inliers = torch.tensor([f.n_inliers for f in found], dtype=torch.long)
        H_last = torch.stack([f.H_last for f in found]).to(dtype)

    if implicit:
        if cacheable:  # a fresh exact search at the final pose, whether or not the pass was cached
            nn = _Correspondences(maps, p.detach(), finite, dtype, bound=query_bound,
                                  reuse=cfg.nn_reuse_m, lists=_lists(cfg, mode))
        R, t = _implicit_pose(p.transpose(1, 2).contiguous(), R.detach(), t.detach(), nn,
                              query_bound, cfg, mode, scan_cov)

    T_out = torch.cat([torch.cat([R, t[..., None]], -1),
                       T_init[:, 3:4, :].to(dtype)], 1)
    status = health(H_last, n_inliers, converged, T_out.detach(), cfg)
    converged = converged & torch.tensor([s == "ok" for s in status])
    return Registration(
        T=T_out,
        converged=converged,
        iterations=iterations,
        inlier_fraction=n_inliers.to(torch.float64) / max(N, 1),
        status=status,
    )


def _iterate(p: torch.Tensor, finite: torch.Tensor, maps: Sequence[MapIndex], T_init: torch.Tensor,
             cfg: ICPConfig, mode: Mode, implicit: bool, query_bound: float,
             scan_cov: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                        torch.Tensor, _Correspondences]:
    """The ICP iterations on scans p (B, N, 3) (non-finite points zeroed, ``finite`` (B, N)) from
    T_init (B, 4, 4): final R (B, 3, 3) and t (B, 3) (with the unrolled graph unless ``implicit``
    or without grad), converged (B,), iterations (B,), inliers at the last iteration (B,), the last
    normal-equation matrix (B, 6, 6) and the correspondence search at its end."""
    B, dtype = p.shape[0], p.dtype
    T = T_init.to(dtype)
    R, t = T[:, :3, :3], T[:, :3, 3]
    active = torch.ones(B, dtype=torch.bool)
    iterations = torch.full((B,), cfg.max_iterations, dtype=torch.long)
    converged = torch.zeros(B, dtype=torch.bool)
    n_inliers = torch.zeros(B, dtype=torch.long)
    nn = _Correspondences(maps, p.detach(), finite, dtype, bound=query_bound, reuse=cfg.nn_reuse_m,
                          lists=_lists(cfg, mode))
    H_last = torch.zeros(B, 6, 6, dtype=dtype)
    src = (p.detach() if implicit else p).transpose(1, 2).contiguous()  # (B, 3, N)
    cov = scan_cov.detach() if implicit and scan_cov is not None else scan_cov
    with torch.set_grad_enabled(torch.is_grad_enabled() and not implicit):
        for it in range(cfg.max_iterations):
            H, g, w = _linearise(src, R, t, nn, active, query_bound, cfg, mode, cov)
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
    return R, t, converged, iterations, n_inliers, H_last, nn


def _compiled_forward(cfg: ICPConfig, mode: Mode, dtype: torch.dtype) -> bool:
    """Whether the iterations before an implicit gradient run compiled
    (:func:`icpbench.targets.point_forward.register_point`: the same iteration, poses equal to
    about 1e-15 m and the same iteration counts): point-to-point in float64 with the hard gate
    and no ``nn_reuse_m``. The gradient attacks' surrogate registrations of point-to-point
    targets and KISS-ICP's replica took most of ``pgd``'s time in PyTorch (2026-11-30: 0.54 s of
    a 10,000-point ``unseen`` scan's registration by KISS-ICP's replica)."""
    return (mode == "point" and dtype == torch.float64 and not cfg.soft_dmax
            and cfg.nn_reuse_m == 0)


def _iterate_compiled(p: torch.Tensor, finite: torch.Tensor, maps: Sequence[MapIndex],
                      T_init: torch.Tensor, cfg: ICPConfig, mode: Mode, implicit: bool,
                      query_bound: float
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                 torch.Tensor, torch.Tensor, None]:
    """As :func:`_iterate` without a graph, each sample by the compiled point-to-point pass
    (:func:`_compiled_forward`); no correspondence search is returned (the implicit step makes
    its own at the final pose)."""
    from icpbench.targets.point_forward import register_point  # it imports this module

    x = torch.where(finite[..., None], p.detach(), torch.full((), torch.nan, dtype=p.dtype))
    x_np, T0 = x.numpy(), T_init.detach().to(torch.float64).numpy()
    out = [register_point(x_np[b], maps[b], T0[b], cfg) for b in range(p.shape[0])]
    T = torch.as_tensor(np.stack([o[0] for o in out]))
    return (T[:, :3, :3].contiguous(), T[:, :3, 3].contiguous(),
            torch.tensor([o[1] for o in out]),
            torch.tensor([o[2] for o in out], dtype=torch.long),
            torch.tensor([o[3] for o in out], dtype=torch.long),
            torch.as_tensor(np.stack([o[4] for o in out])), None)


def _lists(cfg: ICPConfig, mode: Mode) -> bool:
    """Whether the correspondence search keeps candidate lists (:class:`_Correspondences`):
    point-to-point ICP without ``nn_reuse_m``. Its rows are the exact neighbours either way; the
    plane and GICP modes keep the slack alone, so their results (and the boards carried over
    with them) stay the same even where a map holds duplicated points with other normals or
    covariances (the two rules may name different twins)."""
    return mode == "point" and cfg.nn_reuse_m == 0


class _Correspondences:
    """Nearest map point of every scan point, re-queried only where it may have changed.

    After a query at position ``q_ref`` with nearest and second-nearest map distances d1 <= d2,
    any position within ``(d2 - d1) / 2`` of ``q_ref`` has the same nearest map point (triangle
    inequality: its distance to that point is < d1 + s <= d2 - s, below its distance to any other
    map point). So each iteration re-queries only the points that moved at least that far since
    their last query; the result is exactly that of a full query (less a 1e-9 m safety margin on
    the slack). Late ICP iterations move points by millimetres, so most points skip the KD-tree.

    With a finite ``bound`` (the ICP's query bound: correspondences at or beyond it get no weight)
    a point whose nearest map point was at ``d1 > bound`` also keeps its row while it moves less
    than ``d1 - bound`` (less a relative margin of 1e-4): every map point is then still farther
    than the bound, so the ICP's result is the same as with a full query, although the row may no
    longer be the nearest. Such points are the expensive ones (a KD-tree search far from the data
    visits many cells: measured 3.0 us per point beyond 5 m against 0.3 us within 0.5 m), and an
    attack at a large budget puts many points there (about a fifth of the queries of the iterated
    sector attack at lambda = 4 m).

    Queries go in a spatially coherent order (1 m voxels of the scan, fixed for the run): measured
    ~25% faster KD-tree queries; the result does not depend on the order. Indices point into one
    table of all B maps (``MapIndex.table`` rows concatenated), so one gather fetches every
    correspondence's point and normal.

    With ``lists`` (:func:`_lists`) the compiled forward pass's per-point candidate lists decide
    instead (:class:`icpbench.targets.point_forward.NearestRows`: the same rows, about 15% of
    the points searched per iteration against about half; 2026-11-30, PGD's surrogate
    registrations on KISS-ICP's replica).
    """

    _MARGIN_M = 1e-9
    _FAR_MARGIN = 1e-4  # relative to the bound: far above the float32 rounding of a distance

    def __init__(self, maps: Sequence[MapIndex], p: torch.Tensor, finite: torch.Tensor,
                 dtype: torch.dtype, bound: float = np.inf, reuse: float = 0.0,
                 lists: bool = False) -> None:
        B, N, _ = p.shape
        self.maps = maps
        self.bound = float(bound)
        self.reuse = float(reuse)
        if lists and self.reuse > 0:
            raise InputError("candidate lists give exact rows: no nn_reuse_m with them")
        firsts: dict[int, int] = {}  # one table entry per distinct map object
        tables, offsets, off = [], [], 0
        for m in maps:
            if id(m) not in firsts:
                firsts[id(m)] = off
                tables.append(m.table(dtype))
                off += len(m) + 1
            offsets.append(firsts[id(m)])
        self.table = tables[0] if len(tables) == 1 else torch.cat(tables)
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.finite = finite.numpy()
        p_np = p.to(torch.float64).numpy()
        self.lists = None
        if lists:  # the compiled pass's candidate lists decide the same rows (imported late:
            # that module imports this one); they keep the same coherent order
            from icpbench.targets.point_forward import NearestRows

            self.lists = [NearestRows(m, np.ascontiguousarray(p_np[b]), self.finite[b], self.bound)
                          for b, m in enumerate(maps)]
            self.orders = [rows.order for rows in self.lists]
        else:
            self.orders = [np.lexsort(np.floor(p_np[b] / 1.0).T[::-1]) for b in range(B)]
        sentinel = np.asarray([off_b + len(m) for off_b, m in zip(offsets, maps, strict=True)])
        self.idx = np.repeat(sentinel[:, None], N, axis=1)  # (B, N) rows of the table
        self.ref = np.full((B, 3, N), np.nan)  # where each point was last queried
        self.slack = np.full((B, N), -np.inf)  # how far it may move from there
        self.found = np.zeros((B, N), dtype=bool)  # the tree returned a neighbour
        self.queried = 0  # points sent to the KD-tree (for profiling)

    def update(self, q: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """Nearest-neighbour rows (B, N) int64 of the table for map-frame points q (B, 3, N)
        (only the ``active`` samples are updated)."""
        q_np = q.detach().to(torch.float64).numpy()
        if self.lists is not None:
            for b in np.flatnonzero(active.numpy()):
                rows = self.lists[b]
                before = rows.searched
                i = rows.update_at(q_np[b])
                self.idx[b] = i + self.offsets[b]
                self.found[b] = i < len(self.maps[b])
                self.queried += rows.searched - before
            return torch.from_numpy(self.idx)
        for b in np.flatnonzero(active.numpy()):
            qb = q_np[b]
            moved = qb - self.ref[b]
            # a slack <= 0 (a tie d2 = d1, nothing found, or a gap below the margin) means: ask
            # again after any move (squaring -inf would say "never")
            need = ~(np.einsum("ij,ij->j", moved, moved) < np.maximum(self.slack[b], 0.0) ** 2)
            need &= self.finite[b]  # (non-finite queries get the sentinel from nearest2)
            order = self.orders[b]
            sel = order[need[order]]
            if sel.size == 0:
                continue
            qs = qb[:, sel]
            d1, d2, i = self.maps[b].nearest2(qs.T)
            self.idx[b, sel] = i + self.offsets[b]
            self.found[b, sel] = i < len(self.maps[b])
            self.ref[b][:, sel] = qs
            gap = d2 > d1  # False where the tree found nothing (inf, inf): re-query every time
            self.slack[b, sel] = -np.inf
            self.slack[b, sel[gap]] = 0.5 * (d2[gap] - d1[gap]) - self._MARGIN_M
            if np.isfinite(self.bound):  # beyond the bound: no weight until it comes this close
                far = np.isfinite(d1) & (d1 > self.bound)
                self.slack[b, sel[far]] = np.maximum(
                    self.slack[b, sel[far]], d1[far] - self.bound * (1.0 + self._FAR_MARGIN))
            if self.reuse > 0:  # approximate (ICPConfig.nn_reuse_m); found rows only
                ok = self.found[b, sel]
                self.slack[b, sel[ok]] = np.maximum(self.slack[b, sel[ok]], self.reuse)
            self.queried += sel.size
        return torch.from_numpy(self.idx)

    def gather(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Map points (B, 3, N) and the rest of their table rows (normals (B, 3, N), or GICP
        covariances (B, 6, N)) at table rows idx (B, N). (A row gather then a
        transpose: measured 10-15x faster than gathering columns of a (6, M) table.)"""
        B, N = idx.shape
        W = self.table.shape[1]
        mn = self.table.index_select(0, idx.reshape(-1)).view(B, N, W).transpose(1, 2).contiguous()
        return mn[:, :3], mn[:, 3:]


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross products of 3-vectors stored as rows: a, b (B, 3, N) -> (B, 3, N). (On this layout
    measured ~2.5x faster than ``torch.linalg.cross`` on (B, N, 3).)"""
    ax, ay, az = a.unbind(1)
    bx, by, bz = b.unbind(1)
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], 1)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise dot products of (B, 3, N) tensors -> (B, N)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


class _PlaneNormalEquations(torch.autograd.Function):
    """Point-to-plane IRLS normal equations with a hand-written backward (hard gate).

    Forward: q (B, 3, N) map-frame scan points, m and n (B, 3, N) their map correspondences and
    unit normals (no gradient), ``mask`` (B, N) bool (finite, active, distance below the gate),
    ``c2`` the squared kernel scale (``inf``: no robust kernel) and ``kernel`` its name
    (:func:`kernel_weight`). Returns ``H = sum_i w_i J_i J_i^T`` (B, 6, 6),
    ``g = sum_i w_i r_i J_i`` (B, 6) and w (B, N), with ``r_i = n_i.(q_i - m_i)``,
    ``J_i = [n_i, q_i x n_i]``, ``w_i = mask_i k(r_i^2)`` (Cauchy: ``k = 1 / (1 + r^2 / c^2)``).

    Backward (exact; the gate is a step with no gradient, as in autograd of the same formula):
    with ``S = dL/dH + dL/dH^T``, ``P_i = S J_i`` and ``gJ_i = dL/dg . J_i``,
    ``dL/dw_i = J_i.P_i / 2 + r_i gJ_i``, ``dL/dr_i = w_i gJ_i + dL/dw_i dw_i/dr_i`` (with
    ``dw_i/dr_i = 2 r_i dk/d(r^2)``),
    ``dL/dJ_i = w_i (P_i + r_i dL/dg)`` and ``dL/dq_i = dL/dr_i n_i + n_i x (dL/dJ_i)[3:]``.
    One graph node per iteration instead of ~30 (measured in docs/performance.md).
    """

    @staticmethod
    def forward(ctx: Any, q: torch.Tensor, m: torch.Tensor, n: torch.Tensor, mask: torch.Tensor,
                c2: float, kernel: str = "cauchy"
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        r = _dot(q - m, n)  # (B, N)
        w = mask.to(q.dtype)
        slope = None
        if np.isfinite(c2):
            if kernel == "cauchy":  # dICP's kernel, in its original arithmetic
                w = w / (1.0 + r * r / c2)
            else:
                k, slope = kernel_weight(r * r, kernel, c2)
                w, slope = w * k, slope * mask
        r = r * mask
        J = torch.cat([n, _cross(q, n)], 1)  # (B, 6, N): [d/drho, d/dphi]
        Jw = J * w[:, None]
        H = Jw @ J.transpose(1, 2)
        g = (Jw @ r[..., None])[..., 0]
        ctx.save_for_backward(n, J, w, r, slope if slope is not None else w)
        ctx.c2, ctx.kernel = c2, kernel
        ctx.mark_non_differentiable(w)
        return H, g, w

    @staticmethod
    def backward(ctx: Any, gH: torch.Tensor | None, gg: torch.Tensor | None,
                 _gw: torch.Tensor | None) -> tuple[torch.Tensor | None, ...]:
        n, J, w, r, slope = ctx.saved_tensors
        B = J.shape[0]
        if gH is None:
            gH = torch.zeros(B, 6, 6, dtype=J.dtype)
        if gg is None:
            gg = torch.zeros(B, 6, dtype=J.dtype)
        P = (gH + gH.transpose(1, 2)) @ J  # (B, 6, N)
        gJ = (gg[:, None, :] @ J)[:, 0]  # (B, N)
        dw = 0.5 * (J * P).sum(1) + r * gJ
        dr = w * gJ
        if np.isfinite(ctx.c2):
            if ctx.kernel == "cauchy":
                dr = dr - dw * (2.0 / ctx.c2) * r * w * w
            else:  # dw/dr = 2 r dw/d(r^2)
                dr = dr + dw * 2.0 * r * slope
        dJu = w[:, None] * (P[:, 3:] + r[:, None] * gg[:, 3:, None])  # (B, 3, N)
        dq = dr[:, None] * n + _cross(n, dJu)
        return dq, None, None, None, None, None


def _linearise(p: torch.Tensor, R: torch.Tensor, t: torch.Tensor, nn: _Correspondences,
               active: torch.Tensor, query_bound: float, cfg: ICPConfig, mode: Mode,
               scan_cov: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Gauss-Newton linearisation at the pose (R (B, 3, 3), t (B, 3)) of scan points p (B, 3, N)
    (coordinates as rows: measured 2-3x faster element-wise ops than (B, N, 3)).

    Correspondences (KD-tree, no gradient) for the ``active`` samples only (the others get none).
    Returns H (B, 6, 6), g (B, 6) of the IRLS normal equations ``H delta = -g`` and the weights
    w (B, N) (0 for points without a correspondence). ``scan_cov`` (B, 6, N): GICP's scan
    covariances (:func:`_gicp_normal_equations`)."""
    dtype = p.dtype
    q = R @ p + t[..., None]  # (B, 3, N), map frame
    m, n = nn.gather(nn.update(q, active))
    valid = torch.from_numpy(nn.finite & nn.found) & active[:, None]
    diff = q - m
    dd = diff.detach()
    d2 = _dot(dd, dd)  # (B, N) squared correspondence distances
    if mode == "plane" and not cfg.soft_dmax:
        # hard gate: the correspondence exists and is closer than d_max (= the query bound)
        mask = valid & (d2 < query_bound**2) if np.isfinite(query_bound) else valid
        c2 = np.inf if cfg.cauchy_c is None or cfg.kernel == "none" else cfg.cauchy_c**2
        return _PlaneNormalEquations.apply(q, m, n, mask, c2, cfg.kernel)
    ok = valid & (d2 < query_bound**2)
    if mode in ("point", "gicp"):
        e = torch.where(ok[:, None], diff, torch.zeros((), dtype=dtype))  # (B, 3, N)
        if mode == "gicp":
            return _gicp_normal_equations(q, e, ok, R, n, scan_cov)
        d = torch.sqrt(torch.where(ok, _dot(diff, diff), torch.ones((), dtype=dtype)))
        w = _gate(d, cfg) * _robust(_dot(e, e), cfg)
        w = torch.where(ok, w, torch.zeros((), dtype=dtype))
        H, g = _point_normal_equations(q, e, w)
        return H, g, w
    q, diff, n = q.transpose(1, 2), diff.transpose(1, 2), n.transpose(1, 2)  # (B, N, 3) views
    d = torch.linalg.norm(torch.where(ok[..., None], diff, torch.ones((), dtype=dtype)), dim=-1)
    r = (diff * n).sum(-1)  # (B, N)
    w = _gate(d, cfg) * _robust(r * r, cfg)
    w = torch.where(ok, w, torch.zeros((), dtype=dtype))
    r = torch.where(ok, r, torch.zeros((), dtype=dtype))
    J = torch.cat([n, torch.linalg.cross(q, n, dim=-1)], -1)  # (B, N, 6): [d/drho, d/dphi]
    Jw = J * w[..., None]
    H = Jw.transpose(1, 2) @ J
    g = (Jw * r[..., None]).sum(1)
    return H, g, w


def _skew_sum(s: torch.Tensor) -> torch.Tensor:
    """``[s]x`` (B, 3, 3) of vectors s (B, 3)."""
    z = torch.zeros_like(s[:, 0])
    return torch.stack([torch.stack([z, -s[:, 2], s[:, 1]], -1),
                        torch.stack([s[:, 2], z, -s[:, 0]], -1),
                        torch.stack([-s[:, 1], s[:, 0], z], -1)], 1)


def _point_normal_equations(q: torch.Tensor, e: torch.Tensor, w: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Point-to-point IRLS normal equations in closed form (differentiable by autograd).

    q (B, 3, N) map-frame scan points, e (B, 3, N) residuals ``q - m`` (zero where there is no
    correspondence), w (B, N) weights. With ``J_i = [I, -[q_i]x]`` (3 x 6, ``[rho, phi]``):
    ``H = sum_i w_i J_i^T J_i = [[sum w I, -[s]x], [[s]x, sum w |q|^2 I - sum w q q^T]]`` with
    ``s = sum_i w_i q_i``, and ``g = sum_i w_i J_i^T e_i = [sum w e, sum w q x e]``. The same
    numbers as the per-point 3x3 products, without (B, N, 3, 3) intermediates (measured
    docs/methods.md, "Per-target settings")."""
    dtype = q.dtype
    qw = q * w[:, None]  # (B, 3, N)
    sw = w.sum(1)
    eye = torch.eye(3, dtype=dtype)
    Sx = _skew_sum(qw.sum(2))
    Hpp = (qw * q).sum((1, 2))[:, None, None] * eye - qw @ q.transpose(1, 2)
    H = torch.cat([torch.cat([sw[:, None, None] * eye, -Sx], 2), torch.cat([Sx, Hpp], 2)], 1)
    g = torch.cat([(e * w[:, None]).sum(2), _cross(qw, e).sum(2)], 1)
    return H, g


def _gicp_normal_equations(q: torch.Tensor, e: torch.Tensor, ok: torch.Tensor, R: torch.Tensor,
                           cov_m: torch.Tensor, cov_s: torch.Tensor | None
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Generalized-ICP normal equations (Segal, Haehnel and Thrun, RSS 2009), as small_gicp's GICP
    factor linearises them (Koide, JOSS 2024): residual ``e_i = q_i - m_i`` (map frame), weight
    matrix ``M_i = (C_m,i + R C_s,i R^T)^-1`` evaluated at the current rotation and held in the
    Gauss-Newton step (not differentiated in ``H``; its value and its dependence on R and on the
    scan covariances do enter ``g``, so the implicit gradient is that of small_gicp's fixed point
    ``sum_i J_i^T M_i e_i = 0``).

    Args:
        q, e: (B, 3, N) map-frame scan points and residuals (zero without a correspondence).
        ok: (B, N) the point has a correspondence within the gate.
        R: (B, 3, 3) current rotation.
        cov_m: (B, 6, N) map covariances of the correspondences, entries ``xx yy zz xy xz yz``.
        cov_s: (B, 6, N) scan covariances (sensor frame), same layout.

    Returns H (B, 6, 6) ``sum J^T M J``, g (B, 6) ``sum J^T M e`` with ``J_i = [I, -[q_i]x]`` and
    the inlier indicator (B, N) as weights.
    """
    if cov_s is None:
        raise InputError("GICP needs the scan covariances")
    dtype = q.dtype
    Cm, Cs = _sym3(cov_m), _sym3(cov_s)  # (B, N, 3, 3)
    Rb = R[:, None]
    C = Cm + Rb @ Cs @ Rb.transpose(-1, -2)
    eye = torch.eye(3, dtype=dtype)
    C = torch.where(ok[..., None, None], C, eye)  # no correspondence: any invertible matrix
    M = torch.linalg.inv(C) * ok[..., None, None]
    qt = q.transpose(1, 2)  # (B, N, 3)
    Qx = hat(qt)  # (B, N, 3, 3)
    MQ = M @ Qx
    Me = (M @ e.transpose(1, 2)[..., None])[..., 0]  # (B, N, 3)
    Hrr = M.sum(1)
    Hrp = -MQ.sum(1)
    Hpp = -(Qx @ MQ).sum(1)
    H = torch.cat([torch.cat([Hrr, Hrp], 2), torch.cat([Hrp.transpose(1, 2), Hpp], 2)], 1)
    g = torch.cat([Me.sum(1), torch.linalg.cross(qt, Me, dim=-1).sum(1)], 1)
    return H, g, ok.to(dtype)


def _sym3(c: torch.Tensor) -> torch.Tensor:
    """Symmetric 3x3 matrices (B, N, 3, 3) from their entries (B, 6, N) ``xx yy zz xy xz yz``."""
    xx, yy, zz, xy, xz, yz = c.unbind(1)
    return torch.stack([torch.stack([xx, xy, xz], -1), torch.stack([xy, yy, yz], -1),
                        torch.stack([xz, yz, zz], -1)], -2)


def _implicit_pose(p: torch.Tensor, R0: torch.Tensor, t0: torch.Tensor, nn: _Correspondences,
                   query_bound: float, cfg: ICPConfig, mode: Mode,
                   scan_cov: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The final pose (R0 (B, 3, 3), t0 (B, 3), no graph) with the implicit-function gradient of
    the scan points p (B, 3, N).

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
    cov_x = None if scan_cov is None else scan_cov.detach()

    def g_of(dl: torch.Tensor) -> torch.Tensor:
        return _linearise(x, *_left_update(dl, R0, t0), nn, on, query_bound, cfg, mode, cov_x)[1]

    with torch.enable_grad():
        A = torch.autograd.functional.jacobian(g_of, torch.zeros(B, 6, dtype=p.dtype))  # (B,6,B,6)
    A = A[torch.arange(B), :, torch.arange(B), :]  # per-sample blocks (B, 6, 6)
    _, g, _ = _linearise(p, R0, t0, nn, on, query_bound, cfg, mode, scan_cov)
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


def health(H: torch.Tensor, n_inliers: torch.Tensor, converged: torch.Tensor,
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
