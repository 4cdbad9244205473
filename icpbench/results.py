"""The results store: one CSV row per (sample, attack, target, budget, seed), appended atomically,
and a ``manifest.json`` beside it.

Crash safety: every unit of work is appended as one ``write`` of complete lines followed by
``fsync``. A process killed mid-write can leave at most one partial trailing line; it is detected
(no final newline) and cut off when the store is reopened, so a resumed run neither loses finished
rows nor duplicates them.
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from icpbench.errors import InputError

RESULTS_FILE = "results.csv"
MANIFEST_FILE = "manifest.json"
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


def row_key(row: Mapping[str, Any]) -> tuple:
    """The identity of a row: (sample_id, attack, target, budget, seed)."""
    return (str(row["sample_id"]), str(row["attack"]), str(row["target"]),
            float(row["budget"]), int(row["seed"]))


class ResultsStore:
    """Append-only CSV of result rows in ``out_dir``, resumable after a crash."""

    def __init__(self, out_dir: str | Path) -> None:
        self.dir = Path(out_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / RESULTS_FILE
        self._repair()
        self._keys = {row_key(r) for r in self._read_rows()}

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
            return list(reader)

    def has(self, key: tuple) -> bool:
        """Whether a row with this key is already stored."""
        return key in self._keys

    def __len__(self) -> int:
        return len(self._keys)

    def append(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Append complete rows in one write + fsync (rows already stored are skipped)."""
        rows = [r for r in rows if row_key(r) not in self._keys]
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


def _cell(v: Any) -> Any:
    if isinstance(v, Mapping):
        return json.dumps(v, sort_keys=True, default=_json_default)
    if isinstance(v, float):
        return repr(v)
    return v


def _json_default(v: Any) -> Any:
    if hasattr(v, "item"):
        return v.item()
    if hasattr(v, "tolist"):
        return v.tolist()
    return str(v)


def load_results(path: str | Path, expand: bool = True) -> pd.DataFrame:
    """Load a results directory (or CSV file) as a DataFrame.

    With ``expand``, the JSON ``meta`` and ``extra`` columns are expanded into ``meta.<key>`` and
    ``extra.<key>`` columns.
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
    missing = [c for c in KEY_COLUMNS + ("converged", "strict", "meta", "extra") if c not in df]
    if missing:
        raise InputError(f"{p} is not a results CSV written by `icpbench run` (no column "
                         f"{missing[0]!r})")
    df["converged"] = df["converged"].astype(str).str.lower().isin(["true", "1"])
    df["strict"] = df["strict"].astype(str).str.lower().isin(["true", "1"])
    if expand:
        for col in ("meta", "extra"):
            parsed = [json.loads(s) if isinstance(s, str) and s else {} for s in df[col]]
            keys = sorted({k for d in parsed for k in d})
            for k in keys:
                df[f"{col}.{k}"] = [d.get(k) for d in parsed]
    return df


def write_json_atomic(path: str | Path, obj: Any) -> None:
    """Write JSON to ``path`` atomically (temp file + rename)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=True, default=_json_default)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_manifest(out_dir: str | Path) -> dict[str, Any] | None:
    """The manifest of a results directory, or None."""
    p = Path(out_dir) / MANIFEST_FILE
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{p} is not valid JSON ({exc}); delete it or use a new --out") from exc


def rows_equal_ignoring_timing(a: Iterable[Mapping[str, Any]], b: Iterable[Mapping[str, Any]]) -> bool:
    """Compare result rows, ignoring wall-time columns (for determinism checks)."""
    def strip(rows):
        return sorted(tuple((k, str(v)) for k, v in sorted(r.items()) if k not in TIMING_COLUMNS)
                      for r in rows)
    return strip(a) == strip(b)
