"""Output folders and every write into them.

Each command owns its ``--out`` folder: it writes only into a new folder or into a folder of its
own kind (:func:`claim`), so a board is never written over a run, a training run over a danger map,
and so on. A folder records its kind in :data:`MARKER` when first claimed; folders made before the
marker existed are recognised by the files their command writes (:func:`folder_kind`).

Every manifest, summary, CSV, Markdown table and figure is written by :func:`write_file` (or its
helpers :func:`write_json`, :func:`write_csv`, :func:`save_figure`): the bytes go to a temporary
file beside the destination, are flushed to disk and renamed over it, so a reader (or a crash)
sees the old file or the new one, never half of one; a destination that is a symbolic link or a
folder is refused, never followed.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any

from icpbench.core.errors import InputError

#: The file in which a claimed folder records the kind of command that owns it.
MARKER = ".icpbench-kind"
#: The kinds of output folder, and the command that writes each.
KINDS: dict[str, str] = {
    "run": "icpbench run", "leaderboard": "icpbench leaderboard", "map": "icpbench map",
    "validate-map": "icpbench validate-map", "train": "icpbench train",
    "object-study": "icpbench object-study",
}


def _json_default(v: Any) -> Any:
    if hasattr(v, "item"):
        return v.item()
    if hasattr(v, "tolist"):
        return v.tolist()
    return str(v)


def _manifest(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads((path / "manifest.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


#: What a path names, in the words of messages (:func:`path_kind`).
PATH_WORDS = {"missing": "missing", "file": "a file", "folder": "a folder",
              "link": "a symbolic link", "other": "a device, pipe or socket"}


def path_kind(path: str | Path) -> str:
    """What ``path`` names, precisely: ``"missing"``, ``"file"``, ``"folder"``, ``"link"`` (a
    symbolic link, whatever it points to, also a broken one) or ``"other"`` (a device, a pipe,
    a socket). Links are never followed by the output guards: a link would let a command write
    where its folder does not say."""
    p = Path(path)
    if p.is_symlink():
        return "link"
    if not p.exists():
        return "missing"
    if p.is_dir():
        return "folder"
    return "file" if p.is_file() else "other"


def folder_kind(path: str | Path) -> str | None:
    """The kind (a key of :data:`KINDS`) of the output folder ``path``; None for a missing or
    empty folder, ``"other"`` for a folder holding files no icpbench command is known to write.

    Read from :data:`MARKER`, else from the files each command writes (folders made before the
    marker): a run's ``results.csv`` or manifest ``config``, a board's manifest ``kind`` or
    ``variants``, a validation's ``run_config``, a training's ``train_config.json``, a map's or
    object study's own files."""
    p = Path(path)
    if not p.is_dir():
        return None
    try:
        kind = (p / MARKER).read_text().strip()
    except OSError:
        kind = ""
    if kind:
        return kind
    m = _manifest(p) or {}
    if m.get("kind") in KINDS:
        return str(m["kind"])
    if "variants" in m:
        return "leaderboard"
    if "run_config" in m or (p / "places.csv").exists():
        return "validate-map"
    if (p / "results.csv").exists() or "targets" in (m.get("config") or {}):
        return "run"
    if (p / "train_config.json").exists() or (p / "train_state.pt").exists():
        return "train"
    if (p / "object_study_rows.csv").exists():
        return "object-study"
    if any(p.glob("*_locations.csv")):
        return "map"
    names = [q.name for q in p.iterdir() if not q.name.startswith(".")]  # locks, temporaries
    return None if not names else "other"


def check_owner(path: str | Path, kind: str, flag: str = "--out") -> str | None:
    """Check, creating nothing, that a command of ``kind`` may write into ``path``: a missing or
    empty folder, or one that already belongs to that kind (a resumed or repeated command).
    Returns the folder's kind (None: new).

    Raises:
        InputError: ``path`` is a file, or a folder that belongs to another kind of command or
            holds files no icpbench command wrote (the message says which and what to do).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r}")
    p = Path(path)
    what = path_kind(p)
    if what == "link":
        raise InputError(f"{flag} {p} is a symbolic link (to {p.resolve()}); give the folder "
                         "itself: outputs never follow links")
    if what not in ("missing", "folder"):
        raise InputError(f"{flag} {p} is {PATH_WORDS[what]}; {KINDS[kind]} writes into a folder")
    found = folder_kind(p)
    if found not in (None, kind):
        whose = (f"the output of `{KINDS[found]}`" if found in KINDS else
                 "files that no icpbench command wrote")
        raise InputError(f"{flag} {p} holds {whose}; `{KINDS[kind]}` writes only into a new "
                         "folder or one of its own: choose another folder")
    return found


def claim(path: str | Path, kind: str, flag: str = "--out") -> Path:
    """:func:`check_owner`, then make ``path`` the folder of ``kind`` (created, and marked if it
    was new: a folder that already belongs to ``kind`` is left as it is). Returns the path."""
    found = check_owner(path, kind, flag)
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    if found is None:  # a new folder; one of its kind already says so by its files
        write_file(p / MARKER, kind + "\n")
    return p


def write_file(path: str | Path, data: str | bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all (module docstring); creates the folder.

    Raises:
        InputError: ``path`` is a symbolic link or a folder.
    """
    p = Path(path)
    if p.is_symlink():
        raise InputError(f"refusing to write {p}: it is a symbolic link (never followed)")
    if p.is_dir():
        raise InputError(f"refusing to write {p}: it is a folder")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
    return p


def write_json(path: str | Path, obj: Any) -> Path:
    """``obj`` as indented JSON with sorted keys (NumPy values as numbers), via :func:`write_file`."""
    return write_file(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default)
                      + "\n")


def write_csv(path: str | Path, frame: Any, **to_csv: Any) -> Path:
    """A pandas frame as CSV (``to_csv`` keywords passed on), via :func:`write_file`."""
    return write_file(path, frame.to_csv(**to_csv))


def save_figure(fig: Any, path: str | Path, **savefig: Any) -> Path:
    """A matplotlib figure, its format from the suffix (``savefig`` keywords passed on), via
    :func:`write_file`."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or "png", **savefig)
    return write_file(path, buf.getvalue())
