"""The analytic sector baseline: closed-form worst case of one linearised point-to-plane ICP step.

Method of Laconte, Lisus and Barfoot, "Toward Certifying Maps for Safe Registration-based
Localization Under Adverse Conditions", IEEE RA-L 2024 (arXiv 2309.04251), as reconstructed in
docs/methods.md ("Analytic sector attack") and used as the "Sector" baseline by Zhang et al.
(ICRA 2025).

Model (one Gauss-Newton step from the true pose, known association, no robust kernel):

* each clean scan point ``p_i`` (sensor frame) is moved into the map frame, ``q_i = T_gt p_i``, and
  associated with its nearest map point ``m_i`` and that point's unit normal ``n_i``;
* a *fault* ``f_i`` (metres) shifts the scan point along the normal, ``q_i' = q_i + f_i n_i``. This
  changes the point-to-plane residual ``n_i.(q_i - m_i)`` by exactly ``f_i`` and leaves the Jacobian
  row unchanged (``(q + f n) x n = q x n``), so the one-step pose error is *exactly* linear in f:
  ``xi = G f`` with ``G = -(A^T W A + lam I)^-1 A^T W`` (6, K);
* a per-point bound ``|f_i| <= lambda`` gives the closed-form worst case of pose component j over a
  set S of points, ``lambda * sum_{i in S} |g_ji|``, reached by ``f_i = lambda * sign(g_ji)``.
  A Euclidean per-point budget ``||dp_i|| <= lambda`` gives the same value to first order (the
  normal direction is the only one that changes the residual).

Pose-error frame (``frame`` argument):

* ``"map"`` (default): ``xi = log(T_hat inv(T_gt))`` = [rho, phi] in the map frame, exactly the
  harness's pose error (:func:`icpbench.core.se3.pose_error`) and the left-perturbation update of our
  ICP (``T <- exp(delta^) T``): rows ``a_i = [n_i, q_i x n_i]``. For the lidar datasets the map is
  expressed in the true vehicle frame (docs/architecture.md, "Frames, units and pose error"), so
  component 0 (``rho_x``) is longitudinal
  and 1 (``rho_y``) lateral, up to the small random init offset.
* ``"sensor"``: ``xi_s = log(inv(T_gt) T_hat)`` in the true sensor frame (x and y are then
  longitudinal and lateral whatever the map frame): rows ``[R^T n_i, p_i x R^T n_i]``. To first
  order ``xi = Ad(T_gt) xi_s``.

Sectors are azimuth wedges of the sensor frame (angle of ``(p_x, p_y)`` about the sensor's z axis,
all elevations): ``S(theta0, width) = {i : (az_i - theta0) mod 2 pi < width}``.

Regularisation follows our ICP (:class:`icpbench.targets.icp.ICPConfig`):
``lam = damping * trace(H) / 6 + eps``, damping 1e-9, eps 1e-12, so the closed form is computed
from the same normal equations the ICP solves.

Units: metres and radians. All computations in float64. No torch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.special import ndtr

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex

PoseFrame = Literal["map", "sensor"]

#: Names of the 6 pose-error components, in the harness's [rho, phi] order.
COMPONENTS: tuple[str, ...] = ("rho_x", "rho_y", "rho_z", "phi_x", "phi_y", "phi_z")

#: Short axis names -> component index.
AXIS_INDEX: dict[str, int] = {"x": 0, "y": 1, "z": 2, "roll": 3, "pitch": 4, "yaw": 5}

#: Relative and absolute regularisation of our ICP's normal equations (ICPConfig.damping, +1e-12).
DEFAULT_DAMPING = 1e-9
DEFAULT_EPS = 1e-12

TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------
def _points(x: np.ndarray, name: str, *, allow_nonfinite: bool = False) -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (K, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"{name} must be a floating-point array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not allow_nonfinite and not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has NaN or Inf coordinates")
    return arr


def _budget(budget_m: float, name: str = "budget_m") -> float:
    try:
        b = float(budget_m)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number, got {budget_m!r}") from exc
    if not (b > 0 and math.isfinite(b)):
        raise InputError(f"{name} must be a positive finite number (metres), got {budget_m!r}")
    return b


def _transform(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"T_gt must be a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5):
        raise InputError("T_gt must be a rigid transform (its rotation block is not orthonormal)")
    return T


def _axis(axis: int | str) -> int:
    if isinstance(axis, str):
        if axis not in AXIS_INDEX:
            raise InputError(f"unknown axis {axis!r}; valid: {', '.join(AXIS_INDEX)} or 0..5")
        return AXIS_INDEX[axis]
    j = int(axis)
    if not 0 <= j < 6:
        raise InputError(f"axis index must be in 0..5 (rho_x, rho_y, rho_z, phi_x, phi_y, phi_z), "
                         f"got {axis}")
    return j


def _sensitivity_matrix(G: np.ndarray) -> np.ndarray:
    G = np.asarray(G, dtype=np.float64)
    if G.ndim != 2 or G.shape[0] != 6:
        raise InputError(f"G must have shape (6, K), got {G.shape}")
    if not np.all(np.isfinite(G)):
        raise InputError("G has NaN or Inf entries")
    return G


# --------------------------------------------------------------------------------------------
# association and the linear model
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Association:
    """Known data association of a clean scan at the true pose.

    Attributes:
        valid: (N,) bool, True where the scan point has a map point within ``d_max``.
        map_idx: (N,) int64 index of the nearest map point (``M`` where invalid).
        dist: (N,) distance to it, metres (``inf`` where invalid).
        points_map: (N, 3) clean scan points moved into the map frame by ``T_gt`` (metres).
        normals_map: (N, 3) unit normal of the associated map point, map frame (zeros if invalid).
        residual: (N,) clean point-to-plane residual ``n_i.(q_i - m_i)`` at the true pose (metres,
            0 where invalid); the one-step model ignores it (it is 0 for points on a map plane).
    """

    valid: np.ndarray
    map_idx: np.ndarray
    dist: np.ndarray
    points_map: np.ndarray
    normals_map: np.ndarray
    residual: np.ndarray

    @property
    def n_valid(self) -> int:
        """Number of associated points K."""
        return int(self.valid.sum())


def associate(scan: np.ndarray, T_gt: np.ndarray, map_index: MapIndex, d_max: float) -> Association:
    """Associate each clean scan point with its nearest map point (and normal) at the true pose.

    Args:
        scan: (N, 3) clean scan, sensor frame, metres. Non-finite points are left unassociated.
        T_gt: (4, 4) true scan->map transform.
        map_index: prepared map with normals (map frame).
        d_max: association gate (metres); points farther from the map get no correspondence and
            zero influence. ``inf`` disables the gate.

    Raises:
        InputError: bad shapes, a non-rigid ``T_gt``, a map without normals, or a bad ``d_max``.
    """
    p = _points(scan, "scan", allow_nonfinite=True)
    T = _transform(T_gt)
    if not isinstance(map_index, MapIndex):
        raise InputError("map_index must be an icpbench.core.mapindex.MapIndex, got "
                         f"{type(map_index).__name__}")
    if map_index.normals is None:
        raise InputError("the map has no normals; build MapIndex(points, normals) with unit normals")
    d_max = float(d_max)
    if not d_max > 0:
        raise InputError(f"d_max must be > 0 metres (or inf), got {d_max}")
    q = p @ T[:3, :3].T + T[:3, 3]
    dist, idx = map_index.query(q, d_max)
    valid = idx < len(map_index)
    normals = np.zeros_like(q)
    normals[valid] = map_index.normals[idx[valid]]
    residual = np.zeros(q.shape[0])
    residual[valid] = np.einsum("ij,ij->i", q[valid] - map_index.points[idx[valid]], normals[valid])
    return Association(valid=valid, map_idx=idx, dist=dist, points_map=q, normals_map=normals,
                       residual=residual)


def jacobian(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Point-to-plane Jacobian rows ``a_i = [n_i, p_i x n_i]`` (K, 6) for the twist [rho, phi].

    ``a_i`` is the derivative of the residual ``n_i.(p_i - m_i)`` under the left perturbation
    ``p -> exp(xi^) p``, with ``points`` and ``normals`` (K, 3) in the frame of that perturbation
    (map frame for the harness's pose error).
    """
    p = _points(points, "points")
    n = _points(normals, "normals")
    if p.shape != n.shape:
        raise InputError(f"points {p.shape} and normals {n.shape} must have the same shape")
    return np.hstack([n, np.cross(p, n)])


def sensitivity(A: np.ndarray, weights: np.ndarray | None = None, *,
                damping: float = DEFAULT_DAMPING, eps: float = DEFAULT_EPS) -> np.ndarray:
    """Sensitivity ``G`` (6, K) of the one-step pose error to normal-direction faults: ``xi = G f``.

    ``G = -(A^T W A + lam I)^-1 A^T W`` with ``lam = damping * trace(A^T W A) / 6 + eps`` (the
    regularisation of our ICP). ``g_ji`` is the change of pose component j (metres or radians) per
    metre of fault on point i's residual.

    Args:
        A: (K, 6) Jacobian rows from :func:`jacobian`, K >= 6.
        weights: optional (K,) non-negative per-point weights (default 1: no robust kernel).
        damping: relative Levenberg damping (dimensionless).
        eps: absolute damping.
    """
    A = np.asarray(A, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 6:
        raise InputError(f"A must have shape (K, 6), got {A.shape}")
    if A.shape[0] < 6:
        raise InputError(f"at least 6 associated points are needed to constrain a 6-DoF pose, "
                         f"got {A.shape[0]}")
    if not np.all(np.isfinite(A)):
        raise InputError("A has NaN or Inf entries")
    if damping < 0 or eps < 0:
        raise InputError(f"damping and eps must be >= 0, got {damping}, {eps}")
    if weights is None:
        AtW = A.T
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (A.shape[0],) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise InputError(f"weights must be {A.shape[0]} finite non-negative numbers")
        AtW = A.T * w
    H = AtW @ A
    lam = damping * np.trace(H) / 6.0 + eps
    return -np.linalg.solve(H + lam * np.eye(6), AtW)


def worst_case(G: np.ndarray, budget_m: float, subset: np.ndarray | None = None) -> np.ndarray:
    """Closed-form worst case (6,) of each pose component over faults ``|f_i| <= budget_m``.

    ``max_f |xi_j| = budget_m * sum_{i in S} |g_ji|`` (metres for rho, radians for phi), where S is
    ``subset`` (a (K,) bool mask or an index array; default: all K points). Each component has
    its own maximising fault pattern (:func:`worst_faults`).
    """
    G = _sensitivity_matrix(G)
    lam = _budget(budget_m)
    absG = np.abs(G) if subset is None else np.abs(G[:, _subset(subset, G.shape[1])])
    return lam * absG.sum(axis=1)


def _subset(subset: np.ndarray, K: int) -> np.ndarray:
    s = np.asarray(subset)
    if s.dtype == bool:
        if s.shape != (K,):
            raise InputError(f"a boolean subset must have shape ({K},), got {s.shape}")
        return s
    if s.ndim != 1 or not np.issubdtype(s.dtype, np.integer):
        raise InputError("subset must be a (K,) bool mask or a 1-D integer index array")
    if s.size and (s.min() < -K or s.max() >= K):
        raise InputError(f"subset indices must be in [0, {K})")
    return s


def worst_faults(G: np.ndarray, budget_m: float, axis: int | str, direction: int = 1) -> np.ndarray:
    """The fault vector (K,) that maximises ``direction * xi_axis``: ``f = direction*lambda*sign(g)``.

    Points with ``g = 0`` get ``+direction * lambda`` (harmless; keeps every displacement at exactly
    the budget). ``axis``: component index 0..5 or a name from :data:`AXIS_INDEX`.
    """
    G = _sensitivity_matrix(G)
    lam = _budget(budget_m)
    if direction not in (1, -1):
        raise InputError(f"direction must be +1 or -1, got {direction}")
    g = G[_axis(axis)]
    return direction * lam * np.where(g < 0, -1.0, 1.0)


def perturb_scan(scan: np.ndarray, T_gt: np.ndarray, assoc: Association,
                 faults: np.ndarray) -> np.ndarray:
    """Apply normal-direction faults to a scan in its sensor frame.

    ``p_i' = p_i + f_i R_gt^T n_i`` for associated points (the map-frame shift ``f_i n_i`` expressed
    in the sensor frame, with ``n_i`` renormalised to unit length); unassociated points are
    unchanged. Each associated point moves by exactly ``|f_i|``.

    Args:
        scan: (N, 3) clean scan, sensor frame.
        T_gt: (4, 4) true scan->map transform.
        assoc: association of this scan (:func:`associate`).
        faults: (K,) faults of the K associated points (in scan order), metres.
    Returns:
        (N, 3) float64 adversarial scan, sensor frame.
    """
    p = _points(scan, "scan", allow_nonfinite=True)
    T = _transform(T_gt)
    f = np.asarray(faults, dtype=np.float64)
    if assoc.valid.shape != (p.shape[0],):
        raise InputError(f"association is for {assoc.valid.shape[0]} points, scan has {p.shape[0]}")
    if f.shape != (assoc.n_valid,):
        raise InputError(f"faults must have shape ({assoc.n_valid},) (one per associated point), "
                         f"got {f.shape}")
    out = p.copy()
    n_sensor = assoc.normals_map[assoc.valid] @ T[:3, :3]  # rows R^T n_i
    norm = np.linalg.norm(n_sensor, axis=1, keepdims=True)
    # unit direction (stored float32 normals are unit only to ~1e-7): displacement exactly |f_i|
    n_sensor = np.divide(n_sensor, norm, out=np.zeros_like(n_sensor), where=norm > 0)
    out[assoc.valid] += f[:, None] * n_sensor
    return out


# --------------------------------------------------------------------------------------------
# sectors
# --------------------------------------------------------------------------------------------
def azimuth(points: np.ndarray) -> np.ndarray:
    """Azimuth (K,) of points (K, 3) about the z axis of their frame, radians in [-pi, pi]."""
    p = _points(points, "points")
    return np.arctan2(p[:, 1], p[:, 0])


@dataclass(frozen=True)
class _Wrapped:
    """Azimuth-sorted weights duplicated with +2 pi for wrap-around, and their cumulative sum."""

    az: np.ndarray   # (K,) sorted azimuths
    az2: np.ndarray  # (2K,) az then az + 2 pi
    csum: np.ndarray  # (2K + 1,) cumulative sum of the duplicated weights, csum[0] = 0

    @classmethod
    def build(cls, weights: np.ndarray, az: np.ndarray) -> _Wrapped:
        w = np.asarray(weights, dtype=np.float64)
        a = np.asarray(az, dtype=np.float64)
        if w.ndim != 1 or a.shape != w.shape or w.size == 0:
            raise InputError(f"weights {w.shape} and azimuths {a.shape} must be equal-length, "
                             "non-empty 1-D arrays")
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(a))):
            raise InputError("weights and azimuths must be finite")
        if np.any(w < 0):
            raise InputError("sector weights must be non-negative (use |g_ji|)")
        a = np.mod(a + math.pi, TWO_PI) - math.pi  # into [-pi, pi)
        o = np.argsort(a, kind="stable")
        a, w = a[o], w[o]
        return cls(az=a, az2=np.r_[a, a + TWO_PI], csum=np.r_[0.0, np.cumsum(np.r_[w, w])])


@dataclass(frozen=True)
class SweepResult:
    """Worst wedge of each width for one pose component.

    Attributes:
        widths_rad: (W,) wedge widths, radians.
        worst: (W,) ``budget * max_theta0 sum_{i in S(theta0, width)} |g_ji|`` (metres or radians).
        start_rad: (W,) start angle theta0 of the worst wedge (sensor-frame azimuth, [-pi, pi)).
    """

    widths_rad: np.ndarray
    worst: np.ndarray
    start_rad: np.ndarray


def sector_sweep(weights: np.ndarray, az: np.ndarray, widths_rad: Sequence[float] | np.ndarray,
                 budget_m: float = 1.0) -> SweepResult:
    """Worst azimuth wedge of each width, by a sliding window over azimuth-sorted points.

    The maximum over start angles is reached by a wedge starting at some point's azimuth, so for
    every point k the wedge ``[az_k, az_k + width)`` is summed from a cumulative sum over the
    azimuth-sorted weights duplicated with +2 pi (wrap-around at +-pi). O(K log K) per width.

    Args:
        weights: (K,) non-negative per-point weights, normally ``|g_ji|`` of one component j.
        az: (K,) sensor-frame azimuths of the same points, radians.
        widths_rad: (W,) widths in (0, 2 pi]; a width >= 2 pi covers the whole scan.
        budget_m: fault bound tau (metres): the result is scaled by it.
    """
    lam = _budget(budget_m)
    widths = np.asarray(widths_rad, dtype=np.float64).reshape(-1)
    if widths.size == 0 or not np.all(np.isfinite(widths)) or np.any(widths <= 0) \
            or np.any(widths > TWO_PI + 1e-12):
        raise InputError("widths_rad must be non-empty, finite and in (0, 2 pi]")
    wr = _Wrapped.build(weights, az)
    K = wr.az.size
    start = np.arange(K)
    worst = np.empty(widths.size)
    start_rad = np.empty(widths.size)
    for w_i, width in enumerate(widths):
        ends = np.minimum(np.searchsorted(wr.az2, wr.az + width, side="left"), start + K)
        sums = wr.csum[ends] - wr.csum[start]
        k = int(np.argmax(sums))
        worst[w_i] = lam * sums[k]
        start_rad[w_i] = wr.az[k]
    return SweepResult(widths_rad=widths, worst=worst, start_rad=start_rad)


def min_sector_width(weights: np.ndarray, az: np.ndarray, budget_m: float,
                     limit: float) -> tuple[float, float]:
    """Smallest wedge width whose worst case reaches ``limit``, computed exactly.

    Returns ``(width_rad, start_rad)`` with ``width_rad = inf{w : max_theta0 budget *
    sum_{S(theta0, w)} weights >= limit}``: every wedge wider than ``width_rad`` starting at
    ``start_rad`` reaches the limit (the wedge spans the azimuths from its first to its last
    point, so the width may be 0 if a single azimuth suffices). ``(inf, nan)`` if even the whole
    scan stays below the limit. O(K log K).
    """
    lam = _budget(budget_m)
    lim = _budget(limit, "limit")
    wr = _Wrapped.build(weights, az)
    K = wr.az.size
    k = np.arange(K)
    need = lim / lam
    # first index e with csum[e] - csum[k] >= need; points k..e-1 are in the wedge
    e = np.searchsorted(wr.csum, wr.csum[k] + need * (1.0 - 1e-12), side="left")
    ok = e <= k + K
    if not ok.any():
        return math.inf, math.nan
    span = np.full(K, np.inf)
    span[ok] = wr.az2[e[ok] - 1] - wr.az[ok]
    best = int(np.argmin(span))
    return float(span[best]), float(wr.az[best])


@dataclass(frozen=True)
class Resilience:
    """Resilience of one scan location (noise-free form; docs/methods.md, "Analytic sector attack").

    Attributes:
        width_rad: smallest wedge width at which any of ``axes`` reaches its alert limit
            (``inf`` if none does even with the whole scan corrupted). Smaller = less resilient.
        axis: the component index that breaks first (-1 if none).
        start_rad: start azimuth of that wedge (sensor frame; nan if none).
        per_axis_rad: (len(axes),) the same width per axis.
    """

    width_rad: float
    axis: int
    start_rad: float
    per_axis_rad: np.ndarray

    @property
    def width_deg(self) -> float:
        """``width_rad`` in degrees."""
        return math.degrees(self.width_rad)


# --------------------------------------------------------------------------------------------
# noise (hazard probability; docs/methods.md, "Analytic sector attack")
# --------------------------------------------------------------------------------------------
def hazard_probability(mu: np.ndarray | float, sigma: np.ndarray | float,
                       limit: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """``P(|e| > limit)`` for ``e ~ N(mu, sigma^2)`` (exact) and the bound ``min(2(1 - Phi), 1)``.

    ``mu`` is the worst-case bias of a component (>= 0), ``sigma`` its noise std
    (:meth:`SectorAnalysis.noise_std`), ``limit`` the alert limit (same units). Returns
    ``(exact, bound)`` arrays broadcast from the inputs.
    """
    mu_a, s_a, r_a = (np.asarray(v, dtype=np.float64) for v in (mu, sigma, limit))
    if np.any(s_a <= 0) or np.any(r_a <= 0) or np.any(mu_a < 0):
        raise InputError("hazard_probability needs sigma > 0, limit > 0 and mu >= 0")
    exact = (1.0 - ndtr((r_a - mu_a) / s_a)) + ndtr((-r_a - mu_a) / s_a)
    bound = np.minimum(2.0 * (1.0 - ndtr((r_a - mu_a) / s_a)), 1.0)
    return exact, bound


# --------------------------------------------------------------------------------------------
# the analysis of one scan
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SectorAnalysis:
    """Linear worst-case model of one scan at its true pose.

    Attributes:
        scan: (N, 3) clean scan, sensor frame.
        T_gt: (4, 4) true scan->map transform.
        assoc: the association at the true pose.
        G: (6, K) sensitivity of the pose error (in ``frame``) to the faults of the K associated
            points (scan order): ``xi = G f``.
        azimuth_rad: (K,) sensor-frame azimuths of the associated points.
        frame: ``"map"`` (harness pose error) or ``"sensor"``.
    """

    scan: np.ndarray
    T_gt: np.ndarray
    assoc: Association
    G: np.ndarray
    azimuth_rad: np.ndarray
    frame: PoseFrame

    def worst_case(self, budget_m: float, subset: np.ndarray | None = None) -> np.ndarray:
        """(6,) closed-form worst case per component (see :func:`worst_case`)."""
        return worst_case(self.G, budget_m, subset)

    def worst_faults(self, budget_m: float, axis: int | str, direction: int = 1) -> np.ndarray:
        """(K,) maximising faults of one component (see :func:`worst_faults`)."""
        return worst_faults(self.G, budget_m, axis, direction)

    def predict(self, faults: np.ndarray) -> np.ndarray:
        """(6,) one-step pose error ``G f`` caused by faults (K,) (exact for normal shifts)."""
        f = np.asarray(faults, dtype=np.float64)
        if f.shape != (self.G.shape[1],):
            raise InputError(f"faults must have shape ({self.G.shape[1]},), got {f.shape}")
        return self.G @ f

    def perturbation(self, budget_m: float, axis: int | str, direction: int = 1) -> np.ndarray:
        """(N, 3) sensor-frame scan with ``p_i + direction*lambda*sign(g_ji) R^T n_i``."""
        return perturb_scan(self.scan, self.T_gt, self.assoc,
                            self.worst_faults(budget_m, axis, direction))

    def attack(self, budget_m: float, axes: Sequence[int | str] = ("x", "y"),
               direction: int = 1) -> tuple[np.ndarray, int, np.ndarray]:
        """The explicit worst-case perturbation of the whole cloud for the worse of ``axes``.

        Returns ``(adv_scan (N, 3) sensor frame, axis index, predicted xi (6,))``.
        """
        idx = [_axis(a) for a in axes]
        if not idx:
            raise InputError("axes must name at least one component")
        wc = self.worst_case(budget_m)
        j = idx[int(np.argmax(wc[idx]))]
        f = self.worst_faults(budget_m, j, direction)
        return perturb_scan(self.scan, self.T_gt, self.assoc, f), j, self.G @ f

    def noise_std(self, sigma_w: float) -> np.ndarray:
        """(6,) std of each component for i.i.d. residual noise of std ``sigma_w`` (metres)."""
        return _budget(sigma_w, "sigma_w") * np.sqrt((self.G**2).sum(axis=1))

    def sweep(self, budget_m: float, widths_rad: Sequence[float] | np.ndarray,
              axis: int | str) -> SweepResult:
        """Worst wedge per width for one component (see :func:`sector_sweep`)."""
        return sector_sweep(np.abs(self.G[_axis(axis)]), self.azimuth_rad, widths_rad, budget_m)

    def resilience(self, budget_m: float, alert_m: float | Sequence[float] = 0.5,
                   axes: Sequence[int | str] = ("x", "y")) -> Resilience:
        """Smallest corrupted wedge at which any of ``axes`` reaches its alert limit.

        Args:
            budget_m: fault bound tau per point (metres): the ICP's association gate is a natural
                choice (larger faults are rejected as outliers); the attack uses the budget lambda.
            alert_m: alert limit per axis (one number for all, or one per axis); units of the
                component (metres for x/y/z, radians for roll/pitch/yaw). Default 0.5 m (an
                assumption: the paper's limits were not available).
            axes: components tested (default: longitudinal x and lateral y).
        """
        idx = [_axis(a) for a in axes]
        if not idx:
            raise InputError("axes must name at least one component")
        limits = np.broadcast_to(np.asarray(alert_m, dtype=np.float64), (len(idx),))
        per = np.empty(len(idx))
        starts = np.empty(len(idx))
        for n, (j, lim) in enumerate(zip(idx, limits, strict=True)):
            per[n], starts[n] = min_sector_width(np.abs(self.G[j]), self.azimuth_rad, budget_m, lim)
        if not np.isfinite(per).any():
            return Resilience(math.inf, -1, math.nan, per)
        b = int(np.argmin(per))
        return Resilience(float(per[b]), idx[b], float(starts[b]), per)


def analyse(scan: np.ndarray, T_gt: np.ndarray, map_index: MapIndex, *, d_max: float,
            frame: PoseFrame = "map", weights: np.ndarray | None = None,
            damping: float = DEFAULT_DAMPING, eps: float = DEFAULT_EPS) -> SectorAnalysis:
    """Build the linear worst-case model of one scan (association, Jacobian, sensitivity G).

    Args:
        scan: (N, 3) clean scan, sensor frame, metres.
        T_gt: (4, 4) true scan->map transform.
        map_index: the map (map frame) with unit normals.
        d_max: association gate, metres (e.g. 5 for lidar, 0.3 for objects; use the ICP's).
        frame: frame of the pose error, ``"map"`` (harness) or ``"sensor"``; see module doc.
        weights: optional (N,) per-point weights (unassociated points are dropped anyway).
        damping, eps: regularisation, as in :func:`sensitivity`.

    Raises:
        InputError: bad input, or fewer than 6 associated points.
    """
    assoc = associate(scan, T_gt, map_index, d_max)
    if assoc.n_valid < 6:
        raise InputError(
            f"only {assoc.n_valid} scan points have a map point within d_max={d_max} m at the true "
            "pose; at least 6 are needed (check T_gt, the map frame or increase d_max)"
        )
    p = np.asarray(scan, dtype=np.float64)
    T = np.asarray(T_gt, dtype=np.float64)
    v = assoc.valid
    if frame == "map":
        A = jacobian(assoc.points_map[v], assoc.normals_map[v])
    elif frame == "sensor":
        A = jacobian(p[v], assoc.normals_map[v] @ T[:3, :3])
    else:
        raise InputError(f"frame must be 'map' or 'sensor', got {frame!r}")
    w = None
    if weights is not None:
        w_all = np.asarray(weights, dtype=np.float64)
        if w_all.shape != (p.shape[0],):
            raise InputError(f"weights must have shape ({p.shape[0]},), got {w_all.shape}")
        w = w_all[v]
    G = sensitivity(A, w, damping=damping, eps=eps)
    return SectorAnalysis(scan=p, T_gt=T, assoc=assoc, G=G, azimuth_rad=azimuth(p[v]), frame=frame)
