"""OverlayFile (the file object HDF5 writes through) behaves like a plain file: random writes, reads and
truncations across the old end of file, then a commit, give the same bytes as the same operations on a reference
bytearray; nothing reaches the disk before the commit."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.storage.journal import PAGE, OverlayFile, journal_path


def _truncated(ref: bytearray, size: int) -> bytearray:
    return ref[:size] + bytearray(max(0, size - len(ref)))


@pytest.mark.parametrize("seed", range(8))
def test_random_operations_match_a_plain_buffer(tmp_path, seed):
    rng = np.random.default_rng(seed)
    path = tmp_path / "f.bin"
    old = rng.integers(0, 256, int(rng.integers(0, 5 * PAGE)), dtype=np.uint8).tobytes()
    path.write_bytes(old)
    ref = bytearray(old)
    ov = OverlayFile(path, durable=False)
    try:
        for _ in range(300):
            op = rng.choice(["write", "write", "write", "read", "truncate"], p=[0.3, 0.2, 0.2, 0.25, 0.05])
            size = len(ref)
            if op == "write":
                pos = int(rng.integers(0, size + 2 * PAGE + 1))
                data = rng.integers(0, 256, int(rng.integers(1, 3 * PAGE)), dtype=np.uint8).tobytes()
                ov.seek(pos)
                assert ov.write(data) == len(data)
                ref = _truncated(ref, max(len(ref), pos))
                ref[pos:pos + len(data)] = data
            elif op == "read":
                pos = int(rng.integers(0, size + PAGE + 1))
                n = int(rng.integers(0, 3 * PAGE))
                ov.seek(pos)
                buf = bytearray(n)
                got = ov.readinto(buf)
                assert got == max(0, min(n, size - pos))
                assert bytes(buf[:got]) == bytes(ref[pos:pos + got])
            else:
                new = int(rng.integers(0, size + PAGE + 1))
                ov.truncate(new)
                ref = _truncated(ref, new)
            ov.seek(0, 2)
            assert ov.tell() == len(ref)
        assert path.read_bytes() == old  # nothing on disk before the commit
        ov.commit()
    finally:
        ov.close()
    assert path.read_bytes() == bytes(ref)
    assert not journal_path(path).exists()
