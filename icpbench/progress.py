"""One progress-bar factory for every loop a person waits for (tqdm; silent off a TTY)."""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm


def progress_bar(*, disable: bool = False, **kw: Any) -> tqdm:
    """A tqdm bar that is disabled when ``disable`` is set or stderr is not a terminal."""
    return tqdm(disable=disable or not sys.stderr.isatty(), dynamic_ncols=True, **kw)
