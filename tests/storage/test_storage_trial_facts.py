"""Schema 4's trial facts (rigctl.storage.trial_facts): the writer's facts of each trial's samples let the one trial
validator judge a sealed file without reading the samples, and it judges exactly as reading them does.

- Generated sessions damaged as they are written (counts outside the ADC range, byte copies of earlier trials,
  constant trials, seq gaps said and unsaid, short and long trials, NaN and inf readings, empty trials, impossible
  counters), in batches, some trials written by an "older rigctl" (no facts), some resumed: the report from the
  facts equals the report from the samples (the same trials, reasons, frames missing and non-finite readings);
  every trial's samples are read once a report and checked against the checksum sealed with them (issue 52).
- The same sessions damaged after writing (h5py in ``r+`` mode, a lying facts row, a truncation): the seal is
  broken, the damage is found as reading the samples finds it, also after a writer resumed and sealed the file
  again (it drops the facts it can no longer vouch for).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.core.sensor import PAPER_SENSOR
from rigctl.storage import trial_blocks, trial_facts
from rigctl.storage.session import SessionError, SessionWriter, TrialData, open_session
from rigctl.storage.session_reader import SessionReader
from rigctl.storage.validate import precheck, usable_trials

N_EXAMPLES = int(os.environ.get("RIGCTL_FUZZ_EXAMPLES", "25"))
PROPERTY = settings(max_examples=N_EXAMPLES, deadline=None, database=None,
                    derandomize=not os.environ.get("RIGCTL_FUZZ_RANDOM"),
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
#: the session's sensor as a 16-bit one: the writer takes its trials (same channels and rate), as it would from an
#: importer told the wrong resolution, and stores counts the session's 10-bit sensor cannot give
WIDE = dataclasses.replace(PAPER_SENSOR, adc_bits=16)
KINDS = ("good", "good", "range", "copy", "constant", "gaps", "gaps_said", "short", "long", "nan", "inf", "empty",
         "crc")


def _trial(kind: str, rng: np.random.Generator, earlier: list[TrialData]) -> tuple[TrialData, int]:
    """A trial of ``kind`` and the samples its plan asks."""
    planned = 2 if kind == "empty" else int(rng.integers(10, 60))
    n = {"short": planned // 4, "long": 3 * planned + 3, "empty": 0}.get(kind, planned)
    taxels = rng.integers(0, 1024, (n, 18))
    layout = WIDE if kind == "range" else PAPER_SENSOR
    if kind == "copy" and earlier:
        src = earlier[int(rng.integers(len(earlier)))]
        taxels, n, planned, layout = src.taxels.copy(), src.n_samples, max(src.n_samples, 2), src.layout
    elif kind == "constant":
        taxels = np.full((n, 18), int(rng.choice([0, 7, 1023])))
    elif kind == "range" and n:
        taxels[int(rng.integers(n)), int(rng.integers(18))] = int(rng.integers(1024, 65536))
    seq = (int(rng.integers(0, 65536)) + np.arange(n)) % 65536
    dropped = 0
    if kind in ("gaps", "gaps_said") and n > 2:
        seq = (seq + np.where(np.arange(n) >= n // 2, 3, 0)) % 65536
        dropped = 3 + int(rng.integers(0, 2)) if kind == "gaps_said" else int(rng.integers(0, 3))
    k = int(rng.integers(0, 4))
    force, force_t = rng.normal(500, 3, k), np.linspace(0, 0.05, k)
    speed, speed_t = rng.normal(80, 1, 3), np.linspace(0, 0.05, 3)
    if kind == "nan" and k:
        force[int(rng.integers(k))] = np.nan
    if kind == "inf":
        speed_t[int(rng.integers(3))] = np.inf
    data = TrialData(taxels=taxels, seq=seq, force_g=force, force_time_s=force_t, speed_mm_s=speed,
                     speed_time_s=speed_t, dropped_frames=dropped,
                     crc_errors=2 ** 40 if kind == "crc" else int(rng.integers(0, 3)),
                     layout=layout)
    return data, planned


def _forget_facts(path: Path) -> None:
    """What a rigctl before trial facts leaves: no ``/recording/facts``, no seal."""
    with h5py.File(path, "r+") as f:
        del f["recording/facts"]
        del f.attrs[trial_facts.SEAL_ATTR]


def _session(path: Path, kinds: list[str], seed: int, batches: int, old_first: bool, resume: bool) -> list[int]:
    """Write a session of trials of ``kinds`` (batches in shuffled order; the first batch by an "older rigctl" when
    ``old_first``; a writer opened again for the later ones when ``resume``); returns the ids written."""
    rng = np.random.default_rng(seed)
    trials: list[TrialData] = []
    plan = []
    for i, kind in enumerate(kinds):
        data, planned = _trial(kind, rng, trials)
        trials.append(data)
        plan.append(dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0,
                         duration_s=planned / 1000.0))
    order = [int(i) for i in rng.permutation(len(kinds))]
    written = order[: max(1, len(order) - 1)]  # one trial stays pending
    parts = np.array_split(np.array(written), batches)
    w = SessionWriter.create(path, plan=plan, protocol_source="facts", compression=None, durable=False)
    try:
        for b, part in enumerate(parts):
            if resume and b:
                w.close()
                w = SessionWriter.open(path, protocol_source="facts", durable=False)
            w.write_trials([(int(t), trials[int(t)]) for t in part])
            if b == 0 and old_first:
                w.close()
                _forget_facts(path)
                w = SessionWriter.open(path, protocol_source="facts", durable=False)
        if order[-1] not in written:
            w.mark_failed(order[-1], "DrumTimeout: generated")
    finally:
        w.close()
    return written


@contextmanager
def _samples_only():
    """The validator as for a file without facts: it reads every trial's samples."""
    with mock.patch.object(SessionReader, "trusted_facts", lambda self: {}):
        yield


def _judged(path: Path) -> tuple:
    """Both reports (``keep_nonfinite`` False and True) and :func:`precheck` of a fresh opening of ``path``."""
    out = []
    for keep in (False, True):
        with open_session(path) as s:
            r = usable_trials(s, keep_nonfinite=keep)
            out.append((r.ids, r.excluded, r.dropped_frames, r.nonfinite))
    with open_session(path) as s:
        out.append(precheck(s))
    return tuple(out)


@contextmanager
def _taxel_reads():
    """The trials' taxel rows the validator reads (``read_rows`` of ``/recording/taxels``), as a list of counts."""
    rows: list[int] = []
    real = trial_blocks.read_rows

    def counting(ds, starts, lengths, out):
        if ds.name == "/recording/taxels":
            rows.extend(int(n) for n in lengths)
        return real(ds, starts, lengths, out)

    with mock.patch.object(trial_blocks, "read_rows", counting):
        yield rows


sessions = st.tuples(st.lists(st.sampled_from(KINDS), min_size=2, max_size=12), st.integers(0, 2 ** 32 - 1),
                     st.integers(1, 3), st.booleans(), st.booleans())


@PROPERTY
@given(spec=sessions)
def test_facts_judge_as_the_samples_do(tmp_path_factory, spec):
    kinds, seed, batches, old_first, resume = spec
    path = tmp_path_factory.mktemp("facts") / "s.h5"
    written = _session(path, kinds, seed, batches, old_first, resume)
    with open_session(path) as s:
        facts = s.trusted_facts()
        old = set(int(t) for t in np.array_split(np.array(written), batches)[0]) if old_first else set()
        assert set(facts) == set(written) - old  # sealed: every trial written with facts is trusted
        bad_range = {t for t, q in facts.items() if int(q["taxels_max"]) > s.layout.adc_max}
    with _taxel_reads() as reads:
        judged = _judged(path)
    with _samples_only():
        assert _judged(path) == judged
    # every trial's samples are read, its content checked against the checksum sealed with it (issue 52: a seal
    # held by the modification time alone let an edit with the time put back pass), each at most once a report
    # (three reports; a trial an earlier check excluded is not read)
    assert len(reads) <= 3 * len(written)
    assert bad_range <= set(facts)


N = 40  # samples of every trial of the clean session


def _clean_trial(rng: np.random.Generator) -> TrialData:
    return TrialData(taxels=rng.integers(0, 1024, (N, 18)), seq=np.arange(N), force_g=rng.normal(500, 3, 2),
                     force_time_s=[0.0, 0.02], speed_mm_s=rng.normal(80, 1, 2), speed_time_s=[0.0, 0.02])


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """Eight planned trials of N samples, 0-6 written in two commits, 7 pending."""
    path = tmp_path_factory.mktemp("clean") / "clean.h5"
    rng = np.random.default_rng(11)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0, duration_s=N / 1000.0)
            for i in range(8)]
    with SessionWriter.create(path, plan=plan, protocol_source="facts", compression=None, durable=False) as w:
        w.write_trials([(i, _clean_trial(rng)) for i in (2, 0, 1)])
        w.write_trials([(i, _clean_trial(rng)) for i in (3, 4, 5, 6)])
    return path


def _rows(f: h5py.File, tid: int) -> slice:
    idx = f["recording/index"][()]
    r = idx[idx["trial_id"] == tid][0]
    return slice(int(r["sample_start"]), int(r["sample_start"] + r["n_samples"]))


def _range(f: h5py.File) -> int:
    f["recording/taxels"][_rows(f, 1).start + 2, 5] = 2000
    return 1


def _copy(f: h5py.File) -> int:
    f["recording/taxels"][_rows(f, 4)] = f["recording/taxels"][_rows(f, 0)]
    return 4


def _seq(f: h5py.File) -> int:
    f["recording/seq"][_rows(f, 6)] = np.arange(N) * 5
    return 6


def _nan(f: h5py.File) -> int:
    idx = f["recording/index"][()]
    r = idx[idx["trial_id"] == 5][0]
    f["recording/force_g"][int(r["force_start"]) + 1] = np.nan
    return 5


def _group(f: h5py.File) -> int:
    f["trials/000003"].attrs["n_samples"] = 3
    return 3


def _lie(f: h5py.File) -> int:  # the facts say trial 0 is in range, its counts are not (the edit breaks the seal)
    f["recording/taxels"][_rows(f, 0).start, 3] = 4000
    facts = f["recording/facts"][()]
    facts["taxels_max"][facts["trial_id"] == 0] = 7
    f["recording/facts"][...] = facts
    return 0


EDITS = {"range": (_range, "taxels hold 2000 (sample 2)"), "copy": (_copy, "byte copy of trial 0"),
         "seq": (_seq, f"seq column shows {4 * (N - 1)} missing frames"), "nan": (_nan, "1 NaN in force_g"),
         "group": (_group, "n_samples attribute says 3"), "lying facts": (_lie, "taxels hold 4000 (sample 0)")}


@pytest.mark.parametrize("edit", sorted(EDITS))
@pytest.mark.parametrize("then_resume", [False, True], ids=["edited", "edited-then-resumed"])
def test_an_edit_after_writing_is_found_as_reading_finds_it(clean, tmp_path, edit, then_resume):
    """h5py edits a sealed file: the seal no longer holds and the validator finds the damage in the samples; a
    writer that resumes the session later drops the facts it finds unsealed, so sealing it again hides nothing."""
    damage, words = EDITS[edit]
    path = tmp_path / "e.h5"
    shutil.copy2(clean, path)  # the copy keeps the modification time: sealed
    with open_session(path) as s:
        assert sorted(s.trusted_facts()) == list(range(7)) and not usable_trials(s).excluded
    with h5py.File(path, "r+") as f:
        bad = damage(f)
    if then_resume:
        with SessionWriter.open(path, protocol_source="facts", durable=False) as w:
            w.write_trial(7, _clean_trial(np.random.default_rng(1)))
    with open_session(path) as s:
        assert sorted(s.trusted_facts()) == ([7] if then_resume else [])  # only the facts written since the edit
        report = usable_trials(s)
    assert list(report.excluded) == [bad] and words in report.excluded[bad], report.excluded
    judged = _judged(path)
    with _samples_only():
        assert _judged(path) == judged


def test_a_truncated_file_is_refused_sealed_or_not(clean, tmp_path):
    path = tmp_path / "t.h5"
    shutil.copy2(clean, path)
    size = path.stat().st_size
    with open(path, "r+b") as fh:
        fh.truncate(size - 4096)
    with pytest.raises(SessionError):
        open_session(path)


def test_the_seal_is_the_files_modification_time(clean, tmp_path):
    """A session as its writer left it is sealed; a copy that keeps the time (``cp -p``) keeps the seal (it holds the
    same bytes), a plain copy does not (the validator then reads the samples)."""
    with h5py.File(clean, "r") as f:
        assert int(f.attrs[trial_facts.SEAL_ATTR]) == clean.stat().st_mtime_ns
        assert f["recording/facts"].shape == f["recording/index"].shape
    kept, plain = tmp_path / "kept.h5", tmp_path / "plain.h5"
    shutil.copy2(clean, kept)
    shutil.copy(clean, plain)
    for p, sealed in ((kept, True), (plain, False)):
        with open_session(p) as s:
            assert bool(s.trusted_facts()) == sealed, p
    assert _judged(kept) == _judged(plain)


def test_facts_handed_over_with_the_trials_are_the_writers_own_and_others_are_refused(tmp_path):
    """Issue 57 item 6: a trial's sample facts computed where it was made (``trial_facts.sample_facts``: the dataset
    generator's render workers) and handed to ``write_trials`` with it are stored as the facts the writer computes
    itself (every field, mixed with trials handed over without); facts of another trial's samples are refused and
    nothing of the batch is written."""
    rng = np.random.default_rng(23)
    trials = [_clean_trial(rng) for _ in range(6)]
    trials[2].force_g[1] = np.nan  # a trace to count in one trial
    trials.append(TrialData(taxels=np.zeros((0, 18))))  # an empty one
    plan = [dict(trial_id=i, texture="A", speed_mm_s=80.0, force_g=500.0, duration_s=N / 1000.0)
            for i in range(len(trials))]
    facts = {}
    for name, handed in (("own", False), ("handed", True)):
        path = tmp_path / f"{name}.h5"
        with SessionWriter.create(path, plan=plan, protocol_source="facts", compression=None, durable=False) as w:
            items = [(i, d, trial_facts.sample_facts(d, 18)) if handed and i % 3 else (i, d)
                     for i, d in enumerate(trials)]
            assert w.write_trials(items) == len(trials)
        with h5py.File(path, "r") as f:
            facts[name] = f["recording/facts"][()]
    assert facts["own"].tobytes() == facts["handed"].tobytes()
    assert facts["own"]["force_g_nan"].tolist() == [0, 0, 1, 0, 0, 0, 0]

    path = tmp_path / "refused.h5"
    with SessionWriter.create(path, plan=plan, protocol_source="facts", compression=None, durable=False) as w:
        w.write_trials([(0, trials[0], trial_facts.sample_facts(trials[0], 18))])
        with pytest.raises(ValueError, match="trial 3"):
            w.write_trials([(1, trials[1]), (3, trials[3], trial_facts.sample_facts(trials[4], 18))])
        assert w.completed_ids() == [0]
    with open_session(path) as s:
        assert s.completed_ids() == [0] and sorted(s.trusted_facts()) == [0] and not usable_trials(s).excluded


def _reference_seq_gaps(seq):
    """seq_gaps as it was before its uint16 path (int64 steps modulo 65,536)."""
    if seq.size < 2:
        return 0
    d = np.mod(np.diff(seq.astype(np.int64)), 65536)
    return int(np.sum(d[d > 1] - 1))


def _reference_nonfinite(values):
    return int(np.count_nonzero(np.isnan(values))), int(np.count_nonzero(np.isinf(values)))


def test_the_facts_quicker_paths_give_the_reference_counts():
    """Issue 57 item 6: seq_gaps of a uint16 column in uint16 arithmetic, the counts' extremes from the per-taxel
    ones handed in, and one finiteness look over all traces first give every facts field as the full passes do:
    seq columns with wraps, gaps, repeats and backward jumps; traces with NaN, +-inf, both, and huge finite values."""
    rng = np.random.default_rng(31)
    for _ in range(300):
        n = int(rng.integers(0, 400))
        start = int(rng.integers(0, 65536))
        steps = rng.choice([1, 1, 1, 1, 2, 5, 0, 65535, 300], size=max(n - 1, 0))
        seq = ((start + np.concatenate([[0], np.cumsum(steps)])) % 65536).astype(np.uint16)[:n]
        assert trial_facts.seq_gaps(seq) == _reference_seq_gaps(seq)
        assert trial_facts.seq_gaps(seq.astype(np.int64)) == _reference_seq_gaps(seq)
        taxels = rng.integers(0, 1024, size=(n, 18)).astype(np.uint16)
        m = int(rng.integers(0, 40))
        traces = [rng.normal(0, 1, m) for _ in range(2)] + [rng.normal(0, 1, m) for _ in range(2)]
        for values in traces:
            kind = rng.integers(0, 6)
            if m and kind == 1:
                values[rng.integers(0, m)] = np.nan
            elif m and kind == 2:
                values[rng.integers(0, m)] = rng.choice([np.inf, -np.inf])
            elif m > 1 and kind == 3:
                values[0], values[1] = np.inf, -np.inf
            elif m and kind == 4:
                values[:] = 1.7e308  # finite, but their sum is not
        data = TrialData(taxels=taxels, seq=seq, force_g=traces[0], force_time_s=traces[1], speed_mm_s=traces[2],
                         speed_time_s=traces[3])
        row = trial_facts.sample_facts(data, 18)[0]
        extremes = (taxels.min(axis=0), taxels.max(axis=0)) if n else None
        assert trial_facts.sample_facts(data, 18, extremes).tobytes() == row.tobytes()
        assert int(row["seq_gaps"]) == _reference_seq_gaps(seq)
        if n:
            assert (int(row["taxels_min"]), int(row["taxels_max"])) == (int(taxels.min()), int(taxels.max()))
        for name in trial_facts.TRACE_NAMES:
            want = _reference_nonfinite(getattr(data, name))
            assert (int(row[f"{name}_nan"]), int(row[f"{name}_inf"])) == want, name
