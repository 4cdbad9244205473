"""``odometry``: whether the estimated pose agrees with an odometry prediction.

A vehicle predicts its pose from wheel odometry and inertial sensors between lidar fixes; a stack
gates the lidar pose against that prediction and refuses a jump the prediction cannot explain (the
innovation gate of a Kalman filter). A single registration problem of the harness has no
trajectory, so the prediction is simulated around the true pose with a stated noise model:

``t_pred = t_gt + sigma * z``, ``z ~ N(0, I_3)``, ``sigma = sigma0_m + drift * distance_m``

(map frame, metres; rotation not predicted). ``distance_m`` stands for the distance travelled since
the last trusted pose, so the prediction's error grows with it (default: 0.1 m + 1% of 10 m =
0.2 m). The draw ``z`` is seeded per sample: its seed is a stable hash of (``seed``, the sample
id) (:func:`prior_seed`), so a sample always gets the same prediction, whatever batch it is in,
and the seed is recorded with the prediction (:class:`~icpbench.monitors.inputs.MotionPrior`).

The score is the normalised innovation ``||t_hat - t_pred|| / sigma`` (dimensionless). On a
perfect registration it follows a chi distribution with 3 degrees of freedom; the default
threshold 3.368 is its 99% quantile (1% false alarms before any registration error).
"""

from __future__ import annotations

import hashlib
from typing import ClassVar

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.monitors.base import Monitor
from icpbench.monitors.differentiable import DiffInput
from icpbench.monitors.inputs import MonitorInput, MotionPrior

#: 99% quantile of the chi distribution with 3 degrees of freedom: sqrt(chi2.ppf(0.99, 3)).
CHI3_99 = 3.368


def prior_seed(seed: int, sample_id: str) -> int:
    """The seed of one sample's odometry draw: a stable 63-bit hash of (seed, sample id)."""
    text = f"{int(seed)}|odometry|{sample_id}"
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "big") >> 1


def odometry_prior(T_gt: np.ndarray, sample_id: str, *, sigma0_m: float = 0.1, drift: float = 0.01,
                   distance_m: float = 10.0, seed: int = 0) -> MotionPrior:
    """The simulated odometry prediction of one sample (see the module docstring).

    Args:
        T_gt: (4, 4) true scan->map transform.
        sample_id: the sample's identifier (seeds the draw).
        sigma0_m: the prediction's error (metres, per axis) right after a trusted pose.
        drift: growth of that error per metre travelled (dimensionless; 0.01 = 1%).
        distance_m: distance travelled (metres) since the last trusted pose.
        seed: the run's seed for these draws.

    Returns:
        The prediction ``T_pred`` (rotation of ``T_gt``, translation drawn), its ``sigma_m``,
        ``distance_m`` and the draw's seed.
    """
    T = np.asarray(T_gt, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"odometry prior of {sample_id!r}: T_gt must be a finite 4x4 matrix")
    sigma = float(sigma0_m) + float(drift) * float(distance_m)
    s = prior_seed(seed, sample_id)
    z = np.random.default_rng(s).standard_normal(3)
    T_pred = T.copy()
    T_pred[:3, 3] += sigma * z
    return MotionPrior(T_pred=T_pred, sigma_m=sigma, distance_m=float(distance_m), seed=s)


class OdometryMonitor(Monitor):
    """Normalised distance ``||t_hat - t_pred|| / sigma`` of the estimated translation from a
    simulated odometry prediction.

    Args:
        threshold: fires above this many sigmas (default: the chi-3 99% quantile).
        sigma0_m: prediction error (metres, per axis) at zero distance travelled.
        drift: growth of the prediction error per metre travelled (0.01 = 1%).
        distance_m: distance travelled (metres) since the last trusted pose.
        seed: seed of the per-sample draws (with the sample id).
    """

    name: ClassVar[str] = "odometry"
    description: ClassVar[str] = ("distance of the estimated translation from a seeded odometry "
                                  "prediction, in sigmas (0.1 m + 1% of the distance travelled)")
    param_ranges: ClassVar[dict[str, Range]] = {
        "threshold": Range(0.0, lo_open=True), "sigma0_m": Range(0.0, lo_open=True),
        "drift": Range(0.0, 1.0), "distance_m": Range(0.0, 1e6), "seed": Range(0, 2**63 - 1)}
    differentiable: ClassVar[bool] = True

    def __init__(self, *, threshold: float = CHI3_99, sigma0_m: float = 0.1, drift: float = 0.01,
                 distance_m: float = 10.0, seed: int = 0) -> None:
        super().__init__(threshold=threshold, sigma0_m=sigma0_m, drift=drift, distance_m=distance_m,
                         seed=seed)
        self.sigma0_m, self.drift, self.distance_m = float(sigma0_m), float(drift), float(distance_m)
        self.seed = int(seed)

    def motion_prior(self, T_gt: np.ndarray, sample_id: str) -> MotionPrior:
        """This monitor's odometry prediction for a sample (:func:`odometry_prior`)."""
        return odometry_prior(T_gt, sample_id, sigma0_m=self.sigma0_m, drift=self.drift,
                              distance_m=self.distance_m, seed=self.seed)

    def _score(self, inp: MonitorInput) -> float:
        if inp.prior is None:
            raise InputError(f"monitor 'odometry' needs a motion prior for sample {inp.sample_id!r}; "
                             "give MonitorInput(prior=monitor.motion_prior(T_gt, sample_id))")
        d = float(np.linalg.norm(inp.T_hat[:3, 3] - inp.prior.T_pred[:3, 3]))
        return d / inp.prior.sigma_m

    def _differentiable_score(self, x: DiffInput) -> torch.Tensor:
        if x.prior is None:
            raise InputError(f"monitor 'odometry' needs a motion prior for sample {x.sample_id!r}")
        t_pred = torch.as_tensor(x.prior.T_pred[:3, 3])
        return torch.linalg.norm(x.T_hat[:3, 3].to(torch.float64) - t_pred) / x.prior.sigma_m
