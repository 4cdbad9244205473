"""The shipped objects generators (icpbench/checkpoints/objects, scripts/train_objects.sh) keep
the budget by construction (bounded output) and their cards record how they were trained."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import icpbench.datasets.objects  # noqa: F401  (registers the dataset)
from icpbench.core import registry
from icpbench.core.types import Batch
from icpbench.learning.checkpoint import load_checkpoint
from icpbench.learning.prior import sector_prior_batch

CK = Path(__file__).resolve().parents[1] / "icpbench" / "checkpoints" / "objects"
LAM = 0.05


@pytest.fixture(scope="module")
def batch() -> Batch:
    ds = registry.datasets.get("objects")(seed=1, split="test", n_samples=2)
    return Batch.from_samples(ds.take(2))


@pytest.mark.parametrize("name,weights", [("generator", "xy"), ("x-only", "x-only"),
                                          ("theta-only", "theta-only")])
def test_unprojected_output_stays_within_the_budget(batch, name, weights):
    lg = load_checkpoint(CK / f"{name}.pt")
    assert lg.model.config.output == "bounded" and lg.card["weights"] == weights
    x = batch.scans.to(torch.float32)
    with torch.no_grad():
        prior = None
        if lg.model.needs_prior:
            prior = sector_prior_batch(batch.scans, batch.T_gt, batch.maps,
                                       lg.model.config.prior_dmax)
        adv = lg.model(x, lg.model.precompute(x), torch.full((2,), LAM), prior)
    disp = torch.linalg.norm(adv.double() - batch.scans.double(), dim=-1)
    assert float(disp.max()) <= LAM * (1 + 1e-5)  # no projection applied here
    assert float(disp.mean()) > 0.5 * LAM  # and it does attack: most points move far


@pytest.mark.parametrize("name", ["generator", "x-only", "theta-only"])
def test_cards_record_the_fine_tune_on_256_objects(name):
    card = load_checkpoint(CK / f"{name}.pt").card
    assert card["data"]["samples"] == 256 and card["epochs_done"] == 2
    assert card["init_card"]["data"]["samples"] == 160
    init_total = card["init_card"].get("train_wall_s_total", card["init_card"]["train_wall_s"])
    assert card["train_wall_s_total"] == pytest.approx(card["train_wall_s"] + init_total, abs=1)
