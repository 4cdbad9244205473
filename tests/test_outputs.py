"""Every output folder is owned by one kind of command, and every manifest, table and figure is
written whole or not at all through one guarded writer (:mod:`icpbench.harness.outputs`)."""

from __future__ import annotations

import ast
import json
import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core.errors import InputError
from icpbench.harness import outputs
from icpbench.harness.outputs import (
    MARKER,
    check_owner,
    claim,
    folder_kind,
    write_file,
    write_json,
)

cli = CliRunner()
ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("files", "kind"), [
    ({"results.csv": "x\n", "manifest.json": json.dumps({"config": {"targets": ["p2plane"]}})},
     "run"),
    ({"manifest.json": json.dumps({"kind": "leaderboard"})}, "leaderboard"),
    ({"manifest.json": json.dumps({"variants": []})}, "leaderboard"),
    ({"places.csv": "", "manifest.json": json.dumps({"run_config": {}})}, "validate-map"),
    ({"train_config.json": "{}"}, "train"),
    ({"object_study_rows.csv": ""}, "object-study"),
    ({"generator_locations.csv": ""}, "map"),
    ({"notes.txt": "mine"}, "other"),
    ({".icpbench.lock": ""}, None),
    ({}, None),
])
def test_a_folder_made_before_the_marker_is_recognised_by_its_files(tmp_path, files, kind):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    assert folder_kind(tmp_path) == kind


def test_a_claimed_folder_records_its_kind_and_refuses_every_other(tmp_path):
    out = claim(tmp_path / "a", "map")
    assert (out / MARKER).read_text().strip() == "map" and folder_kind(out) == "map"
    assert claim(out, "map") == out  # the same command again: its own folder
    for other in set(outputs.KINDS) - {"map"}:
        with pytest.raises(InputError, match=r"holds the output of `icpbench map`"):
            check_owner(out, other)


def test_a_folder_of_foreign_files_or_a_file_is_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="files that no icpbench command wrote"):
        claim(tmp_path, "run")
    assert not (tmp_path / MARKER).exists()
    with pytest.raises(InputError, match="is a file"):
        claim(tmp_path / "notes.txt", "train")


@pytest.mark.parametrize("args", [
    ["map", "--dataset", "synthetic", "--attack", "uniform", "--samples", "1", "--quiet"],
    ["validate-map", "--dataset", "synthetic", "--attacks", "uniform", "--samples", "1",
     "--quiet"],
    ["train", "--preset", "quick-objects", "--quiet"],
    ["leaderboard", "--variants", "p2point", "--samples", "1", "--quiet"],
])
def test_a_command_refuses_the_folder_of_another_command_and_writes_nothing(tmp_path, args):
    run = tmp_path / "run"
    claim(run, "run")
    (run / "results.csv").write_text("sample_id\n")
    before = sorted(p.name for p in run.iterdir())
    res = cli.invoke(app, [*args, "--out", str(run)])
    assert res.exit_code == 2, res.output
    assert "icpbench run" in res.output and "choose another folder" in res.output \
        or "results of an `icpbench run`" in res.output, res.output
    assert sorted(p.name for p in run.iterdir()) == before


@pytest.mark.parametrize("what", ["file", "link", "broken link", "pipe"])
@pytest.mark.parametrize("args", [
    ["run", "--dataset", "synthetic", "--attacks", "none", "--samples", "1", "--quiet"],
    ["map", "--dataset", "synthetic", "--attack", "uniform", "--samples", "1", "--quiet"],
    ["validate-map", "--dataset", "synthetic", "--attacks", "uniform", "--quiet"],
    ["train", "--preset", "quick-objects", "--quiet"],
    ["leaderboard", "--variants", "p2point", "--samples", "1", "--quiet"],
    ["object-study", "--model", "a=a.pt"],
], ids=lambda a: a[0])
def test_every_out_that_is_not_a_folder_is_refused_saying_what_it_is(tmp_path, args, what):
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    out = tmp_path / "out"
    if what == "file":
        out.write_text("mine")
    elif what == "pipe":
        os.mkfifo(out)
    else:
        out.symlink_to(folder if what == "link" else tmp_path / "gone")
    res = cli.invoke(app, [*args, "--out", str(out)])
    assert res.exit_code == 2, res.output
    word = {"file": "a file", "link": "a symbolic link", "broken link": "a symbolic link",
            "pipe": "a device, pipe or socket"}[what]
    assert "--out must be a non-empty text" not in res.output
    assert f"{str(out)!r} is {word}, not a folder" in res.output, res.output
    assert not any(folder.iterdir())  # nothing written through the link


def test_a_path_is_classified_precisely(tmp_path):
    (tmp_path / "f").write_text("x")
    (tmp_path / "d").mkdir()
    (tmp_path / "l").symlink_to(tmp_path / "d")
    os.mkfifo(tmp_path / "p")
    assert [outputs.path_kind(tmp_path / n) for n in ("f", "d", "l", "p", "m")] == \
        ["file", "folder", "link", "other", "missing"]
    with pytest.raises(InputError, match="is a symbolic link"):
        claim(tmp_path / "l", "run")


def test_run_refuses_a_board_folder(tmp_path):
    board = claim(tmp_path / "board", "leaderboard")
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--attacks", "none", "--samples", "1",
                           "--targets", "p2point", "--quiet", "--out", str(board)])
    assert res.exit_code == 2 and "icpbench leaderboard" in res.output, res.output
    assert not (board / "results.csv").exists()


def test_the_writer_replaces_a_file_whole_and_never_follows_a_link(tmp_path):
    p = write_json(tmp_path / "m.json", {"a": 1})
    assert json.loads(p.read_text()) == {"a": 1}
    with pytest.raises(TypeError):  # a failed write leaves the old file and no temporary
        write_file(p, 3)  # type: ignore[arg-type]
    assert json.loads(p.read_text()) == {"a": 1}
    assert [q.name for q in tmp_path.iterdir()] == ["m.json"]
    target = tmp_path / "elsewhere.txt"
    target.write_text("keep")
    os.symlink(target, tmp_path / "link.json")
    with pytest.raises(InputError, match="symbolic link"):
        write_json(tmp_path / "link.json", {})
    assert target.read_text() == "keep"
    with pytest.raises(InputError, match="is a folder"):
        write_file(tmp_path, "x")


_WRITES = {"to_csv", "write_text", "write_bytes", "savefig", "dump"}
#: Writes that are not a command's manifest, table or figure, and why.
_ALLOWED = {
    ("icpbench/harness/report.py", "to_csv"),  # renders a table to a string (no file)
    ("icpbench/learning/checkpoint.py", "write_text"),  # its own temporary file, then renamed
    ("scripts/replica_agreement.py", "to_csv"),  # appends rows to its resumable row log
}


def test_every_manifest_table_and_figure_goes_through_the_writer():
    """No module writes a file with pandas, pathlib, json or matplotlib directly."""
    found = []
    for folder in ("icpbench", "attacks", "targets", "monitors", "scripts"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel == "icpbench/harness/outputs.py":
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                        node.func.attr in _WRITES and (rel, node.func.attr) not in _ALLOWED:
                    if node.func.attr == "dump" and not (
                            isinstance(node.func.value, ast.Name) and node.func.value.id == "json"):
                        continue
                    found.append(f"{rel}:{node.lineno} .{node.func.attr}(")
    assert not found, found


# -- a corrupted results.csv cell is named by file, line and column ---------------------------------
@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    from icpbench.harness.runner import RunConfig, run

    out = tmp_path_factory.mktemp("run")
    run(RunConfig(dataset="synthetic", attacks=["none"], targets=["p2point"], budgets=[1.0],
                  samples=2, dataset_params={"n_samples": 2, "n_scan": 200, "n_map": 2000}),
        out, progress=False)
    return out


@pytest.mark.parametrize(("column", "value", "needle"), [
    ("seed", "zero", "is not a 64-bit integer seed"),
    ("budget", "one", "is not a number (budget)"),
    ("trans_err_xy", "12cm", "is not a number"),
    ("meta", "{broken", "is not a JSON object"),
    ("extra", "[1, 2]", "is not a JSON object"),
])
def test_a_corrupted_cell_is_refused_naming_file_line_and_column(small_run, tmp_path, column,
                                                                 value, needle):
    import csv
    import shutil

    from icpbench.harness.results import load_results

    out = tmp_path / "copy"
    shutil.copytree(small_run, out)
    rows = list(csv.DictReader((out / "results.csv").open()))
    rows[1][column] = value
    with (out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with pytest.raises(InputError) as exc:
        load_results(out)
    text = str(exc.value)
    assert f"results.csv, line 3, column {column!r}" in text and needle in text, text


def test_a_folder_of_its_kind_is_left_as_it_is(tmp_path):
    """A committed run folder made before the marker is resumed without a new file in it."""
    (tmp_path / "results.csv").write_text("x\n")
    claim(tmp_path, "run")
    assert not (tmp_path / MARKER).exists()
