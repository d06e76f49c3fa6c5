"""A recording's own time stamps (a CSV's time column), by declaration (issue 77 item 2): the one home of the unit
names rigctl knows, the checks made before any allocation, and the regridding onto an even rate.

- **The unit is declared or known, never guessed**: ``--time-unit`` (s, ms, us, ns) or a name rigctl knows
  (:func:`unit_of_name`: ``time``, ``timestamp``, ``t``, ``seconds``, ``time_s`` are seconds; ``time_ms``,
  ``millis``, ``Time (ms)`` milliseconds; ``time_us``, ``micros`` microseconds; ``time_ns``, ``nanos``
  nanoseconds). A time column of another name without ``--time-unit``, or a name that says another unit than the
  option, is refused (:class:`TimeColumnError`, a usage error).
- **A counter is not a taxel**: a column of whole numbers that rises at every row (``millis``, a frame counter) is
  refused as a channel unless ``--columns`` names it (:func:`rising_counter`).
- **Checked before any allocation** (:func:`onto_grid`): the rate the stamps imply (their median spacing) against
  ``--rate`` (within a factor of :data:`RATE_AGREEMENT`), a rate in the range rigctl records, and the grid's length
  at most :data:`MAX_GRID_FACTOR` times the stamped rows: memory is bounded by a fixed multiple of the input's size,
  whatever the file says.
- **Repeated stamps** (two rows with one time) are refused, or with ``repeated="keep-first"`` (``--repeated-stamps
  keep-first``) the first of each run is kept and the rows dropped are counted in the record (the import's steps).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["MAX_GRID_FACTOR", "RATE_AGREEMENT", "REPEATED_STAMPS", "TIME_UNITS", "TimeColumnError", "grid_text",
           "explicit_unit", "gaps_text", "onto_grid", "rising_counter", "stamp_gaps", "unit_of_name"]

#: seconds per unit of a time column
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
#: what repeated stamps do: refused, or the first row of each run kept (the others dropped, counted)
REPEATED_STAMPS = ("refuse", "keep-first")
#: the even grid holds at most this many samples per stamped row (gaps filled included)
MAX_GRID_FACTOR = 4
#: the rate the stamps imply and ``--rate`` agree within this factor (a unit wrong is a factor of 1000)
RATE_AGREEMENT = 2.0
#: the rates a time column may imply, Hz (rigctl's taxel streams: tens of Hz to tens of kHz)
MIN_RATE_HZ, MAX_RATE_HZ = 1.0, 1e6
#: rows a column must have before rising at every row makes it a counter
MIN_COUNTER_ROWS = 16

_WORDS = {"s": "s", "sec": "s", "secs": "s", "second": "s", "seconds": "s", "ms": "ms", "msec": "ms", "millis": "ms",
          "milliseconds": "ms", "us": "us", "usec": "us", "micros": "us", "microseconds": "us", "ns": "ns",
          "nsec": "ns", "nanos": "ns", "nanoseconds": "ns"}
_BASES = ("time", "timestamp", "timestamps", "t", "elapsed", "clock")
_NAME = re.compile(r"^(?P<base>[a-z]+)?[\s_\-]*(?:[(\[]\s*(?P<paren>[a-z]+)\s*[)\]]|(?P<word>[a-z]+))?$")


class TimeColumnError(ValueError):
    """A time column refused for what the command line must say (its unit, a rate that disagrees, a counter read
    as a taxel): a usage error, one line."""


def unit_of_name(name: str) -> str | None:
    """The unit (a key of :data:`TIME_UNITS`) a column's name says it holds, or None if the name is not one of a
    time column rigctl knows: ``time``, ``timestamp``, ``t`` (seconds), ``time_ms``, ``millis``, ``Time (ms)``,
    ``timestamp_us``, ``t [ns]``, ``seconds``, ``micros``, ..."""
    text = str(name).strip().lower().replace("µ", "u").replace("μ", "u")
    m = _NAME.match(text)
    if m is None:
        return None
    base, unit = m.group("base"), m.group("paren") or m.group("word")
    if base is not None and unit is None:  # one word: a time word alone (seconds), or a base (time: seconds)
        return _WORDS.get(base) or ("s" if base in _BASES else None)
    if base is None:
        return _WORDS.get(unit or "")
    if base not in _BASES:
        return None
    return _WORDS.get(unit or "")


def explicit_unit(name: str) -> str | None:
    """The unit a column's name spells out (``time_ms``, ``millis``, ``seconds``, ``Time (us)``), or None: a plain
    ``time``, ``timestamp`` or ``t`` is read as seconds by :func:`unit_of_name` but says no unit, so ``--time-unit``
    sets it without a conflict (a lab's ``timestamp`` in ms)."""
    unit = unit_of_name(name)
    text = str(name).strip().lower()
    return None if unit is None or text in _BASES else unit


def rising_counter(column: np.ndarray) -> bool:
    """True for a column of whole numbers that rises at every row (a clock in ms, a frame counter): never a taxel
    unless named as one. Needs :data:`MIN_COUNTER_ROWS` rows."""
    c = np.asarray(column, np.float64)
    return bool(c.size >= MIN_COUNTER_ROWS and np.all(np.isfinite(c)) and np.all(c == np.rint(c))
                and np.all(np.diff(c) > 0))


def _drop_repeats(x: np.ndarray, t: np.ndarray, where: str, repeated: str, unit: str
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size:
        i = int(back[0])
        raise TimeColumnError(f"{where}: the time column goes back at row {i + 1} ({t[i] / TIME_UNITS[unit]:g} then "
                              f"{t[i + 1] / TIME_UNITS[unit]:g} {unit}): fix the file or give another --time-column")
    same = np.flatnonzero(dt == 0)
    if not same.size:
        return x, t, 0
    if repeated != "keep-first":
        i = int(same[0])
        raise TimeColumnError(f"{where}: {same.size} repeated time stamp(s), the first at row {i + 1} "
                              f"({t[i] / TIME_UNITS[unit]:g} {unit} twice): give --repeated-stamps keep-first to keep "
                              "the first row of each (the others dropped, counted in the import steps), or fix the file")
    keep = np.concatenate([[True], dt != 0])
    return x[keep], t[keep], int(same.size)


def onto_grid(x: np.ndarray, times_s: np.ndarray, rate_hz: float | None, where: str, *, unit: str = "s",
              repeated: str = "refuse") -> tuple[np.ndarray, float, dict[str, Any]]:
    """Readings ``x`` (n, c) stamped with their own times (``times_s``, seconds, read in ``unit``) onto an even grid
    at ``rate_hz`` (default: the median spacing's rate), by linear interpolation per channel (``numpy.interp``) from
    the first stamp to the last.

    Before anything is allocated: the implied rate (1 / the median spacing) must be within :data:`MIN_RATE_HZ` ..
    :data:`MAX_RATE_HZ` and agree with ``rate_hz`` within :data:`RATE_AGREEMENT`, and the grid must hold at most
    :data:`MAX_GRID_FACTOR` samples per stamped row. ``repeated``: :data:`REPEATED_STAMPS`.

    Returns ``(readings on the grid (m, c) float64, rate_hz, record)``; the record states the unit, the jitter (sd
    and largest deviation of the spacing from 1/rate, ms), the gaps (spacings over 1.5 periods plus 6 sd of the
    jitter: start, length) and the repeated stamps dropped. Raises :class:`TimeColumnError` naming the row or the
    number at fault (stamps that go back, repeated stamps refused, fewer than two, a rate that disagrees, a grid
    too long)."""
    t = np.asarray(times_s, np.float64)
    if t.size < 2:
        raise TimeColumnError(f"{where}: a time column needs two samples or more")
    if not np.all(np.isfinite(t)):
        raise TimeColumnError(f"{where}: the time column holds NaN or infinite stamps (row "
                              f"{int(np.flatnonzero(~np.isfinite(t))[0]) + 1}): fix the file")
    x, t, n_repeated = _drop_repeats(np.asarray(x), t, where, repeated, unit)
    dt = np.diff(t)
    implied = 1.0 / float(np.median(dt))
    said = f"read as {unit}" + ("" if unit == "s" else f", {TIME_UNITS[unit]:g} s each")
    if rate_hz and not 1 / RATE_AGREEMENT <= implied / float(rate_hz) <= RATE_AGREEMENT:
        raise TimeColumnError(f"{where}: the time stamps imply {implied:.4g} Hz ({said}) but --rate is "
                              f"{float(rate_hz):g} Hz: is the unit right? (--time-unit s|ms|us|ns; a file of "
                              "another rate: --rate its rate, then --resample HZ)")
    if not MIN_RATE_HZ <= implied <= MAX_RATE_HZ:
        raise TimeColumnError(f"{where}: the time stamps are {1 / implied:g} s apart ({said}): {implied:.3g} Hz, "
                              "not a taxel rate; is the unit right? (--time-unit s|ms|us|ns)")
    rate = float(rate_hz) if rate_hz else implied
    span = float(t[-1] - t[0])
    n = int(np.floor(span * rate + 1e-9)) + 1
    if n > MAX_GRID_FACTOR * t.size:
        longest = float(dt.max())
        raise TimeColumnError(f"{where}: the time column spans {span:g} s ({said}): {n} samples at {rate:g} Hz from "
                              f"{t.size} stamped rows (at most {MAX_GRID_FACTOR} per row; the longest gap "
                              f"{longest:g} s): is the unit right? (--time-unit), or cut the file at the gap")
    grid = t[0] + np.arange(n) / rate
    y = np.empty((n, x.shape[1]), np.float64)
    for c in range(x.shape[1]):
        y[:, c] = np.interp(grid, t, x[:, c])
    period = 1.0 / rate
    dev_ms = (dt - period) * 1e3
    gaps = stamp_gaps(t, rate)
    record = {"method": "linear interpolation (numpy.interp) onto an even grid", "rate_hz": rate,
              "rate_from": "--rate" if rate_hz else "the median spacing of the time column", "unit": unit,
              "samples_in": int(t.size), "samples_out": n, "jitter_ms_sd": float(np.std(dev_ms)),
              "jitter_ms_max": float(np.max(np.abs(dev_ms))), "gaps": gaps,
              "repeated_stamps": {"rows_dropped": n_repeated, "kept": "the first of each"} if n_repeated else None}
    return y, rate, record


def stamp_gaps(stamps_s: np.ndarray, rate_hz: float | None = None) -> list[dict[str, float]]:
    """The gaps among time stamps (seconds): spacings over 1.5 periods (of ``rate_hz``, else the median spacing's)
    plus 6 sd of the jitter (robust: the median absolute deviation), each ``{"at_s": from the first stamp,
    "length_ms": the spacing, "at_sample": the index of the first stamp after it}``. For every importer's stamps: a
    CSV's time column, an NWB series' timestamps, an XDF stream's."""
    t = np.asarray(stamps_s, np.float64)
    if t.size < 3:
        return []
    dt = np.diff(t)
    period = 1.0 / float(rate_hz) if rate_hz else float(np.median(dt))
    spread = 1.4826 * float(np.median(np.abs(dt - np.median(dt))))  # the jitter's sd, robust to the gaps themselves
    gap_i = np.flatnonzero(dt > 1.5 * period + 6.0 * spread)
    return [{"at_s": float(t[i] - t[0]), "length_ms": float(dt[i] * 1e3), "at_sample": int(i) + 1} for i in gap_i]


def gaps_text(gaps: list[dict[str, float]]) -> str:
    """The first three gaps in words (``15.2 ms at 1.500 s, ...``)."""
    return ", ".join(f"{g['length_ms']:.1f} ms at {g['at_s']:.3f} s" for g in gaps[:3]) + (", ..." if len(gaps) > 3
                                                                                         else "")


def grid_text(name: str, record: Mapping[str, Any]) -> str:
    """One line for the user: what :func:`onto_grid` did to one file."""
    gaps = record["gaps"]
    shown = gaps_text(gaps)
    repeated = record.get("repeated_stamps")
    unit = record.get("unit", "s")
    return (f"{name}: time column resampled onto the {record['rate_hz']:g} Hz grid ({record['rate_from']}"
            f"{'' if unit == 's' else f', stamps in {unit}'}; jitter sd {record['jitter_ms_sd']:.3f} ms, max "
            f"{record['jitter_ms_max']:.3f} ms; "
            + (f"{len(gaps)} gap(s) interpolated across: {shown}" if gaps else "no gaps")
            + (f"; {repeated['rows_dropped']} row(s) of repeated stamps dropped, the first of each kept" if repeated
               else "") + ")")
