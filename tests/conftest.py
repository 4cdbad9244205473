"""Shared test settings: one torch thread (measured 5-17x faster than 2 on this 2-core VM for
small tensors) and a per-session dataset cache."""

import os

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="session")
def _cache_dir(tmp_path_factory):
    if "ICPBENCH_CACHE" not in os.environ:
        os.environ["ICPBENCH_CACHE"] = str(tmp_path_factory.mktemp("icpbench-cache"))
    yield
