"""Carry a board's runs over to a board of a later protocol version where their rows stay.

A new version of the standard protocol (:mod:`icpbench.harness.protocol`) changes what some
variants compute, not necessarily all: protocol v3 changed ``valley``'s plan on a Geman-McClure
kernel, so only KISS-ICP's rows differ from v2's. Computing a whole board again costs hours of
runs that would give the same numbers. :func:`carry_over` copies into a new board each of the
older board's runs whose rows the new protocol would compute again, with the very check that
decides whether a run may be resumed (:func:`~icpbench.harness.runner.check_resume`: the same
run configuration, the same attack files, and every attack's settings acting the same on the
variant's target, :meth:`~icpbench.attacks.base.Attack.settings_on`); every other variant is
left to be computed. The copied run keeps its manifest and ``provenance`` (the commits that made
its rows); the board records what it carried over and from where.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from icpbench.core.errors import InputError
from icpbench.harness.protocol import protocol_differences
from icpbench.harness.results import LOCK_FILE, read_manifest
from icpbench.harness.runner import GridWorker, RunConfig, check_resume, run_manifest_head

#: Protocol fields in which the source board may differ from the new one.
VERSION_FIELDS = ("version",)


def carry_over(runs: Mapping[str, tuple[RunConfig, str]], protocol: Mapping[str, Any],
               out: Path, source: Path) -> dict[str, str]:
    """Copy each run of the board ``source`` whose rows stay under ``protocol`` into
    ``out/runs``.

    Args:
        runs: variant label -> (its run configuration under ``protocol``, its folder name under
            ``runs/``), the variants of the new board.
        protocol: the new board's protocol (:meth:`~icpbench.harness.protocol.Protocol.as_dict`).
        out: the new board's folder.
        source: the older board's folder (its ``manifest.json`` records its protocol).

    Returns:
        Variant label -> ``"carried over from PATH"``, or why it was not (it has a run in ``out``
        already, ``source`` has none, or the reason its rows would differ, which names the
        setting).

    Raises:
        InputError: ``source`` is not a board, is ``out`` itself, or was made under a protocol
            that differs in more than its version (another domain, scan count, budget, seed or
            ensemble setting: no row of it would be computed again).
    """
    source, out = Path(source), Path(out)
    if source.resolve() == out.resolve():
        raise InputError(f"--carry-over {source}: that is the board being made")
    old = read_manifest(source)
    if old is None or "protocol" not in old:
        raise InputError(f"--carry-over {source}: not a board (no manifest.json recording a "
                         "protocol)")
    diff = [d for d in protocol_differences(old.get("protocol"), protocol)
            if d.split(":")[0] not in VERSION_FIELDS]
    if diff:
        raise InputError(f"--carry-over {source}: a board of another protocol than its version "
                         f"({'; '.join(diff)}); its rows are not this board's")
    done: dict[str, str] = {}
    for label, (rc, slug) in runs.items():
        src, dst = source / "runs" / slug, out / "runs" / slug
        if dst.exists():
            done[label] = "not carried over: this board has its own run"
            continue
        stored = read_manifest(src)
        if stored is None:
            done[label] = f"not carried over: {source} has no run of it"
            continue
        try:
            worker = GridWorker(rc)
            check_resume(src, stored, run_manifest_head(rc, worker), worker)
        except InputError as exc:
            done[label] = f"not carried over: {exc}"
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(src, dst, ignore=shutil.ignore_patterns(LOCK_FILE))
        done[label] = f"carried over from {src}"
    return done
