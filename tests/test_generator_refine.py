"""Test-time refinement of the generator ("Ours + K steps"): K projected gradient steps through the
surrogate from the generator's output, never worse on the surrogate's objective, within the budget."""

from __future__ import annotations

import pytest
import torch

from icpbench.attacks.generator import GeneratorAttack, GeneratorRefineAttack
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.learning.losses import weighted_pose_error, weights
from icpbench.targets.p2plane import PointToPlaneICP

LAM = 0.05


@pytest.fixture(scope="module")
def batch() -> Batch:
    ds = registry.datasets.get("objects")(seed=0, split="test")
    return Batch.from_samples(ds.take(2))


def _objective(icp, batch, scans):
    with torch.no_grad():
        reg = icp.register(scans.double(), batch.maps, batch.T_init)
    return weighted_pose_error(pose_error(reg.T, batch.T_gt), weights("xy"))


def test_refinement_never_lowers_the_objective_and_keeps_the_budget(batch):
    icp = PointToPlaneICP("objects")
    # the shipped objects models are soft-bound: refinement starts from the output projected onto
    # the budget balls, so compare with the strict (projected) plain output
    plain = GeneratorAttack(dataset="objects", strict=True).run(batch, LAM, surrogate=icp)
    zero = GeneratorAttack(dataset="objects", strict=True, refine_steps=0).run(batch, LAM,
                                                                               surrogate=icp)
    torch.testing.assert_close(zero.scans, plain.scans, atol=0, rtol=0)
    ref = GeneratorRefineAttack(dataset="objects", refine_steps=4,
                                refine_icp_iterations=150).run(batch, LAM, surrogate=icp)
    assert float(ref.stats["disp_max"].max()) <= LAM * (1 + 1e-9)
    assert float(ref.stats["frac_over_budget"].max()) == 0.0
    v_plain, v_ref = _objective(icp, batch, plain.scans), _objective(icp, batch, ref.scans)
    assert (v_ref >= v_plain - 1e-9).all(), (v_plain, v_ref)
    assert (v_ref > v_plain + 1e-4).any(), "four ascent steps should improve at least one scan"


def test_refinement_settings_are_checked(batch):
    assert GeneratorRefineAttack.name == "generator-refine"
    assert GeneratorRefineAttack(dataset="objects").refine_steps == 3
    with pytest.raises(InputError, match="refine_steps"):
        GeneratorAttack(dataset="objects", refine_steps=-1)
    with pytest.raises(InputError, match="differentiable surrogate"):
        GeneratorAttack(dataset="objects", refine_steps=1).run(batch, LAM, surrogate=None)


def test_refine_is_a_preset_that_starts_from_the_generator_rows_output(batch):
    """``generator-refine`` has the generator's settings with its own defaults, and in one batch it
    starts from the ``generator`` row's output (no second network pass: the row reports the reused
    seconds) and ends no lower than it on the surrogate it refines through."""
    assert GeneratorRefineAttack.param_types() == GeneratorAttack.param_types()
    preset = GeneratorRefineAttack(dataset="objects")
    assert (preset.refine_steps, preset.refine_icp_iterations, preset.refine_backprop) == \
        (3, 100, "implicit")
    icp = PointToPlaneICP("objects")
    b = Batch.from_samples(batch.samples)
    plain = GeneratorAttack(dataset="objects", strict=True).run(b, LAM, surrogate=icp)
    assert float(plain.extra["reused_s"].max()) == 0.0
    ref = GeneratorRefineAttack(dataset="objects", strict=True, refine_steps=2,
                                refine_icp_iterations=150).run(b, LAM, surrogate=icp)
    assert float(ref.extra["reused_s"].min()) > 0.0
    assert (_objective(icp, b, ref.scans) >= _objective(icp, b, plain.scans) - 1e-9).all()
