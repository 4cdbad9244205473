"""CLI: --version, list, run/table round trip, and one-line errors with valid choices."""

import subprocess
import sys

import pandas as pd
from typer.testing import CliRunner

from icpbench import __version__
from icpbench.cli import app

runner = CliRunner()
runner_cli = runner


def test_version_and_list_from_installed_console_script():
    out = subprocess.run(["icpbench", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"icpbench {__version__}"
    out = subprocess.run(["icpbench", "list"], capture_output=True, text=True, check=True).stdout
    for name in ("p2plane", "p2point", "none", "uniform", "normal", "sector", "pgd", "objects",
                 "synthetic"):
        assert name in out
    # the package sub-namespaces installed from the top-level folders
    subprocess.run([sys.executable, "-c", "import icpbench.attacks.uniform, icpbench.targets.p2plane"],
                   check=True, cwd="/")


def test_user_errors_exit_2_with_one_line():
    for args, needle in [
        (["run", "--dataset", "nope"], "valid datasets:"),
        (["run", "--dataset", "synthetic", "--attacks", "unifrom"], "valid attacks:"),
        (["run", "--dataset", "synthetic", "--targets", "p2plain"], "valid targets:"),
        (["run", "--dataset", "synthetic", "--budgets", "-1"], "budget must be a positive"),
        (["run", "--dataset", "synthetic", "--budgets", "nan"], "budget must be a positive"),
        (["table", "/nonexistent/dir"], "no results at"),
    ]:
        res = runner.invoke(app, args)
        assert res.exit_code == 2, (args, res.output)
        assert needle in res.output, (args, res.output)
        assert "Traceback" not in res.output


def test_run_then_table_formats(tmp_path):
    res = runner.invoke(app, ["run", "--dataset", "synthetic", "--attacks", "none,uniform",
                              "--targets", "p2plane", "--budgets", "0.5", "--samples", "2",
                              "--reference", "uniform", "--out", str(tmp_path), "--quiet"])
    assert res.exit_code == 0, res.output
    assert "| Original" in res.output and "| Uniform" in res.output
    for fmt, needle in [("md", "| Method"), ("latex", "\\toprule"), ("csv", "Method,")]:
        res = runner.invoke(app, ["table", str(tmp_path), "--format", fmt, "--reference", "uniform"])
        assert res.exit_code == 0 and needle in res.output
    res = runner.invoke(app, ["table", str(tmp_path), "--format", "csv", "--reference", "uniform",
                              "--out", str(tmp_path / "t.csv")])
    t = pd.read_csv(tmp_path / "t.csv")
    assert list(t["Method"]) == ["Original", "Uniform"]
    err = float(t.iloc[1]["λ=0.5 Trans Pose Error [m]"].split(" ± ")[0])
    assert abs(err - 0.5) < 0.05


def test_run_defaults_are_runconfigs(monkeypatch, tmp_path):
    """`icpbench run` with no options builds exactly RunConfig() (one source of defaults)."""
    import icpbench.harness.runner as runner
    from icpbench.core.errors import InputError
    from icpbench.harness.runner import RunConfig

    seen = []

    def capture(cfg, out, **kw):
        seen.append((cfg, out))
        raise InputError("stop here")

    monkeypatch.setattr(runner, "run", capture)
    res = runner_cli.invoke(app, ["run", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "stop here" in res.output
    (cfg, out), = seen
    assert cfg == RunConfig().validate()
    assert cfg.dataset == "lidar-sim" and cfg.samples is None and cfg.budgets == [1, 2, 3, 4, 5]
    assert "generator" in cfg.attacks and cfg.batch_size == 8 and cfg.executor == "local"


SMALL = ["--dataset", "synthetic", "--attacks", "none,uniform,normal", "--targets", "p2plane",
         "--budgets", "0.5,1", "--samples", "3", "--batch-size", "2", "--dataset-param",
         "n_samples=3", "--dataset-param", "n_scan=300", "--dataset-param", "n_map=3000",
         "--reference", "normal", "--quiet"]


def _rows(path):
    from icpbench.harness.results import load_results

    df = load_results(path)
    keep = [c for c in df.columns if c not in ("attack_time_s", "icp_time_s")]
    return df[keep].sort_values(["sample_id", "attack", "target", "budget", "seed"]).reset_index(
        drop=True)


def test_run_config_manifest_repeats_a_run_and_options_override_it(tmp_path):
    import json

    res = runner_cli.invoke(app, ["run", *SMALL, "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    manifest = tmp_path / "a" / "manifest.json"
    res = runner_cli.invoke(app, ["run", "--config", str(manifest), "--out", str(tmp_path / "b"),
                                  "--quiet", "--reference", "normal"])
    assert res.exit_code == 0, res.output
    pd.testing.assert_frame_equal(_rows(tmp_path / "a"), _rows(tmp_path / "b"))
    a, b = (json.loads((tmp_path / d / "manifest.json").read_text())["config"] for d in "ab")
    assert a == b
    # an option given on the command line overrides the file; the rest comes from the file
    res = runner_cli.invoke(app, ["run", "--config", str(manifest), "--budgets", "1", "--out",
                                  str(tmp_path / "c"), "--quiet", "--reference", "normal",
                                  "--target-param", "p2plane.max_iterations=50"])
    assert res.exit_code == 0, res.output
    c = json.loads((tmp_path / "c" / "manifest.json").read_text())["config"]
    assert c["budgets"] == [1.0] and c["target_params"] == {"p2plane": {"max_iterations": 50}}
    assert {k: v for k, v in c.items() if k not in ("budgets", "target_params")} == \
        {k: v for k, v in a.items() if k not in ("budgets", "target_params")}


def test_run_config_yaml(tmp_path):
    cfg = tmp_path / "run.yaml"
    cfg.write_text("dataset: synthetic\nattacks: [none, uniform]\nbudgets: [0.5]\nsamples: 2\n"
                   "dataset_params: {n_samples: 2, n_scan: 300, n_map: 3000}\n")
    res = runner_cli.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "o"),
                                  "--quiet", "--reference", "uniform"])
    assert res.exit_code == 0, res.output
    assert len(_rows(tmp_path / "o")) == 2 * 2
    cfg.write_text("dataset: synthetic\nbudget: [0.5]\n")
    res = runner_cli.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "p")])
    assert res.exit_code == 2 and "unknown setting(s) 'budget'; valid: dataset" in res.output


def test_scripts_show_progress():
    """No script silences the progress output (`make run` talks)."""
    from pathlib import Path

    scripts = sorted((Path(__file__).parents[1] / "scripts").glob("*.sh"))
    assert scripts
    for s in scripts:
        assert "--quiet" not in s.read_text(), s


def test_run_reports_progress_off_a_terminal(tmp_path):
    res = runner_cli.invoke(app, ["run", *[a for a in SMALL if a != "--quiet"],
                                  "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert "icpbench run: 12 units\n" in res.output  # 2 batches x 2 budgets x 3 attacks
    assert "icpbench run: 12/12 units done in" in res.output
