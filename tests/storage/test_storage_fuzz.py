"""Property-based fuzzing (hypothesis) of the two readers of rigctl's files: a session file (``open_session``, and
the header a resuming ``SessionWriter`` reads) and an encoded file (``open_encoded``), truncated, bit-flipped,
overwritten with garbage, or structurally altered (objects deleted or replaced by arrays of other shapes and
types, attributes of other types): opening and reading all of it either works or raises the module's error type
(``SessionError``, ``NotEncodedError``), never another exception and never a crash.

Deterministic (``derandomize``) so that the suite is repeatable; ``RIGCTL_FUZZ_EXAMPLES`` raises the number of
examples for a longer campaign (e.g. ``RIGCTL_FUZZ_EXAMPLES=3000``, then also set ``RIGCTL_FUZZ_RANDOM=1`` for
fresh examples).
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.core import PAPER_SENSOR, PAPER_TEXTURES
from rigctl.storage.encoded import EncodedWriter, NotEncodedError, open_encoded
from rigctl.storage.session import SessionError, SessionWriter, TrialData, open_session

N_EXAMPLES = int(os.environ.get("RIGCTL_FUZZ_EXAMPLES", "60"))
FUZZ = settings(max_examples=N_EXAMPLES, deadline=None, database=None,
                derandomize=not os.environ.get("RIGCTL_FUZZ_RANDOM"),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
#: examples run per reader (the figures of a campaign)
TRIED: dict[str, int] = {}


# -- the files fuzzed ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_originals")
    session = d / "s.h5"
    rng = np.random.default_rng(1)
    plan = [dict(trial_id=i, texture="ABC"[i % 3], speed_mm_s=40.0 + i, force_g=100.0, duration_s=0.05)
            for i in range(5)]
    with SessionWriter.create(session, plan=plan, protocol_source="name = 'fuzz'", compression="gzip",
                              calibration={"taxel_min": np.zeros(18), "taxel_max": np.full(18, 1000.0)}) as w:
        for k in range(3):
            w.write_trial(k, TrialData(taxels=rng.integers(0, 1024, (50, 18)), force_g=[1.0, 2.0],
                                       force_time_s=[0.0, 0.02], speed_mm_s=[40.0], speed_time_s=[0.0]))
        w.mark_failed(3, "DrumTimeout: fuzz")
    encoded = d / "e.h5"
    n = 4
    trials = {"trial_id": np.arange(n), "texture": list("ABAB"), "speed_mm_s": np.full(n, 40.0),
              "force_g": np.full(n, 100.0), "duration_s": np.full(n, 0.05), "n_samples": np.full(n, 50)}
    with EncodedWriter(encoded, layout=PAPER_SENSOR, textures=PAPER_TEXTURES, trials=trials,
                       parameters={"fs_hz": 1000.0}) as ew:
        ew.write_normalisation(np.zeros(18), np.full(18, 1000.0))
        ew.write_features("original", 0, rng.random((n, 12)))
        ew.add_spikes("original", 36, "SA then RA")
        times = np.sort(rng.random(30) * 0.05)
        index = np.sort(rng.integers(0, 31, n * 36))
        index[-1] = 30
        ew.append_spikes("original", type("T", (), {"spike_times": times, "spike_times_index": index,
                                                    "n_trains": 36})())
        table = np.zeros(2, dtype=[("texture", "U1"), ("speed_mm_s", "f4"), ("force_g", "f4"), ("taxel", "i4"),
                                   ("coeff", "f8"), ("converged", "?"), ("target_rate", "f8"), ("rate", "f8")])
        table["texture"] = ["A", "B"]
        ew.write_force_coefficients(table, n_not_converged=0, n_coefficients=2)
        ew.set_attrs(skipped_variants={}, input_rate_hz=1000.0, model_rate_hz=1000.0, resampled=False)
    # the originals read cleanly: a fuzz failure is the fuzzing's, not a broken original
    assert _read_session(session) == "ok" and _read_encoded(encoded) == "ok"
    return _Originals({"session": session.read_bytes(), "encoded": encoded.read_bytes(), "dir": d})


class _Originals(dict):
    def __repr__(self) -> str:  # hypothesis prints the arguments of a failing example: not the files' bytes
        return f"<originals in {self['dir']}>"


# -- reading all of a file -------------------------------------------------------------------------------------------
def _read_session(path: Path) -> str:
    """Everything a user of a session reads: info's view, every complete trial, the resume header."""
    with open_session(path) as s:
        _ = (s.attrs, s.layout, s.textures, s.rig_config, s.protocol_source, s.calibration, len(s))
        for tid in s.completed_ids():
            s.trial_attrs(tid)
            t = s.trial(tid)
            assert t.taxels.dtype == np.uint16 and t.taxels.shape[1] == s.layout.n_channels
            assert int(t.taxels.max(initial=0)) <= s.layout.adc_max
        list(s.iter_trials())
        s.failed_ids()
    with SessionWriter.open(path) as w:
        w.pending_ids()
    return "ok"


def _read_encoded(path: Path) -> str:
    with open_encoded(path) as f:
        _ = (f.attrs, f.layout, f.textures, f.n_trials, f.trials, f.skipped_variants, f.resampling, repr(f))
        for v in f.variants:
            x = f.features(v)
            assert x.shape == f.feature_shape(v) and x.shape[0] == f.n_trials
            f.n_trains(v)
        for v in f.spike_variants:
            sp = f.spikes(v)
            assert sp.spike_times_index.size == f.n_trials * sp.n_trains
            f.spike_trains_description(v)
        if "normalisation" in f._f:
            _ = f.normalisation
        for lf in (False, True):
            f.force_coefficients(label_free=lf)
            f.force_fit_stats(label_free=lf)
    return "ok"


def _outcome(reader, path: Path, error_type) -> str:
    """``ok`` or the error's class name; anything but the module's error type fails the test."""
    try:
        return reader(path)
    except error_type as exc:
        msg = str(exc)
        assert msg and "\n" not in msg.strip(), msg  # one line
        return type(exc).__name__


# -- mutations -------------------------------------------------------------------------------------------------------
def _scratch(originals, name: str, data: bytes) -> Path:
    p = originals["dir"] / f"{name}-{uuid.uuid4().hex[:8]}.h5"
    p.write_bytes(data)
    return p


def _drop(path: Path) -> None:
    for q in (path, path.with_name(path.name + ".lock"), path.with_name(path.name + ".journal")):
        q.unlink(missing_ok=True)


byte_damage = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("flip"), st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 7)), min_size=1, max_size=8)),
    st.tuples(st.just("garbage"), st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=64))),
)


def _damage_bytes(data: bytes, damage) -> bytes:
    kind, arg = damage
    buf = bytearray(data)
    if kind == "truncate":
        return bytes(buf[: int(arg * (len(buf) - 1))])
    if kind == "flip":
        for where, bit in arg:
            buf[int(where * (len(buf) - 1))] ^= 1 << bit
        return bytes(buf)
    where, junk = arg
    i = int(where * (len(buf) - 1))
    buf[i:i + len(junk)] = junk
    return bytes(buf[: len(data)])


dtypes = st.sampled_from(["u1", "u2", "i4", "i8", "f4", "f8", "S4", "bool"])
shapes = st.lists(st.integers(0, 40), min_size=0, max_size=3).map(tuple)
attr_values = st.one_of(st.integers(-2**40, 2**40), st.floats(allow_nan=True), st.text(max_size=30),
                        st.binary(max_size=20), st.lists(st.integers(-5, 5), max_size=6),
                        st.sampled_from(["{}", "[]", "null", '{"name": 3}', json.dumps({"layers": []}), "{bad json"]))


def _objects(f: h5py.File) -> list[str]:
    names = [""]
    f.visit(names.append)
    return names


def _alter(path: Path, ops) -> None:
    """Apply structural changes with h5py: delete an object, replace it by an array of another shape/type, set
    an attribute (one of the object's own, or a new one) to a value of another type."""
    with h5py.File(path, "r+") as f:
        for op, pick, dtype, shape, value in ops:
            names = _objects(f)
            name = names[int(pick * (len(names) - 1))]
            obj = f[name] if name else f
            if op == "delete" and name:
                del f[name]
            elif op == "replace" and name:
                del f[name]
                n = int(np.prod(shape)) if shape else 1
                data = (np.arange(n) % 251).astype(dtype).reshape(shape) if dtype != "S4" else \
                    np.array([b"ab"] * n, "S4").reshape(shape)
                f.create_dataset(name, data=data)
            elif op == "attr":
                keys = list(obj.attrs) or ["status"]
                key = keys[int(pick * 7919) % len(keys)]
                try:
                    obj.attrs[key] = value
                except (TypeError, ValueError):  # a value h5py cannot store: keep the object as it is
                    pass


structure = st.lists(st.tuples(st.sampled_from(["delete", "replace", "attr", "attr"]), st.floats(0.0, 1.0), dtypes,
                               shapes, attr_values), min_size=1, max_size=4)


# -- the properties --------------------------------------------------------------------------------------------------
@FUZZ
@given(damage=byte_damage)
def test_session_reader_on_damaged_bytes(originals, damage):
    p = _scratch(originals, "s", _damage_bytes(originals["session"], damage))
    try:
        _outcome(_read_session, p, SessionError)
        TRIED["session bytes"] = TRIED.get("session bytes", 0) + 1
    finally:
        _drop(p)


@FUZZ
@given(ops=structure)
def test_session_reader_on_altered_structure(originals, ops):
    p = _scratch(originals, "s", originals["session"])
    try:
        _alter(p, ops)
        _outcome(_read_session, p, SessionError)
        TRIED["session structure"] = TRIED.get("session structure", 0) + 1
    finally:
        _drop(p)


@FUZZ
@given(damage=byte_damage)
def test_encoded_reader_on_damaged_bytes(originals, damage):
    p = _scratch(originals, "e", _damage_bytes(originals["encoded"], damage))
    try:
        _outcome(_read_encoded, p, NotEncodedError)
        TRIED["encoded bytes"] = TRIED.get("encoded bytes", 0) + 1
    finally:
        _drop(p)


@FUZZ
@given(ops=structure)
def test_encoded_reader_on_altered_structure(originals, ops):
    p = _scratch(originals, "e", originals["encoded"])
    try:
        _alter(p, ops)
        _outcome(_read_encoded, p, NotEncodedError)
        TRIED["encoded structure"] = TRIED.get("encoded structure", 0) + 1
    finally:
        _drop(p)


def test_each_reader_refuses_the_other_kind_of_file(originals):
    """A session given to the encoded reader and the other way round: each says what it is, in one line."""
    s = _scratch(originals, "s", originals["session"])
    e = _scratch(originals, "e", originals["encoded"])
    try:
        assert _outcome(_read_encoded, s, NotEncodedError) == "NotEncodedError"
        assert _outcome(_read_session, e, SessionError) == "SessionError"
    finally:
        _drop(s)
        _drop(e)


def test_fuzz_cases_were_run():
    """Reports the examples of this run (with ``-s``); all four properties ran when the module ran whole."""
    print("fuzz cases tried:", TRIED, "total", sum(TRIED.values()))
    if len(TRIED) == 4:
        assert all(n >= min(N_EXAMPLES, 10) for n in TRIED.values()), TRIED

