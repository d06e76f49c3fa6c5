"""``rigctl info``: summarise a session file, trial by trial."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import click

from rigctl.cli.jsonout import json_text
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.core.progress import ProgressCallback
from rigctl.storage.ledger import ledger_lines, session_flags, session_ledger
from rigctl.storage.session import TrialStatus, open_session

_STATUS = {int(s): s.name.lower() for s in TrialStatus}


#: the trial attributes ``rigctl info`` shows (read in one pass, :meth:`Session.trial_table`); schema 4 takes the
#: counts from ``/recording/index`` instead
_SHOWN = ("n_samples", "dropped_frames", "crc_errors", "host_rate_hz", "force_mean_g", "speed_mean_mm_s",
          "index_source", "drum_speed_index_mm_s", "drum_speed_mismatch", "drum_speed_warning", "error",
          "encoded_on_board", "scan_duration_s", "tracker_rate_hz", "tracker_dropouts", "floored_windows",
          "occluded_windows")
#: a handheld scan's measured fields (its attributes): shown per trial, and the planned duration replaced by the scan's
HANDHELD_FIELDS = ("scan_duration_s", "tracker_rate_hz", "tracker_dropouts", "floored_windows", "occluded_windows")


def session_summary(path: str | Path, *, keep_nonfinite: bool = False,
                    progress: ProgressCallback | None = None) -> dict:
    """A JSON-able summary of a session file.

    ``keep_nonfinite``: trials with NaN/inf force or speed readings are complete (flagged ``nonfinite``) instead of
    excluded; ``progress``: the validator's ``rigctl.core.progress`` events.

    Returns
    -------
    dict with ``file``, ``size_bytes``, the root attributes (``session_id``, ``created_utc``, ``kind``,
    ``rigctl_version``, ``schema_version``), ``protocol`` (name, format), ``sensor`` (``name``, ``shape``,
    ``n_channels``, ``sample_rate_hz``, ``adc_bits``, ``description`` = ``layout.describe()``, ``layout`` = its
    ``to_dict()``), ``texture_set`` (``name``, ``count``, ``labels``, ``groups``: group -> labels, empty when the
    set has none), ``trials`` (one dict per plan row:
    trial_id, texture, profile, speed_mm_s, ramp_start_mm_s, ramp_end_mm_s, force_g, duration_s, status (``excluded``:
    a complete trial the validator :func:`rigctl.storage.validate.usable_trials` refused, ``error`` says why), samples,
    samples_per_s = samples / duration_s (the trial's length), host_rate_hz (frames per second on the host clock,
    lower-envelope estimate over the stream up to the trial's end), dropped_frames, crc_errors, force_mean_g,
    speed_mean_mm_s, index_source, drum_speed_index_mm_s, drum_speed_warning ("" unless the trial is flagged
    drum_speed_mismatch), source (where an imported or replayed trial came from: ``file``, ``first_sample``,
    ``last_sample`` (inclusive, at the session's rate), ``cycle`` (the cycle or run of a segmented recording),
    ``trial_id`` (a replayed session's trial); None for a trial recorded here), nonfinite (a kept trial's NaN/inf
    readings, in words; None otherwise), encoded_on_board (a scan the finger's board encoded itself, the handheld
    rig's ``--onboard-encoder``: no taxel frames, its samples the ones the board encoded), error) and ``totals``.
    """
    from rigctl.storage.validate import usable_trials

    path = Path(path)
    with open_session(path) as s:
        # the one trial validator: excluded trials say why, as in encode and export
        report = usable_trials(s, keep_nonfinite=keep_nonfinite, progress=progress)
        shown = [int(r["trial_id"]) for r in s.plan if (int(r["status"]) == TrialStatus.COMPLETE and
                                                        int(r["trial_id"]) not in report.excluded)
                 or int(r["status"]) == TrialStatus.FAILED]
        index = s.recording_index()  # schema 4: the counts (older files: the attributes)
        names = _SHOWN[3:] if index else _SHOWN
        attrs = dict(zip(shown, s.trial_table(shown, names + tuple(SOURCE_ATTRS))))  # one pass, no dataset opened
        trials = [_trial_row(row, report, attrs.get(int(row["trial_id"])), index.get(int(row["trial_id"])))
                  for row in s.plan]
        for t in trials:  # a scan the finger's board encoded: no taxel frames, the samples the board encoded
            if t.get("encoded_on_board"):
                onboard = s.trial(t["trial_id"]).onboard
                t["samples"] = onboard.samples if onboard is not None else 0
                t["samples_per_s"] = t["samples"] / t["duration_s"] if t["duration_s"] > 0 else None
        done = [t for t in trials if t["status"] == "complete"]
        totals = {
            "trials": len(trials),
            "complete": len(done),
            "failed": sum(t["status"] == "failed" for t in trials),
            "pending": sum(t["status"] == "pending" for t in trials),
            "excluded": sum(t["status"] == "excluded" for t in trials),
            "nonfinite": sum(t.get("nonfinite") is not None for t in done),
            "encoded_on_board": sum(bool(t.get("encoded_on_board")) for t in done),
            "samples": sum(t["samples"] for t in done),
            "recorded_s": sum(t["duration_s"] for t in done),
            "dropped_frames": sum(t["dropped_frames"] for t in done),
            "crc_errors": sum(t["crc_errors"] for t in done),
            "repeated_samples": sum(t.get("repeated_samples", 0) for t in done),
            "held_trials": sum(bool(t.get("repeated_samples")) for t in done),
        }
        attrs_root = {k: s.attrs.get(k) for k in ("schema_version", "session_id", "created_utc", "kind",
                                                  "rigctl_version")}
        return {
            "file": str(path), "size_bytes": path.stat().st_size, **attrs_root,
            "protocol": {"name": s.protocol_name, "format": s.protocol_format},
            "sensor": _sensor_summary(s.layout),
            "texture_set": _textures_summary(s.textures),
            "rig_mode": s.rig_config.get("mode"),
            "calibration": sorted(s.calibration) if s.calibration else None,
            "trials": trials, "totals": totals,
            "ledger": session_ledger(s.attrs),  # every step that changed a value on import (rigctl.storage.ledger)
            "import_flags": session_flags(s.attrs),  # what the import flagged (outlier files, missed presses)
        }


def _count(v: Any) -> int:
    try:
        return int(v)
    except (TypeError, ValueError, OverflowError):
        return 0


def _trial_row(row: Any, report: Any, a: dict | None, index_row: Any) -> dict:
    """One trial of :func:`session_summary` from its plan row, the validator's report, its shown attributes
    (:data:`_SHOWN`; None when not read) and its ``/recording/index`` row (schema 4, else None)."""
    tid = int(row["trial_id"])
    status = _STATUS.get(int(row["status"]), str(row["status"]))
    t: dict[str, Any] = {
        "trial_id": tid, "texture": str(row["texture"]), "profile": str(row["profile"]),
        "speed_mm_s": float(row["speed_mm_s"]), "force_g": float(row["force_g"]),
        "duration_s": float(row["duration_s"]),
        "ramp_start_mm_s": _num(row["ramp_start_mm_s"]), "ramp_end_mm_s": _num(row["ramp_end_mm_s"]),
        "status": status, "samples": 0, "samples_per_s": None, "host_rate_hz": None,
        "dropped_frames": 0, "crc_errors": 0,
    }
    a = a or {}
    if status == "complete" and tid in report.excluded:
        t["status"] = "excluded"
        t["error"] = report.excluded[tid]
    elif status == "failed":
        t["error"] = str(a.get("error", ""))
    elif status == "complete":
        counts = index_row if index_row is not None else a
        n = _count(counts["n_samples"] if index_row is not None else a.get("n_samples", 0))
        t["samples"] = n
        t["samples_per_s"] = n / t["duration_s"] if t["duration_s"] > 0 else None
        # measured when recorded; None for generated/imported sessions (their clock is synthetic)
        t["host_rate_hz"] = _num(a.get("host_rate_hz", math.nan))
        t["dropped_frames"] = report.dropped_frames.get(tid, 0)
        t["crc_errors"] = _count(counts["crc_errors"] if index_row is not None else a.get("crc_errors", 0))
        t["repeated_samples"] = report.repeated_samples.get(tid, 0)  # held readings, recounted by the validator
        t["force_mean_g"] = _num(a.get("force_mean_g", math.nan))
        t["speed_mean_mm_s"] = _num(a.get("speed_mean_mm_s", math.nan))
        t["index_source"] = str(a.get("index_source", "")) or None
        t["drum_speed_index_mm_s"] = _num(a.get("drum_speed_index_mm_s", math.nan))
        t["drum_speed_warning"] = str(a.get("drum_speed_warning", "")) if a.get("drum_speed_mismatch", False) else ""
        t["source"] = _source(a)
        t["nonfinite"] = report.nonfinite.get(tid)
        t["encoded_on_board"] = bool(a.get("encoded_on_board", False))
        if a.get("scan_duration_s") is not None:  # a handheld scan: its measured length, not the plan's
            for k in HANDHELD_FIELDS:
                if a.get(k) is not None:
                    t[k] = (_count(a[k]) if k in ("tracker_dropouts", "floored_windows", "occluded_windows")
                            else _num(a[k]))
            t["planned_duration_s"], t["duration_s"] = t["duration_s"], float(a["scan_duration_s"])
            t["samples_per_s"] = n / t["duration_s"] if t["duration_s"] > 0 else None
    return t


#: trial attribute -> key of a trial's ``source`` in the summary (written by rigctl import and by replay)
SOURCE_ATTRS = {"source_file": "file", "source_first_sample": "first_sample", "source_last_sample": "last_sample",
                "cycle_index": "cycle", "source_trial_id": "trial_id"}


def _source(attrs) -> dict | None:
    """A trial's provenance from its attributes (:data:`SOURCE_ATTRS`), None when it has none."""
    out: dict[str, Any] = {}
    for attr, key in SOURCE_ATTRS.items():
        v = attrs.get(attr)
        if v is None:
            continue
        if attr == "source_file":
            out[key] = v.decode() if isinstance(v, bytes) else str(v)
        else:
            try:
                out[key] = int(v)
            except (TypeError, ValueError, OverflowError):  # a damaged attribute: shown as it is
                out[key] = str(v)
    return out or None


def _source_text(src) -> str:
    parts = [src.get("file", "")]
    if "trial_id" in src:
        parts.append(f"trial {src['trial_id']}")
    if "first_sample" in src:
        parts.append(f"samples {src['first_sample']}-{src['last_sample']}")
    if "cycle" in src:
        parts.append(f"cycle {src['cycle']}")
    return " ".join(p for p in parts if p)


def _sensor_summary(layout) -> dict:
    return {"name": layout.name, "shape": layout.shape_text, "n_channels": layout.n_channels,
            "sample_rate_hz": layout.sample_rate_hz, "adc_bits": layout.adc_bits, "description": layout.describe(),
            "layout": layout.to_dict()}


def _textures_summary(textures) -> dict:
    groups = {g: [t.label for t in textures if t.group == g] for g in textures.groups}
    return {"name": textures.name, "count": len(textures), "labels": list(textures.labels), "groups": groups}


def _num(v):
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(f) else f


def _fmt(v, spec=".1f", none="-"):
    return none if v is None else format(v, spec)


def _provenance_lines(prov: Any, prefix: str = "") -> list[str]:
    """``prov`` as ``key.path: value`` lines, a multi-line text (the protocol) as an indented block after its key."""
    lines = []
    for key, value in prov.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            lines += _provenance_lines(value, name + ".")
        elif isinstance(value, str) and "\n" in value:
            lines.append(f"{name}:")
            lines += [f"    {line}" for line in value.rstrip().splitlines()]
        else:
            lines.append(f"{name}: {json_text(value) if isinstance(value, (dict, list)) else value}")
    return lines


def _show_provenance(file: Path, as_json: bool) -> None:
    from rigctl.storage.provenance import ProvenanceError, read_provenance

    try:
        prov = read_provenance(file)
    except ProvenanceError as exc:
        raise click.ClickException(str(exc)) from None
    if as_json:
        click.echo(json_text(prov, indent=2))
        return
    for line in _provenance_lines(prov):
        click.echo(line)


@click.command()
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the summary as JSON.")
@click.option("--provenance", is_flag=True, default=False,
              help="Print what made FILE instead (a session, an encoded file or an NWB export): its UUID, rigctl's "
                   "version and git state, Python and package versions, host, command line, both boards' firmware "
                   "against the installed sources, the protocol, the rig config and calibration with their dates, "
                   "seeds, encoder parameters, and the provenance of the files it was made from.")
@click.option("--keep-nonfinite", is_flag=True,
              help="Count trials whose force or speed readings hold NaN or inf as complete (flagged), as encode and "
                   "export do with this option (default: excluded, with the reason).")
@progress_option
def info(file, as_json, provenance, keep_nonfinite, progress):
    """Summarise the session FILE: per trial its setpoints, samples, samples per second, dropped frames, CRC errors
    and status; then the totals. With --provenance: what made FILE."""
    from rigctl.storage.session import SessionError

    if provenance:
        _show_provenance(file, as_json)
        return

    try:
        with bars(show_bars(progress), leave=False) as bar:
            summary = session_summary(file, keep_nonfinite=keep_nonfinite, progress=bar)
    except SessionError as exc:
        raise click.ClickException(str(exc)) from None
    except OSError as exc:
        raise click.ClickException(f"{file} is not a readable HDF5 session file ({exc})") from None
    if as_json:
        click.echo(json_text(summary, indent=2))
        return
    click.echo(f"{summary['file']}  ({summary['size_bytes'] / 1e6:.2f} MB)  kind={summary['kind']}  "
               f"protocol={summary['protocol']['name']} ({summary['protocol']['format']})  rig={summary['rig_mode']}")
    click.echo(f"session {summary['session_id']}  created {summary['created_utc']}  rigctl {summary['rigctl_version']}"
               f"  schema {summary['schema_version']}")
    sensor, tset = summary["sensor"], summary["texture_set"]
    click.echo(f"sensor {sensor['name'] or sensor['shape']}: {sensor['n_channels']} channels, {sensor['description']}")
    groups = "; ".join(f"{g}: {' '.join(labels)}" for g, labels in tset["groups"].items()) or "no groups"
    click.echo(f"textures {tset['name'] or '(unnamed)'}: {tset['count']} ({' '.join(tset['labels'][:30])}"
               f"{' ...' if tset['count'] > 30 else ''}); {groups}")
    tw = max([3] + [len(t["texture"]) for t in summary["trials"]])
    header = (f"{'trial':>6} {'tex':>{tw}} {'profile':<13} {'speed':>7} {'force':>6} {'dur_s':>6} {'samples':>8} "
              f"{'samp/s':>8} {'host_hz':>8} {'dropped':>7} {'crc':>4}  status")
    lines = [header]  # printed at once: a big session has thousands of lines
    for t in summary["trials"]:
        speed = (f"{t['ramp_start_mm_s']:g}>{t['ramp_end_mm_s']:g}" if t["ramp_start_mm_s"] is not None
                 else f"{t['speed_mm_s']:g}")
        line = (f"{t['trial_id']:>6} {t['texture']:>{tw}} {t['profile']:<13} {speed:>7} {t['force_g']:>6g} "
                f"{t['duration_s']:>6.2f} {t['samples']:>8} {_fmt(t['samples_per_s']):>8} "
                f"{_fmt(t['host_rate_hz']):>8} {t['dropped_frames']:>7} {t['crc_errors']:>4}  {t['status']}")
        if t.get("error"):
            line += f" ({t['error']})"
        if t.get("nonfinite"):
            line += f" (non-finite readings: {t['nonfinite']})"
        if t.get("encoded_on_board"):
            line += " (encoded on the board: its spikes and counts, no taxel frames)"
        if t.get("source"):
            line += f"  from {_source_text(t['source'])}"
        lines.append(line)
    click.echo("\n".join(lines))
    for t in summary["trials"]:
        if t.get("drum_speed_warning"):
            click.echo(f"warning: trial {t['trial_id']}: drum speed mismatch: {t['drum_speed_warning']}")
    tot = summary["totals"]
    excluded = f", {tot['excluded']} excluded as damaged" if tot["excluded"] else ""
    if tot["nonfinite"]:
        excluded += f", {tot['nonfinite']} with non-finite readings kept"
    if tot["encoded_on_board"]:
        excluded += f", {tot['encoded_on_board']} encoded on the board"
    click.echo(f"totals: {tot['complete']}/{tot['trials']} trials complete{excluded}, {tot['failed']} failed, "
               f"{tot['pending']} pending; {tot['samples']} samples over {tot['recorded_s']:.1f} s of trials; "
               f"{tot['dropped_frames']} dropped frames; {tot['crc_errors']} CRC errors"
               + (f"; {tot['repeated_samples']} repeated samples (identical on every taxel to the one before) in "
                  f"{tot['held_trials']} trials" if tot["repeated_samples"] else ""))
    for line in ledger_lines(summary.get("ledger") or []):
        click.echo(f"ledger: {line}")
    for line in summary.get("import_flags") or []:
        click.echo(f"import flagged: {line}")
