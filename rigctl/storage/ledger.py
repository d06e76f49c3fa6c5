"""The ledger of a session's values (issue 77 item 1): every step that changed a value on its way into the session,
one entry each, read from what the import recorded (the ``import_steps`` root attribute, written by
:mod:`rigctl.storage.importers`): resampling, unit conversion and rounding to counts, clipping, a time column's
regridding (the gaps it closed, the repeated stamps it dropped), NaN samples filled, gaps in an NWB series' or an XDF
stream's stamps joined, frames lost. ``rigctl import`` prints it (and ``--json`` holds it), ``rigctl info`` shows
it for the session. A recorded session has none (its values are the board's)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

__all__ = ["FLAGS_ATTR", "LedgerEntry", "ledger", "ledger_lines", "session_flags", "session_ledger",
           "use_warnings"]

#: root attribute: JSON list of the lines the import flagged (files whose trials do not follow their presses, whose
#: period or trial count is an outlier): carried so that info, encode and analyze say them too (issue 77 item 7)
FLAGS_ATTR = "import_flags"

#: one step: ``step`` (its kind: resample, units, round, clip, regrid, gaps, repeated_stamps, nan, lost_frames),
#: ``file`` (None: every file), ``count`` (values or samples it touched, None: all), ``what`` (in words)
LedgerEntry = dict[str, Any]


def _file_entries(read: Mapping[str, Any]) -> list[LedgerEntry]:
    name = str(read.get("file", "?")).rsplit("/", 1)[-1]
    out: list[LedgerEntry] = []
    grid = read.get("time_grid") or None
    if grid:
        out.append({"step": "regrid", "file": name, "count": grid.get("samples_out"),
                    "what": f"time column ({grid.get('unit', 's')}) put on the {grid.get('rate_hz', 0):g} Hz grid by "
                            f"linear interpolation: {grid.get('samples_in')} rows -> {grid.get('samples_out')} samples"})
        if grid.get("gaps"):
            out.append({"step": "gaps", "file": name, "count": len(grid["gaps"]),
                        "what": f"{len(grid['gaps'])} gap(s) in the time column interpolated across (--close-gaps)"})
        rep = grid.get("repeated_stamps") or None
        if rep:
            out.append({"step": "repeated_stamps", "file": name, "count": rep.get("rows_dropped"),
                        "what": f"{rep.get('rows_dropped')} row(s) of repeated stamps dropped (the first kept)"})
    nan = read.get("nan") or {}
    if nan.get("samples") and nan.get("policy") != "refuse":
        out.append({"step": "nan", "file": name, "count": nan["samples"],
                    "what": f"{nan['samples']} NaN sample(s) filled ({nan['policy']})"})
    if read.get("gaps"):
        out.append({"step": "gaps", "file": name, "count": len(read["gaps"]),
                    "what": f"{len(read['gaps'])} gap(s) in the time stamps closed (the samples joined back to back, "
                            "--close-gaps)"})
    if read.get("lost_frames"):
        out.append({"step": "lost_frames", "file": name, "count": read["lost_frames"],
                    "what": f"{read['lost_frames']} lost frame(s) closed (the frames joined back to back, "
                            "--close-gaps)"})
    return out


def ledger(steps: Mapping[str, Any]) -> list[LedgerEntry]:
    """The entries of an import's recorded ``steps`` (:class:`rigctl.storage.importers` ``_Import.steps``), in
    the order the steps ran: per file (regrid, gaps, repeated stamps, NaN, lost frames), then resampling, then the
    scale to counts (units, rounding, clipping)."""
    out: list[LedgerEntry] = []
    for read in steps.get("read") or []:
        if isinstance(read, Mapping):
            out.extend(_file_entries(read))
    fs = steps.get("fabricslide") or None
    if isinstance(fs, Mapping):  # the FabricSlide preset: every file regridded, the rest as counted
        out.extend(_fabricslide_entries(fs))
    rs = steps.get("resampling") or None
    if rs and "up" in rs and rs.get("up") != rs.get("down"):
        out.append({"step": "resample", "file": None, "count": None,
                    "what": f"resampled {rs.get('from_hz', 0):g} -> {rs.get('to_hz', 0):g} Hz ({rs.get('method')})"})
    scale = steps.get("value_scale") or None
    if scale:
        if scale.get("unit") == "volts":
            out.append({"step": "units", "file": None, "count": None,
                        "what": f"volts to {scale.get('adc_bits')}-bit counts, {scale.get('formula')} "
                                f"(volts_ref {scale.get('volts_ref'):g} V), rounded"})
        elif (scale.get("scale"), scale.get("offset")) != (1.0, 0.0):
            out.append({"step": "units", "file": None, "count": None,
                        "what": f"readings to counts, {scale.get('formula')} (scale {scale.get('scale'):g}, offset "
                                f"{scale.get('offset'):g}), rounded"})
        if scale.get("clipped_values"):
            n, top = int(scale["clipped_values"]), (1 << int(scale.get("adc_bits", 10))) - 1
            out.append({"step": "clip", "file": None, "count": n, "what": f"{n} value(s) clipped to 0..{top} (--clip)"})
    return out


def _fabricslide_entries(fs: Mapping[str, Any]) -> list[LedgerEntry]:
    out: list[LedgerEntry] = [
        {"step": "regrid", "file": None, "count": fs.get("samples_out"),
         "what": f"time stamps (ms) of {fs.get('files')} files put on the 1 kHz grid by linear interpolation: "
                 f"{fs.get('rows_in')} rows -> {fs.get('samples_out')} samples"},
        {"step": "units", "file": None, "count": None,
         "what": "capacitance counts to 10-bit counts, rint(counts * scale + offset) (adc_map), rounded"}]
    for step, what in (("repeated_stamps", "row(s) of repeated stamps dropped (the first kept)"),
                       ("gaps", "gap(s) in the time stamps interpolated across (--close-gaps)"),
                       ("clip", "reading(s) clipped to 0..1023 (--clip)")):
        n = int(fs.get("clipped_values" if step == "clip" else step) or 0)
        if n:
            out.append({"step": step, "file": None, "count": n, "what": f"{n} {what}"})
    return out


def ledger_lines(entries: list[LedgerEntry]) -> list[str]:
    """One line a step: ``<file>: <what>`` (or ``<what>`` for every file)."""
    return [f"{e['file']}: {e['what']}" if e.get("file") else str(e["what"]) for e in entries]


def _json_attr(attrs: Mapping[str, Any], name: str) -> Any:
    """Root attribute ``name`` parsed as JSON; None when absent or not JSON."""
    raw = attrs.get(name)
    try:
        return None if raw is None else json.loads(raw if isinstance(raw, str) else bytes(raw).decode("utf-8"))
    except (TypeError, ValueError):
        return None


def session_ledger(attrs: Mapping[str, Any]) -> list[LedgerEntry]:
    """The ledger of a session from its root attributes (``import_steps``); [] when it holds none (recorded,
    generated) or they do not parse."""
    steps = _json_attr(attrs, "import_steps")
    return ledger(steps) if isinstance(steps, Mapping) else []


def session_flags(attrs: Mapping[str, Any]) -> list[str]:
    """The lines the import flagged (:data:`FLAGS_ATTR`), [] when it holds none or they do not parse."""
    flags = _json_attr(attrs, FLAGS_ATTR)
    return [str(x) for x in flags] if isinstance(flags, list) else []


def use_warnings(attrs: Mapping[str, Any], repeated: Mapping[int, int], ids: list[int]) -> list[str]:
    """What a command using trials ``ids`` of a session (its root ``attrs``) says beside its work: the import's flags
    (:func:`session_flags`) and the held readings the validator counted (``repeated``: trial id -> repeated samples,
    :attr:`rigctl.storage.validate.TrialReport.repeated_samples`), one line each."""
    out = []
    flags = session_flags(attrs)
    if flags:
        out.append(f"the import flagged {len(flags)} file(s) (rigctl info lists them): {flags[0]}")
    held = [int(repeated.get(t, 0)) for t in ids]
    if any(held):  # a held reading is encoded as recorded: said, like the trials' other counts
        out.append(f"{sum(held)} samples in {sum(h > 0 for h in held)} trials repeat the one before on every taxel "
                   "(held readings, encoded as recorded; rigctl info lists them)")
    return out
