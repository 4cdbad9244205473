"""The shipped lidar-sim generator: loads safely, serves every budget of Table 1 within the budget,
and attacks a real lidar-sim test scan harder than the `normal` baseline at λ = 1 m."""

import pytest
import torch

from icpbench.attacks.generator import resolve_checkpoint, shipped_checkpoint_dir
from icpbench.core import registry
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.learning.checkpoint import load_checkpoint
from icpbench.targets.p2plane import PointToPlaneICP

CKPT = shipped_checkpoint_dir("lidar-sim") / "generator.pt"


def test_card_and_resolution():
    lg = load_checkpoint(CKPT)
    assert lg.model.needs_budget and lg.config.output == "bounded" and lg.config.conditioned
    card = lg.card
    assert card["data"]["dataset"] == "lidar-sim" and card["data"]["split"] == "train"
    assert card["train_wall_s"] > 0 and card["epochs_done"] >= 1
    assert set(card["heldout_eval"]) == {"1", "2", "3", "4", "5"}
    stage, total = card, 0.0  # a fine-tuned model's card holds its whole training chain
    while stage.get("init_checkpoint"):
        total += stage["train_wall_s"]
        stage = stage["init_card"]
    assert stage["epochs_done"] >= 1 and card["train_wall_s_total"] == pytest.approx(
        total + stage["train_wall_s"], abs=0.2)
    for lam in (1.0, 2.0, 3.0, 4.0, 5.0):
        assert resolve_checkpoint("lidar-sim", lam) == CKPT


@pytest.mark.parametrize("budget", [1.0, 5.0])
def test_beats_normal_on_a_test_scan_within_the_budget(budget):
    ds = registry.datasets.get("lidar-sim")(seed=0, split="test")
    batch = Batch.from_samples([ds[2]])  # a dense-street scan
    icp = PointToPlaneICP("lidar")
    errs, disps = {}, {}
    for name in ("normal", "generator"):
        kw = {"dataset": "lidar-sim"} if name == "generator" else {}
        out = registry.attacks.get(name)(**kw).run(batch, budget, surrogate=icp,
                                                   generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            reg = icp.register(out.scans, batch.maps, batch.T_init)
        errs[name] = float(pose_error_components(reg.T, batch.T_gt)["trans_err_xy"][0])
        disps[name] = float(out.stats["disp_max"][0])
    assert disps["generator"] <= budget * (1 + 1e-9)
    assert errs["generator"] > errs["normal"] > 0.5 * budget
