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
def test_random_operations_match_a_plain_buffer(tmp_path, seed, monkeypatch):
    """(Odd seeds: the overlay starts from a buffer of new bytes an earlier one used, full of other bytes.)"""
    from rigctl.storage import journal

    rng = np.random.default_rng(seed)
    monkeypatch.setattr(journal, "_SPARE_TAILS", [bytearray(b"\xee" * int(rng.integers(1, 8 * PAGE)))]
                        if seed % 2 else [], raising=False)
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


def test_the_next_overlay_takes_the_last_ones_buffer_of_new_bytes(tmp_path, monkeypatch):
    """Issue 57 item 6: the buffer an overlay grew for its new bytes (a dataset generator's batch: ~55 MB, grown by
    HDF5's chunk-sized writes into fresh pages, ~0.2 ms a trial) is handed to the next overlay, emptied: the second
    commit appends exactly its own bytes (none of the first's), a gap it leaves reads as zeros, and a buffer above
    SPARE_TAIL_MAX_BYTES is not kept."""
    from rigctl.storage import journal

    monkeypatch.setattr(journal, "_SPARE_TAILS", [])
    path = tmp_path / "f.bin"
    path.write_bytes(b"head")
    ov = OverlayFile(path, durable=False)
    ov.seek(4)
    ov.write(b"\xaa" * (3 * PAGE))
    ov.commit()
    buffer = ov._tail
    ov.close()
    assert journal._SPARE_TAILS == [buffer] and len(buffer) >= 3 * PAGE
    ov = OverlayFile(path, durable=False)
    assert ov._tail is buffer and journal._SPARE_TAILS == []
    ov.seek(4 + 3 * PAGE + 10)  # 10 bytes of gap, then 5 written
    ov.write(b"\x01" * 5)
    gap = bytearray(15)
    ov.seek(4 + 3 * PAGE)
    assert ov.readinto(gap) == 15 and bytes(gap) == bytes(10) + b"\x01" * 5
    ov.commit()
    ov.close()
    assert path.read_bytes() == b"head" + b"\xaa" * (3 * PAGE) + bytes(10) + b"\x01" * 5
    monkeypatch.setattr(journal, "SPARE_TAIL_MAX_BYTES", PAGE)
    journal._SPARE_TAILS.clear()
    ov = OverlayFile(path, durable=False)
    ov.seek(0, 2)
    ov.write(b"\x02" * (2 * PAGE))
    ov.commit()
    ov.close()
    assert journal._SPARE_TAILS == []
