"""rigctl.encoding.sizing.available_memory_bytes: the memory ``rigctl encode`` sizes its batch against is what the
kernel can give, page cache included, not the free pages alone (which a machine that has just written a large file,
the paper's dataset, has almost none of)."""

from __future__ import annotations

import pytest

from rigctl.encoding.sizing import available_memory_bytes


def _meminfo_kb(name: str) -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith(name + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def test_the_memory_available_is_the_kernels_memavailable_page_cache_included():
    if _meminfo_kb("MemAvailable") is None:
        pytest.skip("no MemAvailable in /proc/meminfo (not Linux 3.14+)")
    got = available_memory_bytes()
    want = _meminfo_kb("MemAvailable") * 1024
    assert got is not None and abs(got - want) <= 0.05 * want + (64 << 20)
    free, cached = _meminfo_kb("MemFree") * 1024, _meminfo_kb("Cached") * 1024
    assert got >= free  # the page cache is counted: MemAvailable >= the free pages (old: the free pages alone)
    if cached > (1 << 30) and want > free + (1 << 30):  # a machine with a large page cache (after writing a dataset)
        assert got > free + (512 << 20)
