"""Open3D's point-to-point ICP replayed with compiled correspondences: the same poses, inliers and
status as Open3D on clean and attacked scans, and query attacks answered by it see Open3D's
errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.open3d_icp import Open3DICP
from icpbench.targets.open3d_point_replica import Open3DPointReplica


@pytest.fixture(scope="module")
def batch() -> Batch:
    return Batch.from_samples([scene_sample(1_500, 12_000, seed=s, noise_m=0.02) for s in range(3)])


def _attacked(batch: Batch, seed: int) -> torch.Tensor:
    """A share of each scan's points moved by up to 0.8 m in one heading, a few not finite."""
    rng = np.random.default_rng(seed)
    x = batch.scans.numpy().copy()
    for b in range(x.shape[0]):
        sub = rng.random(x.shape[1]) < 0.4
        head = rng.normal(size=3)
        x[b, sub] += head / np.linalg.norm(head) * rng.uniform(0.1, 0.8, size=(sub.sum(), 1))
        x[b, rng.random(x.shape[1]) < 0.01] = np.nan
    return torch.as_tensor(x)


@pytest.mark.parametrize("settings", [{}, {"d_max": 0.5, "max_iterations": 9}])
def test_replay_registers_as_open3d(batch, settings):
    o3d_target = Open3DICP("lidar", mode="point", **settings)
    replica = o3d_target.exact_replica()
    assert isinstance(replica, Open3DPointReplica)
    maps = [o3d_target.prepare(s.map, s.map_normals) for s in batch.samples]
    for x in (batch.scans, _attacked(batch, 0), _attacked(batch, 1)):
        ref = o3d_target.register(x, maps, batch.T_init)
        got = replica.register(x, batch.maps, batch.T_init)
        np.testing.assert_allclose(got.T.numpy(), ref.T.numpy(), rtol=0, atol=1e-9)
        np.testing.assert_array_equal(got.inlier_fraction.numpy(), ref.inlier_fraction.numpy())
        assert got.status == ref.status


def test_point_to_plane_has_no_replay():
    assert Open3DICP("lidar").exact_replica() is None


def test_queries_answered_by_the_replay_see_open3ds_errors(batch, answers_as_target):
    answers_as_target(Open3DICP("lidar", mode="point"), batch, 0.5, members="uniform,spoof",
                      spoof_queries=4)
