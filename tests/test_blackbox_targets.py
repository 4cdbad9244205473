"""Black-box ICP targets (Open3D, KISS-ICP, small_gicp): accuracy, batching, input guards.

Problem: ``icpbench.synthetic.scene_sample`` (ground, boxes, poles; 2,000-point scan with 2 cm
noise vs a 20,000-point map), ground truth up to 0.3 m / 5 deg per axis from T_init = identity.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from icpbench import registry
from icpbench.errors import InputError, PluginUnavailableError
from icpbench.se3 import pose_error_components
from icpbench.synthetic import scene_sample

torch.set_num_threads(1)

# (entry-point name, module, optional library, constructor kwargs, trans tol m, rot tol deg)
CASES = {
    "open3d-plane": ("open3d", "icpbench.targets.open3d_icp", "open3d", {}, 0.02, 0.1),
    "open3d-point": ("open3d", "icpbench.targets.open3d_icp", "open3d",
                     {"mode": "point", "cauchy_c": None}, 0.05, 0.2),
    "kiss": ("kiss-icp", "icpbench.targets.kiss", "kiss_icp", {}, 0.04, 0.2),
    "sg-gicp": ("small-gicp", "icpbench.targets.small_gicp", "small_gicp", {}, 0.02, 0.1),
    "sg-plane": ("small-gicp", "icpbench.targets.small_gicp", "small_gicp",
                 {"registration_type": "PLANE_ICP"}, 0.03, 0.1),
    "sg-icp": ("small-gicp", "icpbench.targets.small_gicp", "small_gicp",
               {"registration_type": "ICP"}, 0.05, 0.2),
}


def _make(case: str):
    ep, _module, lib, kwargs, _, _ = CASES[case]
    pytest.importorskip(lib)
    return registry.targets.get(ep)(**kwargs)


@pytest.fixture(scope="module")
def samples():
    return [scene_sample(n_scan=2_000, n_map=20_000, seed=k, noise_m=0.02) for k in range(2)]


def _batch(samples):
    scans = torch.as_tensor(np.stack([s.scan for s in samples]), dtype=torch.float64)
    T0 = torch.as_tensor(np.stack([s.T_init for s in samples]), dtype=torch.float64)
    Tgt = torch.as_tensor(np.stack([s.T_gt for s in samples]), dtype=torch.float64)
    return scans, T0, Tgt


@pytest.mark.parametrize("case", list(CASES))
def test_recovers_known_transform_in_a_batch_of_two(case, samples):
    tgt = _make(case)
    assert tgt.differentiable is False
    maps = [tgt.prepare(s.map, s.map_normals) for s in samples]
    scans, T0, Tgt = _batch(samples)
    init = pose_error_components(T0, Tgt)
    assert bool((init["trans_err"] > 0.1).all())  # the problem is not trivial
    reg = tgt.register(scans, maps, T0)
    assert reg.T.shape == (2, 4, 4) and reg.T.dtype == torch.float64
    err = pose_error_components(reg.T, Tgt)
    _, _, _, _, ttol, rtol = CASES[case]
    assert bool((err["trans_err"] < ttol).all()), err["trans_err"]
    assert bool((torch.rad2deg(err["rot_err"]) < rtol).all()), err["rot_err"]
    assert reg.status == ["ok", "ok"] and bool(reg.converged.all())
    assert bool((reg.inlier_fraction > 0.95).all())
    # a batch gives the same answer as its samples one by one
    single = tgt.register(scans[1:], maps[1:], T0[1:])
    assert torch.allclose(single.T[0], reg.T[1], atol=1e-9)
    assert int(single.iterations[0]) == int(reg.iterations[1])


@pytest.mark.parametrize("case", ["open3d-plane", "kiss", "sg-gicp"])
def test_nonfinite_points_are_dropped_and_too_few_points_keep_init(case, samples):
    tgt = _make(case)
    s = samples[0]
    m = tgt.prepare(s.map, s.map_normals)
    scans, T0, Tgt = _batch([s, s, s])
    scans[0, ::10] = float("nan")  # 10% NaN: small_gicp alone would return T_init unchanged
    scans[0, 1] = float("inf")
    scans[1] = float("nan")  # nothing usable
    scans[2, 5:] = float("nan")  # 5 finite points < 6
    reg = tgt.register(scans, [m, m, m], T0)
    err = pose_error_components(reg.T[:1], Tgt[:1])
    assert float(err["trans_err"][0]) < 0.04
    assert reg.status[0] == "ok"
    assert 0.85 < float(reg.inlier_fraction[0]) < 0.91  # dropped points count as outliers
    for b in (1, 2):
        assert reg.status[b] == "too_few_correspondences"
        assert not bool(reg.converged[b]) and int(reg.iterations[b]) == 0
        assert torch.equal(reg.T[b], T0[b])


@pytest.mark.parametrize("case", ["open3d-plane", "kiss", "sg-gicp"])
def test_bad_inputs_raise_input_error(case, samples):
    tgt = _make(case)
    s = samples[0]
    with pytest.raises(InputError):  # small_gicp would segfault on an empty map
        tgt.prepare(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(InputError):
        tgt.prepare(np.full((100, 3), np.nan), np.zeros((100, 3)))
    m = tgt.prepare(s.map, s.map_normals)
    scans, T0, _ = _batch([s])
    with pytest.raises(InputError):  # wrong map handle
        tgt.register(scans, [object()], T0)
    with pytest.raises(InputError):  # map count != batch size
        tgt.register(scans, [m, m], T0)
    with pytest.raises(InputError):
        tgt.register(scans[0], [m], T0)
    with pytest.raises(InputError):
        tgt.register(scans, [m], T0[:, :3])
    settings = tgt.settings()
    assert settings["threads"] == 1 and settings["version"]


def test_open3d_settings_and_rejections():
    pytest.importorskip("open3d")
    from icpbench.targets.open3d_icp import Open3DICP

    with pytest.raises(InputError, match="robust kernel"):
        Open3DICP("lidar", mode="point")  # the preset has cauchy_c=1
    with pytest.raises(InputError):
        Open3DICP("lidar", d_max=None)
    with pytest.raises(InputError):
        Open3DICP("lidar", mode="planar")
    with pytest.raises(InputError, match="normals"):
        Open3DICP("lidar").prepare(np.random.default_rng(0).normal(size=(50, 3)), None)
    st = Open3DICP("objects", threads=1).settings()
    assert st["cauchy_c"] == 0.15 and st["d_max"] == 0.3 and st["max_iterations"] == 150
    assert st["relative_rmse"] == pytest.approx(1e-6)  # 0.01 * tol, Open3D's own default


def test_kiss_stepping_reproduces_a_single_library_call(samples):
    pytest.importorskip("kiss_icp")
    from icpbench.targets.kiss import KissICPTarget, kp

    tgt = KissICPTarget()
    s = samples[1]
    m = tgt.prepare(s.map)
    scans, T0, _ = _batch([s])
    reg = tgt.register(scans, [m], T0)
    full = kp._Registration(max_num_iterations=tgt.max_iterations,
                            convergence_criterion=tgt.convergence, max_num_threads=tgt.threads)
    T_lib = full._align_points_to_map(points=kp._Vector3dVector(s.scan.astype(np.float64)),
                                      voxel_map=m.voxel_map, initial_guess=s.T_init,
                                      max_correspondance_distance=tgt.max_corr, kernel=tgt.kernel)
    np.testing.assert_allclose(reg.T[0].numpy(), T_lib, atol=1e-10)
    assert 5 < int(reg.iterations[0]) < tgt.max_iterations
    # a cap below the needed count: not converged, exactly the cap used
    capped = KissICPTarget(max_iterations=3).register(scans, [m], T0)
    assert capped.status == ["not_converged"] and int(capped.iterations[0]) == 3


def test_kiss_version_gate_and_thread_pinning():
    pytest.importorskip("kiss_icp")
    from icpbench.targets import kiss

    kiss._check_version("1.2.3")
    kiss._check_version("1.3.0")
    for bad in ("1.1.9", "1.4.0", "2.0.0"):
        with pytest.raises(PluginUnavailableError, match="not supported"):
            kiss._check_version(bad)
    kiss.KissICPTarget(threads=1)
    with pytest.raises(InputError, match="separate process"):
        kiss.KissICPTarget(threads=2)


def test_plugins_are_registered_under_their_names():
    for ep, module, lib, *_ in CASES.values():
        if importlib.util.find_spec(lib) is None:
            continue
        cls = registry.targets.get(ep)
        assert cls.__module__ == module and cls.name == ep
