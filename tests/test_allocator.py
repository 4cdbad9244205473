"""icpbench.learning.allocator: the opt-in glibc setting that keeps freed memory in the process."""

import platform

import pytest
import torch

from icpbench.learning.allocator import retain_freed_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_retain_freed_memory_applies_and_changes_no_result():
    x = torch.randn(1000, 64, generator=torch.Generator().manual_seed(0))
    before = (x @ x.T).sum()
    assert retain_freed_memory() is True
    assert retain_freed_memory() is True  # idempotent
    assert torch.equal((x @ x.T).sum(), before)
