"""Every fault's advice names the most likely cause first (issue 75 item 4), judged on its structure: the parts each
advice sends the operator to (``FaultWords.causes``, ``rigctl.acquisition.safety.CAUSE_PARTS``) are the parts its
words name, in the order they name them, and that order is by the FMEA's occurrence rating (``rigctl.core.parts.PARTS``,
docs/safety.md "Occurrence", the same table), ties allowed, except where ``ADVICE_ORDER_EXCEPTIONS`` says why. The
advice walker (tests/simulation/test_sim_advice_walk.py) judges each campaign fault's latch against the part it
breaks."""

from __future__ import annotations

from pathlib import Path

import pytest

from rigctl.acquisition.safety import CAUSE_PARTS, CAUSES, FAULT_CAUSES
from rigctl.core.drum import ACTUATOR_DIRECTION_CAUSES, FAULT_WORDS, Fault
from rigctl.core.parts import ADVICE_ORDER_EXCEPTIONS, PARTS, Part, less_likely_first, named_at
from rigctl.simulation.campaign import CAMPAIGN_FAULTS, FAULT_PARTS

SAFETY_MD = Path(__file__).resolve().parents[2] / "docs" / "safety.md"

#: every advice by its key (a fault bit's name, a host latch cause): (its words, its parts)
ADVICES: dict[str, tuple[str, tuple[Part, ...]]] = {
    **{str(bit.name): (w.advice, w.causes) for bit, w in FAULT_WORDS.items()},
    **{key: (remedy, CAUSE_PARTS.get(key, ())) for key, (_, remedy) in CAUSES.items()},
}


def test_every_advice_has_its_parts():
    assert {b for b in Fault if b} == set(FAULT_WORDS)
    assert set(CAUSE_PARTS) == set(CAUSES)
    for key, (_, causes) in ADVICES.items():
        assert causes, f"{key}'s advice names no part"
        assert len(set(causes)) == len(causes), key


def test_both_faces_send_the_operator_to_the_same_parts():
    """A fault bit's words (the CLI, the doctor: fault_advice) and its latch cause's remedy (the GUI's fault dialog)
    name the same parts in the same order."""
    for bit, cause in FAULT_CAUSES:
        assert FAULT_WORDS[bit].causes == CAUSE_PARTS[cause], (bit.name, cause)


@pytest.mark.parametrize("key", sorted(ADVICES))
def test_the_words_name_the_parts_in_their_order(key):
    """The structure cannot drift from what the operator reads: each part is named (by one of its phrases) and in
    the tuple's order."""
    advice, causes = ADVICES[key]
    at = [named_at(advice, part) for part in causes]
    missing = [part.name for part, i in zip(causes, at, strict=True) if i < 0]
    assert not missing, f"{key}'s advice does not name {missing}: {advice}"
    assert at == sorted(at) and len(set(at)) == len(at), (
        f"{key}'s advice names {[p.name for _, p in sorted(zip(at, causes, strict=True))]}, its causes say "
        f"{[p.name for p in causes]}")


@pytest.mark.parametrize("key", sorted(ADVICES))
def test_the_most_likely_cause_comes_first(key):
    _, causes = ADVICES[key]
    assert less_likely_first(key, causes) == [], (
        f"{key}: less likely named before likelier: "
        f"{[(a.name, PARTS[a].occurrence, b.name, PARTS[b].occurrence) for a, b in less_likely_first(key, causes)]}")


def test_every_exception_is_used_and_says_why():
    """An exception that no advice needs is stale: each one's advice names its part before a likelier one."""
    for (key, part), why in ADVICE_ORDER_EXCEPTIONS.items():
        assert key in ADVICES and why, key
        causes = ADVICES[key][1]
        later = causes[causes.index(part) + 1:]
        assert any(PARTS[b].occurrence > PARTS[part].occurrence for b in later), (key, part.name)


def test_the_order_check_sees_a_less_likely_part_first():
    """The check can fail: a broken cell (O 2) named before a changed plate (O 8), and the exception that allows a
    quick harmless check first only for its own advice."""
    assert less_likely_first("LOADCELL_SCALE", (Part.LOADCELL, Part.PLATE)) == [(Part.LOADCELL, Part.PLATE)]
    assert less_likely_first("HX711_STUCK", (Part.HX711_CHIP, Part.HX711_WIRES)) == []
    assert less_likely_first("HX711_LINE", (Part.HX711_CHIP, Part.HX711_WIRES)) == [(Part.HX711_CHIP, Part.HX711_WIRES)]
    assert named_at("check the plate, then the coupling", Part.COUPLING) > named_at("check the plate", Part.PLATE)
    assert named_at("nothing here", Part.COUPLING) == -1


def test_the_ratings_are_an_fmea_scale_with_sources():
    for part in Part:
        rating = PARTS[part]
        assert 1 <= rating.occurrence <= 10 and rating.source and rating.names and rating.words, part


def test_the_walker_table_covers_the_campaign_and_says_why_where_it_does_not_judge():
    assert set(FAULT_PARTS) == set(CAMPAIGN_FAULTS)
    for fault, broken in FAULT_PARTS.items():
        assert broken.part is not None or broken.unjudged, fault
        if not broken.unjudged:  # the part it breaks is one some advice sends the operator to
            assert any(broken.part in causes for _, causes in ADVICES.values()), fault


def occurrence_table() -> str:
    """docs/safety.md's "Occurrence" table as PARTS makes it."""
    rows = ["| part | O | what fails | source |", "|---|---|---|---|"]
    rows += [f"| `{part.value}` | {r.occurrence} | {r.words} | {r.source} |" for part, r in PARTS.items()]
    return "\n".join(rows)


def test_docs_safety_md_holds_the_ratings_verbatim():
    doc = SAFETY_MD.read_text(encoding="utf-8")
    block = doc.split("<!-- fmea: occurrence -->\n", 1)[1].split("\n\n", 1)[0]
    assert block == occurrence_table(), "docs/safety.md's occurrence table is not rigctl.core.parts.PARTS:\n" + (
        occurrence_table())
    ordered = [r.occurrence for r in PARTS.values()]
    assert ordered == sorted(ordered, reverse=True), "PARTS most likely first"


def test_actuator_direction_changes_no_wire_before_the_evidence():
    """The walker's finding kept by the order: the coil pair is the last part ACTUATOR_DIRECTION names, after the
    zero, the hand press (A+/A-) and the home switch."""
    causes = FAULT_WORDS[Fault.ACTUATOR_DIRECTION].causes
    assert causes[-1] == Part.ACTUATOR_COILS and causes[0] == Part.LOADCELL_ZERO
    assert ACTUATOR_DIRECTION_CAUSES.index("home switch") < ACTUATOR_DIRECTION_CAUSES.index("coil pair")
