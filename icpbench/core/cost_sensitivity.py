"""The one-step analytic worst case of any least-squares ICP cost: point-to-plane, point-to-point,
GICP.

The sector baseline (Laconte, Lisus and Barfoot, RA-L 2024, arXiv 2309.04251;
:mod:`icpbench.core.sector_math`) bounds one Gauss-Newton step of *point-to-plane* ICP. Its
argument carries over to every ICP whose cost is a sum of quadratic forms of the residuals
``r_i = q_i - m_i`` (``q_i = T p_i`` the scan point in the map frame, ``m_i`` its correspondence):

    E(T) = sum_i r_i^T W_i r_i,   W_i (3, 3) symmetric positive semi-definite,

* point-to-plane: ``W_i = w_i n_i n_i^T`` (the textbook ``(n_i . r_i)^2``; ``w_i`` the robust
  weight);
* point-to-point: ``W_i = w_i I`` (KISS-ICP, Open3D's and our ``p2point``);
* GICP (Segal, Haehnel and Thrun, RSS 2009): ``W_i = (C_m,i + R C_s,i R^T)^-1`` with the
  covariances of the map point's and of the scan point's neighbourhoods.

With left increments ``T <- exp(delta^) T``, ``delta = [rho, phi]``, the residual's Jacobian is
``J_i = [I, -[q_i]x]`` (3, 6), the Gauss-Newton matrix ``H = sum_i J_i^T W_i J_i`` and the step
``delta = -H^-1 sum_i J_i^T W_i r_i``. Displacing scan point i by ``d_i`` (map frame) changes
``r_i`` by ``d_i``; with the correspondences and weights held (the first-order model of the sector
attack), the step changes by exactly

    d delta = sum_i S_i d_i,   S_i = -H^-1 J_i^T W_i   (6, 3),

(``J_i`` also moves with ``q_i``, but ``J_i^T W_i r_i`` then changes by a term proportional to the
residual, which the model drops as the sector model does.) For a unit direction ``u`` of the pose
space and per-point balls ``||d_i|| <= lambda``, the largest change of ``u . delta`` is

    lambda * sum_i ||S_i^T u||,   reached by d_i = lambda S_i^T u / ||S_i^T u||,

since the objective is linear in each ``d_i`` separately (Cauchy-Schwarz per point). For
point-to-plane ``S_i^T u = -n_i w_i (a_i^T H^-1 u)`` with ``a_i = [n_i, q_i x n_i]``: the point
moves along its normal and the value is the sector attack's ``lambda * sum_i |g_i . u|``. For
point-to-point ``S_i^T u = -w_i J_i H^-1 u``: each point moves with the rigid motion ``-H^-1 u``
(a translation of the whole scan when the rotation part is small), which is why a point-to-point
cost is first-order robust: its one-step amplification ``sum_i ||S_i^T u||`` stays near 1.

The horizontal worst case maximises over unit ``u`` in the x-y plane (pose components rho_x,
rho_y): ``f(u) = sum_i ||S_i^T u||`` is convex in u, so its maximum on the circle is found by a
dense grid of directions (``f(u) = f(-u)``: half a circle suffices).

Frames: scan points ``p`` in the sensor frame, map points and normals in the map frame, poses
``T_map_scan``; displacements are returned in the sensor frame (``R^T d``). Units: metres,
radians. NumPy, float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from icpbench.core.errors import InputError
from icpbench.core.map_cache import PerMapCache
from icpbench.core.mapindex import MapIndex

CostKind = Literal["plane", "point", "gicp"]
COST_KINDS: tuple[str, ...] = ("plane", "point", "gicp")

#: Relative and absolute damping of the normal equations (our ICP's, ``ICPConfig.damping``).
DAMPING = 1e-9
EPS = 1e-12
#: Neighbours of a GICP covariance and the eigenvalues of its plane regularisation (Segal et al.:
#: a point is a small disc, variance ``GICP_EPS`` along the normal, 1 in the plane).
GICP_NEIGHBOURS = 20
GICP_EPS = 1e-3


#: Robust kernels a :class:`CostSpec` may model (the weights of ``icpbench.targets.icp``).
COST_KERNELS: tuple[str, ...] = ("cauchy", "huber", "geman_mcclure")


@dataclass(frozen=True)
class CostSpec:
    """Which cost a target minimises, as far as the one-step model needs it.

    Attributes:
        kind: ``"plane"``, ``"point"`` or ``"gicp"``.
        d_max: correspondence gate (metres): farther pairs carry no weight.
        cauchy_c: scale c (metres) of the robust weight on the residual (its norm for
            point-to-point and GICP); None: no kernel.
        kernel: which robust weight of scale c: ``"cauchy"`` ``1 / (1 + (r/c)^2)`` (the default,
            and the only one :func:`cost_of` reports unless asked for the target's own),
            ``"huber"`` ``min(1, c / |r|)`` or ``"geman_mcclure"`` ``1 / (1 + (r/c)^2)^2``.
    """

    kind: CostKind
    d_max: float
    cauchy_c: float | None = None
    kernel: str = "cauchy"

    def __post_init__(self) -> None:
        if self.kind not in COST_KINDS:
            raise InputError(f"cost kind must be one of {', '.join(COST_KINDS)}, got {self.kind!r}")
        if not (np.isfinite(self.d_max) and self.d_max > 0):
            raise InputError(f"d_max must be a positive number of metres, got {self.d_max}")
        if self.kernel not in COST_KERNELS:
            raise InputError(f"cost kernel must be one of {', '.join(COST_KERNELS)}, got "
                             f"{self.kernel!r}")

    def weight(self, r: np.ndarray) -> np.ndarray:
        """The robust weight w(r) (same shape) of residuals ``r`` in metres (1 without a kernel)."""
        if self.cauchy_c is None:
            return np.ones_like(np.asarray(r, dtype=np.float64))
        u = np.asarray(r, dtype=np.float64) / self.cauchy_c
        if self.kernel == "huber":
            return 1.0 / np.maximum(1.0, np.abs(u))
        w = 1.0 / (1.0 + u * u)
        return w * w if self.kernel == "geman_mcclure" else w

    def rho(self, r: np.ndarray) -> np.ndarray:
        """The cost rho(r) (same shape, m^2) of residuals ``r`` in metres whose derivative is
        ``r w(r)``: ``r^2 / 2`` without a kernel; Cauchy ``c^2/2 log(1 + r^2/c^2)``; Huber
        ``r^2 / 2`` up to c, ``c |r| - c^2 / 2`` beyond; Geman-McClure ``r^2 / 2 / (1 + r^2/c^2)``.
        The gate is not applied here."""
        r = np.abs(np.asarray(r, dtype=np.float64))
        if self.cauchy_c is None:
            return 0.5 * r**2
        c = self.cauchy_c
        if self.kernel == "huber":
            return np.where(r <= c, 0.5 * r**2, c * r - 0.5 * c**2)
        if self.kernel == "geman_mcclure":
            return 0.5 * r**2 / (1.0 + (r / c) ** 2)
        return 0.5 * c**2 * np.log1p((r / c) ** 2)


#: How a plan models a target's robust kernel (:func:`cost_of`'s ``kernel_model``):
#: ``"cauchy"`` every kernel as Cauchy's of the target's scale and KISS-ICP's as none (the standard
#: protocol up to v2); ``"geman-mcclure"`` the same, except a Geman-McClure kernel (KISS-ICP's)
#: as itself (the standard protocol from v3); ``"own"`` every target's own kernel.
KERNEL_MODELS: tuple[str, ...] = ("cauchy", "geman-mcclure", "own")
KernelModel = Literal["cauchy", "geman-mcclure", "own"]


def cost_of(target: Any, default_d_max: float = 5.0,
            kernel_model: KernelModel = "cauchy") -> CostSpec:
    """The cost a target minimises, read from its settings.

    Known targets: ``mode`` ``"plane"``/``"point"`` (``p2plane``, ``p2point``, ``open3d``), KISS-ICP
    (point-to-point, gate ``max_corr``), small_gicp (``registration_type`` GICP / PLANE_ICP / ICP,
    gate ``max_corr``). Any other target (a user's black box) is modelled as point-to-plane with its
    ``config.d_max`` (``default_d_max`` when it has none), the cost the analytic baseline assumes.

    ``kernel_model`` (:data:`KERNEL_MODELS`) says which robust kernel the spec carries. The
    target's own kernel is ``config.kernel`` (``"none"``: no kernel) of scale ``config.cauchy_c``,
    and KISS-ICP's Geman-McClure weight ``kernel^2 / (kernel + r^2)^2``, i.e. scale
    ``c = sqrt(kernel)``.

    Raises:
        InputError: an unknown ``kernel_model``.
    """
    if kernel_model not in KERNEL_MODELS:
        raise InputError(f"kernel_model must be one of {', '.join(KERNEL_MODELS)}, got "
                         f"{kernel_model!r}")
    own = _own_cost(target, default_d_max)
    if kernel_model == "own" or kernel_model == "geman-mcclure" and own.kernel == "geman_mcclure":
        return own
    cfg = getattr(target, "config", None)
    if getattr(target, "name", "") == "kiss-icp" or getattr(target, "registration_type", None):
        return CostSpec(own.kind, own.d_max, None)
    return CostSpec(own.kind, own.d_max, getattr(cfg, "cauchy_c", None))


def acting_kernel_model(kernel_model: str | None, target: Any) -> str:
    """The kernel model as it acts on ``target``: ``"cauchy"`` wherever ``kernel_model`` gives
    the plan that ``"cauchy"`` gives (e.g. ``"geman-mcclure"`` on a target whose kernel is not
    Geman-McClure's), else ``kernel_model``. None (a setting recorded before the model could be
    chosen) is ``"cauchy"``; a value that is not a kernel model is returned as it is.

    Two recorded settings that act alike on a target make the same rows; a resume compares them
    this way (:meth:`icpbench.attacks.base.Attack.settings_on`)."""
    km = "cauchy" if kernel_model is None else kernel_model
    if km in KERNEL_MODELS and cost_of(target, kernel_model=km) == cost_of(target):
        return "cauchy"
    return km


def _own_cost(target: Any, default_d_max: float) -> CostSpec:
    """:func:`cost_of` with the target's own kernel (None where it has none)."""
    cfg = getattr(target, "config", None)
    d_max = getattr(target, "max_corr", None) or getattr(cfg, "d_max", None) or default_d_max
    rtype = getattr(target, "registration_type", None)
    if rtype is not None:
        kind = {"GICP": "gicp", "PLANE_ICP": "plane", "ICP": "point"}.get(str(rtype), "plane")
        return CostSpec(kind, float(d_max), None)
    if getattr(target, "name", "") == "kiss-icp":
        return CostSpec("point", float(d_max), float(np.sqrt(target.kernel)), "geman_mcclure")
    kind = "point" if getattr(target, "mode", "plane") == "point" else "plane"
    own = getattr(cfg, "kernel", "cauchy")  # one of icpbench.targets.icp.KERNELS
    c = getattr(cfg, "cauchy_c", None)
    if own == "none" or c is None:
        return CostSpec(kind, float(d_max), None)
    return CostSpec(kind, float(d_max), c, own)


def _skew(v: np.ndarray) -> np.ndarray:
    """(K, 3) vectors -> (K, 3, 3) cross-product matrices."""
    S = np.zeros((*v.shape[:-1], 3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def plane_covariances(points: np.ndarray, k: int = GICP_NEIGHBOURS, eps: float = GICP_EPS,
                      tree: cKDTree | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """GICP covariances (K, 3, 3) of ``points`` (M, 3) (of the rows ``rows``; default all): the
    covariance of each point's ``k`` nearest neighbours with its eigenvalues replaced by
    ``(eps, 1, 1)`` (Segal et al., RSS 2009, "plane-to-plane")."""
    pts = np.asarray(points, dtype=np.float64)
    tree = cKDTree(pts) if tree is None else tree
    sel = np.arange(pts.shape[0]) if rows is None else np.asarray(rows)
    _, nb = tree.query(pts[sel], k=min(k, pts.shape[0]))
    nbp = pts[nb]  # (K, k, 3)
    c = nbp - nbp.mean(1, keepdims=True)
    C = np.einsum("kni,knj->kij", c, c) / max(nbp.shape[1] - 1, 1)
    _, V = np.linalg.eigh(C)
    return np.einsum("kij,j,klj->kil", V, np.array([eps, 1.0, 1.0]), V)


_MAP_COVARIANCES: PerMapCache[np.ndarray] = PerMapCache()


def map_covariances(map_index: MapIndex) -> np.ndarray:
    """GICP covariances (M, 3, 3) of a map's points, computed once per map object."""
    return _MAP_COVARIANCES.get(map_index, lambda m: plane_covariances(m.points))


@dataclass(frozen=True)
class LinearisedCost:
    """One Gauss-Newton step of a cost at a pose, as a linear function of point displacements.

    Attributes:
        index: (K,) rows of the scan that have a correspondence within the gate.
        S: (K, 6, 3) sensitivities: ``d delta = sum_i S_i d_i`` (d_i map frame, metres).
        R: (3, 3) rotation of the pose (map <- sensor).
    """

    index: np.ndarray
    S: np.ndarray
    R: np.ndarray

    def value(self, u: np.ndarray) -> float:
        """``sum_i ||S_i^T u||``: the first-order change of ``u . delta`` per metre of budget."""
        return float(np.linalg.norm(np.einsum("kaj,a->kj", self.S, u), axis=1).sum())

    def displacement(self, u: np.ndarray, budget_m: float) -> np.ndarray:
        """The maximising displacements (K, 3) in the *sensor* frame, each of norm ``budget_m``
        (zero where ``S_i^T u`` vanishes)."""
        v = np.einsum("kaj,a->kj", self.S, u)
        n = np.linalg.norm(v, axis=1, keepdims=True)
        d_map = np.where(n > 1e-300, budget_m * v / np.maximum(n, 1e-300), 0.0)
        return d_map @ self.R  # R^T d per row

    def worst_xy(self, n_angles: int = 180) -> tuple[np.ndarray, float]:
        """The unit direction u (6,) in the rho_x-rho_y plane that maximises :meth:`value`, and
        its value; a grid of ``n_angles`` directions over half a circle (``f(u) = f(-u)``)."""
        th = np.pi * np.arange(n_angles) / n_angles
        U = np.zeros((n_angles, 6))
        U[:, 0], U[:, 1] = np.cos(th), np.sin(th)
        vals = np.linalg.norm(np.einsum("kaj,na->nkj", self.S, U), axis=2).sum(1)
        j = int(np.argmax(vals))
        return U[j], float(vals[j])


def linearise(scan: np.ndarray, T: np.ndarray, map_index: MapIndex, cost: CostSpec,
              scan_cov: np.ndarray | None = None) -> LinearisedCost:
    """Linearise ``cost`` for ``scan`` (N, 3), sensor frame, at pose ``T`` (4, 4) against a map.

    Correspondences: each scan point's nearest map point within ``cost.d_max``. Weights: Cauchy
    on the residual (point-to-plane: ``n . r``; point-to-point and GICP: ``||r||``) when the cost
    has a kernel, else 1. GICP: covariances of the map point (:func:`map_covariances`) and of the
    scan point (``scan_cov`` (N, 3, 3), sensor frame; default: :func:`plane_covariances` of the
    scan itself).

    Raises:
        InputError: fewer than 6 correspondences (a 6-DoF step is not constrained), or a point-to-
            plane cost on a map without normals.
    """
    p = np.asarray(scan, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    q = p @ R.T + t
    finite = np.isfinite(q).all(axis=1)
    d1, _, idx = map_index.nearest2(np.where(finite[:, None], q, 0.0))
    ok = finite & np.isfinite(d1) & (d1 < cost.d_max)
    index = np.flatnonzero(ok)
    if index.size < 6:
        raise InputError(f"only {index.size} scan points have a correspondence within "
                         f"{cost.d_max:g} m: a 6-DoF step is not constrained")
    qk, mk = q[index], map_index.points[idx[index]]
    r = qk - mk
    if cost.kind == "plane":
        if map_index.normals is None:
            raise InputError("a point-to-plane cost needs map normals")
        n = map_index.normals[idx[index]]
        rr = np.einsum("ki,ki->k", n, r)
        W = n[:, :, None] * n[:, None, :]
    elif cost.kind == "point":
        rr = np.linalg.norm(r, axis=1)
        W = np.broadcast_to(np.eye(3), (index.size, 3, 3)).copy()
    else:
        Cm = map_covariances(map_index)[idx[index]]
        Cs = plane_covariances(p)[index] if scan_cov is None else np.asarray(scan_cov)[index]
        W = np.linalg.inv(Cm + R @ Cs @ R.T)
        rr = np.linalg.norm(r, axis=1)
    if cost.cauchy_c is not None and cost.kernel == "cauchy":  # (divided, as before kernels)
        W = W / (1.0 + (rr / cost.cauchy_c) ** 2)[:, None, None]
    elif cost.cauchy_c is not None:
        W = W * cost.weight(rr)[:, None, None]
    return LinearisedCost(index=index, S=sensitivities(qk, W), R=R)


def sensitivities(q: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Per-point sensitivities ``S_i = -(H + lam I)^-1 J_i^T W_i`` (K, 6, 3) of one Gauss-Newton
    step to displacements of the map-frame points q (K, 3) with weight matrices W (K, 3, 3)
    (module docstring; ``lam`` is our ICP's damping)."""
    K = q.shape[0]
    J = np.concatenate([np.broadcast_to(np.eye(3), (K, 3, 3)), -_skew(q)], axis=2)  # (K, 3, 6)
    JtW = np.einsum("kai,kab->kib", J, W)  # (K, 6, 3)
    H = np.einsum("kib,kbj->ij", JtW, J)
    lam = DAMPING * np.trace(H) / 6.0 + EPS
    S = -np.linalg.solve(H + lam * np.eye(6), JtW.transpose(1, 0, 2).reshape(6, -1))
    return S.reshape(6, K, 3).transpose(1, 0, 2)
