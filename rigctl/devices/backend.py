"""The serial-hardware backend: the real Mega and Uno on two serial ports; an operator mounts the plates.

Implements :class:`rigctl.core.interfaces.RigBackend` for ``rigctl.rigs.open_rig("hardware", drum_port=...,
taxel_port=...)``; the simulated backends (:mod:`rigctl.simulation.backend`) reuse :class:`PortBackend` on the
ports their virtual boards open.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream

__all__ = ["PortBackend", "SerialBackend", "OperatorMounter", "console_prompt"]


def console_prompt(message: str) -> None:
    """Default operator prompt on hardware: print ``message`` and wait for Enter on the terminal."""
    input(f"\n>>> {message} [Enter] ")


class OperatorMounter:
    """:class:`rigctl.core.interfaces.PlateMounter` for hardware: asks the operator to mount the plate by label."""

    def __init__(self, prompt: Callable[[str], Any] | None = None) -> None:
        self.prompt = prompt

    def mount(self, label: str, textures: TextureSet, prompt: Callable[[str], Any] | None = None) -> None:
        label = textures.resolve(label)
        (prompt or self.prompt or console_prompt)(
            f"Mount texture plate {label} on the drum (the sensor is released), then confirm.")


class PortBackend:
    """A backend whose two boards are on serial ports: new :class:`DrumClient` / :class:`TaxelStream` clients.

    Subclasses set :attr:`drum_port` / :attr:`taxel_port` (may be properties that exist once started) and
    :attr:`drum_timeout_s` (the answer timeout of the drum client, s; chosen per backend by the composition root,
    :data:`rigctl.rigs.ANSWER_TIMEOUT_S`) and :attr:`drum_watchdog_ms` (WATCHDOG_MS the client writes when it opens,
    None: the controller's default; :data:`rigctl.rigs.WATCHDOG_MS`).
    """

    mode = "hardware"
    drum_port: str
    taxel_port: str
    drum_timeout_s: float = 0.5
    drum_watchdog_ms: int | None = None

    def drum(self, **options: Any) -> DrumClient:
        """A new Modbus RTU client of the drum controller (not yet opened), answer timeout :attr:`drum_timeout_s`,
        WATCHDOG_MS :attr:`drum_watchdog_ms` once opened; ``options``: more :class:`DrumClient` keywords."""
        return DrumClient(self.drum_port, timeout_s=self.drum_timeout_s, poll_s=0.02, watchdog_ms=self.drum_watchdog_ms,
                          **options)

    def taxels(self, **options: Any) -> TaxelStream:
        """A new taxel stream reader (not yet opened); ``options``: :class:`TaxelStream` keywords."""
        return TaxelStream(self.taxel_port, **options)


class SerialBackend(PortBackend):
    """The real rig: drum controller on ``drum_port``, taxel streamer on ``taxel_port``; plates by an operator.

    Parameters
    ----------
    drum_port, taxel_port : serial device paths (``rigctl ports`` lists the candidates).
    prompt : operator prompt for plate changes (default :func:`console_prompt`).
    textures : the texture set of the lab's plates (default the paper's A-P); a protocol brings its own.
    drum_timeout_s : the drum client's answer timeout, s (default 0.5: inside the controller's 1 s watchdog).
    """

    mode = "hardware"

    def __init__(self, drum_port: str, taxel_port: str, *, prompt: Callable[[str], Any] | None = None,
                 textures: TextureSet | None = None, drum_timeout_s: float = 0.5) -> None:
        self.drum_timeout_s = drum_timeout_s
        self.drum_port = str(drum_port)
        self.taxel_port = str(taxel_port)
        self.mounter = OperatorMounter(prompt)
        self.textures = textures or PAPER_TEXTURES

    def __enter__(self) -> "SerialBackend":
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def describe(self) -> dict[str, Any]:
        return {"mode": self.mode, "drum_port": self.drum_port, "taxel_port": self.taxel_port, "seed": None}
