"""radarslam.memory: the heap's free pages go back to the system where the C library can."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from radarslam import memory


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1e3
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_freed_heap_pages_go_back_to_the_system():
    if memory._malloc_trim() is None:
        pytest.skip("this C library has no malloc_trim (not glibc)")
    # many blocks below the mmap threshold, every other one kept: the freed half stays in the
    # heap between the kept ones until it is trimmed
    blocks = [np.ones(2_000, np.float64) for _ in range(20_000)]  # 16 kB each, 320 MB
    kept = blocks[::2]
    del blocks
    before = _rss_mb()
    assert memory.release_free_memory() is True
    after = _rss_mb()
    assert before - after > 100.0, (before, after)
    assert all(float(k[0]) == 1.0 for k in kept[:: len(kept) // 10])


def test_no_trim_where_the_c_library_has_none(monkeypatch):
    monkeypatch.setattr(memory, "_malloc_trim", lambda: None)
    assert memory.release_free_memory() is False
