"""Attack contracts: shapes, budgets, the displacement audit, strict mode, seeding, and PGD."""

import math

import pytest
import torch

from icpbench.attacks.base import SampleGenerators, displacement_stats, project_to_ball
from icpbench.attacks.none import NoAttack
from icpbench.attacks.normal import NormalTranslationAttack
from icpbench.attacks.pgd import PGDAttack
from icpbench.attacks.uniform import UniformTranslationAttack, random_xy_directions
from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.p2plane import PointToPlaneICP


@pytest.fixture(scope="module")
def batch():
    return Batch.from_samples([scene_sample(800, 10_000, seed=s, noise_m=0.02) for s in range(2)])


@pytest.mark.parametrize("cls", [NoAttack, UniformTranslationAttack, NormalTranslationAttack])
def test_shapes_seeding_and_audit(cls, batch):
    a = cls().run(batch, 0.7, generator=3)
    b = cls().run(batch, 0.7, generator=3)
    assert a.scans.shape == batch.scans.shape
    assert torch.equal(a.scans, b.scans)
    expect = 0.0 if cls is NoAttack else 0.7
    for k in ("disp_max", "disp_mean", "disp_p95"):
        assert torch.allclose(a.stats[k], torch.full((2,), expect, dtype=torch.float64), atol=1e-9)
    assert (a.stats["frac_over_budget"] == 0).all()


def test_uniform_moves_horizontally_in_map_frame(batch):
    out = UniformTranslationAttack().run(batch, 1.0, generator=0)
    d = out.scans - batch.scans
    assert torch.allclose(d[:, :, 2], torch.zeros_like(d[:, :, 2]), atol=1e-12)  # T_init = I
    assert not torch.allclose(d[0, 0], d[1, 0])  # a different direction per sample


def test_normal_follows_consistently_oriented_normals(batch):
    out = NormalTranslationAttack().run(batch, 1.0, generator=0)
    d = out.scans - batch.scans
    # all displacements point into the half-plane of the sample's drawn direction u
    u = random_xy_directions(batch, SampleGenerators.for_batch(batch, 0, "normal", 1.0))
    assert ((d * u[:, None, :]).sum(-1) >= -1e-9).all()
    assert (torch.linalg.norm(d[..., :2], dim=-1) - 1.0).abs().max() < 1e-9


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "a"])
def test_bad_budgets_raise(batch, bad):
    with pytest.raises(InputError, match="budget"):
        UniformTranslationAttack().run(batch, bad)


def test_project_to_ball_per_sample_budget_is_differentiable():
    clean = torch.zeros(2, 3, 3, dtype=torch.float64)
    adv = torch.tensor([[[3.0, 0, 0], [0, 0.5, 0], [0, 0, 0]],
                        [[3.0, 0, 0], [0, 0.5, 0], [0, 0, 0]]], dtype=torch.float64, requires_grad=True)
    proj = project_to_ball(clean, adv, torch.tensor([1.0, 0.25], dtype=torch.float64))
    assert torch.allclose(torch.linalg.norm(proj, dim=-1).detach(),
                          torch.tensor([[1.0, 0.5, 0.0], [0.25, 0.25, 0.0]], dtype=torch.float64))
    # a float budget gives the same result as a tensor holding it for every sample
    assert torch.equal(project_to_ball(clean, adv, 1.0)[0], proj[0])
    proj.sum().backward()
    assert torch.isfinite(adv.grad).all()
    assert torch.equal(adv.grad[:, 2], torch.ones(2, 3, dtype=torch.float64))  # identity inside the ball
    assert adv.grad[0, 0, 0].item() == pytest.approx(0.0)  # radial component clipped on the sphere
    with pytest.raises(InputError, match="shape"):
        project_to_ball(clean, adv, torch.tensor([1.0, 2.0, 3.0]))


def test_strict_mode_projects_and_keeps_raw_audit():
    clean = torch.zeros(1, 4, 3, dtype=torch.float64)
    adv = torch.tensor([[[3.0, 0, 0], [0, 0.5, 0], [0, 0, -2], [1, 1, 1]]], dtype=torch.float64)
    proj = project_to_ball(clean, adv, 1.0)
    assert torch.allclose(torch.linalg.norm(proj, dim=-1),
                          torch.tensor([[1.0, 0.5, 1.0, 1.0]], dtype=torch.float64))
    st = displacement_stats(clean, adv, 1.0)
    assert st["frac_over_budget"].item() == pytest.approx(0.75)
    assert st["disp_max"].item() == pytest.approx(3.0)

    class Overshoot(UniformTranslationAttack):
        def _perturb(self, batch, budget_m, *, surrogate, generator):
            return super()._perturb(batch, 2.5 * budget_m, surrogate=surrogate, generator=generator)

    b = Batch.from_samples([scene_sample(300, 3_000, seed=0)])
    soft = Overshoot().run(b, 1.0)
    strict = Overshoot(strict=True).run(b, 1.0)
    assert soft.stats["disp_max"].item() == pytest.approx(2.5)
    assert strict.stats["disp_max"].item() == pytest.approx(1.0)
    assert strict.stats["disp_max_raw"].item() == pytest.approx(2.5)
    assert strict.stats["frac_over_budget"].item() == 1.0


def test_pgd_needs_differentiable_surrogate(batch):
    with pytest.raises(InputError, match="surrogate"):
        PGDAttack(steps=1).run(batch, 1.0)


def test_pgd_beats_normal_and_respects_budget():
    b = Batch.from_samples([scene_sample(1_000, 10_000, seed=s, noise_m=0.02) for s in range(2)])
    tgt = PointToPlaneICP("lidar")
    errs = {}
    for atk in (NormalTranslationAttack(), PGDAttack(steps=8, step_size=0.25, icp_iterations=15)):
        out = atk.run(b, 1.0, surrogate=tgt, generator=0)
        assert out.stats["disp_max"].max() <= 1.0 + 1e-9
        reg = tgt.register(out.scans, b.maps, b.T_init)
        errs[atk.name] = pose_error_components(reg.T, b.T_gt)["trans_err_xy"]
    assert (errs["pgd"] > errs["normal"]).all(), errs
    assert math.isfinite(float(errs["pgd"].sum()))
