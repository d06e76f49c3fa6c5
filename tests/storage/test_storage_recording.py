"""Schema 4's recording arrays (rigctl.storage.session_recording): trials back to back in ``/recording``, views in
each trial's group for plain h5py (schema 5, the dataset generator's: none, the index says where), block reads for
the encoder; old (schema 3) and view-less (schema 5) files read and encode identically; the validator's checks on
the arrays. (Crash safety of schema 4: the kill -9 tests of test_storage_session.py and
the full-disk test of test_storage_faults.py write it, the default.)"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from rigctl.storage.session import DEFAULT_SCHEMA_VERSION, SCHEMA_VERSION, SessionWriter, TrialData, open_session
from rigctl.storage.validate import usable_trials

N = 300


def _plan(n):
    return [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=[60.0, 120.0][i // 2 % 2],
                 force_g=[250.0, 500.0, 1000.0][i // 4 % 3], duration_s=N / 1000.0) for i in range(n)]


def _trial(rng, n=N, **kw):
    kw.setdefault("attrs", {"started_utc": f"2030-01-01T00:00:{int(rng.integers(10, 59))}+00:00"})
    start = int(rng.integers(0, 65536))
    k = int(rng.integers(0, 6))
    return TrialData(taxels=rng.integers(100, 900, (n, 18)), seq=(start + np.arange(n)) % 65536,
                     flags=rng.integers(0, 4, n), host_time_s=np.arange(n) / 1000 + rng.uniform(0, 1e-3, n),
                     force_g=rng.normal(500, 3, k), force_time_s=np.linspace(0, 0.3, k),
                     speed_mm_s=rng.normal(120, 1, 6 - k), speed_time_s=np.linspace(0, 0.3, 6 - k), **kw)


def _write(path, trials, n_plan, schema_version=DEFAULT_SCHEMA_VERSION, **kw):
    with SessionWriter.create(path, plan=_plan(n_plan), protocol_source="src", schema_version=schema_version,
                              **kw) as w:
        for tid, data in trials.items():
            w.write_trial(tid, data)
    return path


ARRAYS = ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s", "speed_time_s")


@pytest.mark.parametrize("compression, schema", [(None, 4), ("gzip", 4), (None, 5), ("gzip", 5)])
def test_trials_back_to_back_with_views_for_plain_h5py(tmp_path, compression, schema):
    rng = np.random.default_rng(1)
    trials = {3: _trial(rng), 0: _trial(rng, 250, dropped_frames=0), 5: _trial(rng, 280)}  # written out of order
    path = _write(tmp_path / "s.h5", trials, 8, compression=compression, schema_version=schema)
    with h5py.File(path, "r") as f:  # plain h5py: the schema-3 names read as before, the arrays hold every trial
        assert f.attrs["schema_version"] == schema
        rec = f["recording"]
        assert rec["taxels"].shape == (830, 18) and rec["taxels"].compression == compression
        idx = rec["index"][()]
        assert idx["trial_id"].tolist() == [3, 0, 5] and idx["sample_start"].tolist() == [0, 300, 550]
        for tid, data in trials.items():
            g = f[f"trials/{tid:06d}"]
            row = idx[idx["trial_id"] == tid][0]
            for name in ARRAYS:
                if schema == 4:  # the group's views
                    np.testing.assert_array_equal(g[name][()], getattr(data, name), err_msg=name)
                else:  # schema 5: no views, the index row says where the trial's rows are (docs/session-format.md)
                    assert name not in g
                prefix = {"force_g": "force", "force_time_s": "force", "speed_mm_s": "speed",
                          "speed_time_s": "speed"}.get(name, "sample")
                start, n = int(row[f"{prefix}_start"]), int(row["n_samples" if prefix == "sample" else f"n_{prefix}"])
                np.testing.assert_array_equal(rec[name][start:start + n], getattr(data, name), err_msg=name)
            if schema == 4:
                assert g["taxels"].is_virtual and g["taxels"].attrs["unit"] == "ADC counts"
            assert g.attrs["n_samples"] == data.n_samples and g.attrs["status"] == "complete"
    with open_session(path) as s:
        for tid, data in trials.items():
            back = s.trial(tid)
            for name in ARRAYS:
                np.testing.assert_array_equal(getattr(back, name), getattr(data, name), err_msg=name)
        blk = s.read_taxels([0, 3, 5], traces=True)  # plan order: two runs of the arrays (0, then 3 and 5 ... )
        np.testing.assert_array_equal(blk.data, np.concatenate([trials[t].taxels for t in (0, 3, 5)]))
        assert blk.starts.tolist() == [0, 250, 550, 830]
        for (t, v), tid in zip(blk.speed_traces, (0, 3, 5)):
            np.testing.assert_array_equal(v, trials[tid].speed_mm_s)
            np.testing.assert_array_equal(t, trials[tid].speed_time_s)
        assert blk.has_speed_trace.tolist() == [trials[t].speed_mm_s.size > 0 for t in (0, 3, 5)]
        with pytest.raises(KeyError):
            s.read_taxels([1])
        counts = [{k: s.trial_attrs(t)[k] for k in ("n_samples", "dropped_frames", "crc_errors", "started_utc")}
                  for t in (5, 0)]
        assert s.trial_counts([5, 0]) == counts
        traces = s.read_traces([5, 0])
        for (ft, fv, vt, vv), tid in zip(traces, (5, 0)):
            for got, name in ((ft, "force_time_s"), (fv, "force_g"), (vt, "speed_time_s"), (vv, "speed_mm_s")):
                np.testing.assert_array_equal(got, getattr(trials[tid], name), err_msg=name)


def test_a_resumed_session_appends_and_a_failed_trial_is_recorded_later(tmp_path):
    rng = np.random.default_rng(2)
    path = _write(tmp_path / "r.h5", {0: _trial(rng)}, 4)
    with SessionWriter.open(path, protocol_source="src") as w:
        w.mark_failed(1, "link lost")
        late = _trial(rng)
        w.write_trials([(2, _trial(rng)), (1, late)])
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1, 2] and usable_trials(s).ids == [0, 1, 2]
        np.testing.assert_array_equal(s.trial(1).taxels, late.taxels)
        np.testing.assert_array_equal(s.read_taxels([1]).data, late.taxels)
    with h5py.File(path, "r") as f:
        assert f["recording/index"]["trial_id"].tolist() == [0, 2, 1]


@pytest.mark.parametrize("schema_version", [3, 4])
def test_a_batch_from_one_reused_buffer_keeps_every_trial(tmp_path, schema_version):
    """write_trials takes each trial as it is yielded: a generator that fills one buffer for every trial (the
    dataset generator's shared-memory slots) still gets each trial's own data on disk."""
    rng = np.random.default_rng(9)
    expected = [rng.integers(100, 900, (N, 18)).astype(np.uint16) for _ in range(5)]
    buf = np.zeros((N, 18), np.uint16)

    def batch():
        for tid, x in enumerate(expected):
            buf[...] = x
            yield tid, TrialData(taxels=buf, force_g=buf[:3, 0].astype(float), force_time_s=np.arange(3.0))

    path = tmp_path / "b.h5"
    with SessionWriter.create(path, plan=_plan(5), protocol_source="src", schema_version=schema_version) as w:
        assert w.write_trials(batch()) == 5
    with open_session(path) as s:
        assert usable_trials(s).ids == [0, 1, 2, 3, 4]
        for tid, x in enumerate(expected):
            np.testing.assert_array_equal(s.trial(tid).taxels, x)
            np.testing.assert_array_equal(s.trial(tid).force_g, x[:3, 0])


def test_a_batchs_per_sample_arrays_are_copied_once_into_buffers_kept_from_batch_to_batch():
    """Issue 57 item 6: each trial's per-sample arrays are copied once, in their stored types, into buffers that grow
    by doubling and serve the next batch; the batch is appended from there (no second concatenation). A trial's
    views stay its own data when the buffers grow under them."""
    from rigctl.storage.session_recording import SAMPLE_ARRAYS, BatchArrays, stored

    rng = np.random.default_rng(3)
    trials = [_trial(rng, n=n) for n in (300, 900, 2500, 0, 40)]  # (past the first 1024 rows, then 4096)
    batch = BatchArrays(18)
    views = [batch.take(t) for t in trials]
    for t, v in zip(trials, views):
        for name, dtype in SAMPLE_ARRAYS:
            assert v[name].dtype == dtype
            np.testing.assert_array_equal(v[name], stored(name, getattr(t, name), 18))
    whole = batch.stacked()
    for name, _ in SAMPLE_ARRAYS:
        np.testing.assert_array_equal(whole[name], np.concatenate([stored(name, getattr(t, name), 18) for t in trials]))
    batch.clear()
    again = batch.take(trials[1])
    assert np.shares_memory(again["taxels"], whole["taxels"])  # the same buffer, no fresh pages
    assert len(batch.stacked()["taxels"]) == 900


@pytest.mark.parametrize("schema_version", [4, SCHEMA_VERSION])
def test_two_batches_of_trials_of_several_lengths_read_back_as_written(tmp_path, schema_version):
    """write_trials from the reused batch buffers: every array of every trial as written, over two batches."""
    rng = np.random.default_rng(5)
    lengths = [300, 2000, 10, 1200, 300, 5000, 0, 700]
    trials = {i: _trial(rng, n=n) for i, n in enumerate(lengths)}
    path = tmp_path / "two.h5"
    with SessionWriter.create(path, plan=_plan(len(lengths)), protocol_source="src",
                              schema_version=schema_version) as w:
        assert w.write_trials((i, trials[i]) for i in range(4)) == 4
        assert w.write_trials((i, trials[i]) for i in range(4, 8)) == 4
    with open_session(path) as s:
        assert s.completed_ids() == list(range(8))  # (the validator: only the 300-sample ones match the plan)
        for i, t in trials.items():
            got = s.trial(i)
            for name in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s",
                         "speed_time_s"):
                np.testing.assert_array_equal(getattr(got, name), getattr(t, name))


def _copy_as_schema(src, dst, schema_version=3):
    """The same trials, plan and attributes in a file of ``schema_version`` (3: one group of datasets per trial)."""
    with open_session(src) as s:
        plan = s.plan.copy()
        plan["status"] = 0
        with SessionWriter.create(dst, plan=plan, layout=s.layout, textures=s.textures, protocol_source=s.protocol_source,
                                  kind=s.kind, schema_version=schema_version, compression=None) as w:
            ids = s.completed_ids()
            w.write_trials(zip(ids, s.iter_trials(ids)))
    return dst


@pytest.mark.parametrize("schema", [3, 4])
def test_old_files_read_validate_and_encode_to_identical_features(tmp_path, schema):
    """A schema-3 (or 4) file and the generator's schema-5 file of the same trials: the same block reads, trials,
    trial attributes, validator report, and ``encode_session`` writes identical features, spike trains,
    normalisation and force coefficients."""
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.encoding.pipeline import encode_session
    from rigctl.simulation.dataset import generate_dataset
    from rigctl.storage.encoded import ALL_VARIANTS, open_encoded

    proto = tmp_path / "p.toml"
    proto.write_text('name = "old_new"\ntextures = ["A", "L"]\nspeeds_mm_s = [60, 120]\nforces_g = [250, 500]\n'
                     'trials_per_condition = 2\ntravel_mm = 30\norder = "blocked"\n')
    new = tmp_path / "new.h5"
    generate_dataset(load_protocol(proto), new, seed=4, workers=0, progress=False)
    old = _copy_as_schema(new, tmp_path / "old.h5", schema)
    with open_session(old) as so, open_session(new) as sn:
        assert so.attrs["schema_version"] == schema and sn.attrs["schema_version"] == SCHEMA_VERSION == 5
        ids = sn.completed_ids()
        assert so.completed_ids() == ids and len(ids) == 16
        for tid in ids:
            to, tn = so.trial(tid), sn.trial(tid)
            for name in ARRAYS:
                np.testing.assert_array_equal(getattr(to, name), getattr(tn, name), err_msg=name)
            same = {json.dumps(a, sort_keys=True, default=repr)  # NaN (a constant-speed trial's ramp) equals itself
                    for a in (to.attrs, tn.attrs, so.trial_attrs(tid), sn.trial_attrs(tid))}
            assert len(same) == 1
        a, b = so.read_taxels(ids, traces=True), sn.read_taxels(ids, traces=True)
        for name in ("data", "starts", "dropped_frames", "has_speed_trace"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        for (ta, va), (tb, vb) in zip(a.speed_traces, b.speed_traces):
            np.testing.assert_array_equal(ta, tb)
            np.testing.assert_array_equal(va, vb)
        ra, rb = usable_trials(so), usable_trials(sn)
        assert (ra.ids, ra.excluded, ra.dropped_frames) == (rb.ids, rb.excluded, rb.dropped_frames)
    outs = [encode_session(p, tmp_path / f"{p.stem}.enc.h5", batch_trials=5, progress=False) for p in (old, new)]
    with open_encoded(outs[0]) as eo, open_encoded(outs[1]) as en:
        for v in ALL_VARIANTS:
            np.testing.assert_array_equal(eo.features(v), en.features(v), err_msg=v)
        assert eo.spike_variants == en.spike_variants and eo.spike_variants
        for v in eo.spike_variants:
            so_, sn_ = eo.spikes(v), en.spikes(v)
            np.testing.assert_array_equal(so_.spike_times, sn_.spike_times, err_msg=v)
            np.testing.assert_array_equal(so_.spike_times_index, sn_.spike_times_index, err_msg=v)
        for k in ("taxel_min", "taxel_max"):
            np.testing.assert_array_equal(eo.normalisation[k], en.normalisation[k])
        for lf in (False, True):
            np.testing.assert_array_equal(eo.force_coefficients(label_free=lf), en.force_coefficients(label_free=lf))


def _edit(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f["recording"])
    return path


def _rows(rec, tid):
    r = rec["index"][()]
    r = r[r["trial_id"] == tid][0]
    return slice(int(r["sample_start"]), int(r["sample_start"] + r["n_samples"]))


def _set_index(rec, tid, **values):
    idx = rec["index"][()]
    for k, v in values.items():
        idx[k][idx["trial_id"] == tid] = v
    rec["index"][...] = idx


@pytest.mark.parametrize("damage, reason", [
    (lambda rec: rec["taxels"].__setitem__((_rows(rec, 2).start + 7, 4), 4000),
     "taxels hold 4000 (sample 7), outside the sensor's 10-bit range 0..1023"),
    (lambda rec: rec["taxels"].__setitem__(_rows(rec, 2), rec["taxels"][_rows(rec, 1)]),
     "its taxels are a byte copy of trial 1's"),
    (lambda rec: rec["seq"].__setitem__(_rows(rec, 2), (np.arange(N) * 2) % 65536),
     f"its seq column shows {N - 1} missing frames, its dropped_frames attribute says 0"),
    (lambda rec: _set_index(rec, 2, crc_errors=2 ** 40), "its crc_errors attribute 1099511627776 is impossible"),
    (lambda rec: _set_index(rec, 2, n_samples=N // 4),  # the group still says N
     f"its n_samples attribute says {N}, /recording/index gives it {N // 4} samples"),
    (lambda rec: _set_index(rec, 2, sample_start=10 ** 6), "/recording/index puts its samples at rows 1000000+300"),
    (lambda rec: _set_index(rec, 2, trial_id=99), "it is marked complete but /recording/index has no row for it"),
])
@pytest.mark.parametrize("schema", [4, 5])
def test_damage_in_the_recording_arrays_is_excluded_with_its_reason(tmp_path, damage, reason, schema):
    rng = np.random.default_rng(3)
    path = _edit(_write(tmp_path / "d.h5", {t: _trial(rng, dropped_frames=0) for t in range(4)}, 4,
                        schema_version=schema), damage)
    with open_session(path) as s:
        report = usable_trials(s)
        assert report.ids == [0, 1, 3] and list(report.excluded) == [2]
        assert reason in report.excluded[2], report.excluded[2]
        np.testing.assert_array_equal(s.read_taxels([0, 1, 3]).data[:N], s.trial(0).taxels)


def test_threads_reading_one_session_at_once_never_see_a_trial_listed_twice(tmp_path):
    """Two threads reading batches of one open session at once build its ``/recording/index`` table together on
    their first reads. Built in place, a thread could see the other's half-built table, or fill it as well, and
    read a trial as "listed 2 times" (a damaged index). Each thread here is switched out after every few bytecodes
    while both build it."""
    import sys
    import threading

    rng = np.random.default_rng(5)
    path = _write(tmp_path / "s.h5", {i: _trial(rng, 40) for i in range(400)}, 400)
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for _ in range(10):
            with open_session(path) as s:
                errors: list[BaseException] = []
                go = threading.Barrier(2)

                def read(ids, s=s, errors=errors, go=go):
                    try:
                        go.wait()
                        s.read_taxels(ids)
                    except BaseException as exc:  # noqa: BLE001 - said below
                        errors.append(exc)

                threads = [threading.Thread(target=read, args=(list(range(k, 400, 2)),)) for k in (0, 1)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                assert not errors, errors
                assert s.index_duplicates() == {}
    finally:
        sys.setswitchinterval(old)
