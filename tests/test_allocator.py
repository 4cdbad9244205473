"""icpbench.learning.allocator: the glibc setting that keeps freed memory in the process (training
turns it on)."""

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


def test_training_turns_it_on_unless_the_environment_says_no(monkeypatch):
    from icpbench.learning import allocator

    calls = []
    monkeypatch.setattr(allocator, "retain_freed_memory", lambda: calls.append(1) or True)
    for off in ("0", "false", "No", " off "):
        monkeypatch.setenv(allocator.KEEP_FREED_MEMORY_ENV, off)
        assert allocator.retain_for_training() is False
    assert calls == []
    for on in ("1", "yes", ""):
        monkeypatch.setenv(allocator.KEEP_FREED_MEMORY_ENV, on)
        assert allocator.retain_for_training() is True
    monkeypatch.delenv(allocator.KEEP_FREED_MEMORY_ENV)
    assert allocator.retain_for_training() is True
    assert calls == [1, 1, 1, 1]
