"""Progress for every loop a person waits for.

On a terminal: a tqdm bar (units done, rate, time left). Off a terminal (CI, a log file): one plain
line per minute, ``icpbench run: 120/1200 units (10%), 0.52 units/s, about 35 min left``, so a log
shows that a long run is alive without filling up with bar redraws.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from tqdm.auto import tqdm


def progress_bar(*, disable: bool = False, **kw: Any) -> tqdm:
    """A tqdm bar that is disabled when ``disable`` is set or stderr is not a terminal."""
    return tqdm(disable=disable or not sys.stderr.isatty(), dynamic_ncols=True, **kw)


def _duration(seconds: float) -> str:
    """``42 s``, ``7 min``, ``2.5 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class RunProgress:
    """Progress of ``total`` units, ``done`` of which were finished before (resumed runs).

    Args:
        total: units in the whole job.
        done: units already finished when it starts (counted, but not in the rate).
        desc: what is running (the start of every line).
        unit: the unit's name (singular).
        enabled: False = silent (``--quiet``).
        stream: where to write (default stderr). A bar when it is a terminal, else log lines.
        interval_s: seconds between log lines off a terminal.
        clock: monotonic clock in seconds (tests pass a fake one).
    """

    def __init__(self, total: int, *, done: int = 0, desc: str = "icpbench", unit: str = "unit",
                 enabled: bool = True, stream: TextIO | None = None, interval_s: float = 60.0,
                 clock: Callable[[], float] = time.monotonic, warmup: int = 1) -> None:
        self.total, self.done, self.start_done = int(total), int(done), int(done)
        self.warmup = max(1, int(warmup))
        self.desc, self.unit, self.enabled = desc, unit, enabled
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s, self.clock = float(interval_s), clock
        self.t0 = self.last = clock()
        self.first_t: float | None = None  # when the first unit came back, and units done then
        self.first_done = self.done
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar = (tqdm(total=self.total, initial=self.done, desc=desc, unit=unit,
                         file=self.stream, dynamic_ncols=True, smoothing=0.1)
                    if enabled and tty else None)
        if enabled and self.bar is None:
            self._line(f"{self.total} {unit}s, {self.done} already done" if self.done
                       else f"{self.total} {unit}s")

    def _line(self, text: str) -> None:
        print(f"{self.desc}: {text}", file=self.stream, flush=True)

    def status(self) -> str:
        """``done/total units (pct), rate, time left`` (rate over the units computed here).

        The time left is shown once ``warmup`` units were computed here (e.g. one work item's
        units: cheap and expensive units then weigh as they will over the run), from the rate
        since the first unit came back; before that the line says it is still estimating."""
        new = self.done - self.start_done
        pct = 100.0 * self.done / self.total if self.total else 100.0
        text = f"{self.done}/{self.total} {self.unit}s ({pct:.0f}%)"
        if new >= self.warmup and self.done > self.first_done:
            # the rate since the first unit came back: start-up (process and cluster start,
            # dataset generation, the first batch's maps) is not work the rest of the run repeats
            rate = (self.done - self.first_done) / max(self.clock() - self.first_t, 1e-9)
            left = (self.total - self.done) / rate
            text += f", {rate:.3g} {self.unit}s/s, about {_duration(left)} left"
        elif self.done < self.total:
            text += ", estimating the time left"
        return text

    def update(self, n: int = 1) -> None:
        """``n`` more units are done."""
        self.done += n
        if self.first_t is None:
            self.first_t, self.first_done = self.clock(), self.done
        if self.bar is not None:
            self.bar.update(n)
        elif self.enabled and self.clock() - self.last >= self.interval_s:
            self.last = self.clock()
            self._line(self.status())

    def write(self, text: str) -> None:
        """A message (e.g. a warning) that does not break the bar; written even when quiet."""
        if self.bar is not None:
            self.bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def close(self) -> None:
        """Close the bar, or write the final line (units done and wall time)."""
        if self.bar is not None:
            self.bar.close()
        elif self.enabled:
            self._line(f"{self.done}/{self.total} {self.unit}s done in "
                       f"{_duration(self.clock() - self.t0)}")
