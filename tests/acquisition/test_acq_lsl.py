"""LSL outlets of a protocol run (issue 27 item 1): an inlet in this process receives, from a session recorded on
the in-process rig, every taxel frame (equal to the session's, sequence-checked), the SA/RA spike events equal to the
batch encoder's on the same readings, the drum state of every poll, and one marker per trial event; the session stores
the streams and the host <-> LSL offset. Pushed live: a trial's frames reach the inlet before the trial ends, the
frames between trials too. Loopback only (LSLAPICFG: tests/conftest.py)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest

from rigctl.acquisition.clock import fitted_times
from rigctl.acquisition.protocol import parse_protocol
from rigctl.rigs import open_rig
from rigctl.storage.session import open_session

PROTOCOL = ('name = "lsl_test"\ntextures = ["A", "L"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
            'trials_per_condition = 2\nduration_s = 0.4\n[settle]\nsettle_time_ms = 50\n')


def _inlet(pylsl, source_id):
    found = pylsl.resolve_byprop("source_id", source_id, minimum=1, timeout=10)
    assert found, f"stream {source_id} not found on loopback"
    inlet = pylsl.StreamInlet(found[0], max_buflen=360, recover=False)
    inlet.open_stream(timeout=10)
    return inlet


class _Rx:
    """What one inlet has received so far, pulled as the test goes."""

    def __init__(self, inlet):
        self.inlet, self.data, self.ts = inlet, [], []

    def pull(self, timeout_s=0.2):
        chunk, ts = self.inlet.pull_chunk(timeout=timeout_s, max_samples=100_000)
        self.data.extend(chunk)
        self.ts.extend(ts)
        return len(ts)

    def until(self, done, timeout_s=10.0):
        deadline = time.monotonic() + timeout_s
        while not done(self):
            if time.monotonic() > deadline:
                return False
            self.pull(0.05)
        return True

    def drain(self, n, hang_s=60.0):
        """Everything the outlet pushed: pulled until ``n`` samples have come (``hang_s`` only bounds a hang), then
        whatever else is already there (a sample too many shows). Not "until nothing came for 0.5 s": liblsl's
        threads starved on a loaded machine deliver later than that, and the stream looked short."""
        deadline = time.monotonic() + hang_s
        while len(self.ts) < n and time.monotonic() < deadline:
            self.pull(0.2)
        self.pull(0.0)
        return self.data, np.asarray(self.ts)


@pytest.mark.lsl
def test_a_run_is_published_on_lsl_live(lsl, tmp_path):
    from rigctl.encoding.izhikevich import encode_ra, encode_sa
    from rigctl.operations import LslPublisher, ProtocolRun, RigControl

    sid = f"rigctl-test-{uuid.uuid4().hex[:8]}"
    events, live = [], []
    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json") as rig:
        pub = LslPublisher(RigControl(rig), source_id=sid, protocol_name="lsl_test")
        rx = {k: _Rx(_inlet(lsl, f"{sid}-{k}")) for k in ("taxels", "spikes", "drum", "markers")}
        info = rx["taxels"].inlet.info()
        stream, end_capture = rig.stream, rig.stream.end_capture

        def end_capture_once_live():
            # the trial has not ended (its capture is still open, the simulation stands still): every frame received
            # so far, this trial's included, reaches the inlet now, pushed live, not once the trial is recorded
            n_now, newest = stream.ring.total, int(stream.ring.latest(1)[2][0])
            live.append(rx["taxels"].until(lambda r: len(r.data) >= n_now, timeout_s=10.0)
                        and int(rx["taxels"].data[n_now - 1][-1]) == newest)
            return end_capture()

        stream.end_capture = end_capture_once_live
        run = ProtocolRun(rig, parse_protocol(PROTOCOL), tmp_path / "s.h5", lsl=pub, on_trial=events.append)
        summary = run.run()
        n_streamed = stream.ring.total
        pub.live.stop()  # pushes the rest
        got, ts = rx["taxels"].drain(n_streamed)
        sp, sts = rx["spikes"].drain(pub.live.spikes)
        drum, dts = rx["drum"].drain(pub.live.drum_samples)
        marks, mts = rx["markers"].drain(len(pub.markers))
        for r in rx.values():  # before the outlets go
            r.inlet.close_stream()
        pub.close()
    assert summary.ok and summary.recorded == 4
    assert live == [True] * 4, live
    # the taxel stream's description: channel labels, units, the sensor
    ch = info.desc().child("channels").child("channel")
    labels = []
    while not ch.empty():
        labels.append((ch.child_value("label"), ch.child_value("unit")))
        ch = ch.next_sibling()
    with open_session(tmp_path / "s.h5") as s:
        layout = s.layout
        trials = [s.trial(t) for t in sorted(s.completed_ids())]
        lsl_attr = json.loads(s.attrs["lsl"])
    assert labels == [(lab, "ADC counts") for lab in layout.channel_labels()] + [("frame_seq", "count")]
    assert info.nominal_srate() == layout.sample_rate_hz and info.channel_count() == layout.n_channels + 1
    assert json.loads(info.desc().child_value("sensor_layout"))["n_channels"] == layout.n_channels
    assert lsl_attr["streams"]["taxels"]["source_id"] == f"{sid}-taxels"
    offset = lsl_attr["lsl_offset_s"]

    # the whole stream, between trials too: every frame the reader received, in sequence, increasing timestamps
    got = np.asarray(got)
    assert got.shape == (n_streamed, layout.n_channels + 1)
    seq = got[:, -1]
    assert np.all((np.diff(seq) & 0xFFFF) == 1) and np.all(np.diff(ts) > 0)
    assert n_streamed > sum(t.n_samples for t in trials) + 1000  # the sensor streamed between trials
    # each trial's frames within it, equal to the session's, at their fitted times on the LSL clock
    for t in trials:
        (k,) = np.flatnonzero(seq == t.seq[0])
        assert np.array_equal(got[k:k + t.n_samples, :-1], t.taxels)
        assert np.array_equal(seq[k:k + t.n_samples], t.seq)
        np.testing.assert_allclose(ts[k:k + t.n_samples], fitted_times(t.attrs, t.seq) + offset, rtol=0, atol=1e-6)

    # spikes: the batch encoder's on the same readings, the whole stream (full ADC range: no normalisation stored)
    full = pub.normaliser
    want = []
    for kind, enc in enumerate((encode_sa, encode_ra)):
        trains = enc(got[None, :, :-1].astype(np.float64), normalise=full, fs=layout.sample_rate_hz)
        for taxel in range(layout.n_channels):
            for st in trains.train(0, taxel):
                want.append((kind * layout.n_channels + taxel,
                             round(float(ts[int(round(st * layout.sample_rate_hz))]), 6)))
    have = sorted((int(v[0]), round(float(x), 6)) for v, x in zip(sp, sts))
    assert len(want) > 100 and have == sorted(want)

    # drum state at every status poll, the actuator's position with it: each trial's force trace is among them
    drum = np.asarray(drum)
    assert np.all(np.isfinite(drum)) and np.all(np.diff(dts) >= 0)
    for t in trials:
        at = float(t.attrs["host_time_origin_s"]) + np.asarray(t.force_time_s) + offset
        i = np.clip(np.searchsorted(dts, at), 0, len(dts) - 1)
        np.testing.assert_allclose(dts[i], at, rtol=0, atol=1e-6)
        np.testing.assert_allclose(drum[i, 1], t.force_g, rtol=1e-6)
        assert np.all(drum[i, 2] > 0)  # pressed: the actuator out of its home

    # one marker per trial event, in order, plus the run's start and end
    docs = [json.loads(m[0]) for m in marks]
    assert docs[0]["event"] == "run_start" and docs[-1]["event"] == "run_end" and docs[-1]["complete"] == 4
    kinds = {"start": "trial_start", "complete": "trial_end", "texture": "plate_change", "retry": "retry",
             "failed": "fault"}
    assert [d["event"] for d in docs[1:-1]] == [kinds[e.kind] for e in events]
    ends = [d for d in docs if d["event"] == "trial_end"]
    assert [(d["trial_id"], d["texture"], d["speed_mm_s"], d["force_g"]) for d in ends] == [
        (t.attrs["trial_id"], t.attrs["texture"], 120.0, 300.0) for t in trials]
    assert all(d["protocol"] == "lsl_test" for d in docs)
    inlets = {k: r.inlet for k, r in rx.items()}

    # what LabRecorder would write from these streams (rigctl.storage.xdf.write_xdf), imported back as a session:
    # one labelled trial per trial_end marker, the readings and labels of the recorded session
    from click.testing import CliRunner

    from rigctl.cli import main
    from rigctl.storage.xdf import XdfStream, write_xdf

    write_xdf(tmp_path / "lab.xdf", [
        XdfStream(inlets["taxels"].info().as_xml(), "int32", got, ts),
        XdfStream(inlets["markers"].info().as_xml(), "string", marks, mts)])
    res = CliRunner().invoke(main, ["import", str(tmp_path / "lab.xdf"), "--out", str(tmp_path / "lab.h5"), "--quiet"])
    assert res.exit_code == 0, res.output
    with open_session(tmp_path / "lab.h5") as imported:
        assert imported.layout.n_channels == layout.n_channels
        assert imported.layout.sample_rate_hz == layout.sample_rate_hz
        got_trials = [imported.trial(t) for t in sorted(imported.completed_ids())]
        assert [str(x) for x in imported.plan["texture"]] == [t.attrs["texture"] for t in trials]
        assert list(imported.plan["speed_mm_s"]) == [120.0] * len(trials)
    assert [g.taxels.tolist() for g in got_trials] == [t.taxels.tolist() for t in trials]


def test_without_pylsl_asking_for_lsl_is_one_line_and_nothing_moves(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from rigctl.cli import main

    monkeypatch.setitem(sys.modules, "pylsl", None)  # import pylsl raises ImportError
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "none.json"))
    out = tmp_path / "s.h5"
    res = CliRunner().invoke(main, ["acquire", "quick_check", "--out", str(out), "--lsl", "--quiet"])
    assert res.exit_code == 1 and res.output.count("\n") == 1, res.output
    assert res.output.startswith("Error: LSL streaming needs pylsl") and "pip install 'rigctl[lsl]'" in res.output
    assert not out.exists()
    # asked for by the rig config: said so
    cfg = tmp_path / "rig.json"
    cfg.write_text(json.dumps({"lsl": {"enabled": True}}))
    res = CliRunner().invoke(main, ["acquire", "quick_check", "--out", str(out), "--quiet", "--config", str(cfg)])
    assert res.exit_code == 1 and "lsl.enabled" in res.output and not out.exists()


def test_nothing_loads_pylsl_unless_asked(tmp_path):
    code = ("import sys; sys.modules['pylsl'] = None\n"
            "import rigctl.operations, rigctl.cli.acquire, rigctl.acquisition.lsl, rigctl.storage\n"
            "from rigctl.acquisition.lsl import LslUnavailable, require_pylsl\n"
            "try:\n    require_pylsl()\nexcept LslUnavailable as e:\n    print('refused:', e)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("refused: LSL streaming needs pylsl")


def test_the_rig_config_switches_it_on_and_a_flag_overrides(tmp_path):
    from rigctl.acquisition.rigconfig import RigConfigError, validate_rig_config
    from rigctl.operations import lsl_requested

    assert lsl_requested(None, {}) is False
    assert lsl_requested(None, {"lsl": {"enabled": True}}) is True
    assert lsl_requested(False, {"lsl": {"enabled": True}}) is False
    validate_rig_config({"lsl": {"enabled": True, "name": "bench2", "source_id": "rig-7"}})
    with pytest.raises(RigConfigError, match="lsl.enabled: expected true or false"):
        validate_rig_config({"lsl": {"enabled": "yes"}})
