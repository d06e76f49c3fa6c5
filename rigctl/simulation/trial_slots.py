"""Rendered trials from worker processes to the writing process through shared memory, not through pipes.

The dataset generator's writer is its slower half, and receiving a pickled trial through a ``multiprocessing``
pipe (about 180 kB: taxels, sequence numbers, flags, host times) cost it about a third of its time. Here the
workers write the per-sample arrays into slots of one memory-mapped file (in ``/dev/shm`` where it exists) and send
only the slot number and the small parts (force and speed traces, attributes, and what an optional ``prepare``
function computed from the trial in the worker: the dataset generator's trial facts and per-taxel extremes, work
the writer need not do). The writer reads the arrays in place and hands the slot back once the trial is written.

A slot's size follows the sensor: ``slot_samples x`` :func:`sample_bytes` ``(layout.n_channels)``.

Flow: :class:`TrialSlots` owns the file; :func:`init_worker_slots` (a pool initializer) maps it in a worker;
:func:`render_into_slots` (the worker task) renders a block of plan rows into a block of slots;
:meth:`TrialSlots.results` keeps the workers busy with blocks and yields ``(trial_id, TrialData, prepared)`` in plan
order.
"""

from __future__ import annotations

import collections
import copy
import glob
import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.trial import TrialData
from rigctl.core.worker_signals import worker_ignores_ctrl_c

_STATE: dict = {}


def sample_bytes(n_channels: int) -> int:
    """Bytes per sample in a slot: taxels (``n_channels`` x uint16), seq (uint16), flags (uint8), host time
    (float64); 47 for the paper's 18 taxels."""
    return 2 * int(n_channels) + 2 + 1 + 8


def _views(mm: np.ndarray, slot: int, slot_samples: int, n: int, n_channels: int):
    base = slot * slot_samples * sample_bytes(n_channels)
    cut = [base]
    for width in (2 * n_channels, 8, 2, 1):  # taxels, host time, seq, flags (8-byte alignment first)
        cut.append(cut[-1] + width * slot_samples)
    taxels = mm[cut[0]:cut[0] + 2 * n_channels * n].view(np.uint16).reshape(n, n_channels)
    host = mm[cut[1]:cut[1] + 8 * n].view(np.float64)
    seq = mm[cut[2]:cut[2] + 2 * n].view(np.uint16)
    flags = mm[cut[3]:cut[3] + n]
    return taxels, seq, flags, host


def init_worker_slots(path: str, n_slots: int, slot_samples: int, n_channels: int, render: Callable,
                      init: Callable, init_args: tuple, prepare: Callable[[TrialData], Any] | None = None) -> None:
    """Pool initializer: map the slot file, remember the render function, run the model's own initializer.
    ``path, n_slots, slot_samples, n_channels`` are :attr:`TrialSlots.initargs`. ``prepare``: called in the worker
    with each rendered trial as the writer will see it (its per-sample arrays the slot's), its result handed over
    with the trial (picklable; None without ``prepare``)."""
    worker_ignores_ctrl_c()  # Ctrl-C is the parent's: it stops the pool, no worker traceback (rigctl.core.worker_signals)
    size = n_slots * slot_samples * sample_bytes(n_channels)
    # a plain ndarray over the map (its views then skip np.memmap's Python __array_finalize__: ~24 us a trial)
    _STATE.update(mm=np.memmap(path, dtype=np.uint8, mode="r+", shape=(size,)).view(np.ndarray),
                  slot_samples=slot_samples,
                  n_channels=int(n_channels), render=render, prepare=prepare)
    init(*init_args)


def render_into_slots(task: tuple[Sequence[int], Sequence[tuple]]) -> list[tuple]:
    """Worker task: render plan rows into slots; returns per trial ``(trial_id, slot, n, small, prepared)``, where
    ``small`` holds the traces and attributes, or ``(trial_id, None, 0, data, prepared)`` for a trial too long for a
    slot; ``prepared`` is what the initializer's ``prepare`` returned for the trial (None without one).

    Raises ValueError if a rendered trial's channel count is not the slots' (the sensor of :class:`TrialSlots`).
    """
    slots, rows = task
    out: list[tuple] = []
    n_ch = _STATE["n_channels"]
    prepare = _STATE.get("prepare")
    for slot, row in zip(slots, rows):
        trial_id, data = _STATE["render"](row)
        if data.layout.n_channels != n_ch:
            raise ValueError(f"trial {trial_id} was rendered with {data.layout.n_channels} channels; the slots hold "
                             f"{n_ch} (TrialSlots(layout=...) must be the model's sensor)")
        n = data.n_samples
        if n > _STATE["slot_samples"]:
            out.append((trial_id, None, 0, data, None if prepare is None else prepare(data)))
            continue
        taxels, seq, flags, host = _views(_STATE["mm"], slot, _STATE["slot_samples"], n, n_ch)
        taxels[...] = data.taxels
        seq[...] = data.seq
        flags[...] = data.flags
        host[...] = data.host_time_s
        prepared = None
        if prepare is not None:  # from the slot's bytes, which the writer reads (no __post_init__: checked above)
            seen = copy.copy(data)
            seen.taxels, seen.seq, seen.flags, seen.host_time_s = taxels, seq, flags, host
            prepared = prepare(seen)
        small = dict(force_g=data.force_g, force_time_s=data.force_time_s, speed_mm_s=data.speed_mm_s,
                     speed_time_s=data.speed_time_s, dropped_frames=data.dropped_frames,
                     crc_errors=data.crc_errors, attrs=data.attrs)
        out.append((trial_id, slot, n, small, prepared))
    return out


def remove_stale_slot_files(directory: str | None = None) -> list[str]:
    """Delete slot files left by generator processes that no longer run (killed with SIGKILL, which leaves no
    chance to clean up); the creating process id is in the name. Returns the deleted paths."""
    directory = directory or tempfile.gettempdir()
    removed = []
    for path in glob.glob(os.path.join(directory, "rigctl-trials-*-*.slots")):
        try:
            pid = int(os.path.basename(path).split("-")[2])
            os.kill(pid, 0)  # raises if no such process
        except ProcessLookupError:
            try:
                os.unlink(path)
                removed.append(path)
            except FileNotFoundError:
                pass
        except (ValueError, IndexError, PermissionError):  # not ours, or another user's live process
            continue
    return removed


class TrialSlots:
    """A memory-mapped file of ``n_blocks`` x ``block`` slots of ``slot_samples`` samples each.

    Parameters
    ----------
    slot_samples : samples a slot holds (longer trials are sent through the pipe instead).
    n_blocks, block : blocks in flight and plan rows per block (one worker task).
    directory : where the file lives (default ``/dev/shm`` if it exists, else the temp directory); it is
        deleted by :meth:`close`.
    layout : the sensor the trials come from (default the paper's 3x3x2): a slot holds ``layout.n_channels``
        taxels per sample, and the trials :meth:`results` yields carry this layout.
    """

    def __init__(self, slot_samples: int, n_blocks: int, block: int, directory: str | None = None, *,
                 layout: SensorLayout = PAPER_SENSOR):
        if directory is None:
            directory = "/dev/shm" if os.path.isdir("/dev/shm") else None
        self.layout = layout
        self.n_channels = layout.n_channels
        self.slot_samples = max(1, int(slot_samples))
        self.n_blocks, self.block = int(n_blocks), int(block)
        n_slots = self.n_blocks * self.block
        remove_stale_slot_files(directory)
        fd, self.path = tempfile.mkstemp(prefix=f"rigctl-trials-{os.getpid()}-", suffix=".slots", dir=directory)
        try:
            os.ftruncate(fd, n_slots * self.slot_samples * sample_bytes(self.n_channels))
        finally:
            os.close(fd)
        self._mm: np.memmap | None = np.memmap(self.path, dtype=np.uint8, mode="r+")
        self.initargs = (self.path, n_slots, self.slot_samples, self.n_channels)

    def results(self, pool, rows: Sequence[tuple]) -> Iterator[tuple[int, TrialData, Any]]:
        """Render ``rows`` on ``pool`` (initialised with :func:`init_worker_slots`); yield ``(trial_id, TrialData,
        prepared)`` in plan order (``prepared``: the initializer's ``prepare`` of the trial, None without one). A
        trial's arrays live in its slot until the caller asks for the next trial: write it (or copy it) before that.
        Raises ValueError once closed."""
        if self._mm is None:
            raise ValueError(f"the trial slots {self.path} are closed")
        mm = self._mm.view(np.ndarray)  # (a plain ndarray over the map: its views skip np.memmap's Python hooks)
        free = collections.deque(range(self.n_blocks))
        pending: collections.deque = collections.deque()
        starts = iter(range(0, len(rows), self.block))

        def submit() -> bool:
            k = next(starts, None)
            if k is None:
                return False
            b = free.popleft()
            part = rows[k:k + self.block]
            slots = list(range(b * self.block, b * self.block + len(part)))
            pending.append((b, pool.apply_async(render_into_slots, ((slots, part),))))
            return True

        while free and submit():
            pass
        while pending:
            b, result = pending.popleft()
            for trial_id, slot, n, small, prepared in result.get():
                if slot is None:
                    yield trial_id, small, prepared
                    continue
                taxels, seq, flags, host = _views(mm, slot, self.slot_samples, n, self.n_channels)
                yield trial_id, TrialData(taxels=taxels, seq=seq, flags=flags, host_time_s=host, layout=self.layout,
                                          **small), prepared
            free.append(b)  # the caller has written every trial of the block
            submit()

    def close(self) -> None:
        """Unmap and delete the slot file."""
        mm, self._mm = self._mm, None
        del mm
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass

    def __enter__(self) -> "TrialSlots":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
