"""Benchmark settings: one torch thread (threads are chosen deliberately on small CPUs; README,
"Conventions"), no cached computation, and a terminal summary of the speed ratios that the
benchmarks record.

A benchmark times computation: the ICP forward-pass cache (``icpbench.targets.forward_cache``,
which in a run hands back the result of a scan registered before) is disabled for every benchmark
and checked to hold nothing afterwards, so no timed round can be a cache hit; each benchmark's
``extra_info`` says so (``forward_cache: disabled``). Before 2026-11-27 it was on, and the
``forward`` phase of ``bench_icp.py`` timed the cache from the second round on (1 ms against
Open3D's 500 ms for the 10k-point scan).
"""

from __future__ import annotations

import pytest
import torch

from icpbench.targets import forward_cache

torch.set_num_threads(1)

#: (case, phase) -> our median time, Open3D's median time and their ratio, filled by the benches.
RATIOS: dict[tuple[str, str], dict[str, float]] = {}


@pytest.fixture(autouse=True)
def no_forward_cache(request):
    """Every benchmark runs with the ICP forward-pass cache off, and must leave it empty."""
    forward_cache.clear()
    if "benchmark" in request.fixturenames:
        request.getfixturevalue("benchmark").extra_info["forward_cache"] = "disabled"
    with forward_cache.disabled():
        yield
    assert forward_cache.size() == 0, "a benchmark stored an ICP result: later rounds could hit it"


@pytest.fixture(scope="session")
def ratios() -> dict[tuple[str, str], dict[str, float]]:
    return RATIOS


def pytest_terminal_summary(terminalreporter) -> None:
    if not RATIOS:
        return
    tr = terminalreporter
    tr.section("ratios to Open3D registration_icp measured in the same run (medians)")
    tr.write_line(f"{'case':<28} {'phase':<16} {'ours ms':>9} {'open3d ms':>10} {'ratio':>7}")
    for (case, phase), r in RATIOS.items():
        extra = f"  ({r['scans_per_s']:.2f} scans/s)" if "scans_per_s" in r else ""
        tr.write_line(f"{case:<28} {phase:<16} {1e3 * r['ours_s']:>9.1f} {1e3 * r['open3d_s']:>10.1f} "
                      f"{r['ratio']:>7.2f}{extra}")
    base = next((r for (c, ph), r in RATIOS.items() if ph == "train-1proc-no-retain"), None)
    if base is not None:
        tr.write_line("training throughput relative to train-1proc-no-retain (same run):")
        for (_case, phase), r in RATIOS.items():
            if "scans_per_s" in r and phase.startswith("train"):
                tr.write_line(f"  {phase:<28} {r['scans_per_s'] / base['scans_per_s']:.2f}x")
