"""NWB export (rigctl.storage.nwb, `rigctl export nwb`): a recorded quick_check session and an encoded simulated
dataset written with pynwb, checked by the NWB inspector (no critical issue), read back with pynwb (samples, trials
and spike counts equal to the session and encoded files), imported back by `rigctl import`, and the CLI's refusals."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.core import PAPER_SENSOR
from rigctl.encoding.pipeline import encode_session
from rigctl.storage.encoded import open_encoded
from rigctl.storage.nwb import export_nwb, read_nwb_summary
from rigctl.storage.session import open_session

PROTOCOL = """
name = "nwb_test"
textures = ["A", "L"]
speeds_mm_s = [60, 120]
forces_g = [250, 1000]
trials_per_condition = 2
duration_s = 0.6
"""


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """quick_check recorded on the in-process simulated rig (the real runner, the real session writer)."""
    from pathlib import Path

    from rigctl.acquisition.protocol import load_protocol
    from rigctl.acquisition.runner import run_protocol
    from rigctl.rigs import open_rig

    d = tmp_path_factory.mktemp("nwb_rec")
    proto = load_protocol(Path(__file__).resolve().parents[2] / "protocols" / "quick_check.toml")
    with open_rig("inprocess", seed=2, host_config_path=d / "rig.json") as rig:
        run_protocol(proto, d / "quick.h5", rig=rig, progress=False)
    return d / "quick.h5"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("nwb_ds")
    (d / "p.toml").write_text(PROTOCOL)
    generate_dataset(load_protocol(d / "p.toml"), d / "ds.h5", seed=4, workers=0, progress=False)
    encode_session(d / "ds.h5", d / "ds.enc.h5", progress=False)
    return d / "ds.h5", d / "ds.enc.h5"


def _inspect(path):
    from nwbinspector import Importance, inspect_nwbfile

    messages = list(inspect_nwbfile(nwbfile_path=str(path)))
    critical = [m for m in messages if m.importance in (Importance.CRITICAL, Importance.PYNWB_VALIDATION,
                                                         Importance.ERROR)]
    return critical, messages


def test_a_recorded_session_round_trips(recorded, tmp_path):
    out = tmp_path / "quick.nwb"
    events = []
    summary = export_nwb(recorded, out, progress=events.append)
    for stage in ("reading traces", "writing NWB"):  # progress events, one per trial, through the write itself
        assert [e.done for e in events if e.stage == stage] == list(range(summary.n_trials + 1))
    assert {(e.stage, e.total) for e in events} == {("reading traces", summary.n_trials),
                                                     ("writing NWB", summary.n_trials)}
    assert out.stat().st_size > 0
    critical, _ = _inspect(out)
    assert critical == []
    back, arrays = read_nwb_summary(out)
    with open_session(recorded) as s:
        ids = s.completed_ids()
        taxels = np.concatenate([s.trial(t).taxels for t in ids])
        layout = s.layout
    assert (back.n_trials, back.n_samples, back.n_channels, back.rate_hz) == (
        len(ids), taxels.shape[0], layout.n_channels, layout.sample_rate_hz) == (
        summary.n_trials, summary.n_samples, summary.n_channels, summary.rate_hz)
    np.testing.assert_array_equal(arrays["taxels"], taxels)
    np.testing.assert_array_equal(arrays["trial_id"], ids)
    with open_session(recorded) as s:
        per_trial = [s.trial(t).taxels.shape[0] / layout.sample_rate_hz for t in ids]
    np.testing.assert_allclose(arrays["stop_time"] - arrays["start_time"], per_trial)
    np.testing.assert_allclose(arrays["start_time"][1:], arrays["stop_time"][:-1])  # back to back


def test_the_nwb_file_holds_the_sensor_trials_and_traces(recorded, tmp_path):
    from pynwb import NWBHDF5IO

    out = tmp_path / "quick.nwb"
    export_nwb(recorded, out)
    with open_session(recorded) as s, NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        ts = nwb.acquisition["taxels"]
        assert ts.rate == s.layout.sample_rate_hz and ts.conversion == pytest.approx(1 / s.layout.adc_max)
        assert nwb.devices["taxel_sensor"].description == s.layout.to_json()
        trials = nwb.trials.to_dataframe()
        plan = {int(r["trial_id"]): r for r in s.plan}
        for _, row in trials.iterrows():
            p = plan[int(row["trial_id"])]
            assert row["texture"] == p["texture"] and row["status"] == "complete"
            assert row["force_g"] == pytest.approx(p["force_g"]) and row["speed_mm_s"] == pytest.approx(p["speed_mm_s"])
            assert row["dropped_frames"] == s.trial_attrs(int(row["trial_id"]))["dropped_frames"]
            assert abs(row["force_mean_g"] - p["force_g"]) < 30  # the load-cell trace went in
        force = nwb.acquisition["load_cell_force"]
        n_force = sum(s.trial(t).force_g.size for t in s.completed_ids())
        times = force.timestamps[()] if force.timestamps is not None else \
            force.starting_time + np.arange(len(force.data)) / force.rate
        assert force.unit == "g" and len(force.data) == n_force and np.all(np.diff(times) >= 0)
        traces = np.concatenate([d.force_time_s for d in (s.trial(t) for t in s.completed_ids())])
        assert times.size == traces.size
        assert len(nwb.processing["misc"]["plan"]) == len(s.plan)


def test_an_encoded_dataset_exports_its_spike_trains_as_units(dataset, tmp_path):
    session, encoded = dataset
    out = tmp_path / "ds.nwb"
    summary = export_nwb(session, out, encoded_path=encoded, variants=["original", "speed_scaled"])
    critical, _ = _inspect(out)
    assert critical == []
    back, _ = read_nwb_summary(out)
    with open_encoded(encoded) as e:
        for v in ("original", "speed_scaled"):
            times, index, n_trains = e.spikes(v)
            assert back.units[v] == summary.units[v] == n_trains == 2 * e.layout.n_channels
            assert back.spikes[v] == summary.spikes[v] == times.size  # every spike of every trial
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(str(out), "r") as io:
        units = io.read().units.to_dataframe()
    sa = units[(units["variant"] == "original") & (units["receptor"] == "SA")]
    assert list(sa["taxel"]) == list(range(18))
    assert list(sa["receptor_type"]) == [la.receptor for la in PAPER_SENSOR.layers for _ in range(la.n_channels)]
    assert set(units.loc[units["variant"] == "speed_scaled", "time_base"]) == {"speed-scaled"}


def test_the_units_are_written_without_decoding_a_whole_variant(dataset, tmp_path, monkeypatch):
    """Issue 57: the export's peak memory was a whole variant's spike times decoded to float64 seconds (at paper
    size ~10^8 spikes, 0.9 GB, beside their ticks) just for the row ends: the Units table now takes the row ends
    from EncodedFile.spike_index and the times unit by unit, so EncodedFile.spikes (the whole decode) is never called;
    the file still holds every spike of every unit."""
    from rigctl.storage.encoded import EncodedFile

    session, encoded = dataset
    variants = ["original", "speed_scaled"]
    with open_encoded(encoded) as e:
        want = {v: e.spikes(v) for v in variants}
        for v in variants:
            index, n_trains = e.spike_index(v)
            assert np.array_equal(index, want[v].spike_times_index) and n_trains == want[v].n_trains

    def whole_decode(self, variant, trials=None):
        raise AssertionError(f"the export decoded every spike of {variant} at once")

    monkeypatch.setattr(EncodedFile, "spikes", whole_decode)
    out = tmp_path / "units.nwb"
    summary = export_nwb(session, out, encoded_path=encoded, variants=variants)
    monkeypatch.undo()
    back, _ = read_nwb_summary(out)
    for v in variants:
        assert back.spikes[v] == summary.spikes[v] == want[v].spike_times.size
    # each unit decoded in blocks of its trials (bounded temporaries): the same spike times, bit for bit
    import h5py

    from rigctl.storage import nwb

    monkeypatch.setattr(nwb, "_UNIT_BLOCK_SPIKES", 7)
    export_nwb(session, tmp_path / "small_blocks.nwb", encoded_path=encoded, variants=variants)
    # nor are a variant's stored ticks read whole (at paper size 0.43 GB a variant): a group of units at a time,
    # gathered from blocks of trials
    monkeypatch.setattr(nwb, "_UNIT_GROUP_SPIKES", 50)
    monkeypatch.setattr(nwb, "_UNIT_READ_SPIKES", 30)
    read = []
    stored = EncodedFile.spikes_stored

    def spy(self, variant, trials=None, *, times=True):
        got = stored(self, variant, trials, times=times)
        read.append(got[0].size)
        return got

    monkeypatch.setattr(EncodedFile, "spikes_stored", spy)
    export_nwb(session, tmp_path / "small_groups.nwb", encoded_path=encoded, variants=variants)
    monkeypatch.undo()
    with open_encoded(encoded) as e:
        largest_trial = max(int(np.diff(e.spike_index(v)[0].reshape(-1, want[v].n_trains)[:, -1], prepend=0).max())
                            for v in variants)
    assert 0 < max(read) <= max(30, largest_trial) < min(want[v].spike_times.size for v in variants)
    for other in ("small_blocks.nwb", "small_groups.nwb"):
        with h5py.File(out, "r") as a, h5py.File(tmp_path / other, "r") as b:
            for name in ("spike_times", "spike_times_index"):
                assert np.array_equal(a["units"][name][()], b["units"][name][()])


def test_the_trials_attributes_are_read_through_a_bounded_metadata_cache(dataset, monkeypatch):
    """Issue 57 item 5: Session.trial_counts (the export's trials table) reads an attribute of every trial group; a
    cached group header keeps its decoded attributes (~20 kB a generated trial), so at paper size the unbounded
    cache kept 0.48 GB. It reads them with the cache held at h5objects.VISIT_CACHE_BYTES (here 4 KiB)."""
    from rigctl.storage import h5objects

    monkeypatch.setattr(h5objects, "VISIT_CACHE_BYTES", 4096)
    with open_session(dataset[0]) as s:
        ids = s.completed_ids()
        max_size = s._f.id.get_mdc_config().max_size
        counts = s.trial_counts(ids)
        assert s._f.id.get_mdc_size()[2] <= 2 * 4096  # (an open group's header may stay: 59 kB unbounded)
        assert s._f.id.get_mdc_config().max_size == max_size
        assert [c["n_samples"] for c in counts] == [s.trial(t).n_samples for t in ids]


def _reference_units(encoded, ids, starts, layout, variants, path):
    """The Units table as the export wrote it before it was written in blocks: pynwb's add_unit per unit, each
    unit's spike times gathered trial by trial (the oracle of the block export)."""
    import datetime as dt

    from pynwb import NWBHDF5IO, NWBFile
    from pynwb.misc import Units

    from rigctl.storage import nwb as nwbmod

    nwb = NWBFile(session_description="ref", identifier="ref", session_start_time=dt.datetime.now(dt.UTC))
    nwb.units = Units(name="units", resolution=1.0 / layout.sample_rate_hz, description="ref")
    for name, desc in nwbmod._UNIT_COLUMNS:
        nwb.add_unit_column(name=name, description=desc)
    with open_encoded(encoded) as enc:
        row_of = {int(t): i for i, t in enumerate(enc.trials["trial_id"])}
        for v in variants:
            times, index, n_trains = enc.spikes(v)
            ends = index.reshape(-1, n_trains)
            begins = np.concatenate([[0], index[:-1]]).reshape(-1, n_trains)
            for j, (rec, c, label, layer, rtype) in enumerate(nwbmod._train_columns(layout, n_trains)):
                parts = [starts[k] + times[begins[row_of[t], j]:ends[row_of[t], j]] for k, t in enumerate(ids)]
                nwb.add_unit(spike_times=np.concatenate(parts), variant=v, receptor=rec, taxel=c, taxel_label=label,
                             layer=layer, receptor_type=rtype,
                             time_base="speed-scaled" if "speed" in v else "session")
    with NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)


def test_the_block_export_writes_what_the_per_trial_export_wrote(dataset, tmp_path):
    """Units written variant by variant from the encoded tables, taxels and traces read in blocks: the same
    values and types as the per-unit / per-trial path (pynwb's add_unit, Session.trial), with progress through the
    units' write."""
    import h5py

    from rigctl.storage import nwb as nwbmod

    session, encoded = dataset
    out, ref = tmp_path / "blocks.nwb", tmp_path / "ref.nwb"
    events = []
    with open_encoded(encoded) as e:
        variants = list(e.spike_variants)  # every stored variant, the speed-scaled ones included
    assert len(variants) >= 2
    summary = export_nwb(session, out, encoded_path=encoded, variants=variants, progress=events.append)
    n_units = sum(summary.units.values())
    assert [e.done for e in events if e.stage == "writing units"] == list(range(n_units + 1))
    with open_session(session) as s:
        ids = s.completed_ids()
        trials = [s.trial(t) for t in ids]
        layout = s.layout
    starts = np.concatenate([[0], np.cumsum([t.n_samples for t in trials])[:-1]]) / layout.sample_rate_hz
    lead = max(0.0, -min([0.0] + [float(x.min()) for x in (trials[0].force_time_s, trials[0].speed_time_s) if x.size]))
    _reference_units(encoded, ids, lead + starts, layout, variants, ref)
    with h5py.File(out, "r") as f, h5py.File(ref, "r") as g:
        for name in ("spike_times", "spike_times_index", "id", *[c for c, _ in nwbmod._UNIT_COLUMNS]):
            a, b = f["units"][name], g["units"][name]
            assert a.dtype == b.dtype and a.shape == b.shape, name
            np.testing.assert_array_equal(a[()], b[()], err_msg=name)
        assert tuple(f["units"].attrs["colnames"]) == tuple(g["units"].attrs["colnames"])
        assert f["units/spike_times"].chunks is not None  # chunked for a unit's slice
        np.testing.assert_array_equal(f["acquisition/taxels/data"][()], np.concatenate([t.taxels for t in trials]))
        force_t = np.concatenate([lead + st + t.force_time_s for st, t in zip(starts, trials)])
        order = np.argsort(force_t, kind="stable")
        g_force = f["acquisition/load_cell_force"]
        if "timestamps" in g_force:
            np.testing.assert_array_equal(g_force["timestamps"][()], force_t[order])
        else:  # regular (issue 79 item 7): starting_time and rate, the same times within 1 ns
            rate = g_force["starting_time"].attrs["rate"]
            times = g_force["starting_time"][()] + np.arange(force_t.size) / rate
            np.testing.assert_allclose(times, force_t[order], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(f["acquisition/load_cell_force/data"][()],
                                      np.concatenate([t.force_g for t in trials])[order])


def test_an_exported_file_imports_back(recorded, tmp_path):
    """`rigctl import` reads a file rigctl exported: one trial per row of its trials table, with its labels, at
    its rate and with its sensor description."""
    out = tmp_path / "quick.nwb"
    export_nwb(recorded, out)
    back = tmp_path / "back.h5"
    r = CliRunner().invoke(main, ["import", str(out), "--out", str(back)])
    assert r.exit_code == 0, r.output
    with open_session(back) as b, open_session(recorded) as s:
        assert b.layout == s.layout
        assert len(b.completed_ids()) == len(s.completed_ids())
        for tb, ts in zip(b.completed_ids(), s.completed_ids()):
            np.testing.assert_array_equal(b.trial(tb).taxels, s.trial(ts).taxels)
        pb = [(str(r["texture"]), float(r["speed_mm_s"]), float(r["force_g"])) for r in b.plan]
        ps = [(str(r["texture"]), float(r["speed_mm_s"]), float(r["force_g"])) for r in s.plan
              if int(r["trial_id"]) in s.completed_ids()]
        assert pb == ps


def test_the_command_refuses_what_it_must(recorded, tmp_path):
    out = tmp_path / "q.nwb"
    run = CliRunner().invoke
    r = run(main, ["export", "nwb", str(recorded), "--out", str(out), "--no-progress"])
    assert r.exit_code == 0, r.output
    assert "6 trials" in r.stdout
    before = out.read_bytes()
    r = run(main, ["export", "nwb", str(recorded), "--out", str(out), "--no-progress"])
    assert r.exit_code == 2 and "exists" in r.output and out.read_bytes() == before
    r = run(main, ["export", "nwb", str(recorded), "--out", str(recorded), "--no-progress"])
    assert r.exit_code == 2 and "input" in r.output
    r = run(main, ["export", "nwb", str(recorded), "--out", str(tmp_path / "x.h5"), "--no-progress"])
    assert r.exit_code == 2 and ".nwb" in r.output and not (tmp_path / "x.h5").exists()
    r = run(main, ["export", "nwb", str(recorded), "--encoded", str(recorded), "--out", str(tmp_path / "y.nwb"),
                   "--no-progress"])
    assert r.exit_code == 1 and "Error:" in r.output and not (tmp_path / "y.nwb").exists()


def test_unknown_variants_are_refused_before_the_export_runs(dataset, tmp_path, monkeypatch):
    """`export nwb --variants nope` was refused only after the export ran (issue 24): now a usage error before any
    work, with --encoded (not among its variants) and without it (nothing to choose among)."""
    from rigctl.storage import nwb as nwbmod

    session, encoded = dataset
    ran = []
    monkeypatch.setattr(nwbmod, "export_nwb", lambda *a, **k: ran.append(a))  # the command must not get here
    for extra in (["--encoded", str(encoded)], []):
        r = CliRunner().invoke(main, ["export", "nwb", str(session), *extra, "--variants", "nope", "--out",
                                      str(tmp_path / "v.nwb"), "--no-progress"])
        assert r.exit_code == 2 and "--variants" in r.output, (extra, r.output)
    assert ran == [] and list(tmp_path.iterdir()) == []


def test_the_blocks_by_running_sum_are_the_greedy_item_by_item_blocks():
    """nwb._blocks' search of the running sum (non-negative integer lengths) gives exactly the ranges of the
    item-by-item greedy loop it replaced: zeros, items longer than the limit, a limit of 0, empty input."""
    from rigctl.storage.nwb import _blocks

    def greedy(lengths, limit):  # the item-by-item loop: _blocks' own path for lengths that are not integers
        return _blocks(np.asarray(lengths, dtype=np.float64), limit)

    rng = np.random.default_rng(57)
    for case in range(300):
        n = int(rng.integers(0, 40))
        lengths = rng.integers(0, 12, n) * (rng.random(n) < 0.8)  # some zeros
        for limit in (0, 1, 5, 11, 30, 1000):
            for given in (lengths, list(map(int, lengths)), lengths.astype(np.uint32)):
                assert _blocks(given, limit) == greedy(lengths, limit), (case, limit)
    assert _blocks([], 4) == [] and _blocks([1] * 10, 4) == [(0, 4), (4, 8), (8, 10)]


def test_the_command_sets_experimenter_institution_and_lab(recorded, tmp_path):
    """``export nwb --experimenter --institution --lab`` (DANDI asks for them; issue 79 item 7): the file carries what
    was given, and without them nothing made up (they were "rigctl" and "unknown")."""
    from click.testing import CliRunner
    from pynwb import NWBHDF5IO

    from rigctl.cli import main

    out = tmp_path / "meta.nwb"
    r = CliRunner().invoke(main, ["export", "nwb", str(recorded), "--out", str(out), "--no-progress",
                                  "--experimenter", "Doe, Jane", "--experimenter", "Roe, Rick",
                                  "--institution", "Uni of Somewhere", "--lab", "Touch Lab"])
    assert r.exit_code == 0, r.output
    with NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        assert tuple(nwb.experimenter) == ("Doe, Jane", "Roe, Rick")
        assert (nwb.institution, nwb.lab) == ("Uni of Somewhere", "Touch Lab")
    plain = tmp_path / "plain.nwb"
    export_nwb(recorded, plain)
    with NWBHDF5IO(str(plain), "r") as io:
        nwb = io.read()
        assert nwb.experimenter is None and nwb.institution is None and nwb.lab is None


def test_regular_traces_are_stored_with_a_rate(dataset, tmp_path):
    """A trace whose times are regular (a simulated session's 50 Hz traces, trials back to back) is stored with NWB's
    starting_time and rate, the same times within 1 ns, and nwbinspector no longer asks for it (issue 79 item 7); an
    irregular one keeps its timestamps."""
    from pynwb import NWBHDF5IO

    from rigctl.storage.nwb import _regular_rate

    out = tmp_path / "ds.nwb"
    export_nwb(dataset[0], out)
    _, messages = _inspect(out)
    assert not [m for m in messages if m.check_function_name == "check_regular_timestamps"], messages
    with NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        rates = {name: nwb.acquisition[name].rate for name in ("load_cell_force", "drum_speed")}
    assert any(r is not None for r in rates.values()), rates
    t = 0.5 + np.arange(100) / 50.0
    assert _regular_rate(t) == pytest.approx(50.0)
    assert np.max(np.abs(t[0] + np.arange(100) / _regular_rate(t) - t)) < 1e-9
    jitter = t.copy()
    jitter[40] += 1e-6
    assert _regular_rate(jitter) is None and _regular_rate(t[:2]) is None
    assert _regular_rate(np.concatenate([t, t[-1] + 1.0 + np.arange(10) / 50.0])) is None  # a gap
