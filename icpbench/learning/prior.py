"""Analytic per-point channels for the generator: the sector attack's one-step sensitivities.

Beyond the paper (docs/methods.md, "Sensitivity prior"): the PointNet++ generator sees only point
coordinates, so it must discover from data which points constrain which pose direction. The
linearised point-to-plane step of the sector baseline (Laconte, Lisus & Barfoot, RA-L 2024,
arXiv 2309.04251; :mod:`icpbench.core.sector_math`) gives exactly that in closed form at the cost of one
nearest-neighbour query and a 6x6 solve. With ``GeneratorConfig.prior = "sector"`` the generator
receives, for every scan point (sensor frame):

==========  =====  =================================================================================
channels    shape  meaning
==========  =====  =================================================================================
0:3         (3,)   the sector attack's unit displacement direction ``sign(g_ji) R^T n_i`` for its
                   worst axis j (x or y); zero for points without a map point within ``d_max``
3:6         (3,)   the unit normal of the associated map point, ``R^T n_i`` (zero if unassociated)
6:8         (2,)   sensitivities ``g_xi``, ``g_yi`` of the one-step x/y pose error to a fault on
                   point i, divided by their mean absolute value over the scan (dimensionless)
==========  =====  =================================================================================

The attacker is thus assumed to know the map and the true pose, the same knowledge the sector
baseline and the PGD oracle use. The channels do not depend on the budget.

``GeneratorConfig.prior = "sector-iter"`` (beyond the paper) replaces channels 0:3 by the
displacement of the iterated analytic attack (:mod:`icpbench.core.iterated_sector`) divided by
the budget (|.| <= 1): the sector step re-linearised where the surrogate ICP lands, which depends on
lambda and on the initial guess, so these channels are computed per budget
(:func:`iterated_prior_batch`); channels 3:8 stay the one-step ones above.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from icpbench.core import sector_math as sector
from icpbench.core.errors import InputError
from icpbench.core.iterated_sector import SectorIterSettings, iterated_sector
from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Batch
from icpbench.targets.base import Target

#: Number of prior channels per point (see the module docstring).
PRIOR_CHANNELS = 8
#: Default association gate of the prior (metres): the lidar ICP preset's d_max (a model's
#: ``GeneratorConfig.prior_dmax`` sets its own, e.g. 0.3 for the objects ICP preset).
PRIOR_DMAX_M = 5.0


def sector_prior(scan: np.ndarray, T_gt: np.ndarray, map_index: MapIndex,
                 d_max: float = PRIOR_DMAX_M) -> np.ndarray:
    """Prior channels (N, 8) float32 of one clean scan (N, 3) (sensor frame, metres).

    Args:
        scan: (N, 3) clean scan, sensor frame.
        T_gt: (4, 4) true scan->map transform.
        map_index: the map (map frame) with unit normals.
        d_max: association gate (metres).

    Scans with fewer than 6 associated points get all-zero channels (the generator then falls
    back to its coordinate-only behaviour).
    """
    scan = np.asarray(scan, dtype=np.float64)
    out = np.zeros((scan.shape[0], PRIOR_CHANNELS), dtype=np.float32)
    try:
        model = sector.analyse(scan, T_gt, map_index, d_max=d_max)
    except InputError:
        if sector.associate(scan, T_gt, map_index, d_max).n_valid >= 6:
            raise
        return out
    v = model.assoc.valid
    R = np.asarray(T_gt, dtype=np.float64)[:3, :3]
    n_s = model.assoc.normals_map[v] @ R
    n_s /= np.maximum(np.linalg.norm(n_s, axis=1, keepdims=True), 1e-12)
    wc = model.worst_case(1.0)
    j = int(np.argmax(wc[:2]))
    sign = np.where(model.G[j] < 0, -1.0, 1.0)
    out[v, 0:3] = sign[:, None] * n_s
    out[v, 3:6] = n_s
    g = model.G[:2]
    out[v, 6:8] = (g / np.maximum(np.abs(g).mean(axis=1, keepdims=True), 1e-12)).T
    return out


def sector_prior_batch(scans: torch.Tensor, T_gt: torch.Tensor, maps: list[MapIndex],
                       d_max: float = PRIOR_DMAX_M) -> torch.Tensor:
    """Prior channels (B, N, 8) float32 of a batch of clean scans (B, N, 3), sensor frame, with
    association gate ``d_max`` (metres, or normalised units for objects)."""
    if scans.ndim != 3 or scans.shape[-1] != 3 or T_gt.shape != (scans.shape[0], 4, 4):
        raise InputError(f"need scans (B, N, 3) and T_gt (B, 4, 4), got {tuple(scans.shape)} "
                         f"and {tuple(T_gt.shape)}")
    if len(maps) != scans.shape[0]:
        raise InputError(f"need one map per scan, got {len(maps)} for {scans.shape[0]} scans")
    s = scans.detach().to("cpu", torch.float64).numpy()
    T = T_gt.detach().to("cpu", torch.float64).numpy()
    return torch.as_tensor(np.stack([sector_prior(s[b], T[b], maps[b], d_max)
                                     for b in range(len(maps))]))


def iterated_prior_batch(batch: Batch, budget_m: torch.Tensor, icp: Target, d_max: float = PRIOR_DMAX_M,
                         settings: SectorIterSettings | None = None) -> torch.Tensor:
    """Prior channels (B, N, 8) float32 of ``prior="sector-iter"`` models (module docstring).

    Args:
        batch: clean scans (B, N, 3) (sensor frame) with their maps, true poses and initial guesses.
        budget_m: (B,) budget of each sample (metres).
        icp: the surrogate ICP that locates the attacked pose (forward only).
        d_max: association gate (metres) of the one-step channels 3:8.
        settings: of the iterated analytic attack (default: its defaults, the ``sector-iter``
            attack's); a batch with one budget takes the result from ``batch.memo`` when the
            ``sector-iter`` attack computed it already.
    """
    lam = torch.as_tensor(budget_m, dtype=torch.float64).reshape(-1)
    if lam.shape != (len(batch),) or not bool(torch.all(lam > 0)):
        raise InputError(f"need one budget > 0 per sample, got {tuple(lam.shape)} for {len(batch)}")
    out = sector_prior_batch(batch.scans, batch.T_gt, batch.maps, d_max)
    for value in torch.unique(lam).tolist():
        idx = torch.nonzero(lam == value)[:, 0]
        sub = batch if idx.numel() == len(batch) else Batch.from_samples(
            [batch.samples[i] for i in idx.tolist()], dtype=batch.scans.dtype,
            maps=[batch.maps[i] for i in idx.tolist()])
        adv = torch.as_tensor(iterated_sector(sub, value, icp, settings).scans)
        out[idx, :, 0:3] = ((adv - sub.scans.to(torch.float64)) / value).to(torch.float32)
    return out


def prior_channels(config: Any, batch: Batch, budget_m: torch.Tensor | None,
                   icp: Target | None = None,
                   settings: SectorIterSettings | None = None) -> torch.Tensor | None:
    """The prior channels (B, N, 8) a generator with ``config`` (a
    :class:`~icpbench.learning.network.GeneratorConfig`) takes for ``batch``, or None
    (``prior="none"``). ``budget_m`` (B,) metres, the surrogate ``icp`` and the iterated attack's
    ``settings`` (default: its defaults) are used by ``prior="sector-iter"`` only.

    Raises:
        InputError: ``sector-iter`` without a budget or a surrogate.
    """
    if config.prior == "none":
        return None
    if config.prior == "sector":
        return sector_prior_batch(batch.scans, batch.T_gt, batch.maps, config.prior_dmax)
    if budget_m is None or icp is None:
        raise InputError("a generator with prior='sector-iter' needs the budget and a surrogate ICP")
    return iterated_prior_batch(batch, budget_m, icp, config.prior_dmax, settings)
