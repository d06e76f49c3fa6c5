"""Replay sources: the simulated taxel board streams recorded signals instead of the physical model.

Every source has a ``layout`` (:class:`rigctl.core.sensor.SensorLayout`: channel count, rate, bits), which the
simulated rig gives its virtual Uno (``VirtualUno(layout=...)``): the board announces it in its banner and streams
frames of that channel count at that rate, so the host captures exactly the source's samples.

- :class:`SessionReplay` streams ANY session file (a recorded, simulated or imported one, e.g. from
  ``rigctl import``) at its own rate and layout. It follows the plates the protocol mounts: on :meth:`mount` of
  texture X the stream continues with the session's next trial of texture X, then the following ones of X, in
  plan order, looping over X's trials. Before any mount it plays every complete trial in plan order, looping.
- :class:`FabricSlideReplay` streams the FabricSlide CSV folder (``../shared/data/fabricslide``; a preset: each
  recording resampled onto a 1 ms grid from its timestamps, 16 channels, 10 bits, :mod:`rigctl.storage.fabricslide`),
  one recording after the other in file-name order, looping forever.

``expected_samples(n, start)`` gives the exact samples of the unmounted stream, computed independently of the
streaming state, so a test can prove that what the host recorded equals the source sample for sample.

Trials follow the source's trials and keep its labels: :meth:`begin_trial` (called by the rig as each recorded trial
starts, through :meth:`rigctl.simulation.rig.SimulatedRig.begin_source_trial`) drops the rest of the block being
streamed, so the trial starts at the first sample of the source's next trial (of the mounted plate); with
``continuous=True`` the stream runs on across trials instead. Every block served is logged with its stream
position, so :meth:`provenance` says which source trial (file, trial id, texture, speed, force) and which of its
samples a stretch of the stream holds: the recorded trial's ``source_*`` attributes.

Used by :class:`rigctl.simulation.rig.SimulatedRig` (``source=...``), which pulls ``read(n) -> (n, ch) uint16``
as the simulated clock advances by n sample periods.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet, TextureSetError
from rigctl.storage.fabricslide import (
    DEFAULT_OFFSET,
    DEFAULT_SCALE,
    FABRICSLIDE_SENSOR,
    fabricslide_textures,
    list_files,
    parse_name,
    read_recording,
    recording_adc,
)

__all__ = ["SessionReplay", "FabricSlideReplay", "ReplayShortfall"]


class ReplayShortfall(ValueError):
    """A replayed recording cannot give each planned trial a source trial of its own (too few trials of a texture,
    or none): the run is refused before it starts, or a retry past the source's trials stops (never a source trial
    recorded twice, never another texture's)."""


class _BlockReplay:
    """A looping stream of consecutive blocks ``(m, ch) uint16``; subclasses give the blocks. Thread-safe."""

    layout: SensorLayout
    _blocks: Iterator[np.ndarray]
    _block: np.ndarray  #: the block being read, from sample _pos on
    _pos: int
    textures: TextureSet
    by_texture: dict[str, Any]  #: texture label -> its trials / recordings, in stream order
    mounted: str | None
    mounts: list[tuple[int, str]]  #: ``(stream position, label)`` of every mount

    def __init__(self, loop: bool, continuous: bool = False):
        self.loop = bool(loop)
        self.continuous = bool(continuous)
        #: the source trials (recordings) given to a recorded trial (:meth:`begin_trial`): each is given once
        self._claimed: set[Any] = set()
        #: the texture last mounted when the source has nothing of it (:meth:`mount`), else None
        self.missing: str | None = None
        self._lock = threading.Lock()
        self._restart()
        #: samples handed out by :meth:`read` since construction / :meth:`rewind`
        self.samples_served = 0
        #: ``(stream position of the block's first sample served, the block's source labels)``, in stream order
        self.served_blocks: list[tuple[int, dict[str, Any]]] = []

    def _block_labels(self) -> dict[str, Any]:  # pragma: no cover - abstract
        """The source labels of the block just taken from the iterator (file, trial, texture, speed, force)."""
        raise NotImplementedError

    # -- one source trial per recorded trial (subclasses: the keys of their trials / recordings) ------------------
    def _keys(self, texture: str | None) -> list[Any]:  # pragma: no cover - abstract
        """The source's trials (or recordings) of ``texture`` (None: every one), in stream order."""
        raise NotImplementedError

    def _current_key(self) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def _take(self, key: Any) -> np.ndarray:  # pragma: no cover - abstract
        """Make ``key`` the current trial (its labels for :meth:`_block_labels`) and return its samples."""
        raise NotImplementedError

    def _what(self) -> str:
        return "trials"

    def check_plan(self, textures: list[str]) -> None:
        """Refuse (:class:`ReplayShortfall`, one line naming every shortfall) a plan whose trials this source cannot
        give a source trial each: a texture it has nothing of, or more planned trials of a texture than it has
        (``textures``: the plan's texture per trial). Continuous play (no trial mapping) passes."""
        if self.continuous:
            return
        planned: dict[str, int] = {}
        missing = []
        for texture in textures:
            label = self._label_of(texture)
            if label is None:
                missing.append(texture)
            else:
                planned[label] = planned.get(label, 0) + 1
        short = [f"{label}: {n} planned, {len(self._keys(label))} in the source" for label, n in planned.items()
                 if n > len(self._keys(label))]
        problems = ([self._no_texture(sorted(set(missing))[0]) + (f" (nor of {', '.join(sorted(set(missing))[1:])})"
                                                                   if len(set(missing)) > 1 else "")]
                    if missing else [])
        if short:
            problems.append(f"each planned trial needs {self._what()[:-1]} of its own and the source has too few "
                            f"({'; '.join(short)}): plan fewer trials or replay a larger recording")
        if problems:
            raise ReplayShortfall(f"{self._source_name()}: " + "; ".join(problems))

    def _source_name(self) -> str:
        return str(getattr(self, "path", getattr(self, "directory", "the replay source")))

    def _label_of(self, texture: str) -> str | None:
        if texture in self.by_texture:
            return texture
        try:
            label = self.textures.resolve(texture)
        except TextureSetError:
            return None
        return label if label in self.by_texture else None

    def begin_trial(self) -> int | None:
        """A recorded trial starts: the stream goes on at the first sample of a source trial of the mounted plate
        that no recorded trial has had yet, the one streaming now if so (from its first sample), else the next;
        unless ``continuous``. Returns the stream position of that sample (None: continuous).

        Raises :class:`ReplayShortfall` when every source trial of the plate was recorded once already (a retry past
        the source's trials): a trial is never recorded twice from one source trial."""
        if self.continuous:
            return None
        if self.missing is not None:
            raise ReplayShortfall(f"{self._source_name()}: {self._no_texture(self.missing)}: a trial of "
                                  f"{self.missing} would record another texture's samples")
        with self._lock:
            keys = self._keys(self.mounted)
            cur = self._current_key()
            at = keys.index(cur) if cur in keys else -1
            order = ([cur] if at >= 0 else []) + keys[at + 1:] + keys[:max(at, 0)]
            pick = next((k for k in order if k not in self._claimed), None)
            if pick is None:
                what = f"of {self.mounted}" if self.mounted is not None else ""
                raise ReplayShortfall(f"{self._source_name()}: every source {self._what()[:-1]} {what} was recorded "
                                      "once already; another trial would repeat one (a retry?): replay a larger "
                                      "recording")
            self._claimed.add(pick)
            self._block = self._take(pick)
            self._pos = 0
            self.served_blocks.append((self.samples_served, self._block_labels()))
            self._blocks = self._after(pick, keys)
            return self.samples_served

    def _after(self, pick: Any, keys: list[Any]) -> Iterator[np.ndarray]:
        """The stream after trial ``pick``: ``keys`` from the one after it on, looping (the stream between trials)."""
        i = keys.index(pick)
        while True:
            for key in keys[i + 1:] + (keys[:i + 1] if self.loop else []):
                yield self._take(key)
            if not self.loop:
                return

    def provenance(self, first: int, n: int) -> list[dict[str, Any]]:
        """Which source samples stream positions ``first`` .. ``first + n - 1`` held: one dict per source block
        crossed, its labels plus ``source_first_sample`` / ``source_last_sample`` (inclusive, in the block).
        Raises ValueError for positions not served yet."""
        first, last = int(first), int(first) + int(n) - 1
        if first < 0 or last >= self.samples_served:
            raise ValueError(f"stream samples {first}..{last} were not served (served: {self.samples_served})")
        starts = [p for p, _ in self.served_blocks]
        out = []
        i = max(0, bisect.bisect_right(starts, first) - 1)
        while i < len(self.served_blocks) and self.served_blocks[i][0] <= last:
            p0, labels = self.served_blocks[i]
            end = self.served_blocks[i + 1][0] - 1 if i + 1 < len(self.served_blocks) else self.samples_served - 1
            a, b = max(first, p0), min(last, end)
            if a <= b:
                out.append({**labels, "source_first_sample": a - p0, "source_last_sample": b - p0})
            i += 1
        return out

    def _iter_blocks(self, *, track: bool = True) -> Iterator[np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _iter_texture(self, texture: str) -> Iterator[np.ndarray]:  # pragma: no cover - abstract
        """The blocks of texture ``texture`` (a key of ``by_texture``), from its next one on, looping."""
        raise NotImplementedError

    def _no_texture(self, texture: str) -> str:  # pragma: no cover - abstract
        """The KeyError message for a texture the source has nothing of."""
        raise NotImplementedError

    def mount(self, texture: str) -> None:
        """The protocol mounted plate ``texture`` (a label of the source, or one its texture set resolves): from the
        next sample on, stream that texture's next trial or recording (then its following ones, looping), so a
        trial labelled Denim holds Denim's samples. A texture the source has nothing of raises KeyError."""
        label = texture
        if label not in self.by_texture:
            try:
                label = self.textures.resolve(texture)
            except TextureSetError:
                pass
        if label not in self.by_texture:
            self.missing = texture  # a trial recorded now would hold another texture's samples: begin_trial refuses
            raise KeyError(self._no_texture(texture))
        with self._lock:
            self.missing = None
            self.mounted = label
            self.mounts.append((self.samples_served, label))
            self._restart(self._iter_texture(label))

    def unmount(self) -> None:
        """Back to the unmounted order (a session's plan order, FabricSlide's file-name order), from the first."""
        with self._lock:
            self.mounted = None
            self._restart()

    def _eof(self) -> str:
        return "end of the replayed recordings (loop=False)"

    def read(self, n: int) -> np.ndarray:
        """The next ``n`` samples of the stream: ``(n, layout.n_channels) uint16`` ADC counts.

        Raises EOFError with ``loop=False`` when the recordings are exhausted (the samples up to the end are lost).
        """
        n = int(n)
        out = np.empty((n, self.layout.n_channels), dtype=np.uint16)
        with self._lock:
            filled = 0
            while filled < n:
                if self._pos >= self._block.shape[0]:
                    try:
                        self._block = next(self._blocks)
                    except StopIteration:
                        raise EOFError(self._eof()) from None
                    self._pos = 0
                    self.served_blocks.append((self.samples_served + filled, self._block_labels()))
                    continue
                k = min(n - filled, self._block.shape[0] - self._pos)
                out[filled:filled + k] = self._block[self._pos:self._pos + k]
                self._pos += k
                filled += k
            self.samples_served += n
        return out

    #: alias of :meth:`read`
    next_samples = read

    def __call__(self, n: int) -> np.ndarray:
        return self.read(n)

    def rewind(self) -> None:
        """Start the stream again at its first sample (the unmounted order), every source trial unrecorded."""
        with self._lock:
            self._restart()
            self.samples_served = 0
            self.served_blocks = []
            self._claimed = set()

    def _restart(self, blocks: Iterator[np.ndarray] | None = None) -> None:
        """Stream ``blocks`` (default the unmounted order) from their first sample on."""
        self._blocks = self._iter_blocks() if blocks is None else blocks
        self._block = np.empty((0, self.layout.n_channels), np.uint16)
        self._pos = 0

    def expected_samples(self, n: int, start: int = 0) -> np.ndarray:
        """Samples ``start`` ... ``start + n - 1`` of the unmounted stream, computed afresh (independent of
        :meth:`read`): exactly what :meth:`read` returns for those positions after construction or :meth:`rewind`
        when nothing is mounted. ``(n, layout.n_channels) uint16``."""
        n, start = int(n), int(start)
        out = np.empty((n, self.layout.n_channels), dtype=np.uint16)
        filled, skip = 0, start
        if n == 0:
            return out
        for block in self._iter_blocks(track=False):
            if skip >= block.shape[0]:
                skip -= block.shape[0]
                continue
            k = min(n - filled, block.shape[0] - skip)
            out[filled:filled + k] = block[skip:skip + k]
            filled += k
            skip = 0
            if filled >= n:
                return out
        raise EOFError(f"the recordings hold fewer than {start + n} samples (loop=False)")


class SessionReplay(_BlockReplay):
    """Streams the complete trials of a session file at the session's own rate and layout, following mounts.

    Parameters
    ----------
    path : a session file (any schema ``rigctl.storage.session.open_session`` opens: recorded, simulated,
        imported).
    loop : start again after the last trial (otherwise :meth:`read` raises EOFError at the end).

    Attributes
    ----------
    layout : SensorLayout, the session's sensor (its channel count, rate and bits go on the wire).
    textures : TextureSet, the session's texture set.
    trial_ids : list of int, the complete trials in plan order.
    mounted : str or None, the texture last mounted.
    mounts : list of ``(stream_sample, texture)``: where in the stream (``samples_served`` at the mount) each mount
        took effect; the stream from there is the texture's next trials (:meth:`texture_samples`).
    current_trial : int or None, the trial being streamed.

    Raises
    ------
    FileNotFoundError, rigctl.storage.session.SessionError (not a session), ValueError (no complete trial).
    """

    def __init__(self, path: str | Path, *, loop: bool = True, continuous: bool = False):
        from rigctl.storage.session import open_session
        from rigctl.storage.validate import TrialsExcluded, usable_trials

        self.path = Path(path)
        with open_session(self.path) as s:
            self.layout = s.layout
            self.textures: TextureSet = s.textures
            report = usable_trials(s)  # the one trial validator: a damaged trial is never replayed
            if report.excluded:
                import warnings

                warnings.warn(f"{self.path}: {report.summary()}", TrialsExcluded, stacklevel=2)
            done = set(report.ids)
            plan = s.plan
            self.trial_ids = [int(t) for t in plan["trial_id"] if int(t) in done]
            labels = {int(t): str(x.decode() if isinstance(x, bytes) else x)
                      for t, x in zip(plan["trial_id"], plan["texture"])}
            #: trial id -> (speed_mm_s, force_g) of the source's plan
            self.trial_setpoints = {int(t): (float(v), float(f)) for t, v, f in
                                    zip(plan["trial_id"], plan["speed_mm_s"], plan["force_g"])}
        if not self.trial_ids:
            raise ValueError(f"{self.path}: no usable complete trial to replay"
                             + (f" ({report.summary()})" if report.excluded else ""))
        self.trial_texture = {t: labels[t] for t in self.trial_ids}
        self.by_texture: dict[str, list[int]] = {}
        for t in self.trial_ids:
            self.by_texture.setdefault(self.trial_texture[t], []).append(t)
        self._next_of: dict[str, int] = {}  # texture -> index of its next trial (persists across mounts)
        self._cache: dict[int, np.ndarray] = {}
        self.mounted: str | None = None
        self.mounts: list[tuple[int, str]] = []
        self.current_trial: int | None = None
        super().__init__(loop, continuous)

    def _eof(self) -> str:
        return f"end of the trials of {self.path.name} (loop=False)"

    def _block_labels(self) -> dict[str, Any]:
        t = int(self.current_trial) if self.current_trial is not None else -1
        speed, force = self.trial_setpoints.get(t, (float("nan"), float("nan")))
        return {"source_file": self.path.name, "source_trial_id": t, "source_texture": self.trial_texture.get(t, ""),
                "source_speed_mm_s": speed, "source_force_g": force}

    def trial_samples(self, trial_id: int) -> np.ndarray:
        """The taxels of one trial, ``(n, ch) uint16`` (read once, then cached)."""
        out = self._cache.get(trial_id)
        if out is None:
            from rigctl.storage.session import open_session

            with open_session(self.path) as s:
                out = np.ascontiguousarray(s.trial(int(trial_id)).taxels, dtype=np.uint16)
            self._cache[trial_id] = out
        return out

    def _iter_blocks(self, *, track: bool = True) -> Iterator[np.ndarray]:
        while True:
            for t in self.trial_ids:
                if track:
                    self.current_trial = t
                yield self.trial_samples(t)
            if not self.loop:
                return

    def _iter_texture(self, texture: str) -> Iterator[np.ndarray]:
        ids = self.by_texture[texture]
        while True:
            i = self._next_of.get(texture, 0)
            if i >= len(ids):
                if not self.loop:
                    return
                i = 0
            self._next_of[texture] = i + 1
            self.current_trial = ids[i]
            yield self.trial_samples(ids[i])

    def _no_texture(self, texture: str) -> str:
        return f"{self.path.name} has no trial of texture '{texture}' (it has: {', '.join(self.by_texture)})"

    def _keys(self, texture: str | None) -> list[Any]:
        return list(self.trial_ids if texture is None else self.by_texture[texture])

    def _current_key(self) -> Any:
        return self.current_trial

    def _take(self, key: Any) -> np.ndarray:
        self.current_trial = int(key)
        return self.trial_samples(int(key))

    def texture_samples(self, texture: str, n: int, *, first: int = 0) -> np.ndarray:
        """``n`` samples of texture ``texture``'s trials concatenated in plan order, looping, from its trial index
        ``first``: what the stream holds after a mount (computed afresh). ``(n, ch) uint16``."""
        ids = self.by_texture[texture]
        out = np.empty((int(n), self.layout.n_channels), np.uint16)
        filled, i = 0, int(first)
        while filled < n:
            block = self.trial_samples(ids[i % len(ids)])
            k = min(n - filled, block.shape[0])
            out[filled:filled + k] = block[:k]
            filled += k
            i += 1
        return out


class FabricSlideReplay(_BlockReplay):
    """A looping taxel source streaming FabricSlide recordings at 1 kHz, 16 channels (the preset). Thread-safe.

    Parameters
    ----------
    directory : path
        The FabricSlide subset (``fabric/`` and optionally ``board/``).
    include_board : bool
        Also replay the Board10mm recordings (after the fabrics).
    pattern : str
        Glob of file names to replay (e.g. ``"Canvas_F120_*"``); default all.
    scale, offset : float
        The linear 10-bit map ``adc = clip(rint(counts * scale + offset), 0, 1023)``.
    loop : bool
        Start again at the first recording after the last one (otherwise :meth:`read` raises EOFError at the end).

    Attributes
    ----------
    layout : :data:`rigctl.storage.fabricslide.FABRICSLIDE_SENSOR` (16 channels, 1 kHz, 10 bits)
    textures : the FabricSlide texture set
    files : list of Path, the replayed files, in order.

    Raises
    ------
    FileNotFoundError
        If the directory has no ``fabric/`` folder or no file matches ``pattern``.
    """

    layout = FABRICSLIDE_SENSOR

    def __init__(self, directory: str | Path, *, include_board: bool = False, pattern: str = "*.csv",
                 scale: float = DEFAULT_SCALE, offset: float = DEFAULT_OFFSET, loop: bool = True,
                 continuous: bool = False):
        self.directory = Path(directory)
        self.files = list_files(self.directory, include_board=include_board, pattern=pattern)
        if not self.files:
            raise FileNotFoundError(f"no FabricSlide files matching {pattern!r} under {self.directory}")
        self.textures = fabricslide_textures(parse_name(p.name)["label"] for p in self.files)
        self.scale, self.offset = float(scale), float(offset)
        self.current_file: Path | None = None
        #: texture -> its files in replay order (a mount streams these)
        self.by_texture: dict[str, list[Path]] = {}
        for p in self.files:
            self.by_texture.setdefault(parse_name(p.name)["label"], []).append(p)
        self._next_of: dict[str, int] = {}
        self.mounted: str | None = None
        self.mounts: list[tuple[int, str]] = []
        super().__init__(loop, continuous)

    def _eof(self) -> str:
        return "end of the FabricSlide recordings (loop=False)"

    def _block_labels(self) -> dict[str, Any]:
        if self.current_file is None:
            return {}
        name = parse_name(self.current_file.name)
        return {"source_file": self.current_file.name, "source_texture": name["label"],
                "source_speed_mm_s": abs(name["velocity_mm_s"]), "source_velocity_mm_s": name["velocity_mm_s"],
                "source_force_setpoint": name["force_setpoint"], "source_repeat": name["repeat"]}

    def _iter_texture(self, texture: str) -> Iterator[np.ndarray]:
        files = self.by_texture[texture]
        while True:
            i = self._next_of.get(texture, 0)
            if i >= len(files):
                if not self.loop:
                    return
                i = 0
            self._next_of[texture] = i + 1
            self.current_file = files[i]
            yield self._adc(files[i])

    def _no_texture(self, texture: str) -> str:
        return f"no FabricSlide recording of texture '{texture}' here (there are: {', '.join(self.by_texture)})"

    def _what(self) -> str:
        return "recordings"

    def _keys(self, texture: str | None) -> list[Any]:
        return list(self.files if texture is None else self.by_texture[texture])

    def _current_key(self) -> Any:
        return self.current_file

    def _take(self, key: Any) -> np.ndarray:
        self.current_file = key
        return self._adc(key)

    def _adc(self, path: Path) -> np.ndarray:
        return recording_adc(read_recording(path), scale=self.scale, offset=self.offset)

    def _iter_blocks(self, *, track: bool = True) -> Iterator[np.ndarray]:
        while True:
            for path in self.files:
                if track:
                    self.current_file = path
                yield self._adc(path)
            if not self.loop:
                return

    def recording_lengths(self) -> list[int]:
        """Samples of each file at 1 kHz (in replay order)."""
        return [self._adc(p).shape[0] for p in self.files]
