"""Benchmark settings: one torch thread (threads are chosen deliberately on small CPUs; README,
"Conventions") and a terminal summary of the speed ratios that ``bench_icp.py`` records."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)

#: (case, phase) -> ratio of our median time to Open3D's median time, filled by bench_icp.py.
RATIOS: dict[tuple[str, str], dict[str, float]] = {}


@pytest.fixture(scope="session")
def ratios() -> dict[tuple[str, str], dict[str, float]]:
    return RATIOS


def pytest_terminal_summary(terminalreporter) -> None:
    if not RATIOS:
        return
    tr = terminalreporter
    tr.section("p2plane vs Open3D registration_icp (medians, equal iterations)")
    tr.write_line(f"{'case':<28} {'phase':<14} {'ours ms':>9} {'open3d ms':>10} {'ratio':>7}")
    for (case, phase), r in RATIOS.items():
        tr.write_line(f"{case:<28} {phase:<14} {1e3 * r['ours_s']:>9.1f} {1e3 * r['open3d_s']:>10.1f} "
                      f"{r['ratio']:>7.2f}")
