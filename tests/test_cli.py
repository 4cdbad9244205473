"""CLI: --version, list, run/table round trip, and one-line errors with valid choices."""

import subprocess
import sys

import pandas as pd
from typer.testing import CliRunner

from icpbench import __version__
from icpbench.cli import app

runner = CliRunner()


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
