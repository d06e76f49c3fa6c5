"""HDF5 session files: one file per session, one group per trial, written trial by trial (h5py).

The layout is documented in ``docs/session-format.md``. The rules that make a session survive a crash:

- the file is open for writing only while one trial (or, for the dataset generator, one batch) is written:
  :meth:`SessionWriter.write_trial` opens it, writes the whole trial in one go, marks the trial ``complete`` in the
  ``/plan`` table last, flushes and closes it; between trials the file is closed and consistent;
- the default h5py/HDF5 file format is used (no SWMR), so a writer killed with the file closed leaves nothing
  flagged "already open", and plain ``h5py.File(path, "r")`` opens it;
- the ``/plan`` table holds every trial of the protocol with a status (pending / complete / failed), so an
  interrupted session is resumed from it (:meth:`SessionWriter.open`) and no trial is recorded twice.

Every session stores the sensor that recorded it (root attribute ``sensor_layout``: a
:class:`rigctl.core.sensor.SensorLayout` as JSON; it fixes the channel count, the rate and the ADC resolution of
every trial) and its texture set (``texture_set``: a :class:`rigctl.core.textures.TextureSet` as JSON; the plan's
labels are variable-length UTF-8 strings of that set, never truncated; codes are positions in the set). Files of
schema 1 and 2 (written before both attributes existed) open as the paper's sensor with the texture set of their
plan's labels (``docs/session-format.md``, "Older files").

Data flow: acquisition, the dataset generator and the importers write (:class:`SessionWriter`); encoding, analysis,
the GUI and ``rigctl info`` read (:func:`open_session`).

The module is the public face of five: :mod:`rigctl.storage.session_format` (schema version, ``/plan`` table, trial
status, errors, opening), :mod:`rigctl.storage.session_schema` (decoding the header of every schema, schema 1/2
included), :mod:`rigctl.storage.session_recording` (schema 4: every trial's data back to back under ``/recording``
with a trial index, and the per-trial views), :mod:`rigctl.storage.session_writer` (:class:`SessionWriter`) and
:mod:`rigctl.storage.session_reader` (:class:`SessionReader`, the reader :class:`Session` is built on with the trial
validator, :mod:`rigctl.storage.validate`); import from here.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

from rigctl.core.trial import TrialData
from rigctl.storage.session_format import (
    DEFAULT_SCHEMA_VERSION,
    EVENTS_ATTR,
    PLAN_CHUNK_ROWS,
    PLAN_DTYPE,
    PLAN_FIELDS,
    SCHEMA_VERSION,
    SESSION_KINDS,
    STATUS_ENUM,
    TAXEL_CHUNK_BYTES,
    VLEN_UTF8,
    SessionError,
    SessionLocked,
    SessionWriteError,
    TrialStatus,
    plan_array,
    taxels_description,
    trial_group_name,
)
from rigctl.storage.session_reader import (
    SessionReader,
    TaxelBlock,
)
from rigctl.storage.session_writer import (
    SessionWriter,
)
from rigctl.storage.validate import usable_trials

__all__ = [
    "DEFAULT_SCHEMA_VERSION", "EVENTS_ATTR",
    "PLAN_CHUNK_ROWS", "PLAN_DTYPE", "PLAN_FIELDS", "SCHEMA_VERSION", "SESSION_KINDS", "STATUS_ENUM", "Session",
    "SessionError", "SessionLocked", "SessionReader", "SessionWriteError", "SessionWriter", "TAXEL_CHUNK_BYTES",
    "TaxelBlock", "TrialData", "TrialStatus", "VLEN_UTF8", "open_session", "plan_array", "taxels_description",
    "trial_group_name",
]


class Session(SessionReader):
    """A session file opened read-only (:func:`open_session`): :class:`SessionReader`'s header, trials and checks
    (its docstring says which), and :meth:`iter_trials` over the trials the trial validator finds usable."""

    def iter_trials(self, ids: Sequence[int] | None = None) -> Iterator[TrialData]:
        """Yield :class:`TrialData` of the usable complete trials (the trial validator's,
        :func:`rigctl.storage.validate.usable_trials`: excluded ones are listed in :attr:`problems`), or of ``ids``,
        in plan order. A damaged trial is skipped with a warning naming it (also added to :attr:`problems`)."""
        return super().iter_trials(usable_trials(self).ids if ids is None else ids)

    def usable_trial(self, trial_id: int) -> TrialData:
        """Trial ``trial_id`` read as :meth:`trial` does, if the trial validator finds it usable (a viewer showing
        one trial uses what every command uses). SessionError naming the reason for an excluded trial, KeyError for
        one that is not a complete trial of the session."""
        report = usable_trials(self)
        tid = int(trial_id)
        if tid in report.excluded:
            raise SessionError(f"trial {tid} is excluded: {report.excluded[tid]}; its data are not used")
        if tid not in report.ids:
            raise KeyError(f"trial {tid} is not a complete trial of {self.path.name}")
        return self.trial(tid)


def open_session(path: str | os.PathLike[str]) -> Session:
    """Open a session file read-only (:class:`Session`, which says what it checks).

    Raises
    ------
    FileNotFoundError; SessionError (not HDF5, not a session file, a newer schema, a malformed plan or header);
    rigctl.storage.journal.FileBusy (an OSError: a writer holds the file for long).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    return Session(path)
