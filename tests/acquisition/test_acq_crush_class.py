"""Crush-class faults named as such wherever advice is given (issue 55 item 4): the controller's fault advice, the
rig's latch (CLI lines, the GUI's fault dialog)."""

from __future__ import annotations

from rigctl.acquisition.safety import CAUSES, latch_from_faults
from rigctl.core.drum import CRUSH_FAULTS, CRUSH_NOTE, Fault, fault_advice


def test_every_crush_class_fault_is_named_so_and_no_other():
    """Each bit of CRUSH_FAULTS (FORCE_LIMIT, LOADCELL_REVERSED, ACTUATOR_DIRECTION, CONTACT_STIFFNESS, and firmware
    1.2's position channel and lying readings: POSITION_LIMIT, CONTACT_LOST, HX711_STUCK, HX711_LINE, HX711_CADENCE;
    1.6's LOADCELL_SCALE; 1.7's LOADCELL_ZERO; 1.9's CONTACT_MISSING) says in its
    advice and its latch that opening the rig never clears it; the other bits do not. CONTACT_STIFFNESS latches as
    itself (it was taken for an unexpected reset: the latch's default cause)."""
    assert {b.name for b in Fault if b and b in CRUSH_FAULTS} == {
        "FORCE_LIMIT", "LOADCELL_REVERSED", "ACTUATOR_DIRECTION", "CONTACT_STIFFNESS", "POSITION_LIMIT", "CONTACT_LOST",
        "HX711_STUCK", "HX711_LINE", "HX711_CADENCE", "LOADCELL_SCALE", "LOADCELL_ZERO", "CONTACT_MISSING"}
    for bit in Fault:
        if not bit:
            continue
        crush = bit in CRUSH_FAULTS
        assert (CRUSH_NOTE in fault_advice(int(bit))) == crush, bit.name
        latch = latch_from_faults(int(bit))
        assert (CRUSH_NOTE in latch.describe()) == crush, (bit.name, latch.describe())
        # no bit falls to the latch's default cause; RESET is the controller's own reset latch (firmware 1.5)
        assert (latch.cause == "reset") == (bit == Fault.RESET), bit.name
    assert latch_from_faults(int(Fault.CONTACT_STIFFNESS)).label == "contact too stiff"
    assert CRUSH_NOTE in CAUSES["contact-stiffness"][1]
