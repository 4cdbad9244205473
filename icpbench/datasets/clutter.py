"""Street clutter for ``lidar-sim`` towns with a ``town_seed``: irregular vegetation, poles and
signs, kerbs, and moving road users.

Town frame, metres (see :mod:`icpbench.datasets.town`). Vegetation is not made of planes or
ellipsoids: a crown or a bush is a blob whose radius varies over its surface with a smooth random
function of direction (a sum of a few random "bumps"), so its returns are scattered over an
irregular, non-planar surface like foliage. Signs are thin plates on posts facing the traffic;
posts (bollards, delineators) are short cylinders; kerbs are low strips along the road edges.
Moving road users (cars, cyclists, pedestrians) are drawn per live scan of a repeat pass and are
never part of the teach pass, so they never reach the map.

Everything is placed through the town builder's placer (footprints must stay off the roads) and
drawn from its own random stream, so the original town (no ``town_seed``) is untouched.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from icpbench.datasets.town import MeshBuilder


def unit_sphere(res: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 1 with ``res`` latitude bands: vertices (V, 3), triangles (F, 3)."""
    lat = np.linspace(0, np.pi, res + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, 2 * res, endpoint=False)
    La, Lo = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(La) * np.cos(Lo), np.sin(La) * np.sin(Lo), np.cos(La)], -1).reshape(-1, 3)
    V = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    m = 2 * res
    F = []
    for j in range(m):
        F.append([0, 1 + j, 1 + (j + 1) % m])
        base = 1 + (res - 2) * m
        F.append([len(V) - 1, base + (j + 1) % m, base + j])
    for r in range(res - 2):
        for j in range(m):
            a, b = 1 + r * m + j, 1 + r * m + (j + 1) % m
            F += [[a, a + m, b], [b, a + m, b + m]]
    return V, np.array(F)


_BLOB = unit_sphere(9)


def blob(mb: MeshBuilder, centre: np.ndarray, radii: tuple[float, float, float],
         rng: np.random.Generator, roughness: float = 0.3) -> None:
    """An irregular closed surface around ``centre`` (3,): a sphere scaled by ``radii`` whose
    radius is multiplied by ``1 + roughness * n(u)``, ``n`` a smooth random function of the
    direction ``u`` in [-1, 1] (six random bumps of random width)."""
    V, F = _BLOB
    axes = rng.normal(size=(6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    width = rng.uniform(0.3, 0.8, 6)
    sign = rng.choice([-1.0, 1.0], 6)
    n = (sign * np.exp(-(1 - V @ axes.T) / width)).sum(1)
    n = n / max(np.abs(n).max(), 1e-9)
    mb.add(V * (1 + roughness * n)[:, None] * np.asarray(radii) + np.asarray(centre), F)


def tree(mb: MeshBuilder, xy: np.ndarray, z: float, rng: np.random.Generator) -> float:
    """A tree standing at xy on ground height z: a trunk and a crown of 2-4 irregular blobs.
    Returns the crown radius (metres)."""
    r = rng.uniform(1.5, 3.5)
    trunk = rng.uniform(1.8, 3.2)
    mb.cylinder(xy, rng.uniform(0.12, 0.3), z, z + trunk + r * 0.6, seg=7)
    for _ in range(int(rng.integers(2, 5))):
        off = rng.normal(0, 0.35 * r, 3) * [1, 1, 0.5]
        rk = r * rng.uniform(0.55, 0.85)
        blob(mb, np.r_[xy, z + trunk + r] + off, (rk, rk, rk * rng.uniform(0.7, 1.2)), rng, 0.35)
    return r


def bush(mb: MeshBuilder, xy: np.ndarray, z: float, rng: np.random.Generator) -> None:
    """A bush at xy on ground height z: 1-3 low irregular blobs (0.4-1.3 m)."""
    for _ in range(int(rng.integers(1, 4))):
        r = rng.uniform(0.4, 1.3)
        off = np.r_[rng.normal(0, 0.5, 2), 0.0]
        blob(mb, np.r_[xy, z + 0.6 * r] + off, (r, r * rng.uniform(0.7, 1.3), 0.8 * r), rng, 0.4)


def sign(mb: MeshBuilder, xy: np.ndarray, z: float, yaw: float, rng: np.random.Generator) -> None:
    """A traffic sign at xy on ground height z: a post and a plate (0.6-1.2 m) facing along
    ``yaw`` (the plate's normal), 2.0-2.8 m up."""
    h = rng.uniform(2.0, 2.8)
    mb.cylinder(xy, 0.04, z, z + h, seg=6)
    w = rng.uniform(0.6, 1.2)
    plate_h = rng.uniform(0.5, 0.9) if rng.random() < 0.7 else w
    mb.box(xy, yaw, 0.04, w, z + h - plate_h, z + h)


def post(mb: MeshBuilder, xy: np.ndarray, z: float, rng: np.random.Generator) -> None:
    """A bollard or delineator post (0.8-1.2 m high, 0.06-0.12 m radius)."""
    mb.cylinder(xy, rng.uniform(0.06, 0.12), z, z + rng.uniform(0.8, 1.2), seg=6)


def _spots(rng: np.random.Generator, s0: float, s1: float, every_m: float) -> np.ndarray:
    """Arc lengths of a Poisson process with mean spacing ``every_m`` on [s0, s1]."""
    if every_m <= 0 or s1 <= s0:
        return np.zeros(0)
    return np.sort(rng.uniform(s0, s1, rng.poisson((s1 - s0) / every_m)))


def add_clutter(pl: Any, s0: float, s1: float, place: str, rng: np.random.Generator) -> None:
    """Add the clutter of one stretch [s0, s1] (metres of arc length) of place ``place`` with the
    placer ``pl`` (:class:`~icpbench.datasets.town._Placer`: ``route``, ``mb``, ``style``,
    ``at``, ``clear``, ``lift``, ``sweep``)."""
    st = pl.style
    road_r, road_l = st.road[place]
    if place in ("field", "highway"):  # kerbs along both road edges
        pl.sweep(s0, s1, road_r - 0.2, road_r, 0.0, 0.12)
        pl.sweep(s0, s1, road_l, road_l + 0.2, 0.0, 0.12)
    if place == "underpass":
        return
    for side, edge in ((-1.0, road_r), (1.0, road_l)):
        walk = 2.0 if place == "suburb" else 0.0
        if place != "highway":
            for s in _spots(rng, s0, s1, st.bush_every_m):
                xy, _ = pl.at(s, edge + side * (walk + rng.uniform(0.8, 6.0)))
                if pl.clear(xy, 0.0, 2.0, 2.0, 0.3):
                    bush(pl.mb, xy, pl.lift(xy, 1.0), rng)
        for s in _spots(rng, s0, s1, st.sign_every_m):
            xy, h = pl.at(s, edge + side * (walk + rng.uniform(0.6, 1.5)))
            if pl.clear(xy, 0.0, 0.3, 0.3, 0.3):
                facing = h + (np.pi if side > 0 else 0.0) + rng.normal(0, 0.15)
                sign(pl.mb, xy, pl.lift(xy, 0.1), float(facing), rng)
        for s in _spots(rng, s0, s1, st.post_every_m):
            xy, _ = pl.at(s, edge + side * (walk + rng.uniform(0.3, 0.8)))
            if pl.clear(xy, 0.0, 0.25, 0.25, 0.2):
                post(pl.mb, xy, pl.lift(xy, 0.1), rng)


#: Moving road users: (kind, probability).
MOVER_KINDS: tuple[tuple[str, float], ...] = (("car", 0.55), ("cyclist", 0.2), ("pedestrian", 0.25))


def mover(mb: MeshBuilder, kind: str, xy: np.ndarray, z: float, yaw: float,
          rng: np.random.Generator) -> None:
    """A moving road user at xy on ground height z heading ``yaw``: a car (body and cabin), a
    cyclist (bike and rider) or a pedestrian (legs, torso, head)."""
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    if kind == "car":
        length, width = rng.uniform(4.0, 5.0), rng.uniform(1.7, 1.95)
        top = rng.uniform(0.95, 1.2)
        mb.box(xy, yaw, length, width, z + 0.3, z + top)
        mb.box(xy - fwd * 0.2, yaw, length * 0.55, width - 0.15, z + top, z + rng.uniform(1.4, 1.8))
    elif kind == "cyclist":
        mb.box(xy, yaw, 1.7, 0.12, z + 0.1, z + 0.9)
        mb.cylinder(xy - fwd * 0.1, 0.2, z + 0.9, z + 1.55, seg=6)
        mb.add(*_scaled_sphere(np.r_[xy - fwd * 0.05, z + 1.7], 0.13))
    elif kind == "pedestrian":
        mb.cylinder(xy, 0.14, z, z + 0.85, seg=6)
        mb.cylinder(xy, 0.2, z + 0.85, z + 1.5, seg=6)
        mb.add(*_scaled_sphere(np.r_[xy, z + 1.62], 0.11))
    else:
        raise ValueError(f"unknown mover kind {kind!r}")


def _scaled_sphere(centre: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    V, F = unit_sphere(4)
    return V * r + centre, F
