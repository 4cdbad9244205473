"""File names built from user text (dataset settings, attack names, sequence names).

Every user string that becomes part of a path goes through :func:`safe_component` (for a file
that icpbench writes) or :func:`plain_name` (for a folder or file it reads by name), so that text
such as ``../../x`` or ``a/b`` can neither write nor read outside the folder it belongs in.
"""

from __future__ import annotations

import re

from icpbench.core.errors import InputError

_UNSAFE = re.compile(r"[^A-Za-z0-9._+=-]+")


def safe_component(text: object) -> str:
    """``text`` as one file-name component: every run of characters other than letters, digits
    and ``. _ + = -`` becomes ``_``, and leading dots are dropped (no ``..``, no hidden files,
    no separators). Distinct plain names stay distinct; the empty result is ``_``."""
    out = _UNSAFE.sub("_", str(text)).lstrip(".")
    return out or "_"


def plain_name(text: object, what: str) -> str:
    """``text`` if it is a plain name (one path component, not ``.`` or ``..``).

    Raises:
        InputError: it holds a path separator, is empty, or is ``.``/``..``; ``what`` names the
            setting in the message.
    """
    s = str(text)
    if not s.strip() or s in (".", "..") or "/" in s or "\\" in s or "\0" in s:
        raise InputError(f"{what} must be a plain name (no '/', not '.' or '..'), got {s!r}")
    return s
