"""XDF files (Lab Streaming Layer recordings: LabRecorder's format): reading them for ``rigctl import`` (pyxdf, the
optional extra ``rigctl[lsl]``) and writing them (:func:`write_xdf`, the XDF 1.0 specification,
github.com/sccn/xdf/wiki/Specifications: the ``XDF:`` magic, then chunks of NumLengthBytes, Length, Tag and content:
FileHeader (1), StreamHeader (2: the stream's info XML, as LabRecorder writes it), Samples (3), ClockOffset (4),
StreamFooter (6)).

:func:`read_xdf` picks the stream to import: the one named by ``--variable`` (a stream name), else a stream rigctl
published (type ``Tactile`` with a ``frame_seq`` last channel, :mod:`rigctl.acquisition.lsl`: that channel is
dropped, its sensor layout taken from the stream description), else the numeric stream with a nominal rate and the
most samples. When the file also holds a rigctl marker stream, each ``trial_end`` marker (its first and last
sample's LSL times, texture, speed, force) cuts one labelled trial out of the stream, as an NWB trials table does;
otherwise the stream is one block (segment it with ``rigctl import``'s options). Timestamps are synchronised across
streams with the file's clock offsets (pyxdf) and not dejittered, so a trial's samples are found by their own
acquisition times.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from rigctl.core.errors import describe_error
from rigctl.storage.time_column import stamp_gaps

__all__ = ["XdfStream", "read_xdf", "stream_info_xml", "write_xdf"]


def _first(info: dict[str, Any], key: str, default: Any = None) -> Any:
    v = info.get(key)
    return v[0] if isinstance(v, list) and v else default


def _desc(info: dict[str, Any]) -> dict[str, Any]:
    d = _first(info, "desc")
    return d if isinstance(d, dict) else {}


def _channel_labels(info: dict[str, Any]) -> list[str]:
    chans = _first(_desc(info), "channels")
    if not isinstance(chans, dict):
        return []
    return [str(_first(c, "label", "")) for c in chans.get("channel", []) if isinstance(c, dict)]


def _is_rigctl_taxels(info: dict[str, Any]) -> bool:
    labels = _channel_labels(info)
    return _first(info, "type") == "Tactile" and bool(labels) and labels[-1] == "frame_seq"


def read_xdf(path: Path, variable: str | None, error: type[Exception]) -> tuple[np.ndarray, float | None,
                                                                               dict[str, Any]]:
    """``(samples (n, n_channels) float64, nominal rate Hz or None, meta)`` of the stream to import from ``path``
    (module docstring); ``meta`` holds ``stream`` (its name), ``sensor`` (a rigctl stream's layout), ``trials``
    (sample ranges with labels from rigctl markers) and ``timestamps`` ranges. Raises ``error`` in one line."""
    try:
        import pyxdf
    except ImportError as exc:
        raise error(f"{path}: reading XDF needs pyxdf: pip install 'rigctl[lsl]' ({exc})") from None
    try:
        streams, _header = pyxdf.load_xdf(str(path), dejitter_timestamps=False)
    except Exception as exc:  # noqa: BLE001 - pyxdf raises many types for a bad file
        raise error(f"{path}: not a readable XDF file ({describe_error(exc)})") from None
    numeric = [s for s in streams if _first(s["info"], "channel_format") != "string"
               and len(s.get("time_stamps", [])) > 0]
    names = [str(_first(s["info"], "name", "?")) for s in streams]
    if variable is not None:
        chosen = [s for s in numeric if _first(s["info"], "name") == variable]
        if not chosen:
            raise error(f"{path}: no numeric stream named {variable!r} (streams: {', '.join(names)})")
        stream = chosen[0]
    else:
        ours = [s for s in numeric if _is_rigctl_taxels(s["info"])]
        regular = [s for s in numeric if float(_first(s["info"], "nominal_srate", 0) or 0) > 0]
        if not (ours or regular):
            raise error(f"{path}: no numeric stream with a sample rate (streams: {', '.join(names) or 'none'})")
        stream = ours[0] if ours else max(regular, key=lambda s: len(s["time_stamps"]))
    info = stream["info"]
    data = np.asarray(stream["time_series"], dtype=np.float64)
    stamps = np.asarray(stream["time_stamps"], dtype=np.float64)
    rate = float(_first(info, "nominal_srate", 0) or 0) or None
    meta: dict[str, Any] = {"stream": str(_first(info, "name", "?")), "stream_type": str(_first(info, "type", "")),
                            "first_timestamp": float(stamps[0]), "last_timestamp": float(stamps[-1]),
                            "gaps": stamp_gaps(stamps, rate)}
    if _is_rigctl_taxels(info):
        meta["frame_seq"] = data[:, -1].astype(np.int64)
        data = data[:, :-1]
        with_layout = _first(_desc(info), "sensor_layout")
        if with_layout:
            try:
                meta["sensor"] = json.loads(with_layout)
            except ValueError:
                pass
        trials = _marker_trials(streams, stamps, rate)
        if trials:
            meta["trials"] = trials
    return data, rate, meta


def _marker_trials(streams: list[dict[str, Any]], stamps: np.ndarray, rate: float | None) -> list[dict[str, Any]]:
    """Sample ranges and labels of the trials rigctl's marker stream announces (``trial_end`` markers)."""
    half = 0.5 / rate if rate else 1e-6
    out = []
    for s in streams:
        info = s["info"]
        if _first(info, "type") != "Markers" or _first(info, "channel_format") != "string":
            continue
        for value in s["time_series"]:
            try:
                doc = json.loads(value[0])
            except (ValueError, TypeError, IndexError):
                continue
            if not isinstance(doc, dict) or doc.get("event") != "trial_end" or "first_sample_lsl_s" not in doc:
                continue
            a = int(np.searchsorted(stamps, float(doc["first_sample_lsl_s"]) - half))
            b = int(np.searchsorted(stamps, float(doc["last_sample_lsl_s"]) + half))
            if b > a:
                labels = {k: doc[k] for k in ("texture", "speed_mm_s", "force_g") if doc.get(k) is not None}
                out.append({"start": a, "stop": b, "labels": labels})
    return sorted(out, key=lambda t: t["start"])


# ------------------------------------------------------------------------------------------------------ writing
_FORMATS = {"float32": "<f4", "double64": "<f8", "int8": "<i1", "int16": "<i2", "int32": "<i4", "int64": "<i8"}


def _varlen(n: int) -> bytes:
    if n < 256:
        return struct.pack("<BB", 1, n)
    if n < 2**32:
        return struct.pack("<BI", 4, n)
    return struct.pack("<BQ", 8, n)


def _chunk(tag: int, content: bytes) -> bytes:
    return _varlen(len(content) + 2) + struct.pack("<H", tag) + content


@dataclass
class XdfStream:
    """One stream: its info XML (``StreamInfo.as_xml()`` of an inlet, or :func:`stream_info_xml`), its channel
    format (``float32``, ``double64``, ``int8/16/32/64``, ``string``), samples (n, channels), timestamps (n,) s and
    clock offsets ``(collection time, offset)`` s."""

    info_xml: str
    channel_format: str
    samples: Any
    time_stamps: Sequence[float]
    clock_offsets: list[tuple[float, float]] = field(default_factory=lambda: [(0.0, 0.0)])


def stream_info_xml(name: str, stype: str, channel_count: int, nominal_srate: float, channel_format: str,
             source_id: str, labels: Sequence[str] = ()) -> str:
    """A minimal LSL stream info XML (what ``StreamInfo.as_xml()`` holds) with channel labels."""
    chans = "".join(f"<channel><label>{escape(label)}</label></channel>" for label in labels)
    return (f'<?xml version="1.0"?><info><name>{escape(name)}</name><type>{escape(stype)}</type>'
            f"<channel_count>{channel_count}</channel_count><nominal_srate>{nominal_srate}</nominal_srate>"
            f"<channel_format>{channel_format}</channel_format><source_id>{escape(source_id)}</source_id>"
            f"<created_at>0</created_at><uid>{escape(source_id)}-uid</uid><session_id>default</session_id>"
            f"<hostname>localhost</hostname><desc><channels>{chans}</channels></desc></info>")


def _samples(stream: XdfStream) -> bytes:
    out = [_varlen(len(stream.time_stamps))]
    if stream.channel_format == "string":
        for row, t in zip(stream.samples, stream.time_stamps):
            out.append(struct.pack("<Bd", 8, float(t)))
            for value in row:
                b = str(value).encode()
                out.append(_varlen(len(b)) + b)
    else:
        data = np.asarray(stream.samples, dtype=_FORMATS[stream.channel_format])
        for row, t in zip(data, stream.time_stamps):
            out.append(struct.pack("<Bd", 8, float(t)) + row.tobytes())
    return b"".join(out)


def write_xdf(path: Path, streams: Sequence[XdfStream], *, chunk_samples: int = 500) -> None:
    """Write ``streams`` into the XDF file ``path`` (samples in chunks, interleaved per stream)."""
    parts = [b"XDF:", _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')]
    for sid, s in enumerate(streams, start=1):
        parts.append(_chunk(2, struct.pack("<I", sid) + s.info_xml.encode()))
    for sid, s in enumerate(streams, start=1):
        for a in range(0, len(s.time_stamps), chunk_samples):
            part = XdfStream(s.info_xml, s.channel_format, s.samples[a:a + chunk_samples],
                             s.time_stamps[a:a + chunk_samples])
            parts.append(_chunk(3, struct.pack("<I", sid) + _samples(part)))
        for collected, offset in s.clock_offsets:
            parts.append(_chunk(4, struct.pack("<Idd", sid, collected, offset)))
    for sid, s in enumerate(streams, start=1):
        t = s.time_stamps
        footer = (f'<?xml version="1.0"?><info><first_timestamp>{t[0] if len(t) else 0}</first_timestamp>'
                  f"<last_timestamp>{t[-1] if len(t) else 0}</last_timestamp><sample_count>{len(t)}</sample_count>"
                  "<clock_offsets>" + "".join(f"<offset><time>{c}</time><value>{o}</value></offset>"
                                              for c, o in s.clock_offsets) + "</clock_offsets></info>")
        parts.append(_chunk(6, struct.pack("<I", sid) + footer.encode()))
    Path(path).write_bytes(b"".join(parts))
