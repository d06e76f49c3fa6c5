"""Property-based fuzzing of the protocol schema (hypothesis): any TOML document either parses into a protocol whose
plan can be expanded, or raises ProtocolError, one line, naming the key and/or the line at fault. Nothing else."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.acquisition.protocol import Protocol, ProtocolError, parse_protocol

PROTOCOLS = Path(__file__).resolve().parents[2] / "protocols"
MISSING = object()
#: examples per property in the suite (each run draws new ones; 4,000 per property passed when this was written)
FUZZ = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])

# ------------------------------------------------------------------------------------------------ TOML text
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # JSON's escapes are TOML basic-string escapes
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(doc: dict, tables: bool) -> str:
    """TOML text of ``doc``; with ``tables``, sub-tables as ``[name]`` sections and lists of tables as ``[[name]]``."""
    head, tail = [], []
    for k, v in doc.items():
        if tables and isinstance(v, dict) and v and not any(isinstance(x, dict) for x in v.values()):
            tail.append(f"[{_key(k)}]")
            tail += [f"{_key(kk)} = {_value(vv)}" for kk, vv in v.items()]
        elif tables and isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                tail.append(f"[[{_key(k)}]]")
                tail += [f"{_key(kk)} = {_value(vv)}" for kk, vv in item.items()]
        else:
            head.append(f"{_key(k)} = {_value(v)}")
    return "\n".join(head + tail) + "\n"


# ------------------------------------------------------------------------------------------------ strategies
names = st.text(alphabet="ABCDEFGHIJKLMNOPabcxyz_- 0123456789", min_size=1, max_size=8)
numbers = st.one_of(
    st.integers(min_value=-(2 ** 63), max_value=2 ** 63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, -1, 1e-300, 40, 150, 150.000001, 600, 1500, 1500.5, 1e6, 1_000_001, 10, 11]),
)
scalars = st.one_of(st.booleans(), numbers, st.text(max_size=6), names)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(names, inner, max_size=3)), max_leaves=4)


def field(good):
    """A field: its good value, absent, or any TOML value."""
    return st.one_of(st.just(good), st.just(MISSING), values)


def table(fields: dict, extra=True):
    keys = {k: field(v) for k, v in fields.items()}
    base = st.fixed_dictionaries(keys)
    if extra:
        base = st.tuples(base, st.dictionaries(names, values, max_size=1)).map(lambda t: {**t[1], **t[0]})
    return base.map(lambda d: {k: v for k, v in d.items() if v is not MISSING})


settle = table({"force_timeout_s": 10, "speed_timeout_s": 5.0, "speed_tolerance_mm_s": 2, "force_tolerance_g": 15,
                 "settle_time_ms": 50})
profile = table({"name": "up", "kind": "ramp", "start_mm_s": 40, "end_mm_s": 120, "speed_mm_s": 80})
texture_set = table({"name": "fabrics", "textures": ["Linen", "HB3", "Velvet"],
                     "groups": {"woven": ["Linen"], "knit": ["HB3", "Velvet"]},
                     "geometry": {"Linen": {"kind": "wave", "height_mm": 1.0, "period_mm": 10.0}}})
documents = st.builds(
    lambda top, st_, prof, ts: {**top, **{k: v for k, v in (("settle", st_), ("profiles", prof),
                                                             ("texture_set", ts)) if v is not MISSING}},
    table({"name": "fuzz", "description": "d", "textures": ["A", "B"], "speeds_mm_s": [40, 120],
           "forces_g": [250, 1000], "trials_per_condition": 2, "travel_mm": 240, "duration_s": 1.5,
           "order": "random", "seed": 3, "max_dropped_frames": 0, "retries": 2}),
    st.one_of(st.just(MISSING), settle, values),
    st.one_of(st.just(MISSING), st.lists(profile, max_size=3), values),
    st.one_of(st.just(MISSING), texture_set, values),
)


# ------------------------------------------------------------------------------------------------ the property
def check(text: str):
    """Parse ``text``: a Protocol whose plan expands, or a ProtocolError naming the key and/or line at fault."""
    try:
        proto = parse_protocol(text, path="fuzz.toml")
    except ProtocolError as err:
        msg = str(err)
        assert "\n" not in msg and msg.startswith("fuzz.toml:"), msg
        assert err.line is not None or err.key is not None, msg
        lines = text.splitlines()
        if err.line is not None:
            assert 1 <= err.line <= max(1, len(lines)), msg
            if err.key:  # the line shows the key, or the table / array it sits in
                parts = [p for p in re.sub(r"\[\d+\]", ".", err.key).split(".") if p]  # [i]: an array index
                assert any(p in lines[err.line - 1] for p in parts), (msg, lines[err.line - 1])
        return err
    assert isinstance(proto, Protocol)
    n = len(proto.textures) * len(proto.forces_g) * len(proto.profiles) * proto.trials_per_condition
    if n <= 2000:
        plan = proto.plan()
        assert len(plan) == n and all(0 < p.duration_s <= 600 for p in plan)
        assert math.isfinite(proto.estimated_duration_s())
    assert proto.max_dropped_frames >= 0 and 0 <= proto.retries <= 10
    return proto


@settings(FUZZ, max_examples=100)  # drawing these documents is what takes the time (~50 ms each), not parsing
@given(documents, st.booleans())
def test_any_document_parses_or_names_the_key_at_fault(doc, tables):
    check(to_toml(doc, tables))


def _mutate(text: str, edits) -> str:
    for pos, cut, insert in edits:
        p = pos % (len(text) + 1)
        text = text[:p] + insert + text[p + cut:]
    return text


@FUZZ
@given(st.sampled_from(sorted(p.name for p in PROTOCOLS.glob("*.toml"))),
       st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 6),
                          st.sampled_from(["", "=", "[", "]", "\"", "\n", "#", ",", "0", "-1", "nan", "{", "}",
                                           "[[profiles]]\n", "[settle]\n", "x = 1\n", "retries = 99\n", "'''"])),
                min_size=1, max_size=4))
def test_any_edit_of_a_shipped_protocol_parses_or_names_the_line_at_fault(name, edits):
    check(_mutate((PROTOCOLS / name).read_text(), edits))


def test_the_new_keys_are_checked_with_their_line():
    base = 'name = "t"\ntextures = ["A"]\nspeeds_mm_s = [40]\nforces_g = [250]\n'
    p = check(base + "max_dropped_frames = 20\nretries = 0\n")
    assert (p.max_dropped_frames, p.retries) == (20, 0)
    p = check(base)
    assert (p.max_dropped_frames, p.retries) == (0, 2)
    for bad, key in (("max_dropped_frames = -1", "max_dropped_frames"), ("retries = 11", "retries"),
                     ("retries = 1.5", "retries"), ('max_dropped_frames = "all"', "max_dropped_frames"),
                     ("trials_per_condition = 2000000", "trials_per_condition")):
        err = check(base + bad + "\n")
        assert isinstance(err, ProtocolError) and err.key == key and err.line == 5, str(err)
