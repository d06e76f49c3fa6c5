"""The rig config file (``~/.config/rigctl/rig.json``): the calibration a rig keeps between sessions.

A JSON file (default ``$XDG_CONFIG_HOME/rigctl/rig.json``, i.e. ``~/.config/rigctl/rig.json``; overridden by the
``RIGCTL_CONFIG`` environment variable or an explicit path) with the ``loadcell`` and ``taxel_normalisation`` blocks
of :mod:`rigctl.acquisition.calibration`. Shared by the rig facade (:mod:`rigctl.acquisition.rig`, which copies it
into every session) and the calibration, which import this module, not each other.

The schema (:data:`SCHEMA`, checked by :func:`validate_rig_config` on every load and save): a JSON object with the
optional blocks

- ``loadcell``: ``counts_per_g`` (required, a non-zero number: negative for a cell calibrated as reversed),
  ``scale_x100`` (a non-zero integer of absolute value up to 10,000,000: the controller's signed scale), ``mass_g`` (> 0),
  ``zero_raw``, ``loaded_raw``, ``check_force_g``, ``noise_counts``, ``contact_stiffness_g_per_mm`` (numbers: the
  contact's stiffness the probe measured with the verified scale, stored with the controller's calibration too,
  docs/wire-protocol.md 2.12), ``calibrated_utc`` (text);
- ``taxel_normalisation``: ``taxel_min``, ``taxel_max`` (required, lists of ADC counts, one per taxel, of the same
  non-zero length, min <= max), ``n_trials`` (an integer >= 0), ``source``, ``calibrated_utc`` (text);
- ``force_loop``: the force loop's settings for this rig's contact stiffness and HX711 (all required):
  ``hx711_rate_sps`` (10 or 80), ``kp_80sps_mm_s_per_g``, ``ki_80sps_mm_s_per_g_s``, ``kp_10sps_mm_s_per_g``,
  ``ki_10sps_mm_s_per_g_s`` (numbers >= 0; :class:`rigctl.core.drum.ForceLoopConfig`), written to the controller
  when the rig opens (the controller refuses gains outside its registers' ranges, docs/wire-protocol.md 2.1);
- ``taxel_normalisation_previous``: the taxel normalisation the current one replaced (the same keys), kept for undo;
- ``doctor``: the last ``rigctl doctor`` report per rig kind (``hardware``, ``sim``, ``hil``, ``replay``,
  ``inprocess``): ``checked_utc`` and ``rig`` (text), ``ok`` (true/false), ``checks`` (a list of objects with
  ``name``, ``status`` ("pass", "fail" or "skip"), ``summary``, optional ``fix`` (text) and ``values`` (an object of
  numbers, text, true/false, null or lists of them)) (:mod:`rigctl.acquisition.doctor`);
- ``lsl``: Lab Streaming Layer (:mod:`rigctl.acquisition.lsl`): ``enabled`` (true/false: every run publishes its
  streams unless the command says otherwise; default off), ``name`` (the streams' name prefix), ``source_id``
  (their stable source id prefix, so LabRecorder finds the rig again after a restart).

Numbers are finite (JSON ``NaN``/``Infinity`` are refused) and never ``true``/``false``. Any other key is refused, by
name (a misspelt key would otherwise be ignored without a word).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

from rigctl.core.interfaces import RIG_KINDS
from rigctl.storage.sidecars import write_small_file

__all__ = ["CalibrationError", "RigConfigError", "SCHEMA", "default_config_path", "config_path", "load_rig_config",
           "loadcell_scale_mismatch", "save_rig_config", "update_rig_config", "validate_rig_config"]

#: the controller's load-cell scale and the rig config's may differ by this fraction before the host warns (the
#: scale is stored x100 as an integer: 0.5 % is far above its rounding at any plausible cell)
LOADCELL_SCALE_TOLERANCE = 0.005
#: the largest rig config read, bytes (a real one is a few KiB; ``--config /dev/zero`` or a wrong large file is
#: refused after this many bytes instead of being read until memory runs out)
MAX_CONFIG_BYTES = 1 << 20


class CalibrationError(RuntimeError):
    """A calibration could not be done or gave an implausible result (the reason in words)."""


class RigConfigError(CalibrationError):
    """The rig config file is not valid JSON or does not follow :data:`SCHEMA`; the message names the file and the
    key at fault (e.g. ``rig.json: loadcell.counts_per_g: expected a non-zero number, got "420"``)."""


#: block -> key -> (kind, required); kinds: "number", "positive", "nonzero", "count" (int >= 0), "scale" (a
#: non-zero int, |v| <= 10,000,000), "text", "counts" (a non-empty list of numbers)
SCHEMA: dict[str, dict[str, tuple[str, bool]]] = {
    "loadcell": {
        "counts_per_g": ("nonzero", True), "scale_x100": ("scale", False), "mass_g": ("positive", False),
        "zero_raw": ("number", False), "loaded_raw": ("number", False), "check_force_g": ("number", False),
        "noise_counts": ("number", False), "calibrated_utc": ("text", False),
        "contact_stiffness_g_per_mm": ("number", False),
    },
    "taxel_normalisation": {
        "taxel_min": ("counts", True), "taxel_max": ("counts", True), "n_trials": ("count", False),
        "source": ("text", False), "calibrated_utc": ("text", False),
    },
}
SCHEMA["force_loop"] = {
    "hx711_rate_sps": ("hx711_rate", True), "kp_80sps_mm_s_per_g": ("gain", True),
    "ki_80sps_mm_s_per_g_s": ("gain", True), "kp_10sps_mm_s_per_g": ("gain", True),
    "ki_10sps_mm_s_per_g_s": ("gain", True),
}
SCHEMA["taxel_normalisation_previous"] = SCHEMA["taxel_normalisation"]
SCHEMA["doctor"] = {kind: ("report", False) for kind in RIG_KINDS}
SCHEMA["lsl"] = {"enabled": ("bool", False), "name": ("text", False), "source_id": ("text", False)}
#: the handheld rig's plate axis in the tracker's frame (mm): the tracked point with the finger on the plate's start
#: and on its end (rigctl.core.handheld.PlateAxis)
SCHEMA["handheld"] = {"start_xyz": ("counts", True), "end_xyz": ("counts", True), "length_mm": ("positive", False),
                      "calibrated_utc": ("text", False)}

_EXPECTED = {"number": "a number", "positive": "a number > 0", "count": "an integer >= 0",
             "nonzero": "a non-zero number",
             "scale": "a non-zero integer of absolute value up to 10000000", "text": "text", "counts": "a non-empty list of numbers",
             "report": "a doctor report (checked_utc, rig, ok, checks)", "hx711_rate": "10 or 80",
             "gain": "a number >= 0", "bool": "true or false"}

#: a doctor report's keys -> kind; each check's keys -> kind (``values`` checked by _is_plain_value)
_REPORT_KEYS = {"checked_utc": "text", "rig": "text", "ok": "bool", "checks": "list"}
_CHECK_KEYS = {"name": "text", "status": "status", "summary": "text", "fix": "text", "values": "values"}


def _shown(value: Any) -> str:
    """A short JSON rendering of a value for a message (never a Python or numpy repr)."""
    try:
        text = json.dumps(value, allow_nan=True, default=str)
    except (TypeError, ValueError, RecursionError):
        text = type(value).__name__
    return text if len(text) <= 40 else text[:37] + "..."


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_value(kind: str, v: Any) -> bool:
    if kind == "number":
        return _is_number(v)
    if kind == "positive":
        return _is_number(v) and v > 0
    if kind == "nonzero":
        return _is_number(v) and v != 0
    if kind == "count":
        return isinstance(v, int) and not isinstance(v, bool) and v >= 0
    if kind == "scale":
        return isinstance(v, int) and not isinstance(v, bool) and 0 < abs(v) <= 10_000_000
    if kind == "text":
        return isinstance(v, str)
    if kind == "counts":
        return isinstance(v, list) and len(v) > 0 and all(_is_number(x) for x in v)
    if kind == "report":
        return _is_report(v)
    if kind == "hx711_rate":
        return isinstance(v, int) and not isinstance(v, bool) and v in (10, 80)
    if kind == "gain":
        return _is_number(v) and v >= 0
    if kind == "bool":
        return isinstance(v, bool)
    raise AssertionError(kind)


def _is_plain_value(v: Any, depth: int = 0) -> bool:
    """A finite number, text, true/false, null, or a list of them (nested lists at most 2 deep)."""
    if v is None or isinstance(v, (str, bool)) or _is_number(v):
        return True
    return isinstance(v, list) and depth < 2 and all(_is_plain_value(x, depth + 1) for x in v)


def _is_check(c: Any) -> bool:
    if not isinstance(c, dict) or set(c) - set(_CHECK_KEYS) or not {"name", "status", "summary"} <= set(c):
        return False
    if c["status"] not in ("pass", "fail", "skip"):
        return False
    if not all(isinstance(c[k], str) for k in ("name", "summary", "fix") if k in c):
        return False
    values = c.get("values", {})
    return isinstance(values, dict) and all(isinstance(k, str) and _is_plain_value(x) for k, x in values.items())


def _is_report(v: Any) -> bool:
    return (isinstance(v, dict) and set(v) == set(_REPORT_KEYS) and isinstance(v["checked_utc"], str)
            and isinstance(v["rig"], str) and isinstance(v["ok"], bool) and isinstance(v["checks"], list)
            and all(_is_check(c) for c in v["checks"]))


def validate_rig_config(doc: Any, where: str = "rig config") -> dict:
    """Check a rig config document against :data:`SCHEMA`; returns it unchanged.

    Raises
    ------
    RigConfigError naming ``where`` and the key at fault (an unknown key, a missing required key, a value of the
    wrong type or range, taxel lists of different lengths or with a minimum above its maximum).
    """
    if not isinstance(doc, dict):
        raise RigConfigError(f"{where}: the rig config must be a JSON object, got {_shown(doc)}")
    for block, value in doc.items():
        if block not in SCHEMA:
            raise RigConfigError(f"{where}: unknown key {_shown(block)}; the rig config has "
                                 f"{' and '.join(SCHEMA)}")
        keys = SCHEMA[block]
        if not isinstance(value, dict):
            raise RigConfigError(f"{where}: {block}: expected an object, got {_shown(value)}")
        for key, v in value.items():
            if key not in keys:
                raise RigConfigError(f"{where}: {block}: unknown key {_shown(key)} (known: {', '.join(keys)})")
            kind, _ = keys[key]
            if not _check_value(kind, v):
                raise RigConfigError(f"{where}: {block}.{key}: expected {_EXPECTED[kind]}, got {_shown(v)}")
        missing = [k for k, (_, required) in keys.items() if required and k not in value]
        if missing:
            raise RigConfigError(f"{where}: {block}: missing {', '.join(missing)}")
        if block in ("taxel_normalisation", "taxel_normalisation_previous"):
            lo, hi = value["taxel_min"], value["taxel_max"]
            if len(lo) != len(hi):
                raise RigConfigError(f"{where}: {block}: taxel_min has {len(lo)} taxels but taxel_max {len(hi)}")
            bad = [i for i, (a, b) in enumerate(zip(lo, hi)) if a > b]
            if bad:
                raise RigConfigError(f"{where}: {block}: taxel {bad[0]}: taxel_min {lo[bad[0]]:g} is above "
                                     f"taxel_max {hi[bad[0]]:g}")
    return doc


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def default_config_path() -> Path:
    """``$RIGCTL_CONFIG``, else ``$XDG_CONFIG_HOME/rigctl/rig.json`` (``~/.config/rigctl/rig.json``)."""
    env = os.environ.get("RIGCTL_CONFIG")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "rigctl" / "rig.json"


def config_path(path: str | os.PathLike | None = None) -> Path:
    """``path`` if given, else :func:`default_config_path`."""
    return Path(path) if path is not None else default_config_path()


def load_rig_config(path: str | os.PathLike | None = None) -> dict:
    """Read the rig config file; ``{}`` if it does not exist.

    Raises
    ------
    RigConfigError (a CalibrationError) if the file cannot be read, is not valid JSON or does not follow
    :data:`SCHEMA` (the message names the key at fault).
    """
    p = config_path(path)
    if not p.exists():
        return {}
    try:
        if not stat.S_ISREG(os.stat(p).st_mode):
            raise RigConfigError(f"{p}: not a regular file (a device, a FIFO or a folder): give the rig config's "
                                 "JSON file")
        with open(p, "rb") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)
        if len(raw) > MAX_CONFIG_BYTES:
            raise RigConfigError(f"{p}: larger than {MAX_CONFIG_BYTES // 1024} KiB: not a rig config (a few KiB of "
                                 "JSON)")
        text = raw.decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        why = "not UTF-8 text: not a rig config (JSON)" if isinstance(exc, UnicodeDecodeError) else exc
        raise RigConfigError(f"{p}: cannot read the rig config ({why})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RigConfigError(f"{p}:{exc.lineno}: the rig config is not valid JSON: {exc.msg}") from None
    except RecursionError:
        raise RigConfigError(f"{p}: the rig config is nested too deeply") from None
    return validate_rig_config(doc, str(p))


def save_rig_config(config: dict, path: str | os.PathLike | None = None) -> Path:
    """Write the rig config file atomically (write a temporary file, then rename); returns its path.

    Raises RigConfigError (nothing written) if ``config`` does not follow :data:`SCHEMA`."""
    p = config_path(path)
    validate_rig_config(config, str(p))
    p.parent.mkdir(parents=True, exist_ok=True)
    # a sidecar of a random name, created new (never a file or link already there), renamed over the config
    write_small_file(p, (json.dumps(config, indent=2, sort_keys=True) + "\n").encode("utf-8"))
    return p


def update_rig_config(path: str | os.PathLike | None = None, **blocks: Any) -> dict:
    """Replace top-level blocks (e.g. ``loadcell=...``, ``taxel_normalisation=...``) of the rig config file."""
    cfg = load_rig_config(path)
    cfg.update(blocks)
    save_rig_config(cfg, path)
    return cfg


def loadcell_scale_mismatch(config: dict, board_counts_per_g: float) -> str | None:
    """Compare the drum controller's load-cell scale with the rig config's calibration (``loadcell.counts_per_g``).

    Returns None when they agree within :data:`LOADCELL_SCALE_TOLERANCE` (or the config holds no load-cell
    calibration), else the warning in words: the controller's EEPROM lost or never got the calibration (a bad
    checksum falls back to the default 420 counts/g), or another board or cell is connected.
    """
    block = config.get("loadcell") if isinstance(config, dict) else None
    if not block or "counts_per_g" not in block:
        return None
    want = float(block["counts_per_g"])
    have = float(board_counts_per_g)
    if abs(have - want) <= LOADCELL_SCALE_TOLERANCE * abs(want):
        return None
    return (f"the drum controller's load-cell scale is {have:g} counts/g but the rig config's calibration is "
            f"{want:g} counts/g ({block.get('calibrated_utc', 'undated')}): forces would be off by "
            f"{(want / have - 1) * 100:+.1f} %; recalibrate (rigctl calibrate loadcell) or check the board and cell")
