"""The allocator setting of the diagnosis: freed large blocks stay with the process inside the
block and are given back after it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from recon.diagnose.allocator import _glibc, reuse_freed_memory

BLOCK = 256 * 1024 * 1024  # well above glibc's largest mmap threshold (32 MiB)


def resident_bytes() -> int:
    """This process's resident memory (Linux /proc)."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(_glibc() is None, reason="glibc's mallopt only")
def test_freed_blocks_are_kept_inside_and_given_back_after():
    with reuse_freed_memory() as applied:
        assert applied
        block = torch.ones(BLOCK // 4)
        touched = resident_bytes()
        del block
        kept = resident_bytes()
        # Served from the heap and not trimmed: freeing it does not unmap it (the next large
        # tensor can take its pages without faulting them in).
        assert kept > touched - BLOCK // 2
    # Afterwards the defaults are back and the freed memory is returned.
    assert resident_bytes() < kept - BLOCK // 2
    outside = torch.ones(BLOCK // 4)
    assert float(outside[-1]) == 1.0


def test_without_glibc_nothing_changes(monkeypatch):
    import recon.diagnose.allocator as allocator

    monkeypatch.setattr(allocator, "_glibc", lambda: None)
    with reuse_freed_memory() as applied:
        assert not applied
        assert float(torch.ones(4).sum()) == 4.0
