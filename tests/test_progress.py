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


def test_time_left_waits_for_a_work_item_and_leaves_start_up_out():
    """With ``warmup`` units (one work item per worker) the line says it is estimating until
    they are done; the rate then runs from the first unit back, so a slow start-up does not
    inflate the time left."""
    out, clock = io.StringIO(), _Clock()
    p = RunProgress(total=100, desc="icpbench run", stream=out, clock=clock, warmup=40)
    clock.t += 120.0  # start-up: nothing comes back for two minutes
    for _ in range(30):
        clock.t += 2.0
        p.update()
    assert p.status().endswith("estimating the time left")
    assert out.getvalue().splitlines()[-1].endswith("estimating the time left")  # the line says so
    for _ in range(20):
        clock.t += 2.0
        p.update()
    # 49 units in 98 s since the first came back: 0.5 units/s, 50 left, 100 s (not 220 s / 50)
    assert p.status() == "50/100 units (50%), 0.5 units/s, about 2 min left", p.status()


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
