"""Issue 5 object case study with the shipped objects checkpoints: the theta-only model causes
larger heading errors than the x-only model, and the x-only model larger x errors (paper §IV-C2)."""

from importlib import resources
from pathlib import Path

from icpbench.analysis.object_study import study, summary_table

CK = Path(str(resources.files("icpbench") / "checkpoints" / "objects"))


def test_loss_weights_shape_the_perturbation():
    models = {"theta-only": str(CK / "theta-only.pt"), "x-only": str(CK / "x-only.pt")}
    rows, clouds, _ = study(models, 0.05, n_objects=6, n_figure=1, baselines=())
    t = summary_table(rows).set_index("attack")
    assert t.loc["theta-only", "heading_err_deg"] > 3 * t.loc["x-only", "heading_err_deg"]
    assert t.loc["x-only", "x_err"] > 3 * t.loc["theta-only", "x_err"]
    # strict mode keeps every point within the budget and the ordering of heading errors
    assert t.loc["x-only (strict)", "disp_max"] <= 0.05 + 1e-9
    assert t.loc["theta-only (strict)", "heading_err_deg"] > t.loc["x-only (strict)",
                                                                  "heading_err_deg"]
    assert set(clouds) >= {"original", "theta-only", "x-only", "_clean"}
