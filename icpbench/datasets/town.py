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
Everything is deterministic given the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from icpbench.errors import InputError

#: place -> stretch type (the ``stretch`` metadata of samples).
PLACES: dict[str, str] = {
    "suburb": "dense",
    "parking": "open",
    "field": "open",
    "highway": "highway",
    "underpass": "underpass",
}
STRETCH_TYPES: tuple[str, ...] = ("dense", "open", "highway", "underpass")

#: Road extent (d_right, d_left) in metres around the driven lane centre, per place. The lane to the
#: left (d = +3.5 m) is the oncoming / overtaking lane where the passing truck drives.
ROAD: dict[str, tuple[float, float]] = {
    "suburb": (-4.5, 8.0),
    "parking": (-4.5, 8.0),
    "field": (-2.5, 5.5),
    "highway": (-3.5, 12.0),
    "underpass": (-3.5, 8.0),
}

#: Range of the distance from the sidewalk to the house fronts in suburbs (metres).
SUBURB_SETBACK_M: tuple[float, float] = (3.0, 9.0)

#: Default route: corners of a hexagon-like loop (metres, about 2.8 km once the corners are rounded).
DEFAULT_CORNERS: tuple[tuple[float, float], ...] = (
    (0.0, 0.0), (600.0, 0.0), (900.0, 250.0), (900.0, 650.0), (350.0, 700.0), (0.0, 450.0),
)
#: Default layout: (start as a fraction of the route length, place), in driving order.
DEFAULT_LAYOUT: tuple[tuple[float, str], ...] = (
    (0.00, "suburb"), (0.22, "parking"), (0.30, "suburb"), (0.40, "field"), (0.52, "highway"),
    (0.70, "underpass"), (0.76, "highway"), (0.84, "field"), (0.93, "suburb"),
)


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


def _unit_sphere(res: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 1: vertices (V, 3), triangles (F, 3)."""
    lat = np.linspace(0, np.pi, res + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, 2 * res, endpoint=False)
    La, Lo = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(La) * np.cos(Lo), np.sin(La) * np.sin(Lo), np.cos(La)], -1).reshape(-1, 3)
    V = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    m = 2 * res
    F = []
    for j in range(m):  # caps
        F.append([0, 1 + j, 1 + (j + 1) % m])
        base = 1 + (res - 2) * m
        F.append([len(V) - 1, base + (j + 1) % m, base + j])
    for r in range(res - 2):
        for j in range(m):
            a, b = 1 + r * m + j, 1 + r * m + (j + 1) % m
            c, d = a + m, b + m
            F += [[a, c, b], [b, c, d]]
    return V, np.array(F)


_SPHERE = _unit_sphere(4)


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
              z1: float, step: float = 2.0) -> None:
        """A closed tube of rectangular section [d0, d1] x [z0, z1] following the route from s0 to
        s1 (curbs, walls, guard rails, bridge decks)."""
        k = max(2, int(np.ceil((s1 - s0) / step)) + 1)
        s = np.linspace(s0, s1, k)
        sec = [(d0, z0), (d1, z0), (d1, z1), (d0, z1)]
        V = np.zeros((k, 4, 3))
        for j, (d, z) in enumerate(sec):
            xy, _ = route.pose(s, d)
            V[:, j, :2] = xy
            V[:, j, 2] = z
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
    """Ground height (metres) over the town: 0 except on :class:`HillPatch` es."""

    route: Route
    patches: list[HillPatch] = field(default_factory=list)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (K,) at town-frame points xy (K, 2)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        if not self.patches:
            return np.zeros(len(xy))
        s, d = self.route.project(xy)
        return np.max([p.height(s, d) for p in self.patches], axis=0)

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
        nx, ny = X.shape
        i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
        a = (i * ny + j).ravel()
        b, c, d = a + ny, a + ny + 1, a + 1
        F = np.vstack([np.c_[a, b, c], np.c_[a, c, d]])
        F = F[z[F].max(1) > 1e-3]
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
        terrain: ground height (rolling fields); objects stand on it.
    """

    route: Route
    vertices: np.ndarray
    triangles: np.ndarray
    car_slots: np.ndarray
    base_cars: np.ndarray
    bounds: tuple[float, float, float, float]
    terrain: Terrain

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
        for (x, y, yaw, _), (occ, along, length, width, top, roof) in zip(self.car_slots, cars,
                                                                         strict=True):
            if occ:
                fwd = np.array([np.cos(yaw), np.sin(yaw)])
                car_mesh(mb, np.array([x, y]) + fwd * along, float(yaw), length, width, top, roof)
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
        return mb.arrays()


def _random_cars(rng: np.random.Generator, p_occupied: np.ndarray) -> np.ndarray:
    """(K, 6) random parked cars ``[occupied, along_m, length, width, body_top, roof]``."""
    k = len(p_occupied)
    return np.stack([rng.random(k) < p_occupied, rng.uniform(-0.4, 0.4, k), rng.uniform(4.2, 5.0, k),
                     rng.uniform(1.75, 1.95, k), rng.uniform(0.95, 1.15, k), rng.uniform(1.4, 1.8, k)],
                    1).astype(np.float64)


def car_mesh(mb: MeshBuilder, xy: np.ndarray, yaw: float, length: float, width: float,
             body_top: float, roof: float) -> None:
    """A parked car (sedan/SUV proportions): a body box from 0.3 m to ``body_top`` and a cabin box
    up to ``roof`` (metres)."""
    mb.box(xy, yaw, length, width, 0.3, body_top)
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    mb.box(xy - fwd * 0.2, yaw, length * 0.55, width - 0.15, body_top, roof)


class _Placer:
    """Places objects in route coordinates, rejecting those whose footprint reaches a road."""

    def __init__(self, route: Route, mb: MeshBuilder, rng: np.random.Generator) -> None:
        self.route, self.mb, self.rng = route, mb, rng
        bounds = [ROAD[p] for _, p in route.layout]
        self._road = np.array(bounds)
        self.terrain = Terrain(route)

    def lift(self, xy: np.ndarray, radius: float = 0.0) -> float:
        """Lowest ground height under a footprint of ``radius`` around xy (objects stand on it)."""
        if not self.terrain.patches:
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
        self.mb.cylinder(xy, radius, self.lift(xy, radius), height, seg=6)
        if arm:  # a lamp arm reaching over the road
            side = 1.0 if self.route.project(xy[None])[1][0] < 0 else -1.0
            left = np.array([-np.sin(h), np.cos(h)])
            self.mb.box(xy + side * left * 1.2, h + np.pi / 2, 2.4, 0.25, height - 0.3, height)
        return True


def _suburb(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    rng = pl.rng
    road_r, road_l = ROAD["suburb"]
    route = pl.route
    for side in (-1.0, 1.0):
        edge = road_r if side < 0 else road_l
        walk = (edge - 2.0, edge) if side < 0 else (edge, edge + 2.0)
        pl.mb.sweep(route, s0, s1, walk[0], walk[1], 0.0, 0.15)  # sidewalk + curb
        lot_edge = abs(edge) + 2.0
        crossings = np.arange(s0 + rng.uniform(60, 120), s1 - 20, rng.uniform(100, 150))
        s = s0 + rng.uniform(0, 8)
        while s < s1 - 8:
            lot = rng.uniform(14, 22)
            sc = s + lot / 2
            if any(abs(sc - c) < 10 for c in crossings):  # side street: leave a gap
                s += lot
                continue
            length, width = rng.uniform(8, 14), rng.uniform(8, 12)
            setback = rng.uniform(*SUBURB_SETBACK_M)
            dyaw = rng.normal(0, np.deg2rad(6))
            if rng.random() < 0.2:
                dyaw += rng.choice([-1, 1]) * np.deg2rad(rng.uniform(20, 45))
            roof = rng.uniform(1.5, 3.0) if rng.random() < 0.7 else 0.0
            pl.house(sc, side * (lot_edge + setback + width / 2), dyaw, min(length, lot - 2), width,
                     rng.uniform(3.0, 6.5), roof)
            if rng.random() < 0.3:  # a shed or garage at an arbitrary angle behind the house
                pl.box(sc + rng.uniform(-4, 4), side * (lot_edge + setback + width + rng.uniform(3, 7)),
                       rng.uniform(0, np.pi), rng.uniform(3, 6), rng.uniform(3, 5), 0.0,
                       rng.uniform(2.2, 3.2))
            if rng.random() < 0.6:  # front fence with a driveway gap
                gap = rng.uniform(3, 4)
                fl = lot - gap - 0.5
                if fl > 2:
                    pl.box(s + fl / 2, side * (lot_edge + 0.2), 0.0, fl, 0.1, 0.0, rng.uniform(1.0, 1.8),
                           margin=0.2)
            if rng.random() < 0.5:  # fence between lots, perpendicular to the street
                depth = rng.uniform(8, 18)
                pl.box(s, side * (lot_edge + 0.5 + depth / 2), np.pi / 2, depth, 0.1, 0.0,
                       rng.uniform(1.2, 2.0), margin=0.2)
            for _ in range(rng.integers(0, 3)):
                pl.tree(s + rng.uniform(0, lot), side * (lot_edge + rng.uniform(1.0, max(setback, 1.5))))
            s += lot
        for sl in np.arange(s0 + rng.uniform(0, 30), s1, 35.0):  # street lamps
            pl.pole(sl, side * (lot_edge - 0.6), 7.0, 0.12, arm=True)
        slot_d = edge + 1.1 if side < 0 else edge - 1.1
        for sc in np.arange(s0 + 4, s1 - 4, 6.5):  # kerbside parking
            if any(abs(sc - c) < 10 for c in crossings):
                continue
            xy, h = route.pose(sc, slot_d)
            slots.append([xy[0], xy[1], h, 0.35])


def _parking(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    rng = pl.rng
    road_r, road_l = ROAD["parking"]
    route = pl.route
    pl.mb.sweep(route, s0, s1, road_r - 0.3, road_r, 0.0, 0.15)
    pl.mb.sweep(route, s0, s1, road_l, road_l + 0.3, 0.0, 0.15)
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
                slots.append([xy[0], xy[1], h + np.pi / 2, 0.4])
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
    road_r, road_l = ROAD["field"]
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
    for _ in range(rng.poisson((s1 - s0) / 100.0)):
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
    road_r, road_l = ROAD["highway"]
    route = pl.route
    rail_d = road_r - 1.2
    pl.mb.sweep(route, s0, s1, rail_d - 0.1, rail_d, 0.5, 0.82)  # W-beam guard rail
    for sc in np.arange(s0 + 1, s1, 4.0):  # its posts
        pl.box(sc, rail_d - 0.3, 0.0, 0.15, 0.15, 0.0, 0.82, margin=0.1)
    pl.mb.sweep(route, s0, s1, road_l + 0.6, road_l + 1.2, 0.0, 0.85)  # concrete median barrier
    for sc in np.arange(s0 + rng.uniform(0, 60), s1, 60.0):
        pl.pole(sc, road_l + 0.9, 11.0, 0.16, arm=True)
    for sc in np.arange(s0 + rng.uniform(80, 200), s1 - 20, 350.0):  # sign gantries
        for dd in (rail_d - 1.5, road_l + 2.0):
            pl.box(sc, dd, 0.0, 0.5, 0.5, 0.0, 7.5, margin=0.1)
        pl.mb.sweep(route, sc - 0.4, sc + 0.4, rail_d - 1.5, road_l + 2.0, 6.5, 7.5, step=0.8)
        pl.mb.sweep(route, sc - 0.15, sc + 0.15, road_r + 1.0, road_r + 6.0, 5.2, 6.5, step=0.3)
    for _ in range(rng.poisson((s1 - s0) / 150.0)):  # a few far trees
        side = rng.choice([-1.0, 1.0])
        pl.tree(rng.uniform(s0, s1), side * rng.uniform(15, 45) + (road_l if side > 0 else road_r))


def _underpass(pl: _Placer, s0: float, s1: float, slots: list) -> None:
    road_r, road_l = ROAD["underpass"]
    route = pl.route
    wr, wl = road_r - 1.0, road_l + 1.0
    pl.mb.sweep(route, s0, s1, wr - 0.6, wr, 0.0, 7.0)
    pl.mb.sweep(route, s0, s1, wl, wl + 0.6, 0.0, 7.0)
    for sc in np.arange(s0 + 6, s1 - 3, 12.0):  # pilasters
        pl.mb.sweep(route, sc - 0.5, sc + 0.5, wr, wr + 0.5, 0.0, 7.0, step=1.0)
        pl.mb.sweep(route, sc - 0.5, sc + 0.5, wl - 0.5, wl, 0.0, 7.0, step=1.0)
    span = s1 - s0
    for frac in (0.3, 0.7):  # two bridge decks crossing above
        c = s0 + frac * span
        half = min(12.0, 0.12 * span)
        pl.mb.sweep(route, c - half, c + half, wr - 0.6, wl + 0.6, 6.0, 7.2, step=2.0)


_BUILDERS = {"suburb": _suburb, "parking": _parking, "field": _field, "highway": _highway,
             "underpass": _underpass}


def make_town(seed: int, route: Route | None = None, **route_kw) -> Town:
    """Generate the town for ``seed`` (deterministic). ``route_kw`` go to :func:`make_route`."""
    route = route if route is not None else make_route(seed, **route_kw)
    rng = np.random.default_rng([seed, 23])
    mb = MeshBuilder()
    lo, hi = route.xy.min(0) - 250.0, route.xy.max(0) + 250.0
    mb.add(np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]]),
           np.array([[0, 1, 2], [0, 2, 3]]))
    pl = _Placer(route, mb, rng)
    slots: list[list[float]] = []
    for s0, s1, place in route.intervals():
        _BUILDERS[place](pl, s0, s1, slots)
    V, F = mb.arrays()
    car_slots = np.asarray(slots, dtype=np.float64).reshape(-1, 4)
    return Town(route=route, vertices=V, triangles=F, car_slots=car_slots,
                base_cars=_random_cars(rng, car_slots[:, 3]), terrain=pl.terrain,
                bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
