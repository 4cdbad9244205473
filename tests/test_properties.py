"""Property tests (hypothesis) on random small clouds, degenerate ones included:

* every ICP target returns finite poses or says why not (status ``nonfinite``), and a converged
  sample always has status ``ok``;
* in strict mode no attack moves any point by more than its budget;
* input validation either accepts a cloud / budget or raises ``InputError``, nothing else.
"""

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from icpbench.attacks.base import validate_budget
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Batch, Sample, validate_cloud
from icpbench.harness.runner import build_attack, build_target
from icpbench.learning.checkpoint import save_checkpoint
from icpbench.learning.network import Generator, generator_config
from icpbench.targets.oracle import QueryOracle
from icpbench.targets.p2plane import PointToPlaneICP

torch.set_num_threads(1)

STATUSES = {"ok", "not_converged", "singular", "too_few_correspondences", "nonfinite"}
SHAPES = ("random", "planar", "collinear", "duplicated", "tiny", "far", "clustered")
FAST = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _cloud(rng: np.random.Generator, shape: str, n: int) -> np.ndarray:
    """(n, 3) float64 cloud of a given (possibly degenerate) shape, metres."""
    if shape == "random":
        return rng.normal(size=(n, 3))
    if shape == "planar":
        return np.c_[rng.uniform(-2, 2, (n, 2)), np.zeros(n)]
    if shape == "collinear":
        return np.outer(rng.uniform(-2, 2, n), rng.normal(size=3))
    if shape == "duplicated":
        base = rng.normal(size=(6, 3))
        return base[rng.integers(0, 6, n)]
    if shape == "tiny":
        return rng.normal(size=(n, 3)) * 1e-7
    if shape == "far":
        return rng.normal(size=(n, 3)) + 1e5
    centres = rng.normal(size=(2, 3)) * 3  # two tight clusters
    return centres[rng.integers(0, 2, n)] + rng.normal(size=(n, 3)) * 1e-3


def _unit(rng: np.random.Generator, m: int) -> np.ndarray:
    n = rng.normal(size=(m, 3))
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _pose(rng: np.random.Generator, scale: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * min(scale, 3.0)).as_matrix()
    T[:3, 3] = rng.normal(size=3) * scale
    return T


problems = st.fixed_dictionaries({
    "seed": st.integers(0, 2**32 - 1),
    "scan_shape": st.sampled_from(SHAPES),
    "map_shape": st.sampled_from(SHAPES),
    "n": st.integers(6, 40),
    "m": st.integers(6, 60),
    "map_from_scan": st.booleans(),     # map = moved scan + noise (a solvable problem) or unrelated
    "nan_points": st.integers(0, 3),    # NaN scan points (a target must ignore them, not spread NaN)
    "pose_scale": st.sampled_from([0.0, 0.05, 0.5, 3.0, 1e200]),
    "normals": st.sampled_from(["unit", "zero-some", "vertical"]),
})


def _problem(p: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """scan (1, n, 3), map (m, 3), normals (m, 3), T_init (1, 4, 4) from drawn parameters."""
    rng = np.random.default_rng(p["seed"])
    scan = _cloud(rng, p["scan_shape"], p["n"])
    if p["map_from_scan"]:
        T = _pose(rng, 0.1)
        idx = rng.integers(0, p["n"], p["m"])
        mp = scan[idx] @ T[:3, :3].T + T[:3, 3] + rng.normal(size=(p["m"], 3)) * 1e-3
    else:
        mp = _cloud(rng, p["map_shape"], p["m"])
    nrm = _unit(rng, p["m"])
    if p["normals"] == "zero-some":
        nrm[: p["m"] // 3] = 0.0
    elif p["normals"] == "vertical":
        nrm[:] = [0.0, 0.0, 1.0]
    if p["nan_points"]:
        scan[rng.integers(0, p["n"], p["nan_points"])] = np.nan
    return scan[None], mp, nrm, _pose(rng, p["pose_scale"])[None]


def _targets() -> dict:
    out = {"p2plane": build_target("p2plane", "lidar", {"max_iterations": 10}),
           "p2point": build_target("p2point", "lidar", {"max_iterations": 10})}
    for name in ("open3d", "kiss-icp", "small-gicp"):
        if registry.targets.available(name)[0]:
            out[name] = build_target(name, "lidar", {"max_iterations": 10})
    return out


TARGETS = _targets()


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # 1e200 m poses
@FAST
@given(p=problems)
def test_icp_never_returns_nan_without_a_flag(p):
    scan, mp, nrm, T0 = _problem(p)
    scans, T_init = torch.as_tensor(scan), torch.as_tensor(T0)
    for name, target in TARGETS.items():
        try:
            maps = [MapIndex(mp, nrm)] if target.differentiable else [target.prepare(mp, nrm)]
        except InputError:
            continue  # a map the target rejects up front (e.g. fewer than 6 distinct points)
        reg = target.register(scans, maps, T_init)
        status, T = reg.status[0], reg.T.detach()
        assert status in STATUSES, (name, status)
        if not bool(torch.isfinite(T).all()):
            assert status == "nonfinite", (name, status, p)
        if bool(reg.converged[0]):
            assert status == "ok", (name, status)
        frac = float(reg.inlier_fraction[0])
        assert 0.0 <= frac <= 1.0, (name, frac)
        if p["scan_shape"] == "collinear" and name != "small-gicp":
            # rotation about the line is unobservable: the ICP system is singular and must be
            # flagged (small_gicp's GICP regularises its covariances, so its system is not)
            assert status != "ok", (name, p)


# -- strict-mode budgets ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def attacks(tmp_path_factory):
    """Every attack, strict, with settings small enough for property testing; the generator is a
    randomly initialised network whose raw output ignores the budget (so strict mode has work)."""
    G = Generator(generator_config("objects", a=2.0, b=2.0, c=2.0, k=4, offset_scale_m=1.0))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for prm in G.parameters():
            prm.copy_(torch.randn(prm.shape, generator=gen) * 0.3)
    ckpt = save_checkpoint(G, tmp_path_factory.mktemp("gen") / "random.pt")
    params = {"pgd": {"steps": 2}, "sector": {"icp_preset": "objects"},
              "generator": {"checkpoint": str(ckpt)},
              "generator-refine": {"checkpoint": str(ckpt), "refine_steps": 1,
                                   "refine_icp_iterations": 3},
              "sector-adaptive": {"iterations": 1}, "search": {"queries": 3, "wedges": 2},
              "ensemble": {"pgd_steps": 1, "sector_iterations": 1, "queries": 2,
                           "spoof_queries": 1, "valley_queries": 1},
              "spoof": {"queries": 2}, "valley": {"queries": 1}}
    names = [n for n in registry.attacks.names() if registry.attacks.available(n)[0]]
    assert {"none", "uniform", "normal", "sector", "pgd", "generator"} <= set(names)
    return {n: build_attack(n, True, params.get(n, {})) for n in names}


SURROGATE = PointToPlaneICP("objects", max_iterations=5)

attack_problems = st.fixed_dictionaries({
    "seed": st.integers(0, 2**32 - 1),
    "shape": st.sampled_from(("random", "planar", "clustered", "far")),
    "n": st.integers(24, 48),
    "budget": st.floats(1e-3, 10.0, allow_nan=False),
    "pose_scale": st.sampled_from([0.0, 0.1]),
})


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(p=attack_problems)
def test_strict_attacks_never_exceed_their_budget(attacks, p):
    rng = np.random.default_rng(p["seed"])
    samples = []
    for b in range(2):
        scan = _cloud(rng, p["shape"], p["n"])
        mp = np.r_[scan, _cloud(rng, "random", 30)] @ _pose(rng, 0.05)[:3, :3].T
        samples.append(Sample(f"s{b}", scan, mp, _unit(rng, len(mp)), np.eye(4),
                              _pose(rng, p["pose_scale"])))
    batch = Batch.from_samples(samples)
    lam = p["budget"]
    for name, attack in attacks.items():
        oracle = QueryOracle(SURROGATE, batch, batch.maps) if attack.needs_oracle else None
        out = attack.run(batch, lam, surrogate=SURROGATE, generator=p["seed"] % 1000,
                         oracle=oracle)
        d = torch.linalg.norm(out.scans - batch.scans, dim=-1)
        assert bool(torch.isfinite(out.scans).all()), name
        assert float(d.max()) <= lam * (1 + 1e-9) + 1e-12, (name, float(d.max()), lam)
        assert float(out.stats["disp_max"].max()) <= lam * (1 + 1e-9) + 1e-12, name
        assert torch.all(out.stats["disp_max_raw"] >= out.stats["disp_max"] - 1e-12), name
    # the generator's raw output does exceed small budgets, so the projection was exercised
    raw = attacks["generator"].run(batch, 1e-3, generator=0).stats["disp_max_raw"]
    assert float(raw.min()) > 1e-3


# -- validation is total: accept or InputError -----------------------------------------------------
arrays = st.one_of(
    hnp.arrays(dtype=st.sampled_from([np.float64, np.float32, np.int64, np.bool_]),
               shape=hnp.array_shapes(min_dims=1, max_dims=3, min_side=0, max_side=9)),
    hnp.arrays(dtype=np.float64, shape=st.tuples(st.integers(0, 12), st.just(3)),
               elements=st.floats(allow_nan=True, allow_infinity=True, width=64)),
    hnp.arrays(dtype=np.float64, shape=st.tuples(st.integers(0, 12), st.just(3)),
               elements=st.sampled_from([0.0, 1.0, -1.0])),
)


@settings(max_examples=150, deadline=None, derandomize=True)
@given(a=arrays)
def test_validate_cloud_accepts_or_raises_input_error(a):
    try:
        out = validate_cloud(a, "scan")
    except InputError as exc:
        assert str(exc).startswith("scan ")  # the message names what is wrong
        return
    assert out.ndim == 2 and out.shape[1] == 3 and np.isfinite(out).all()
    assert len(np.unique(out, axis=0)) >= 6


@settings(max_examples=100, deadline=None, derandomize=True)
@given(b=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5), st.text(max_size=4),
                   st.none()))
def test_validate_budget_accepts_or_raises_input_error(b):
    try:
        v = validate_budget(b)
    except InputError as exc:
        assert "budget" in str(exc)
        return
    assert isinstance(v, float) and 0 < v < float("inf")
