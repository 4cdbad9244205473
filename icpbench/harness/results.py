"""The results store: one CSV row per (sample, attack, target, budget, seed), appended atomically,
and a ``manifest.json`` beside it.

Crash safety: every unit of work is appended as one ``write`` of complete lines followed by
``fsync``. A process killed mid-write can leave at most one partial trailing line; it is detected
(no final newline) and cut off when the store is reopened, so a resumed run neither loses finished
rows nor duplicates them. A run holds an exclusive lock on its folder (:func:`lock_results_dir`), so
two runs never append to the same file. Reading is robust anyway: a row that is incomplete (a
half-written line, no ``status``) is ignored, and of several rows with the same key the last one
counts (a re-run replaces the rows of a sample whose input file was bad, see :data:`BAD_INPUT`).
"""

from __future__ import annotations

import csv
import fcntl
import io
import json
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from icpbench.core.errors import InputError
from icpbench.harness.outputs import _json_default, write_file

RESULTS_FILE = "results.csv"
MANIFEST_FILE = "manifest.json"
#: Lock file of a results folder (held by the run writing to it).
LOCK_FILE = ".icpbench.lock"
#: Files of a results folder that only ``icpbench run`` writes.
STORE_FILES = (RESULTS_FILE, MANIFEST_FILE, LOCK_FILE)
#: Prefix of the ``error`` of rows of a sample whose input (file) is bad. Such rows are not final:
#: a re-run tries the sample again (e.g. after the file was fixed) and its new rows replace them.
BAD_INPUT = "bad input: "
#: Prefix of the ``error`` of rows of an attack that could not run for a reason the user can fix
#: (a missing or unreadable checkpoint: an icpbench user error). Like :data:`BAD_INPUT` rows they
#: are not final: the next run of the same command tries them again.
NOT_RUN = "not run: "
KEY_COLUMNS = ("sample_id", "attack", "target", "budget", "seed")

#: Columns every row has, in order. ``meta`` and ``extra`` hold JSON dicts (dataset metadata such as
#: route position and stretch type; attack-specific values such as the analytic estimate).
COLUMNS = (
    *KEY_COLUMNS,
    "surrogate", "strict", "status", "converged", "iterations", "inlier_fraction",
    "rho_x", "rho_y", "rho_z", "phi_x", "phi_y", "phi_z",
    "trans_err_xy", "trans_err", "rot_err", "yaw_err",
    "disp_max", "disp_mean", "disp_p95", "frac_over_budget", "disp_max_raw",
    "attack_time_s", "icp_time_s", "error", "meta", "extra",
)
#: Columns that vary from run to run on the same machine (excluded from determinism checks).
TIMING_COLUMNS = ("attack_time_s", "icp_time_s")
#: Pose-error columns: a row with a non-finite one is never counted as converged.
ERROR_COLUMNS = ("trans_err_xy", "trans_err", "rot_err")
#: Columns that hold numbers. A target that returns a NaN or infinite pose writes ``nan``/``inf``
#: into them; they are read as numbers, not as text (text columns keep ``"nan"`` as text).
NUMERIC_COLUMNS = (
    "iterations", "inlier_fraction", "rho_x", "rho_y", "rho_z", "phi_x", "phi_y", "phi_z",
    "trans_err_xy", "trans_err", "rot_err", "yaw_err", "disp_max", "disp_mean", "disp_p95",
    "frac_over_budget", "disp_max_raw", "attack_time_s", "icp_time_s",
)


def row_key(row: Mapping[str, Any]) -> tuple:
    """The identity of a row: (sample_id, attack, target, budget, seed)."""
    return (str(row["sample_id"]), str(row["attack"]), str(row["target"]),
            float(row["budget"]), int(row["seed"]))


def is_results_dir(path: str | Path) -> bool:
    """Whether ``path`` is a folder written by ``icpbench run`` (it holds a results CSV or a manifest)."""
    p = Path(path)
    return p.is_dir() and any((p / f).exists() for f in (RESULTS_FILE, MANIFEST_FILE))


@contextmanager
def lock_results_dir(out_dir: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on a results folder (``fcntl.flock`` on :data:`LOCK_FILE`).

    Raises:
        InputError: another process holds it (the message names it, as far as it is known).
    """
    path = Path(out_dir) / LOCK_FILE
    f = open(path, "a+")  # noqa: SIM115 - held open for the life of the lock
    try:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            raise InputError(f"{out_dir} is in use by another icpbench run ({holder}); wait for it "
                             "to finish, or use another --out") from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()}, since {time.strftime('%Y-%m-%dT%H:%M:%S%z')}\n")
        f.flush()
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    finally:
        f.close()


def _complete(row: Mapping[str, Any]) -> bool:
    """A row with every column present and a status (not a half-written line)."""
    return all(row.get(c) is not None for c in COLUMNS) and bool(row.get("status"))


def _final(row: Mapping[str, Any]) -> bool:
    """A complete row that a re-run must not recompute (not the row of a bad input file)."""
    return _complete(row) and not str(row.get("error") or "").startswith((BAD_INPUT, NOT_RUN))


class ResultsStore:
    """Append-only CSV of result rows in ``out_dir``, resumable after a crash.

    :meth:`has` is true only for keys with a *final* row: an incomplete row or the error row of a
    sample whose input was bad is computed again, and its new row (appended later) is the one
    :func:`load_results` keeps."""

    def __init__(self, out_dir: str | Path) -> None:
        self.dir = Path(out_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / RESULTS_FILE
        self._repair()
        rows = self._read_rows()
        self._keys = {row_key(r) for r in rows if _complete(r)}
        self._final = {row_key(r) for r in rows if _final(r)}

    def _repair(self) -> None:
        """Cut a partial trailing line left by a killed writer."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        with open(self.path, "rb+") as f:
            data = f.read()
            if not data.endswith(b"\n"):
                cut = data.rfind(b"\n") + 1
                f.seek(cut)
                f.truncate()
                f.flush()
                os.fsync(f.fileno())

    def _read_rows(self) -> list[dict[str, str]]:
        if not self.path.exists() or self.path.stat().st_size == 0:
            return []
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            if tuple(reader.fieldnames or ()) != COLUMNS:
                raise InputError(
                    f"{self.path} was written by another version of icpbench (columns differ); "
                    "use a new --out directory"
                )
            return [r for r in reader if r.get("sample_id")]

    def has(self, key: tuple) -> bool:
        """Whether a final row with this key is already stored."""
        return key in self._final

    def __len__(self) -> int:
        return len(self._keys)

    def append(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Append complete rows in one write + fsync (rows whose key is final are skipped)."""
        rows = [r for r in rows if row_key(r) not in self._final]
        if not rows:
            return
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
        new_file = not self.path.exists() or self.path.stat().st_size == 0
        if new_file:
            writer.writeheader()
        for r in rows:
            writer.writerow({c: _cell(r.get(c, "")) for c in COLUMNS})
        with open(self.path, "a", newline="") as f:
            f.write(buf.getvalue())
            f.flush()
            os.fsync(f.fileno())
        self._keys.update(row_key(r) for r in rows)
        self._final.update(row_key(r) for r in rows if _final({c: _cell(r.get(c, "")) for c in COLUMNS}))


def _cell(v: Any) -> Any:
    if isinstance(v, Mapping):
        return json.dumps(v, sort_keys=True, default=_json_default)
    if isinstance(v, float):
        return repr(v)
    return v


def attacks_not_run(df: pd.DataFrame) -> dict[str, str]:
    """``{attack: message}`` of the attacks none of whose rows ran because of a user error
    (:data:`NOT_RUN`), with the first such message."""
    out = {}
    for attack, g in df.groupby("attack"):
        errs = (g["error"].astype(object).where(g["error"].notna(), "").astype(str)
                if "error" in g else pd.Series([""] * len(g)))
        if len(g) and errs.str.startswith(NOT_RUN).all():
            out[str(attack)] = errs.iloc[0][len(NOT_RUN):]
    return out


def _first_bad_cell(col: pd.Series, kind: Any) -> tuple[int, Any]:
    """(CSV line, value) of the first cell of ``col`` that does not convert to ``kind``."""
    for i, v in enumerate(col):
        try:
            np.asarray([v]).astype(kind)
        except (ValueError, OverflowError, TypeError):
            return i + 2, v
    return 0, None


def _json_cell(path: Path, col: str, text: Any, line: int) -> dict[str, Any]:
    """A ``meta`` / ``extra`` cell as a dict ({} if empty); a cell that is not a JSON object is
    refused naming the file, line and column."""
    if not isinstance(text, str) or not text:
        return {}
    try:
        out = json.loads(text)
    except json.JSONDecodeError:
        out = None
    if not isinstance(out, dict):
        raise InputError(f"{path}, line {line}, column {col!r}: {text[:60]!r} is not a JSON "
                         "object (a corrupted cell? rows are written by `icpbench run`)")
    return out


def load_results(path: str | Path, expand: bool = True) -> pd.DataFrame:
    """Load a results directory (or CSV file) as a DataFrame.

    Incomplete rows (a half-written line: no ``status``) are dropped, and of several rows with the
    same key (sample, attack, target, budget, seed) only the last is kept; their numbers are in
    ``df.attrs["incomplete_rows"]``, ``df.attrs["retried_rows"]`` (an error row of a bad input
    or of an attack that could not run, replaced by a re-run as intended) and
    ``df.attrs["duplicate_rows"]`` (any other key stored twice). A cell that cannot be read (a
    seed, budget or number that is not one, a ``meta`` / ``extra`` that is not a JSON object) is
    refused naming the file, its line and column. A row whose pose error is
    not finite never counts as converged; ``nan`` and ``inf`` in the :data:`NUMERIC_COLUMNS` are
    read as numbers (a target that returns NaN poses writes them). With ``expand``, the JSON
    ``meta`` and ``extra`` columns are expanded into ``meta.<key>`` and ``extra.<key>`` columns.
    """
    p = Path(path)
    if p.is_dir():
        p = p / RESULTS_FILE
    if not p.exists():
        raise InputError(f"no results at {p}; run `icpbench run --out {p.parent}` first")
    try:
        df = pd.read_csv(p, keep_default_na=False, na_values=[""])
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise InputError(f"{p} is empty or not a results CSV written by `icpbench run` "
                         f"({type(exc).__name__}: {str(exc).strip().splitlines()[0]})") from exc
    if df.empty:
        raise InputError(f"{p} holds no result rows")
    n_lines = len(df)  # data lines, as the manifest's provenance counts them
    df["_line"] = np.arange(2, len(df) + 2)  # the CSV line of each row (1: the header)
    missing = [c for c in KEY_COLUMNS + ("status", "converged", "strict", "meta", "extra")
               if c not in df]
    if missing:
        raise InputError(f"{p} is not a results CSV written by `icpbench run` (no column "
                         f"{missing[0]!r})")
    # every complete row has a status, a converged flag and a JSON meta ("{}" at least)
    incomplete = df[[*KEY_COLUMNS, "status", "converged", "meta"]].isna().any(axis=1)
    n_incomplete = int(incomplete.sum())
    df = df[~incomplete].copy()
    if df.empty:
        raise InputError(f"{p} holds no complete result rows ({n_incomplete} incomplete)")
    for col, kind in (("seed", "int64"), ("budget", float)):
        try:
            df[col] = df[col].astype(kind)
        except (ValueError, OverflowError, TypeError):
            bad = _first_bad_cell(df[col], kind)
            raise InputError(f"{p}, line {bad[0]}, column {col!r}: {bad[1]!r} is not "
                             + ("a 64-bit integer seed" if col == "seed" else "a number (budget)")
                             + " (a corrupted cell? rows are written by `icpbench run`)") from None
    superseded = df.duplicated(list(KEY_COLUMNS), keep="last")
    retried = superseded & df["error"].fillna("").astype(str).str.startswith((BAD_INPUT, NOT_RUN)) \
        if "error" in df else superseded & False
    n_before = len(df)
    df = df[~superseded].reset_index(drop=True)
    for c in NUMERIC_COLUMNS:  # "nan"/"inf" are numbers here (ids stay text: no default NA)
        if c in df and not pd.api.types.is_numeric_dtype(df[c]):
            num = pd.to_numeric(df[c], errors="coerce").astype(float)
            text = df[c].astype(str).str.strip().str.lower()
            junk = df[c].notna() & num.isna() & ~text.isin(["nan", "+nan", "-nan"])
            if junk.any():
                i = int(np.flatnonzero(junk.to_numpy())[0])
                raise InputError(f"{p}, line {int(df['_line'].iloc[i])}, column {c!r}: "
                                 f"{df[c].iloc[i]!r} is not a number (a corrupted cell? rows are "
                                 "written by `icpbench run`)")
            df[c] = num
    df["converged"] = df["converged"].astype(str).str.lower().isin(["true", "1"])
    df["strict"] = df["strict"].astype(str).str.lower().isin(["true", "1"])
    for c in ERROR_COLUMNS:
        if c in df:
            df["converged"] &= np.isfinite(pd.to_numeric(df[c], errors="coerce").astype(float))
    if expand:
        for col in ("meta", "extra"):
            parsed = [_json_cell(p, col, text, line) for text, line in zip(df[col], df["_line"],
                                                                         strict=True)]
            keys = sorted({k for d in parsed for k in d})
            for k in keys:
                df[f"{col}.{k}"] = [d.get(k) for d in parsed]
    df = df.drop(columns="_line")
    df.attrs["incomplete_rows"] = n_incomplete
    df.attrs["retried_rows"] = int(retried.sum())
    df.attrs["duplicate_rows"] = n_before - len(df) - int(retried.sum())
    manifest = read_manifest(p.parent) if (p.parent / MANIFEST_FILE).is_file() else None
    if manifest is not None:
        df.attrs["config"] = manifest.get("config") or {}
        df.attrs["finished"] = manifest.get("finished")  # None: a manifest older than the flag
        df.attrs["provenance"] = entries_with_rows(manifest, n_lines)  # the runs that made rows
    df.attrs["in_use"] = folder_in_use(p.parent)
    return df


def folder_in_use(out_dir: str | Path) -> bool:
    """Whether a run holds the lock of the results folder ``out_dir`` now (it is still writing)."""
    path = Path(out_dir) / LOCK_FILE
    if not path.is_file():
        return False
    with open(path) as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    return False


#: Manifest fields that describe the software and machine that wrote rows.
PROVENANCE_FIELDS = ("versions", "git", "platform")


def count_rows(out_dir: str | Path, name: str = RESULTS_FILE) -> int:
    """Data lines in the CSV ``name`` (default: the results CSV) of ``out_dir`` (0 when there is
    none)."""
    path = Path(out_dir) / name
    if not path.is_file() or path.stat().st_size == 0:
        return 0
    with open(path, "rb") as f:
        return max(sum(1 for _ in f) - 1, 0)


def drop_attack_rows(out_dir: str | Path, attacks: Sequence[str],
                     provenance: Sequence[Mapping[str, Any]] | None = None,
                     ) -> list[dict[str, Any]]:
    """Remove every row of ``attacks`` from the results CSV of ``out_dir`` (rewritten whole or not
    at all), so that a resumed run computes them again, e.g. after the attack's defaults changed.

    Args:
        out_dir: a results folder.
        attacks: attack names whose rows go.
        provenance: the manifest's ``provenance`` entries, whose ``rows_from`` count data lines.

    Returns:
        The entries of ``provenance`` with ``rows_from`` moved back by the data lines removed
        before it, so each entry still starts at the first line its run wrote ([] if None).
    """
    path = Path(out_dir) / RESULTS_FILE
    entries = [dict(e) for e in provenance or []]
    if not path.is_file() or path.stat().st_size == 0:
        return entries
    with open(path, newline="") as f:
        text = f.read()
    lines = text.splitlines(keepends=True)
    reader = csv.reader(io.StringIO(text, newline=""))
    header = next(reader, None)
    if header is None or "attack" not in header:
        raise InputError(f"{path} has no 'attack' column: not a results file")
    col, drop, start = header.index("attack"), set(attacks), reader.line_num
    removed: list[int] = []  # 0-based data lines (physical lines after the header)
    for record in reader:
        end = reader.line_num
        if len(record) > col and record[col] in drop:
            removed += range(start - 1, end - 1)
        start = end
    if not removed:
        return entries
    gone = set(removed)
    kept = lines[:1] + [ln for i, ln in enumerate(lines[1:]) if i not in gone]
    write_file(path, "".join(kept))
    for e in entries:
        e["rows_from"] = int(e.get("rows_from") or 0) - sum(1 for i in removed
                                                           if i < int(e.get("rows_from") or 0))
    return entries


def merge_provenance(old: Mapping[str, Any] | None, new: Mapping[str, Any],
                     rows_before: int) -> dict[str, Any]:
    """The provenance fields of a manifest being (re)written by a run that starts with
    ``rows_before`` rows in the store.

    ``versions``, ``git`` and ``platform`` stay those of the run that created the folder (a resumed
    run never relabels old rows); ``provenance`` lists one entry per run that wrote to the folder:
    the first data line of the CSV it may have written (``rows_from``, 0-based) with its own
    versions, commit and platform, so each row's software is known (rows of a run that appended
    nothing are never assigned to it: the next entry starts at the same line).
    """
    entry = {"rows_from": int(rows_before), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
             **{k: new.get(k) for k in PROVENANCE_FIELDS}}
    if old is None:
        return {**{k: new.get(k) for k in PROVENANCE_FIELDS}, "provenance": [entry]}
    history = list(old.get("provenance") or
                   [{"rows_from": 0, "started": old.get("created"),
                     **{k: old.get(k) for k in PROVENANCE_FIELDS}}])
    return {**{k: old.get(k, new.get(k)) for k in PROVENANCE_FIELDS},
            "provenance": [*history, entry]}


def resume_provenance(out_dir: str | Path, rows_file: str,
                      software: Mapping[str, Any]) -> dict[str, Any]:
    """The provenance fields (see :func:`merge_provenance`) of a script that appends rows to the
    CSV ``out_dir/rows_file`` and resumes from the rows already there, run by ``software`` (its
    ``versions``, ``git`` and ``platform``).

    Rows made by an earlier commit keep that commit: ``git`` stays the one that created the folder
    and ``provenance`` gains an entry from the first row this invocation may append.

    Raises:
        InputError: the CSV holds rows but the folder has no manifest, so what made them is unknown.
    """
    rows = count_rows(out_dir, rows_file)
    old = read_manifest(out_dir)
    if rows and old is None:
        raise InputError(f"{Path(out_dir) / rows_file} holds {rows} rows but {Path(out_dir)} has "
                         f"no {MANIFEST_FILE}, so the code that made them is unknown; delete the "
                         "folder (or the CSV) to compute them again")
    return merge_provenance(old if rows else None, software, rows)


def row_makers(out_dir: str | Path, rows_file: str = RESULTS_FILE) -> list[dict[str, Any]]:
    """The ``provenance`` entries of ``out_dir``'s manifest that made at least one data line of
    its CSV ``rows_file`` (:func:`entries_with_rows`)."""
    return entries_with_rows(read_manifest(out_dir), count_rows(out_dir, rows_file))


def entries_with_rows(m: Mapping[str, Any] | None, n: int) -> list[dict[str, Any]]:
    """The ``provenance`` entries of the manifest ``m`` that made at least one of the ``n`` data
    lines of its rows file (an entry owns the lines from its ``rows_from`` to the next entry's); a
    manifest without ``provenance`` counts as one entry of its own ``versions``, ``git`` and
    ``platform``. Empty when there is no manifest or no row."""
    if m is None or n == 0:
        return []
    entries = m.get("provenance") or [{"rows_from": 0, **{k: m.get(k) for k in PROVENANCE_FIELDS}}]
    ends = [int(e.get("rows_from") or 0) for e in entries[1:]] + [n]
    return [dict(e) for e, end in zip(entries, ends, strict=True)
            if end > int(e.get("rows_from") or 0)]


def commits_of(entries: Sequence[Mapping[str, Any]]) -> list[str]:
    """The distinct commits (``"<sha>+dirty"`` for a dirty tree) of provenance entries, in order."""
    out = []
    for e in entries:
        git = e.get("git") or {}
        c = f"{git.get('commit') or 'unknown'}{'+dirty' if git.get('dirty') else ''}"
        if c not in out:
            out.append(c)
    return out


def software_of(entry: Mapping[str, Any]) -> tuple:
    """What makes two provenance entries' rows comparable: the package versions and the commit
    (with its dirty flag)."""
    git = entry.get("git") or {}
    return (json.dumps(entry.get("versions"), sort_keys=True), git.get("commit"), git.get("dirty"))


def read_manifest(out_dir: str | Path) -> dict[str, Any] | None:
    """The manifest of a results directory, or None."""
    p = Path(out_dir) / MANIFEST_FILE
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{p} is not valid JSON ({exc}), so what made the rows beside it is "
                         f"unknown and they cannot be resumed; use a new --out (a results.csv "
                         "without its manifest cannot be resumed either)") from exc
