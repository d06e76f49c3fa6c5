"""The rig config file (``~/.config/rigctl/rig.json``): the calibration a rig keeps between sessions.

A JSON file (default ``$XDG_CONFIG_HOME/rigctl/rig.json``, i.e. ``~/.config/rigctl/rig.json``; overridden by the
``RIGCTL_CONFIG`` environment variable or an explicit path) with the ``loadcell`` and ``taxel_normalisation`` blocks
of :mod:`rigctl.acquisition.calibration`. Shared by the rig facade (:mod:`rigctl.acquisition.rig`, which copies it
into every session) and the calibration, which import this module, not each other.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from pathlib import Path
from typing import Any

__all__ = ["CalibrationError", "default_config_path", "config_path", "load_rig_config", "save_rig_config",
           "update_rig_config"]


class CalibrationError(RuntimeError):
    """A calibration could not be done or gave an implausible result (the reason in words)."""


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


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
    CalibrationError if the file exists but is not a JSON object.
    """
    p = config_path(path)
    if not p.exists():
        return {}
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{p}:{exc.lineno}: the rig config is not valid JSON: {exc.msg}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{p}: the rig config must be a JSON object")
    return doc


def save_rig_config(config: dict, path: str | os.PathLike | None = None) -> Path:
    """Write the rig config file atomically (write a temporary file, then rename); returns its path."""
    p = config_path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(tmp, p)
    return p


def update_rig_config(path: str | os.PathLike | None = None, **blocks: Any) -> dict:
    """Replace top-level blocks (e.g. ``loadcell=...``, ``taxel_normalisation=...``) of the rig config file."""
    cfg = load_rig_config(path)
    cfg.update(blocks)
    save_rig_config(cfg, path)
    return cfg
