"""A procedurally generated town along a closed route, as triangle meshes (for ``lidar-sim``).

Frames and units: the *town frame* is an east-north-up frame in metres with the road and most
of the ground at ``z = 0`` (fields roll above it, see :class:`Terrain`). The route is a closed
centre line (the lane the vehicle drives in) parameterised by arc length ``s`` in metres; ``d`` is
the signed lateral offset from it (positive to the left of the driving direction). Every object is
placed in route coordinates ``(s, d)`` and converted to the town frame, so the geometry follows
the curves of the route.

The route is a rounded polygon (corners jittered by the seed) divided into *places*, each with its
own road width and furniture:

========== =========== ==============================================================================
place      stretch     content
========== =========== ==============================================================================
suburb     dense       houses (many facing directions), fences, trees, lamps, curbs, parked cars
parking    open        a lot with rows of cars, lamp posts, planters and a store; a grass bank
field      open        farmland: grass banks along the road, hedgerows across it, poles, a barn
highway    highway     guard rail with posts, a concrete median barrier, light poles, sign gantries
underpass  underpass   a walled corridor with pilasters, crossed by two bridge decks
========== =========== ==============================================================================

Open stretches have few vertical structures, so the ground dominates the scans; their few
landmarks are planar and near the road (banks, hedgerows, car rows, a store front). Dense streets
have walls in many directions and clutter (fences, trees, cars). Parked cars are not part of the
static meshes: each pass draws its own occupancy of the parking *slots* (:meth:`Town.cars_mesh`),
so some cars move between passes.

Everything else that varies between towns (route corners, order and lengths of the stretches,
road widths, house sizes, set-backs, densities, slopes and camber, street clutter) is a
:class:`~icpbench.datasets.town_style.TownStyle`: the original town uses
:data:`~icpbench.datasets.town_style.LEGACY` (flat ground, no clutter) and is reproduced bit for
bit; ``random_style(town_seed)`` gives the others, with sloping and cambered ground
(:mod:`icpbench.datasets.ground`), irregular vegetation, signs, posts and kerbs, and moving road
users in repeat passes (:mod:`icpbench.datasets.clutter`).
Everything is deterministic given the seed (and the style).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from icpbench.core.errors import InputError
from icpbench.datasets import clutter
from icpbench.datasets.ground import Ground
from icpbench.datasets.town_style import DEFAULT_CORNERS, DEFAULT_LAYOUT, DEFAULT_ROAD, LEGACY, TownStyle

#: place -> stretch type (the ``stretch`` metadata of samples).
PLACES: dict[str, str] = {
    "suburb": "dense",
    "parking": "open",
    "field": "open",
    "highway": "highway",
    "underpass": "underpass",
}
STRETCH_TYPES: tuple[str, ...] = ("dense", "open", "highway", "underpass")

#: Road extent (d_right, d_left) of the original town (metres; per town: ``TownStyle.road``).
ROAD: dict[str, tuple[float, float]] = DEFAULT_ROAD


# ---------------------------------------------------------------------------------------------
# Route
# ---------------------------------------------------------------------------------------------
def _fillet_polygon(corners: np.ndarray, radius: float, ds: float) -> np.ndarray:
    """Densely sampled closed polyline (K, 2) of a polygon whose corners are rounded by arcs."""
    n = len(corners)
    pieces: list[np.ndarray] = []
    starts, ends, arcs = [], [], []
    for i in range(n):
        p_prev, p, p_next = corners[i - 1], corners[i], corners[(i + 1) % n]
        u1 = (p - p_prev) / np.linalg.norm(p - p_prev)
        u2 = (p_next - p) / np.linalg.norm(p_next - p)
        h1 = np.arctan2(u1[1], u1[0])
        turn = np.arctan2(u1[0] * u2[1] - u1[1] * u2[0], u1 @ u2)  # signed turning angle
        tlen = radius * np.tan(abs(turn) / 2)
        lim = 0.45 * min(np.linalg.norm(p - p_prev), np.linalg.norm(p_next - p))
        if tlen > lim:
            raise InputError(f"route corner {i} is too sharp for a fillet radius of {radius} m; "
                             "use a smaller radius or move the corners apart")
        a, b = p - u1 * tlen, p + u2 * tlen
        sgn = np.sign(turn) if turn != 0 else 1.0
        centre = a + sgn * radius * np.array([-np.sin(h1), np.cos(h1)])
        k = max(2, int(np.ceil(abs(turn) * radius / ds)) + 1)
        h = h1 + np.linspace(0.0, turn, k)
        arc = centre - sgn * radius * np.stack([-np.sin(h), np.cos(h)], 1)
        starts.append(a)
        ends.append(b)
        arcs.append(arc)
    for i in range(n):
        pieces.append(arcs[i])
        b, a_next = ends[i], starts[(i + 1) % n]
        k = max(2, int(np.ceil(np.linalg.norm(a_next - b) / ds)) + 1)
        pieces.append(b + np.linspace(0, 1, k)[1:-1, None] * (a_next - b))
    return np.vstack(pieces)


class Route:
    """A closed centre line sampled every ``ds`` metres, with places along it.

    Attributes:
        xy: (K, 2) samples in the town frame (metres); ``xy[k]`` is at arc length ``k * ds``.
        tangent: (K, 2) unit driving directions.
        length: loop length L (metres); arc lengths are taken modulo L.
        layout: ((s_start_m, place), ...) in increasing ``s``.
    """

    def __init__(self, polyline: np.ndarray, layout_fracs: tuple[tuple[float, str], ...],
                 ds: float = 0.5) -> None:
        seg = np.linalg.norm(np.diff(np.vstack([polyline, polyline[:1]]), axis=0), axis=1)
        cum = np.r_[0.0, np.cumsum(seg)]
        self.length = float(cum[-1])
        k = int(np.floor(self.length / ds))
        self.ds = self.length / k
        s = np.arange(k) * self.ds
        closed = np.vstack([polyline, polyline[:1]])
        self.xy = np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], 1)
        fwd = np.roll(self.xy, -1, 0) - np.roll(self.xy, 1, 0)
        self.tangent = fwd / np.linalg.norm(fwd, axis=1, keepdims=True)
        self._tree = cKDTree(self.xy)
        fr = [f for f, _ in layout_fracs]
        if fr[0] != 0.0 or any(b <= a for a, b in zip(fr, fr[1:], strict=False)) or fr[-1] >= 1.0:
            raise InputError("layout fractions must start at 0, increase strictly and stay below 1")
        for _, p in layout_fracs:
            if p not in PLACES:
                raise InputError(f"unknown place {p!r} in the layout; valid: {', '.join(PLACES)}")
        self.layout = tuple((f * self.length, p) for f, p in layout_fracs)
        self._starts = np.array([a for a, _ in self.layout])

    def pose(self, s: np.ndarray | float, d: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Town-frame position (..., 2) and heading (...,) in radians at arc length s and lateral d."""
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        u = s / self.ds
        i0 = np.floor(u).astype(int) % len(self.xy)
        i1 = (i0 + 1) % len(self.xy)
        w = (u - np.floor(u))[..., None]
        tan = (1 - w) * self.tangent[i0] + w * self.tangent[i1]
        tan /= np.linalg.norm(tan, axis=-1, keepdims=True)
        p0 = self.xy[i0]
        p1 = np.where((i1 == 0)[..., None], self.xy[0], self.xy[i1])
        xy = (1 - w) * p0 + w * p1
        left = np.stack([-tan[..., 1], tan[..., 0]], -1)
        return xy + np.asarray(d, dtype=np.float64)[..., None] * left, np.arctan2(tan[..., 1], tan[..., 0])

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Route coordinates (s (K,), d (K,)) of town-frame points xy (K, 2)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        _, k = self._tree.query(xy)
        rel = xy - self.xy[k]
        t = self.tangent[k]
        s = np.mod(k * self.ds + (rel * t).sum(1), self.length)
        d = rel[:, 1] * t[:, 0] - rel[:, 0] * t[:, 1]
        return s, d

    def place_at(self, s: np.ndarray | float) -> np.ndarray:
        """Place name(s) at arc length(s) s (array of str)."""
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        idx = np.searchsorted(self._starts, s, side="right") - 1
        return np.array([p for _, p in self.layout], dtype=object)[idx]

    def intervals(self) -> list[tuple[float, float, str]]:
        """(s_start, s_end, place) of every stretch, in driving order (metres)."""
        ends = [a for a, _ in self.layout[1:]] + [self.length]
        return [(a, b, p) for (a, p), b in zip(self.layout, ends, strict=True)]


def make_route(seed: int, scale: float = 1.0, corner_jitter_m: float = 25.0,
               fillet_radius_m: float = 40.0,
               corners: tuple[tuple[float, float], ...] = DEFAULT_CORNERS,
               layout: tuple[tuple[float, str], ...] = DEFAULT_LAYOUT) -> Route:
    """The closed route: ``corners`` scaled by ``scale``, each jittered by up to ``corner_jitter_m``
    (times ``scale``) with the seed, corners rounded with ``fillet_radius_m`` (times ``min(scale, 1)``)."""
    if not scale > 0:
        raise InputError(f"route scale must be positive, got {scale}")
    rng = np.random.default_rng([seed, 11])
    c = np.asarray(corners, dtype=np.float64) * scale
    c = c + rng.uniform(-1, 1, c.shape) * corner_jitter_m * scale
    poly = _fillet_polygon(c, fillet_radius_m * min(scale, 1.0), ds=0.25)
    return Route(poly, layout)


# ---------------------------------------------------------------------------------------------
# Mesh building
# ---------------------------------------------------------------------------------------------
_BOX_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


_SPHERE = clutter.unit_sphere(4)


@dataclass
class MeshBuilder:
    """Accumulates triangle meshes; :meth:`arrays` gives (vertices (V, 3) float32, triangles (F, 3)
    uint32) in the town frame. Triangle winding is arbitrary (the lidar model faces every hit normal
    towards the sensor)."""

    V: list[np.ndarray] = field(default_factory=list)
    F: list[np.ndarray] = field(default_factory=list)
    n: int = 0

    def add(self, V: np.ndarray, F: np.ndarray) -> None:
        self.V.append(np.asarray(V, dtype=np.float64))
        self.F.append(np.asarray(F, dtype=np.int64) + self.n)
        self.n += len(V)

    def box(self, xy: np.ndarray, yaw: float, length: float, width: float, z0: float,
            z1: float) -> None:
        """Box centred at xy, ``length`` along the heading ``yaw`` (radians), from z0 to z1."""
        c, s = np.cos(yaw), np.sin(yaw)
        lx, ly = length / 2, width / 2
        corners = np.array([[-lx, -ly], [lx, -ly], [lx, ly], [-lx, ly]])
        rot = corners @ np.array([[c, s], [-s, c]]) + np.asarray(xy)
        V = np.vstack([np.c_[rot, np.full(4, z0)], np.c_[rot, np.full(4, z1)]])
        self.add(V, _BOX_F)

    def cylinder(self, xy: np.ndarray, radius: float, z0: float, z1: float, seg: int = 8) -> None:
        """Vertical cylinder (with caps) of ``radius`` at xy."""
        a = np.linspace(0, 2 * np.pi, seg, endpoint=False)
        ring = np.c_[np.cos(a), np.sin(a)] * radius + np.asarray(xy)
        V = np.vstack([np.c_[ring, np.full(seg, z0)], np.c_[ring, np.full(seg, z1)],
                       [[xy[0], xy[1], z0], [xy[0], xy[1], z1]]])
        F = []
        for j in range(seg):
            k = (j + 1) % seg
            F += [[j, k, seg + k], [j, seg + k, seg + j], [2 * seg, k, j],
                  [2 * seg + 1, seg + j, seg + k]]
        self.add(V, np.array(F))

    def ellipsoid(self, centre: np.ndarray, radii: tuple[float, float, float]) -> None:
        V, F = _SPHERE
        self.add(V * np.asarray(radii) + np.asarray(centre), F)

    def gable_roof(self, xy: np.ndarray, yaw: float, length: float, width: float, z0: float,
                   height: float) -> None:
        """Triangular prism roof over a box footprint; the ridge runs along ``length``."""
        c, s = np.cos(yaw), np.sin(yaw)
        lx, ly = length / 2, width / 2
        local = np.array([[-lx, -ly, z0], [lx, -ly, z0], [lx, ly, z0], [-lx, ly, z0],
                          [-lx, 0, z0 + height], [lx, 0, z0 + height]])
        R = np.array([[c, -s], [s, c]])
        V = np.c_[local[:, :2] @ R.T + np.asarray(xy), local[:, 2]]
        F = np.array([[0, 1, 5], [0, 5, 4], [3, 2, 5], [3, 5, 4], [0, 3, 4], [1, 2, 5]])
        self.add(V, F)

    def sweep(self, route: Route, s0: float, s1: float, d0: float, d1: float, z0: float,
              z1: float, step: float = 2.0, ground: Ground | None = None) -> None:
        """A closed tube of rectangular section [d0, d1] x [z0, z1] following the route from s0 to
        s1 (curbs, walls, guard rails, bridge decks); z is above ``ground`` when given (a non-flat
        ground), else absolute."""
        k = max(2, int(np.ceil((s1 - s0) / step)) + 1)
        s = np.linspace(s0, s1, k)
        sec = [(d0, z0), (d1, z0), (d1, z1), (d0, z1)]
        V = np.zeros((k, 4, 3))
        lift = None
        if ground is not None and not ground.flat:  # one height per cross-section: no twist
            lift = ground.height(route.pose(s, 0.5 * (d0 + d1))[0])
        for j, (d, z) in enumerate(sec):
            xy, _ = route.pose(s, d)
            V[:, j, :2] = xy
            V[:, j, 2] = z if lift is None else z + lift
        F = []
        for i in range(k - 1):
            for j in range(4):
                a, b = i * 4 + j, i * 4 + (j + 1) % 4
                F += [[a, b, b + 4], [a, b + 4, a + 4]]
        last = (k - 1) * 4
        F += [[0, 1, 2], [0, 2, 3], [last, last + 2, last + 1], [last, last + 3, last + 2]]
        self.add(V.reshape(-1, 3), np.array(F))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.V:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
        return (np.vstack(self.V).astype(np.float32), np.vstack(self.F).astype(np.uint32))


# ---------------------------------------------------------------------------------------------
# Terrain
# ---------------------------------------------------------------------------------------------
def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


@dataclass(frozen=True)
class HillPatch:
    """Rolling ground beside one side of a stretch of road (fields).

    Route coordinates: ``e = side * d - edge`` is the distance from the road edge (metres). The
    height (metres, >= 0, so it lies on or above the flat ground at z = 0) is a bank rising to
    ``bank_m`` between 2 and 5 m from the edge, plus hills of amplitude ``amp_m`` (wavelengths
    ``wave_s_m`` along and ``wave_e_m`` across the road), faded in over the first 30 m of the
    stretch and out over the last 30 m, and back to 0 over the 15 m before ``width_m``.
    """

    s0: float
    s1: float
    side: float
    edge: float
    bank_m: float
    amp_m: float
    wave_s_m: float
    wave_e_m: float
    phase_s: float
    phase_e: float
    width_m: float = 70.0

    def height(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        e = self.side * d - self.edge
        inside = (s >= self.s0) & (s <= self.s1) & (e > 0)
        bank = self.bank_m * _smoothstep((e - 2.0) / 3.0)
        wave = 0.5 + 0.25 * np.sin(2 * np.pi * s / self.wave_s_m + self.phase_s) \
            + 0.25 * np.sin(2 * np.pi * e / self.wave_e_m + self.phase_e)
        hills = self.amp_m * _smoothstep((e - 5.0) / 10.0) * wave
        taper = _smoothstep(np.minimum(s - self.s0, self.s1 - s) / 30.0)
        taper = taper * _smoothstep((self.width_m - e) / 15.0)  # back to z = 0 far from the road
        return np.where(inside, taper * (bank + hills), 0.0)


@dataclass
class Terrain:
    """Ground height (metres) over the town: the :class:`~icpbench.datasets.ground.Ground`
    (slopes, camber; z = 0 in the original town) plus the :class:`HillPatch` es."""

    route: Route
    patches: list[HillPatch] = field(default_factory=list)
    ground: Ground | None = None

    @property
    def flat(self) -> bool:
        """True when the height is 0 everywhere."""
        return not self.patches and (self.ground is None or self.ground.flat)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (K,) at town-frame points xy (K, 2)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        base = self.ground.height(xy) if self.ground is not None and not self.ground.flat else None
        if not self.patches:
            return np.zeros(len(xy)) if base is None else base
        s, d = self.route.project(xy)
        hills = np.max([p.height(s, d) for p in self.patches], axis=0)
        return hills if base is None else base + hills

    def mesh(self, patch: HillPatch, mb: MeshBuilder, step: float = 2.0) -> None:
        """Add a height-field mesh of one patch to ``mb``: a regular town-frame grid over the
        patch (a grid in route coordinates would fold over on the inside of curves); only cells
        above the flat ground are kept."""
        s = np.arange(patch.s0, patch.s1 + 5.0, 5.0)
        outline = np.vstack([self.route.pose(s, patch.side * (patch.edge + e))[0]
                             for e in (0.0, patch.width_m)])
        lo, hi = outline.min(0) - step, outline.max(0) + step
        xs, ys = np.arange(lo[0], hi[0] + step, step), np.arange(lo[1], hi[1] + step, step)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        xy = np.c_[X.ravel(), Y.ravel()]
        ss, dd = self.route.project(xy)
        z = patch.height(ss, dd)
        keep_z = z > 1e-3
        if self.ground is not None and not self.ground.flat:
            z = z + self.ground.height(xy)
        nx, ny = X.shape
        i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
        a = (i * ny + j).ravel()
        b, c, d = a + ny, a + ny + 1, a + 1
        F = np.vstack([np.c_[a, b, c], np.c_[a, c, d]])
        F = F[keep_z[F].any(1)]
        if len(F):
            used, F = np.unique(F, return_inverse=True)
            mb.add(np.c_[xy[used], z[used]], F.reshape(-1, 3))


# ---------------------------------------------------------------------------------------------
# Town
# ---------------------------------------------------------------------------------------------
@dataclass
class Town:
    """Static town meshes, parking slots and the route.

    Attributes:
        route: the closed route.
        vertices, triangles: static meshes (ground, buildings, vegetation, furniture); float32
            (V, 3) town frame metres and uint32 (F, 3).
        car_slots: (K, 4) float64 rows ``[x, y, yaw, p_occupied]`` of parking spaces.
        base_cars: (K, 6) float64 rows ``[occupied, along_m, length, width, body_top, roof]``: the
            "usual" parked car of each slot (see :meth:`cars_mesh`).
        bounds: (xmin, ymin, xmax, ymax) of the ground square (metres).
        terrain: ground height (slopes, camber, rolling fields); objects stand on it.
        style: the town's :class:`~icpbench.datasets.town_style.TownStyle`.
    """

    route: Route
    vertices: np.ndarray
    triangles: np.ndarray
    car_slots: np.ndarray
    base_cars: np.ndarray
    bounds: tuple[float, float, float, float]
    terrain: Terrain
    style: TownStyle = LEGACY

    def cars_mesh(self, rng: np.random.Generator, change: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
        """Meshes of the parked cars of one pass: each slot keeps its usual state (car or empty)
        with probability ``1 - change``; otherwise it is re-drawn (occupied with the slot's
        probability, a new car of random size and placement). Returns (vertices, triangles)."""
        k = len(self.car_slots)
        cars = self.base_cars.copy()
        redraw = rng.random(k) < change
        fresh = _random_cars(rng, self.car_slots[:, 3])
        cars[redraw] = fresh[redraw]
        mb = MeshBuilder()
        yaw = self.car_slots[:, 2]
        xy = self.car_slots[:, :2] + np.c_[np.cos(yaw), np.sin(yaw)] * cars[:, 1:2]
        z = (np.zeros(k) if self.style.legacy or not k  # the original town: on z = 0
             else self.terrain.height(xy))
        for j in np.flatnonzero(cars[:, 0]):
            _, _, length, width, top, roof = cars[j]
            car_mesh(mb, xy[j], float(yaw[j]), length, width, top, roof, float(z[j]))
        return mb.arrays()

    def truck_mesh(self, s: float, d: float = 3.5) -> tuple[np.ndarray, np.ndarray]:
        """A 12 m truck (trailer and cab) centred at route coordinates (s, d), driving along it."""
        mb = MeshBuilder()
        xy, yaw = self.route.pose(s, d)
        fwd = np.array([np.cos(yaw), np.sin(yaw)])
        mb.box(xy - fwd * 1.5, float(yaw), 9.5, 2.55, 0.9, 4.0)
        mb.box(xy + fwd * 4.7, float(yaw), 2.4, 2.45, 0.5, 3.1)
        for off in (-5.0, -3.5, 4.5):  # wheels as low boxes
            mb.box(xy + fwd * off, float(yaw), 1.0, 2.5, 0.0, 0.95)
        V, F = mb.arrays()
        if not self.style.legacy:  # on the ground under its centre
            V[:, 2] += np.float32(self.terrain.height(xy[None])[0])
        return V, F

    def movers_mesh(self, rng: np.random.Generator, s: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``n`` moving road users around arc length ``s`` (metres), 6-45 m ahead or behind:
        cars in either lane, cyclists near the kerb or the oncoming lane, pedestrians beside the
        road (see :func:`~icpbench.datasets.clutter.mover`). Returns (vertices, triangles)."""
        mb = MeshBuilder()
        kinds, p = zip(*clutter.MOVER_KINDS, strict=True)
        for _ in range(int(n)):
            kind = str(rng.choice(kinds, p=p))
            ds = rng.choice([-1.0, 1.0]) * rng.uniform(6.0, 45.0)
            place = str(self.route.place_at(s + ds))
            road_r, road_l = self.style.road[place]
            oncoming = bool(rng.random() < 0.5)
            if kind == "car":
                if not oncoming and abs(ds) < 8.0:
                    ds = float(np.sign(ds) * 8.0)
                d = 3.5 if oncoming else 0.0
            elif kind == "cyclist":
                d = 3.5 + 1.0 if oncoming else max(road_r + 0.8, -2.2)
            else:
                d = road_r - 1.0 if rng.random() < 0.5 else road_l + 1.0
            xy, h = self.route.pose(s + ds, d)
            yaw = float(h) + (np.pi if oncoming else 0.0) + rng.normal(0, 0.05)
            z = float(self.terrain.height(xy[None])[0])
            clutter.mover(mb, kind, xy, z, yaw, rng)
        return mb.arrays()


def _random_cars(rng: np.random.Generator, p_occupied: np.ndarray) -> np.ndarray:
    """(K, 6) random parked cars ``[occupied, along_m, length, width, body_top, roof]``."""
    k = len(p_occupied)
    return np.stack([rng.random(k) < p_occupied, rng.uniform(-0.4, 0.4, k), rng.uniform(4.2, 5.0, k),
                     rng.uniform(1.75, 1.95, k), rng.uniform(0.95, 1.15, k), rng.uniform(1.4, 1.8, k)],
                    1).astype(np.float64)


def car_mesh(mb: MeshBuilder, xy: np.ndarray, yaw: float, length: float, width: float,
             body_top: float, roof: float, z: float = 0.0) -> None:
    """A parked car (sedan/SUV proportions) on ground height ``z``: a body box from 0.3 m to
    ``body_top`` and a cabin box up to ``roof`` (metres above the ground)."""
    mb.box(xy, yaw, length, width, z + 0.3, z + body_top)
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    mb.box(xy - fwd * 0.2, yaw, length * 0.55, width - 0.15, z + body_top, z + roof)


class _Placer:
    """Places objects in route coordinates, rejecting those whose footprint reaches a road."""

    def __init__(self, route: Route, mb: MeshBuilder, rng: np.random.Generator,
                 style: TownStyle = LEGACY, ground: Ground | None = None) -> None:
        self.route, self.mb, self.rng, self.style = route, mb, rng, style
        bounds = [style.road[p] for _, p in route.layout]
        self._road = np.array(bounds)
        self.terrain = Terrain(route, ground=ground)

    def sweep(self, s0: float, s1: float, d0: float, d1: float, z0: float, z1: float,
              step: float = 2.0) -> None:
        """:meth:`MeshBuilder.sweep` along the route, standing on the ground."""
        self.mb.sweep(self.route, s0, s1, d0, d1, z0, z1, step, ground=self.terrain.ground)

    def lift(self, xy: np.ndarray, radius: float = 0.0) -> float:
        """Lowest ground height under a footprint of ``radius`` around xy (objects stand on it)."""
        if self.terrain.flat:
            return 0.0
        ring = np.asarray(xy) + radius * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
        return float(self.terrain.height(ring).min())

    def clear(self, xy: np.ndarray, yaw: float, length: float, width: float,
              margin: float = 0.8) -> bool:
        """True if the footprint (corners and centre) stays off every road (plus ``margin``)."""
        c, s = np.cos(yaw), np.sin(yaw)
        pts = np.array([[0, 0], [-1, -1], [1, -1], [1, 1], [-1, 1],
                        [0, -1], [0, 1], [-1, 0], [1, 0]]) * [length / 2, width / 2]
        pts = pts @ np.array([[c, s], [-s, c]]) + xy
        ss, dd = self.route.project(pts)
        idx = np.searchsorted(self.route._starts, ss, side="right") - 1
        lo, hi = self._road[idx, 0] - margin, self._road[idx, 1] + margin
        return bool(np.all((dd < lo) | (dd > hi)))

    def at(self, s: float, d: float) -> tuple[np.ndarray, float]:
        xy, h = self.route.pose(s, d)
        return xy, float(h)

    def box(self, s: float, d: float, dyaw: float, length: float, width: float, z0: float,
            z1: float, margin: float = 0.8) -> bool:
        xy, h = self.at(s, d)
        if not self.clear(xy, h + dyaw, length, width, margin):
            return False
        z = self.lift(xy, 0.5 * max(length, width))
        self.mb.box(xy, h + dyaw, length, width, z0 + z, z1 + z)
        return True

    def house(self, s: float, d: float, dyaw: float, length: float, width: float,
              wall_h: float, roof_h: float) -> bool:
        xy, h = self.at(s, d)
        if not self.clear(xy, h + dyaw, length, width, 1.5):
            return False
        z = self.lift(xy, 0.5 * max(length, width))
        self.mb.box(xy, h + dyaw, length, width, z, z + wall_h)
        if roof_h > 0:
            self.mb.gable_roof(xy, h + dyaw, length + 0.6, width + 0.6, z + wall_h, roof_h)
        return True

    def tree(self, s: float, d: float) -> bool:
        xy, _ = self.at(s, d)
        if self.style.clutter:  # an irregular crown
            if not self.clear(xy, 0.0, 3.0, 3.0, 0.3):
                return False
            clutter.tree(self.mb, xy, self.lift(xy, 0.3), self.rng)
            return True
        r = self.rng.uniform(1.5, 3.2)
        if not self.clear(xy, 0.0, 2 * r * 0.6, 2 * r * 0.6, 0.3):
            return False
        trunk = self.rng.uniform(1.8, 3.0)
        z = self.lift(xy, 0.3)
        self.mb.cylinder(xy, self.rng.uniform(0.12, 0.3), z, z + trunk + r * 0.5, seg=6)
        self.mb.ellipsoid(np.r_[xy, z + trunk + r], (r, r, r * self.rng.uniform(0.8, 1.3)))
        return True

    def pole(self, s: float, d: float, height: float, radius: float = 0.13,
             arm: bool = False) -> bool:
        xy, h = self.at(s, d)
        if not self.clear(xy, 0.0, 2 * radius, 2 * radius, 0.3):
            return False
        z = self.lift(xy, radius)
        top = height if self.style.legacy else z + height  # the original town: absolute tops
        self.mb.cylinder(xy, radius, z, top, seg=6)
        if arm:  # a lamp arm reaching over the road
            side = 1.0 if self.route.project(xy[None])[1][0] < 0 else -1.0
            left = np.array([-np.sin(h), np.cos(h)])
            self.mb.box(xy + side * left * 1.2, h + np.pi / 2, 2.4, 0.25, top - 0.3, top)
        return True


def _suburb(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    rng, st = pl.rng, pl.style
    road_r, road_l = st.road["suburb"]
    route = pl.route
    for side in (-1.0, 1.0):
        edge = road_r if side < 0 else road_l
        walk = (edge - 2.0, edge) if side < 0 else (edge, edge + 2.0)
        pl.sweep(s0, s1, walk[0], walk[1], 0.0, 0.15)  # sidewalk + curb
        lot_edge = abs(edge) + 2.0
        crossings = np.arange(s0 + rng.uniform(60, 120), s1 - 20, rng.uniform(100, 150))
        s = s0 + rng.uniform(0, 8)
        while s < s1 - 8:
            lot = rng.uniform(*st.lot_m)
            sc = s + lot / 2
            if any(abs(sc - c) < 10 for c in crossings):  # side street: leave a gap
                s += lot
                continue
            length, width = rng.uniform(*st.house_len_m), rng.uniform(*st.house_wid_m)
            setback = rng.uniform(*st.setback_m)
            dyaw = rng.normal(0, np.deg2rad(6))
            if rng.random() < 0.2:
                dyaw += rng.choice([-1, 1]) * np.deg2rad(rng.uniform(20, 45))
            roof = rng.uniform(1.5, 3.0) if rng.random() < 0.7 else 0.0
            pl.house(sc, side * (lot_edge + setback + width / 2), dyaw, min(length, lot - 2), width,
                     rng.uniform(*st.house_h_m), roof)
            if rng.random() < 0.3:  # a shed or garage at an arbitrary angle behind the house
                pl.box(sc + rng.uniform(-4, 4), side * (lot_edge + setback + width + rng.uniform(3, 7)),
                       rng.uniform(0, np.pi), rng.uniform(3, 6), rng.uniform(3, 5), 0.0,
                       rng.uniform(2.2, 3.2))
            if rng.random() < st.fence_front_p:  # front fence with a driveway gap
                gap = rng.uniform(3, 4)
                fl = lot - gap - 0.5
                if fl > 2:
                    pl.box(s + fl / 2, side * (lot_edge + 0.2), 0.0, fl, 0.1, 0.0, rng.uniform(1.0, 1.8),
                           margin=0.2)
            if rng.random() < st.fence_side_p:  # fence between lots, perpendicular to the street
                depth = rng.uniform(8, 18)
                pl.box(s, side * (lot_edge + 0.5 + depth / 2), np.pi / 2, depth, 0.1, 0.0,
                       rng.uniform(1.2, 2.0), margin=0.2)
            for _ in range(rng.integers(0, st.trees_per_lot)):
                pl.tree(s + rng.uniform(0, lot), side * (lot_edge + rng.uniform(1.0, max(setback, 1.5))))
            s += lot
        for sl in np.arange(s0 + rng.uniform(0, 30), s1, st.lamp_spacing_m):  # street lamps
            pl.pole(sl, side * (lot_edge - 0.6), 7.0, 0.12, arm=True)
        slot_d = edge + 1.1 if side < 0 else edge - 1.1
        for sc in np.arange(s0 + 4, s1 - 4, 6.5):  # kerbside parking
            if any(abs(sc - c) < 10 for c in crossings):
                continue
            xy, h = route.pose(sc, slot_d)
            slots.append([xy[0], xy[1], h, st.kerb_occupancy])


def _parking(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    rng = pl.rng
    road_r, road_l = pl.style.road["parking"]
    route = pl.route
    pl.sweep(s0, s1, road_r - 0.3, road_r, 0.0, 0.15)
    pl.sweep(s0, s1, road_l, road_l + 0.3, 0.0, 0.15)
    lot0, lot1 = s0 + 15, s1 - 15
    islands = [lot0 + rng.uniform(10, 30)]  # planted islands break the double row irregularly
    while islands[-1] < lot1 - 30:
        islands.append(islands[-1] + rng.uniform(30, 60))
    for si in islands:
        pl.box(si, road_r - 12.75, 0.0, 2.4, 12.0, 0.0, 0.15, margin=0.3)  # kerb
        pl.box(si, road_r - 12.75, 0.0, 1.6, 10.0, 0.0, rng.uniform(0.6, 1.0), margin=0.3)  # planter
    for row_d in (10.0, 15.5):  # a double row of perpendicular parking spaces on the right
        sc = lot0
        while sc < lot1:  # spaces of uneven width, so a shifted row never matches itself
            if min(abs(sc - si) for si in islands) >= 2.6:
                xy, h = route.pose(sc, road_r - row_d)
                slots.append([xy[0], xy[1], h + np.pi / 2, pl.style.lot_occupancy])
            sc += rng.uniform(2.5, 3.2)
    for dd in (12.75, 22.0):  # tall lamp posts between and behind the rows, irregularly spaced
        sl = lot0 + rng.uniform(0, 15)
        while sl < lot1:
            pl.pole(sl, road_r - dd, 9.0, 0.16)
            sl += rng.uniform(18, 35)
    bank = HillPatch(s0, s1, 1.0, road_l, bank_m=rng.uniform(1.5, 2.5), amp_m=0.0, wave_s_m=50.0,
                     wave_e_m=30.0, phase_s=0.0, phase_e=0.0)
    pl.terrain.patches.append(bank)  # a grass bank across the road from the lot
    pl.terrain.mesh(bank, pl.mb)
    mid = 0.5 * (s0 + s1)
    store_len = min(0.6 * (s1 - s0), 90.0)
    pl.box(mid, road_r - 32.0 - 10, rng.normal(0, 0.02), store_len, 20.0, 0.0, 7.0)
    for _ in range(rng.integers(2, 5)):  # a few trees on the grass across the road
        pl.tree(rng.uniform(s0, s1), road_l + rng.uniform(4, 25))


def _hedge(pl: _Placer, s: float, d: float, length: float, along: bool, height: float) -> None:
    """A 1 m thick hedge made of 5 m blocks that follow the ground: ``along`` the road from arc
    length s, or across it from lateral offset d outwards (sign of d)."""
    n = max(1, int(round(length / 5.0)))
    seg = length / n
    for k in range(n):
        if along:
            pl.box(s + (k + 0.5) * seg, d, 0.0, seg + 0.05, 1.0, 0.0, height, margin=0.3)
        else:
            pl.box(s, d + np.sign(d) * (k + 0.5) * seg, np.pi / 2, seg + 0.05, 1.0, 0.0, height,
                   margin=0.3)


def _field(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    """Farmland: the road runs between grass banks (1.5-2.5 m) with flat fields beyond, split by
    hedgerows running away from the road every 25-45 m; a few utility poles and trees, now and
    then a barn. Vertical structure is sparse; the ground (banks included) dominates."""
    rng = pl.rng
    road_r, road_l = pl.style.road["field"]
    for side, edge in ((-1.0, -road_r), (1.0, road_l)):
        patch = HillPatch(s0, s1, side, edge, bank_m=rng.uniform(1.5, 2.5), amp_m=0.0,
                          wave_s_m=50.0, wave_e_m=30.0, phase_s=0.0, phase_e=0.0)
        pl.terrain.patches.append(patch)
        pl.terrain.mesh(patch, pl.mb)
    for side, edge in ((-1.0, road_r), (1.0, road_l)):
        s = s0 + rng.uniform(5, 40)
        while s < s1 - 5:  # hedgerows (field boundaries) starting 6 m from the road edge
            _hedge(pl, s, edge + side * 6.0, rng.uniform(25, 45), False, rng.uniform(1.5, 2.5))
            s += rng.uniform(25, 45)
    for sc in np.arange(s0 + rng.uniform(0, 60), s1, 60.0):  # utility poles on the left
        pl.pole(sc, road_l + 3.0, 9.0, 0.14)
    for _ in range(rng.poisson((s1 - s0) / pl.style.field_tree_every_m)):
        side = rng.choice([-1.0, 1.0])
        pl.tree(rng.uniform(s0, s1), side * rng.uniform(12, 40) + (road_l if side > 0 else road_r))
    for sc in np.arange(s0 + rng.uniform(40, 150), s1 - 30, 250.0):  # a barn or farmhouse
        side = rng.choice([-1.0, 1.0])
        dist = rng.uniform(25, 45)
        length, width = rng.uniform(15, 30), rng.uniform(10, 16)
        pl.house(sc, side * (dist + width / 2) + (road_l if side > 0 else road_r),
                 rng.uniform(0, np.pi), length, width, rng.uniform(5, 8), rng.uniform(2, 4))


def _highway(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    rng = pl.rng
    road_r, road_l = pl.style.road["highway"]
    rail_d = road_r - 1.2
    pl.sweep(s0, s1, rail_d - 0.1, rail_d, 0.5, 0.82)  # W-beam guard rail
    for sc in np.arange(s0 + 1, s1, 4.0):  # its posts
        pl.box(sc, rail_d - 0.3, 0.0, 0.15, 0.15, 0.0, 0.82, margin=0.1)
    pl.sweep(s0, s1, road_l + 0.6, road_l + 1.2, 0.0, 0.85)  # concrete median barrier
    for sc in np.arange(s0 + rng.uniform(0, 60), s1, 60.0):
        pl.pole(sc, road_l + 0.9, 11.0, 0.16, arm=True)
    for sc in np.arange(s0 + rng.uniform(80, 200), s1 - 20, 350.0):  # sign gantries
        for dd in (rail_d - 1.5, road_l + 2.0):
            pl.box(sc, dd, 0.0, 0.5, 0.5, 0.0, 7.5, margin=0.1)
        pl.sweep(sc - 0.4, sc + 0.4, rail_d - 1.5, road_l + 2.0, 6.5, 7.5, step=0.8)
        pl.sweep(sc - 0.15, sc + 0.15, road_r + 1.0, road_r + 6.0, 5.2, 6.5, step=0.3)
    for _ in range(rng.poisson((s1 - s0) / pl.style.highway_tree_every_m)):  # a few far trees
        side = rng.choice([-1.0, 1.0])
        pl.tree(rng.uniform(s0, s1), side * rng.uniform(15, 45) + (road_l if side > 0 else road_r))


def _underpass(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    road_r, road_l = pl.style.road["underpass"]
    wr, wl = road_r - 1.0, road_l + 1.0
    pl.sweep(s0, s1, wr - 0.6, wr, 0.0, 7.0)
    pl.sweep(s0, s1, wl, wl + 0.6, 0.0, 7.0)
    for sc in np.arange(s0 + 6, s1 - 3, 12.0):  # pilasters
        pl.sweep(sc - 0.5, sc + 0.5, wr, wr + 0.5, 0.0, 7.0, step=1.0)
        pl.sweep(sc - 0.5, sc + 0.5, wl - 0.5, wl, 0.0, 7.0, step=1.0)
    span = s1 - s0
    for frac in (0.3, 0.7):  # two bridge decks crossing above
        c = s0 + frac * span
        half = min(12.0, 0.12 * span)
        pl.sweep(c - half, c + half, wr - 0.6, wl + 0.6, 6.0, 7.2, step=2.0)


_BUILDERS = {"suburb": _suburb, "parking": _parking, "field": _field, "highway": _highway,
             "underpass": _underpass}


#: Ground cells farther than this from the route are left out of a non-flat ground (metres; beyond
#: every sensor's range from the road).
GROUND_BAND_M = 140.0


def make_ground(route: Route, style: TownStyle = LEGACY) -> Ground:
    """The ground shape (slopes, camber) of a town of this style on this route."""
    return Ground(route, tuple(style.grade_waves), float(style.camber))


def make_town(seed: int, route: Route | None = None, style: TownStyle = LEGACY, **route_kw) -> Town:
    """Generate the town for ``seed`` (deterministic) in ``style`` (default: the original town).
    ``route_kw`` go to :func:`make_route` (the style's corners and layout are used unless given)."""
    if route is None:
        route_kw = {"corners": style.corners, "layout": style.layout, **route_kw}
        route = make_route(seed, **route_kw)
    rng = np.random.default_rng([seed, 23])
    mb = MeshBuilder()
    lo, hi = route.xy.min(0) - 250.0, route.xy.max(0) + 250.0
    ground = make_ground(route, style)
    if ground.flat:
        mb.add(np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]]),
               np.array([[0, 1, 2], [0, 2, 3]]))
    else:
        ground.mesh(mb, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])), GROUND_BAND_M)
    pl = _Placer(route, mb, rng, style, ground)
    slots: list[list[float]] = []
    for s0, s1, place in route.intervals():
        _BUILDERS[place](pl, s0, s1, slots)
    if style.clutter:  # its own random stream: the builders' draws do not depend on it
        crng = np.random.default_rng([seed, 31])
        for s0, s1, place in route.intervals():
            clutter.add_clutter(pl, s0, s1, place, crng)
    V, F = mb.arrays()
    car_slots = np.asarray(slots, dtype=np.float64).reshape(-1, 4)
    return Town(route=route, vertices=V, triangles=F, car_slots=car_slots,
                base_cars=_random_cars(rng, car_slots[:, 3]), terrain=pl.terrain,
                bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])), style=style)
