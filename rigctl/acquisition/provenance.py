"""The provenance of a recorded session: the host's (:func:`rigctl.core.provenance.software_provenance`) plus what
only the rig knows: both boards' firmware identity compared with the installed sources, the protocol, the rig config
and calibration with their dates, the seeds.

Stored by the runner as the session's ``provenance`` root attribute (docs/session-format.md); ``rigctl info
--provenance`` prints it; the NWB export carries it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import Any

from rigctl.core.provenance import software_provenance

__all__ = ["firmware_identity", "session_provenance"]


def _version(v: Any) -> list[int] | None:
    try:
        return [int(x) for x in v] if v else None
    except (TypeError, ValueError):
        return None


def firmware_identity(rig_config: Mapping[str, Any]) -> dict[str, Any]:
    """Both boards' firmware identity from a rig description (:meth:`rigctl.acquisition.rig.Rig.describe`: the drum
    controller's FW_VERSION registers, docs/wire-protocol.md 2.2; the taxel streamer's identify banner, 1.3) and the
    installed sources' (:func:`rigctl.firmware.source_versions`, :func:`rigctl.firmware.source_digest`).

    Returns ``{"mega": {"version", "sources_version", "matches_sources"}, "uno": {... "build": the banner's build
    hash or None, "build_matches_sources": bool | None}, "sources_digest": sha256 | None}``; a value nobody reported
    is None (never guessed)."""
    from rigctl import firmware

    want: dict[str, Any] = {}
    digest = None
    with contextlib.suppress(OSError, ValueError):
        want = {k: list(v) for k, v in firmware.source_versions().items()}
    with contextlib.suppress(OSError, ValueError):
        digest = firmware.source_digest()
    banner = rig_config.get("taxel_streamer") or {}
    got = {"mega": _version(rig_config.get("drum_firmware")), "uno": _version(banner.get("firmware"))}
    out: dict[str, Any] = {"sources_digest": digest}
    for board, version in got.items():
        src = want.get(board)
        out[board] = {"version": version, "sources_version": src,
                      "matches_sources": None if version is None or src is None else version == src}
    build = banner.get("build")
    out["uno"]["build"] = None if build is None else str(build)
    out["uno"]["build_matches_sources"] = (None if build is None or digest is None
                                           else digest.startswith(str(build).lower()))
    return out


def _dates(host_config: Mapping[str, Any]) -> dict[str, Any]:
    """The dates of the rig config's blocks (``calibrated_utc``, ``checked_utc``), by block name."""
    out = {}
    for name, block in host_config.items():
        if isinstance(block, Mapping):
            for key in ("calibrated_utc", "checked_utc"):
                if key in block:
                    out[name] = block[key]
    return out


def session_provenance(rig_config: Mapping[str, Any], *, protocol: Any = None, **extra: Any) -> dict[str, Any]:
    """The provenance of a session recorded on a rig described by ``rig_config`` (:meth:`Rig.describe`) with
    ``protocol`` (a loaded protocol: its name, format, resolved text and seed).

    Keys: those of :func:`software_provenance`, ``firmware`` (:func:`firmware_identity`), ``protocol`` (name,
    seed, source: the resolved text), ``rig`` (mode, ports, the simulated rig's seed, a plugin's distribution,
    version and ``describe()``), ``rig_config_path``,
    ``rig_config`` (the rig config file's content: calibration, normalisation, doctor reports) and
    ``rig_config_dates`` (each block's date), then ``extra``."""
    host_config = dict(rig_config.get("host_config") or {})
    proto = None
    if protocol is not None:
        proto = {"name": getattr(protocol, "name", ""), "seed": getattr(protocol, "seed", None),
                 "source": getattr(protocol, "source", "")}
    return software_provenance(
        firmware=firmware_identity(rig_config),
        protocol=proto,
        rig={k: rig_config.get(k) for k in ("mode", "drum_port", "taxel_port", "seed", "plugin")},
        rig_config_path=rig_config.get("host_config_path"),
        rig_config=host_config,
        rig_config_dates=_dates(host_config),
        **extra,
    )
