"""Backends of the simulated rigs on real ptys: the model boards (``sim``, ``replay``) and the firmware under simavr
(``hil``). Each implements :class:`rigctl.core.interfaces.RigBackend` (and :class:`MassPlacer`): the host opens the
same :class:`rigctl.devices.drum.DrumClient` and :class:`rigctl.devices.taxel_stream.TaxelStream` as on hardware,
on the ports the virtual boards open; plates are mounted by setting the model's texture (rendered from the texture
set's geometry, :func:`rigctl.simulation.textures.get_texture`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from rigctl.core.faults import FaultSchedule, FaultSpec
from rigctl.core.shared_clock import SharedClock
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.devices.backend import PortBackend
from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream

__all__ = ["SimMounter", "PtyRigBackend"]


class SimMounter:
    """:class:`rigctl.core.interfaces.PlateMounter` of a simulated rig (or the in-process model):
    ``sim.set_texture(label, textures)``."""

    def __init__(self, sim):
        self.sim = sim

    def mount(self, label: str, textures: TextureSet, prompt: Callable[[str], Any] | None = None) -> None:
        self.sim.set_texture(textures.resolve(label), textures)


class PtyRigBackend(PortBackend):
    """A simulated rig on ptys (:class:`rigctl.simulation.rig.SimulatedRig` or :class:`rigctl.simulation.hil.HilRig`)
    as a :class:`rigctl.core.interfaces.RigBackend`.

    Parameters
    ----------
    sim : the simulated rig, not yet started (started by ``__enter__``, stopped by ``__exit__``).
    mode : "sim" | "replay" | "hil".
    seed : the seed it was built with (for the session's ``rig_config``).
    drum_timeout_s : the drum client's answer timeout, s (:data:`rigctl.rigs.ANSWER_TIMEOUT_S`; the simulated boards
        share the host's CPU and answer late on a loaded machine).
    drum_watchdog_ms : WATCHDOG_MS the drum client writes when it opens (:data:`rigctl.rigs.WATCHDOG_MS`; None: the
        controller's default).

    Attributes
    ----------
    sim : the simulated rig (tests pull its cables: ``rig.backend.sim.unplug_taxel()``).
    """

    def __init__(self, sim, *, mode: str = "sim", seed: int | None = None, textures: TextureSet | None = None,
                 drum_timeout_s: float, drum_watchdog_ms: int | None = None):
        self.sim = sim
        self.drum_timeout_s = drum_timeout_s
        self.drum_watchdog_ms = drum_watchdog_ms
        self.mode = mode
        self.seed = seed
        self.mounter = SimMounter(sim)
        self.textures = textures or PAPER_TEXTURES

    # read-only here: the ports of the started simulated rig (PortBackend's subclasses may set plain attributes)
    @property
    def drum_port(self) -> str:  # type: ignore[override]
        return self.sim.drum_port

    @property
    def taxel_port(self) -> str:  # type: ignore[override]
        return self.sim.taxel_port

    def __enter__(self) -> "PtyRigBackend":
        self.sim.__enter__()
        return self

    def drum(self, **options: Any) -> DrumClient:
        """The drum client, on the rig's :attr:`shared_clock`; on a simulated board that runs its real bootloader
        (``HilRig(bootloaders=True)``), one that waits the boot window out after every open (the rig's
        ``drum_boot_wait_s`` / ``drum_boot_quiet_s``), timed on the board's own simulated clock: a pty gives no sign
        that the board resets on open."""
        if getattr(self.sim, "drum_boot_wait_s", 0.0):
            options = {"boot_wait_s": self.sim.drum_boot_wait_s, "boot_quiet_s": self.sim.drum_boot_quiet_s,
                       "clock": self.sim.clock, **options}
        if self.shared_clock is not None:
            options = {"clock": self.shared_clock, **options}
        return super().drum(**options)

    @property
    def shared_clock(self) -> SharedClock | None:
        """The rig's one clock (docs/architecture.md "Time on a simulated rig"), which the drum client and the taxel
        stream time their waits, timeouts and receive stamps on; None on a rig without one."""
        clock = getattr(self.sim, "clock", None)
        return clock if isinstance(clock, SharedClock) else None

    def taxels(self, **options: Any) -> TaxelStream:
        """The taxel stream reader, waiting ``sim.taxel_banner_timeout_s`` for the banner where the rig gives one (a
        bootloader's wait in simulated time); a rig whose frames stand in for a board it does not run gives those
        (``sim.index_frame_source()``: the Mega alone under simavr, :class:`rigctl.simulation.hil_index_taxels.
        IndexFrames`)."""
        stand_in = getattr(self.sim, "index_frame_source", None)
        source = stand_in() if stand_in is not None else None
        if source is not None:
            return source
        timeout = getattr(self.sim, "taxel_banner_timeout_s", None)
        if timeout:
            options = {"banner_timeout_s": timeout, **options}
        if self.shared_clock is not None:
            options = {"clock": self.shared_clock, **options}
        return super().taxels(**options)

    def __exit__(self, *exc) -> None:
        self.sim.__exit__(None, None, None)

    # the replay rig (:class:`rigctl.core.interfaces.ReplayProvenance`): trials follow the source's and know it
    def begin_source_trial(self) -> int | None:
        """A recorded trial starts: the replay source goes on at its next trial; the wire sequence number of the
        frame carrying its first sample (None on other rigs)."""
        begin = getattr(self.sim, "begin_source_trial", None)
        return begin() if begin is not None else None

    def source_provenance(self, last_seq: int, n: int) -> dict:
        """The replay source's labels and sample range of the ``n`` frames up to ``last_seq`` ({} on other rigs;
        :meth:`rigctl.simulation.rig.SimulatedRig.source_provenance`)."""
        prov = getattr(self.sim, "source_provenance", None)
        return prov(last_seq, n) if prov is not None else {}

    def place_mass(self, mass_g: float) -> None:
        """Rest a calibration mass on the simulated load cell (0 removes it)."""
        self.sim.place_mass(mass_g)

    # fault injection (:class:`rigctl.core.faults.FaultInjector`): the simulated rig's, or the HIL harness's once it
    # implements ``fault_refusal`` / ``inject_faults``
    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why this rig cannot model ``spec`` (None when it can)."""
        refusal = getattr(self.sim, "fault_refusal", None)
        if refusal is None:
            return f"the {self.mode} rig's harness injects no faults yet"
        return refusal(spec)

    def inject_faults(self, specs: Sequence[FaultSpec], *, power_on: bool = False) -> FaultSchedule:
        """Arm ``specs`` on the simulated rig's clock from now (see :meth:`fault_refusal`); ``power_on``: the
        ``FAULT@0`` ones wired from power-on (:class:`rigctl.core.faults.FaultInjector`)."""
        schedule: FaultSchedule = self.sim.inject_faults(specs, power_on=power_on)
        return schedule

    def describe(self) -> dict:
        out: dict[str, Any] = {"mode": self.mode, "drum_port": self.drum_port, "taxel_port": self.taxel_port,
                               "seed": self.seed}
        config = getattr(self.sim, "config", None)
        if config is not None and hasattr(config, "to_dict"):
            out["model"] = config.to_dict()
        source = getattr(self.sim, "source", None)
        if source is not None:
            out["replay_source"] = type(source).__name__
        return out
