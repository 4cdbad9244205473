"""Attack ``sector``: the analytic worst case of Laconte, Lisus and Barfoot (RA-L 2024) on the whole cloud.

The baseline Zhang et al. (ICRA 2025) compare with: one linearised point-to-plane step at the true
pose with known association (:mod:`icpbench.core.sector_math`). Every associated scan point is moved by
exactly the budget lambda along the normal of its map point, with the sign that maximises the
chosen pose component: ``p_i + lambda * sign(g_ji) R_gt^T n_i`` (sensor frame). The component is
the worse of longitudinal ``rho_x`` and lateral ``rho_y`` (map frame, the harness's pose error).
Points without a map point within ``d_max`` are left unchanged. No surrogate, no randomness.

Extras per sample (result columns):

* ``analytic_x``, ``analytic_y`` (m), ``analytic_yaw`` (rad): closed-form worst cases
  ``lambda * sum_i |g_ji|``, each for its own maximising perturbation;
* ``analytic_xy`` (m): ``max(analytic_x, analytic_y)``, the baseline score of the paper;
* ``analytic_pred_xy`` (m): ``||rho_xy||`` that the one-step model predicts for the perturbation
  actually returned (comparable with the realised ``trans_err_xy``);
* ``analytic_axis``: the attacked component (0 = x, 1 = y, ...);
* ``analytic_assoc_frac``: share of scan points with a correspondence;
* ``sector_resilience_deg``: smallest azimuth wedge (degrees) whose corruption (faults up to
  lambda) drives x or y past ``alert_m``; smaller = less resilient.

Samples with fewer than 6 correspondences are returned unchanged with NaN extras.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack
from icpbench.core import sector_math as sector
from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.icp import icp_config

_AXES = {"xy": ("x", "y"), "x": ("x",), "y": ("y",), "z": ("z",), "yaw": ("yaw",)}

EXTRA_COLUMNS = ("analytic_x", "analytic_y", "analytic_xy", "analytic_yaw", "analytic_pred_xy",
                 "analytic_axis", "analytic_assoc_frac", "sector_resilience_deg")


class SectorAttack(Attack):
    """Analytic whole-cloud worst case (Laconte et al., RA-L 2024; arXiv 2309.04251).

    Args:
        icp_preset: ICP preset whose association gate and damping the model uses
            (``"lidar"``: d_max 5 m; ``"objects"``: d_max 0.3).
        d_max: association gate override (metres); ``None`` takes the preset's.
        axes: ``"xy"`` (worse of x and y, default), ``"x"``, ``"y"``, ``"z"`` or ``"yaw"``.
        direction: +1 or -1, the sign of the error the perturbation drives.
        frame: ``"map"`` (the harness's pose error, default) or ``"sensor"``; see
            :mod:`icpbench.core.sector_math`.
        alert_m: alert limit of ``sector_resilience_deg`` (metres).
        strict: project displacements onto the budget ball (a no-op here: they equal the budget).
    """

    name: ClassVar[str] = "sector"
    cost_class: ClassVar[int] = 0
    description: ClassVar[str] = (
        "Analytic worst case of one point-to-plane step (Laconte et al. RA-L 2024): "
        "every point moved by lambda along its map normal"
    )
    needs_surrogate: ClassVar[bool] = False
    param_ranges: ClassVar[dict[str, Range]] = {
        "d_max": Range(0.0, lo_open=True), "direction": Range(-1, 1),
        "alert_m": Range(0.0, lo_open=True)}

    def __init__(self, *, icp_preset: str = "lidar", d_max: float | None = None, axes: str = "xy",
                 direction: int = 1, frame: str = "map", alert_m: float = 0.5,
                 strict: bool = False) -> None:
        cfg = icp_config(icp_preset)
        if axes not in _AXES:
            raise InputError(f"axes must be one of {', '.join(_AXES)}, got {axes!r}")
        if direction not in (1, -1):
            raise InputError(f"direction must be +1 or -1, got {direction}")
        if frame not in ("map", "sensor"):
            raise InputError(f"frame must be 'map' or 'sensor', got {frame!r}")
        gate = cfg.d_max if d_max is None else float(d_max)
        gate = math.inf if gate is None else gate
        if not gate > 0:
            raise InputError(f"d_max must be > 0 metres, got {d_max}")
        if not (alert_m > 0 and math.isfinite(alert_m)):
            raise InputError(f"alert_m must be a positive number of metres, got {alert_m}")
        super().__init__(strict=strict, icp_preset=icp_preset, d_max=gate, axes=axes,
                         direction=direction, frame=frame, alert_m=float(alert_m))
        self.d_max = gate
        self.damping = cfg.damping
        self.axes = _AXES[axes]
        self.direction = direction
        self.frame = frame
        self.alert_m = float(alert_m)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: torch.Generator) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        scans = batch.scans.detach().to(torch.float64).cpu().numpy()
        T_gt = batch.T_gt.detach().to(torch.float64).cpu().numpy()
        B = scans.shape[0]
        extra = {k: np.full(B, np.nan) for k in EXTRA_COLUMNS}
        adv = scans.copy()
        for b in range(B):
            try:
                model = sector.analyse(scans[b], T_gt[b], batch.maps[b], d_max=self.d_max,
                                       frame=self.frame, damping=self.damping)  # type: ignore[arg-type]
            except InputError:
                assoc = sector.associate(scans[b], T_gt[b], batch.maps[b], self.d_max)
                if assoc.n_valid >= 6:
                    raise
                # too few correspondences: leave the scan clean, NaN estimates
                extra["analytic_assoc_frac"][b] = float(np.mean(assoc.valid))
                continue
            extra["analytic_assoc_frac"][b] = float(np.mean(model.assoc.valid))
            adv[b], axis, xi = model.attack(budget_m, self.axes, self.direction)
            wc = model.worst_case(budget_m)
            extra["analytic_x"][b] = wc[0]
            extra["analytic_y"][b] = wc[1]
            extra["analytic_xy"][b] = max(wc[0], wc[1])
            extra["analytic_yaw"][b] = wc[5]
            extra["analytic_pred_xy"][b] = float(np.hypot(xi[0], xi[1]))
            extra["analytic_axis"][b] = axis
            extra["sector_resilience_deg"][b] = model.resilience(budget_m, self.alert_m).width_deg
        return torch.as_tensor(adv, dtype=batch.scans.dtype), extra
