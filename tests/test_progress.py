"""A run that talks: a bar on a terminal, one line per minute off a terminal."""

import io

from icpbench.harness.progress import RunProgress


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_one_line_per_minute_with_rate_and_time_left_off_a_terminal():
    out, clock = io.StringIO(), _Clock()
    p = RunProgress(total=100, done=10, desc="icpbench run", stream=out, clock=clock)
    for _ in range(30):  # 30 units in 90 s: a line at 60 s only
        clock.t += 3.0
        p.update()
    lines = out.getvalue().splitlines()
    assert lines == ["icpbench run: 100 units, 10 already done",
                     "icpbench run: 30/100 units (30%), 0.333 units/s, about 4 min left"]
    for _ in range(60):
        clock.t += 3.5
        p.update()
    p.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 + 4 + 1  # start, at most one line a minute (over 300 s), the last line
    assert lines[-1] == "icpbench run: 100/100 units done in 5 min"


def test_a_bar_on_a_terminal_and_silence_when_quiet():
    tty = _Tty()
    p = RunProgress(total=8, stream=tty, unit="unit")
    p.update(4)
    p.write("warning: skipped sample x: bad file")
    p.close()
    text = tty.getvalue()
    assert "4/8" in text and "unit/s" in text  # units done and rate (tqdm adds time left)
    assert "warning: skipped sample x: bad file" in text
    quiet = io.StringIO()
    q = RunProgress(total=8, stream=quiet, enabled=False)
    q.update(8)
    q.write("warning: still shown")
    q.close()
    assert quiet.getvalue() == "warning: still shown\n"
