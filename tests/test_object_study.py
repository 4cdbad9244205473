"""The object case study (paper fig. 4) with the shipped objects checkpoints, strict (every displacement
within the budget): the theta-only model causes larger heading errors than the x-only model, and
the x-only model larger x errors (paper §IV-C2); the shipped models have the bounded output."""

from importlib import resources
from pathlib import Path

import pytest

from icpbench.analysis.object_study import SOFT_SUFFIX, figure, study, summary_table
from icpbench.learning.checkpoint import read_checkpoint_meta

CK = Path(str(resources.files("icpbench") / "checkpoints" / "objects"))
LAM = 0.05


@pytest.mark.parametrize("name", ["generator", "x-only", "theta-only"])
def test_shipped_objects_models_are_bounded(name):
    cfg, meta = read_checkpoint_meta(CK / f"{name}.pt")
    assert cfg.output == "bounded"  # X + λ·u with |u| < 1: within the budget by construction
    assert meta["card"]["budgets_m"] == [LAM]


def test_loss_weights_shape_the_perturbation(tmp_path):
    models = {"theta-only": str(CK / "theta-only.pt"), "x-only": str(CK / "x-only.pt")}
    rows, clouds, _ = study(models, LAM, n_objects=6, n_figure=1, baselines=(), soft_bound=True)
    t = summary_table(rows).set_index("attack")
    assert t.loc["theta-only", "heading_err_deg"] > t.loc["x-only", "heading_err_deg"]
    assert t.loc["x-only", "x_err"] > t.loc["theta-only", "x_err"]
    # strict rows keep every point within the budget; bounded models are so without projection
    for name in models:
        assert t.loc[name, "disp_max"] <= LAM * (1 + 1e-6)
        assert t.loc[name + SOFT_SUFFIX, "disp_max"] <= LAM * (1 + 1e-6)
    assert set(clouds) == {"original", "theta-only", "x-only", "theta-only" + SOFT_SUFFIX,
                           "x-only" + SOFT_SUFFIX, "_clean"}
    assert figure(rows, clouds, tmp_path / "study.png", LAM).stat().st_size > 10_000
