"""The shape of the ground of a ``lidar-sim`` town: slopes and road camber.

Town frame (east-north-up, metres; see :mod:`icpbench.datasets.town`). The ground height is

    z(x, y) = sum_k a_k sin(2 pi (x cos t_k + y sin t_k) / w_k + p_k)  -  c * min(|d - 1.75|, 7)

a few long plane waves (amplitude ``a_k`` m, wavelength ``w_k`` m, direction ``t_k``, phase
``p_k``): the route climbs and descends with slopes of a few percent wherever it goes, with no
seam on the closed loop; and a road crown along the lane line between the driven and the oncoming
lane (``d = 1.75`` m to the left of the driven lane centre), falling with cross-slope ``c``
(m/m, typically 2 %) for 7 m to either side, then level. ``d`` is the lateral route coordinate.

The vehicle stands on this surface: :meth:`Ground.vehicle_pose` tilts it by the pitch and roll of
the ground under its wheels. With no waves and no camber the ground is the plane ``z = 0`` and the
pose is the plain planar one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from icpbench.datasets.town import MeshBuilder, Route

#: Lateral offset of the road crown from the driven lane centre (metres).
CROWN_D_M = 1.75
#: Half-width of the cambered band around the crown (metres).
CAMBER_HALF_WIDTH_M = 7.0
#: Half wheelbase and half track used to tilt the vehicle (metres).
_HALF_BASE_M, _HALF_TRACK_M = 1.4, 0.8


@dataclass(frozen=True)
class Ground:
    """Ground height of a town (see the module docstring).

    Attributes:
        route: the town's route (for the lateral coordinate of the camber).
        waves: ((amplitude_m, wavelength_m, direction_rad, phase_rad), ...).
        camber: road cross-slope (m/m).
    """

    route: Route
    waves: tuple[tuple[float, float, float, float], ...] = ()
    camber: float = 0.0

    @property
    def flat(self) -> bool:
        """True when the ground is the plane z = 0."""
        return not self.waves and self.camber == 0.0

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (K,) in metres at town-frame points xy (K, 2)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        z = np.zeros(len(xy))
        for a, w, t, p in self.waves:
            z += a * np.sin(2 * np.pi * (xy[:, 0] * np.cos(t) + xy[:, 1] * np.sin(t)) / w + p)
        if self.camber:
            _, d = self.route.project(xy)
            z -= self.camber * np.minimum(np.abs(d - CROWN_D_M), CAMBER_HALF_WIDTH_M)
        return z

    def height_sd(self, s: np.ndarray | float, d: np.ndarray | float) -> np.ndarray:
        """Ground height (...,) at route coordinates (s, d)."""
        xy, _ = self.route.pose(s, d)
        shape = np.shape(xy)[:-1]
        return self.height(np.reshape(xy, (-1, 2))).reshape(shape)

    def vehicle_pose(self, xy: np.ndarray, yaw: float, height_m: float) -> np.ndarray:
        """T_town_sensor (4, 4) of a sensor ``height_m`` above the ground at xy (2,) with heading
        ``yaw`` (radians): the vehicle pitches and rolls with the ground under its wheels
        (heights at +-1.4 m along and +-0.8 m across the heading); the sensor sits ``height_m``
        along the vehicle's up axis above their mean. Rotation = Rz(yaw) Ry(pitch) Rx(roll)."""
        xy = np.asarray(xy, dtype=np.float64)
        fwd = np.array([np.cos(yaw), np.sin(yaw)])
        left = np.array([-fwd[1], fwd[0]])
        pts = np.stack([xy + _HALF_BASE_M * fwd, xy - _HALF_BASE_M * fwd,
                        xy + _HALF_TRACK_M * left, xy - _HALF_TRACK_M * left])
        zf, zb, zl, zr = self.height(pts)
        pitch = -np.arctan2(zf - zb, 2 * _HALF_BASE_M)
        roll = np.arctan2(zl - zr, 2 * _HALF_TRACK_M)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
        T[:3, 3] = [xy[0], xy[1], 0.25 * (zf + zb + zl + zr)]  # the plane under the wheels
        T[:3, 3] += T[:3, :3] @ np.array([0.0, 0.0, height_m])
        return T

    def mesh(self, mb: MeshBuilder, bounds: tuple[float, float, float, float], band_m: float,
             step_m: float = 2.0) -> None:
        """Add the ground as a height field over a regular town-frame grid of ``step_m`` inside
        ``bounds`` (xmin, ymin, xmax, ymax), keeping the cells within ``band_m`` of the route
        (beyond the lidar's range nothing is needed)."""
        x0, y0, x1, y1 = bounds
        xs, ys = np.arange(x0, x1 + step_m, step_m), np.arange(y0, y1 + step_m, step_m)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        xy = np.c_[X.ravel(), Y.ravel()]
        dist, _ = self.route._tree.query(xy)
        z = self.height(xy)
        nx, ny = X.shape
        i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
        a = (i * ny + j).ravel()
        b, c, d = a + ny, a + ny + 1, a + 1
        F = np.vstack([np.c_[a, b, c], np.c_[a, c, d]])
        F = F[dist[F].min(1) <= band_m]
        used, F = np.unique(F, return_inverse=True)
        mb.add(np.c_[xy[used], z[used]], F.reshape(-1, 3))
