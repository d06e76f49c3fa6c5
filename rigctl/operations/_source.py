"""Where a rig comes from: :class:`RigSource` (an installed rig's name, its ports, recording or options).

The CLI builds one from its flags, the GUI from its connect dialog and settings; both open it with
:func:`rigctl.operations.open_control`. The kinds are the installed rigs (:func:`rigctl.core.rig_plugins.rig_names`:
the entry points of the group ``rigctl.rigs``, rigctl's own :data:`rigctl.rigs.KINDS` among them).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from rigctl.core.faults import FaultSpec
from rigctl.core.rig_plugins import rig_names
from rigctl.rigs import KINDS, fault_refusal

__all__ = ["RigSource", "KINDS", "LEGACY_KINDS", "RESERVED_RIG_OPTIONS"]

#: option names a plugin rig cannot take (they are :func:`rigctl.rigs.open_rig`'s own, or the source's fields)
RESERVED_RIG_OPTIONS = frozenset({"kind", "prompt", "host_config_path", "home", "inject", "allow_firmware_mismatch",
                                  "config", "seed", "textures", "truth_log", "hx711_rate_sps"})
#: the rigs whose HX711 is simulated (``hx711_rate_sps``)
SIMULATED_HX711 = ("sim", "hil", "inprocess", "replay")

#: names earlier versions used for a kind (the GUI's saved settings said "serial" for the hardware rig)
LEGACY_KINDS = {"serial": "hardware"}


@dataclasses.dataclass
class RigSource:
    """A rig to open.

    Attributes
    ----------
    kind : an installed rig (:func:`rigctl.core.rig_plugins.rig_names`): "sim" (default), "hardware" (two real boards
        at ``drum_port`` / ``taxel_port``), "replay" (the simulated rig streaming the recording at ``replay_dir``: a
        session file or a FabricSlide folder), "hil" (the firmware under simavr), "inprocess" (the fast in-process
        rig), "handheld", or a plugin's rig. "serial" is taken as "hardware".
    drum_port, taxel_port : serial ports of the Mega and the Uno (hardware); "handheld": ``taxel_port`` is the finger's
        taxel board (with a live ``motion``: its taxels instead of the sensor model's)
    replay_dir : the recording a replay rig streams
    bootloaders : "hil" only: the boards run their real bootloaders under simavr and reset when the host opens their
        ports, as real boards do (:class:`rigctl.simulation.hil.HilRig` ``bootloaders``); the host waits the boot
        windows out
    inject : faults injected into a simulated rig (``--inject``, :mod:`rigctl.core.faults`), timed on its clock from
        the moment it is open; refused by :func:`rigctl.rigs.open_rig` on a rig that cannot model one
    motion : "handheld" only: where the finger's motion comes from: "sim" (the simulated operator, default),
        "lsl:NAME" (a tracker stream) or "replay:S.h5" (a recorded handheld session's scans;
        :func:`rigctl.rigs.open_handheld`)
    options : a plugin rig's options (``--rig-option KEY=VALUE``: text), given to its factory; ``drum`` ("sim" or
        "inprocess") is the simulated drum a sensor-only plugin streams through
    onboard_encoder : "handheld" only: the encoded training block whose normalisation calibrates the finger's board
        running the encoder image (``--onboard-encoder``): the board encodes each scan, the trials keep its spikes
        and counts instead of raw taxels (:mod:`rigctl.devices.onboard_finger`)
    hil_finger : "handheld" only, with ``onboard_encoder``: the finger's board is the encoder image under simavr, the
        simulated operator's passes played to it (``--handheld --hil``; :mod:`rigctl.simulation.hil_finger`)
    hx711_rate_sps : the simulated rigs only (:data:`SIMULATED_HX711`): the simulated HX711's rate, 10 or 80 SPS
        (``--hx711-rate``; its RATE pin); None: the rig config's ``force_loop.hx711_rate_sps``, else 80

    Raises
    ------
    ValueError
        An unknown kind, ``bootloaders`` for a kind other than "hil", options for one of rigctl's own rigs (they take
        their fields) or an option name :data:`RESERVED_RIG_OPTIONS` holds.
    """

    kind: str = "sim"
    drum_port: str | None = None
    taxel_port: str | None = None
    replay_dir: str | None = None
    bootloaders: bool = False
    inject: tuple[FaultSpec, ...] = ()
    motion: str | None = None
    allow_firmware_mismatch: bool = False
    truth_log: str | None = None
    options: dict[str, str] = dataclasses.field(default_factory=dict)
    onboard_encoder: str | None = None
    hil_finger: bool = False
    hx711_rate_sps: int | None = None
    motion_units: str | None = None  # "handheld" with an LSL tracker: "m" or "mm" (None: the stream's metadata)

    def __post_init__(self) -> None:
        self.kind = LEGACY_KINDS.get(self.kind, self.kind)
        if self.kind not in KINDS and self.kind not in rig_names():
            raise ValueError(f"unknown rig kind {self.kind!r}; choose one of {', '.join(rig_names())} (`rigctl rigs` "
                             "lists the installed rigs)")
        if self.options and self.kind in KINDS:
            raise ValueError(f"the {self.kind} rig takes its own settings (ports, recording), not rig options "
                             f"({', '.join(sorted(self.options))})")
        reserved = sorted(RESERVED_RIG_OPTIONS & set(self.options))
        if reserved:
            raise ValueError(f"rig option {', '.join(reserved)}: a name rigctl keeps for itself")
        if self.hx711_rate_sps is not None and self.kind not in SIMULATED_HX711:
            raise ValueError(f"--hx711-rate chooses a simulated HX711's rate (--sim, --hil, --inprocess, --replay), not "
                             f"the {self.kind} rig's (a real board's is its RATE pin)")
        if self.hx711_rate_sps is not None and int(self.hx711_rate_sps) not in (10, 80):
            raise ValueError(f"--hx711-rate: the HX711 runs at 10 or 80 samples/s, got {self.hx711_rate_sps}")
        if self.bootloaders and self.kind != "hil":
            raise ValueError(f"bootloaders are the firmware under simavr's (kind 'hil'), not {self.kind!r}'s")
        if self.motion is not None and self.kind != "handheld":
            raise ValueError(f"a motion source is the handheld rig's (kind 'handheld'), not {self.kind!r}'s")
        if self.kind == "handheld" and self.drum_port is not None:
            raise ValueError("the handheld rig has no drum: no drum port")
        if self.motion_units is not None and not str(self.motion).startswith("lsl:"):
            raise ValueError("--motion-units is the unit of a tracker stream's positions: give --motion lsl:NAME")
        if (self.onboard_encoder is not None or self.hil_finger) and self.kind != "handheld":
            raise ValueError(f"the on-board encoder is the handheld rig's finger board, not {self.kind!r}'s")
        if self.hil_finger and (self.onboard_encoder is None or (self.motion or "sim") != "sim"):
            raise ValueError("the finger's board under simavr runs the encoder image with the simulated operator: "
                             "give --onboard-encoder (and no --motion, no --taxel-port)")
        if self.onboard_encoder is not None and not self.hil_finger and self.taxel_port is None:
            raise ValueError("the on-board encoder runs on the finger's taxel board: give --taxel-port PORT (with "
                             "--motion lsl:NAME or serial:PORT), or --hil for the board under simavr")

    @classmethod
    def from_flags(cls, *, hil: bool = False, drum_port: str | None = None, taxel_port: str | None = None,
                   replay: str | Path | None = None, bootloaders: bool = False,
                   inprocess: bool = False, inject: tuple[FaultSpec, ...] = (), handheld: bool = False,
                   motion: str | None = None, allow_firmware_mismatch: bool = False, rig: str | None = None,
                   options: dict[str, str] | None = None, onboard_encoder: str | None = None,
                   motion_units: str | None = None) -> "RigSource":
        """The source the CLI's flags select: ``rig`` -> that rig (with its ``options``), ports -> "hardware", a
        recording -> "replay", ``hil`` or ``bootloaders`` -> "hil" (with its bootloaders if asked), ``inprocess`` ->
        "inprocess", ``handheld`` or a ``motion`` -> "handheld" (with ``replay``: that recording's scans; with
        ``onboard_encoder``: the finger's board encodes, under simavr with ``hil``), else "sim" (the flags'
        consistency is the CLI's to check)."""
        inject = tuple(inject)
        if rig is not None:
            return cls(rig, inject=inject, allow_firmware_mismatch=allow_firmware_mismatch, options=dict(options or {}))
        if handheld or motion is not None:  # a recording replayed on the handheld rig: its scans
            replayed = None if replay is None else f"replay:{replay}"
            return cls("handheld", motion=motion or replayed or "sim", taxel_port=taxel_port, inject=inject,
                       onboard_encoder=onboard_encoder, hil_finger=bool(hil and onboard_encoder is not None),
                       motion_units=motion_units)
        allow = allow_firmware_mismatch
        if drum_port is not None or taxel_port is not None:
            return cls("hardware", drum_port=drum_port, taxel_port=taxel_port, inject=inject,
                       allow_firmware_mismatch=allow)
        if replay is not None:
            return cls("replay", replay_dir=str(replay), inject=inject, allow_firmware_mismatch=allow)
        if hil or bootloaders:
            return cls("hil", bootloaders=bootloaders, inject=inject, allow_firmware_mismatch=allow)
        return cls("inprocess" if inprocess else "sim", inject=inject, allow_firmware_mismatch=allow)

    @property
    def is_hardware(self) -> bool:
        return self.kind == "hardware"

    def label(self) -> str:
        """The source in a few words, e.g. ``"rig on /dev/ttyACM0 + /dev/ttyACM1"``, ``"simulated rig"``."""
        if self.kind == "hardware":
            return f"rig on {self.drum_port} + {self.taxel_port}"
        if self.kind == "replay" and str(self.replay_dir).startswith("lsl:"):
            return f"LSL replay ({self.replay_dir})"
        if self.kind == "replay":
            what = "session replay" if str(self.replay_dir).lower().endswith((".h5", ".hdf5")) else "FabricSlide replay"
            return f"{what} ({self.replay_dir})"
        if self.kind == "handheld":
            if str(self.motion).startswith("replay:"):
                return f"handheld session replay ({str(self.motion).removeprefix('replay:')})"
            board = f", taxels from {self.taxel_port}" if self.taxel_port else ""
            if self.onboard_encoder is not None:
                return ("simulated operator, encoded on the board under simavr" if self.hil_finger else
                        f"handheld rig, motion from {self.motion}, encoded on the board on {self.taxel_port}")
            return ("simulated operator" if (self.motion or "sim") == "sim" and not board else
                    f"handheld rig, motion from {self.motion or 'sim'}{board}")
        if self.bootloaders:
            return "firmware under simavr, with its bootloaders"
        if self.kind not in KINDS:
            settings = ", ".join(f"{k}={v}" for k, v in self.options.items())
            return f"{self.kind} rig" + (f" ({settings})" if settings else "")
        return {"hil": "firmware under simavr", "inprocess": "in-process simulated rig"}.get(self.kind,
                                                                                           "simulated rig")

    def injection_refusal(self) -> str | None:
        """Why this rig cannot inject one of :attr:`inject` (one line), known before it opens; None when it can (or only
        the opened backend can tell: the firmware under simavr)."""
        for spec in self.inject:
            why = fault_refusal(self.kind, spec)
            if why:
                return f"--inject {spec}: not on the {self.kind} rig: {why}"
        return None

    def open_options(self) -> dict[str, Any]:
        """The keyword arguments of :func:`rigctl.rigs.open_rig` this source selects (kind included)."""
        extra: dict[str, Any] = {"inject": self.inject} if self.inject else {}
        if self.allow_firmware_mismatch and self.kind != "handheld":
            extra["allow_firmware_mismatch"] = True
        if self.truth_log is not None and self.kind in ("sim", "hil"):
            extra["truth_log"] = self.truth_log
        if self.hx711_rate_sps is not None:
            extra["hx711_rate_sps"] = int(self.hx711_rate_sps)
        if self.kind == "hardware":
            return {"kind": "hardware", "drum_port": self.drum_port, "taxel_port": self.taxel_port, **extra}
        if self.kind == "replay":
            return {"kind": "replay", "source": self.replay_dir, **extra}
        if self.bootloaders:
            return {"kind": "hil", "bootloaders": True, **extra}
        if self.kind == "handheld":
            board: dict[str, Any] = {} if self.taxel_port is None else {"taxel_port": self.taxel_port}
            if self.onboard_encoder is not None:
                board["onboard_encoder"] = self.onboard_encoder
            if self.hil_finger:
                board["hil_finger"] = True
            if self.motion_units is not None:
                board["motion_units"] = self.motion_units
            return {"kind": "handheld", "motion": self.motion or "sim", **board, **extra}
        return {"kind": self.kind, **self.options, **extra}
