"""Session schema 3: any sensor (channel count, rate), any texture set (labels of any length, stable codes), the
refusals (a label outside the set, a trial of another sensor), old schema-2 files, and ``rigctl info``."""

from __future__ import annotations

import json
import random

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.core import (
    PAPER_SENSOR,
    PAPER_TEXTURES,
    SensorLayout,
    TextureSet,
    TextureSetError,
    TrialData,
    texture_set_from_labels,
)
from rigctl.storage.session import (
    DEFAULT_SCHEMA_VERSION,
    SCHEMA_VERSION,
    SessionError,
    SessionWriter,
    TrialStatus,
    open_session,
)

NINE_100 = SensorLayout.grid(3, 3, 1, sample_rate_hz=100.0, adc_bits=12, pitch_mm=4.0, name="finger 3x3 @ 100 Hz")
#: 26 labels of one to 40 characters, ASCII and not
LABELS_26 = (["HB3", "Linen", "Canvas", "BeigeCotton", "HB10", "H", "Ünïcödé", "草莓", "ridge 2.5 mm", "x" * 40]
             + [f"fabric-{i:02d}" for i in range(16)])


def _plan(labels, n, duration_s=2.0):
    return [dict(trial_id=i, texture=labels[i % len(labels)], speed_mm_s=float("nan"), force_g=float("nan"),
                 duration_s=duration_s, repeat=i // len(labels)) for i in range(n)]


def _trial(rng, layout, n):
    return TrialData(taxels=rng.integers(0, layout.adc_max + 1, (n, layout.n_channels)), layout=layout,
                     force_g=[1.0, 2.0], force_time_s=[0.0, 0.5], attrs={"note": "é"})


def test_nine_channels_at_100_hz_round_trip_with_layout_rate_and_calibration(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "nine.h5"
    cal = {"taxel_min": np.arange(9) * 1.5, "taxel_max": np.arange(9) + 3000.0, "taxel_source": "test"}
    w = SessionWriter.create(path, plan=_plan(["A", "B"], 4), layout=NINE_100, calibration=cal)
    assert w.layout == NINE_100 and w.textures is PAPER_TEXTURES
    written = {0: _trial(rng, NINE_100, 200), 3: _trial(rng, NINE_100, 150)}
    w.write_trials(written.items())
    with open_session(path) as s:
        assert s.attrs["schema_version"] == DEFAULT_SCHEMA_VERSION == 4
        assert s.layout == NINE_100 and s.layout.n_channels == 9 and s.layout.sample_rate_hz == 100.0
        assert s.completed_ids() == [0, 3]
        for tid, data in written.items():
            back = s.trial(tid)
            assert back.layout == NINE_100 and back.rate_hz == 100.0
            assert back.taxels.shape == (data.n_samples, 9) and back.taxels.max() > 1023  # 12-bit counts kept
            np.testing.assert_array_equal(back.taxels, data.taxels)
            np.testing.assert_array_equal(back.host_time_s, np.arange(data.n_samples) / 100.0)
            assert back.duration_s == data.n_samples / 100.0 and back.attrs["note"] == "é"
        assert s.calibration["taxel_min"].shape == (9,)
        np.testing.assert_array_equal(s.calibration["taxel_max"], cal["taxel_max"])
        assert s.calibration["taxel_source"] == "test"
    with h5py.File(path, "r") as f:  # plain h5py: what a reader without rigctl sees
        tax = f["trials/000000/taxels"]
        assert tax.shape == (200, 9) and tax.is_virtual  # a view of its rows of /recording/taxels (schema 4)
        assert f["recording/taxels"].shape == (350, 9) and f["recording/index"]["n_samples"].tolist() == [200, 150]
        assert tax.attrs["rate_hz"] == 100.0 and tax.attrs["adc_bits"] == 12
        tr = f["trials"].attrs
        assert tr["taxels_channels"] == NINE_100.describe() and tr["taxels_rate_hz"] == 100.0
        assert [n.decode() if isinstance(n, bytes) else n for n in tr["taxels_channel_names"]] == list(
            NINE_100.channel_labels())
        assert json.loads(f.attrs["sensor_layout"])["n_channels"] == 9
    # calibration of the wrong width is refused (at creation: no file; later: the block is unchanged)
    with pytest.raises(ValueError, match=r"\(9,\)"):
        w.set_calibration({"taxel_min": np.zeros(18), "taxel_max": np.ones(18)})
    with open_session(path) as s:
        np.testing.assert_array_equal(s.calibration["taxel_max"], cal["taxel_max"])
    with pytest.raises(ValueError, match=r"\(9,\)"):
        SessionWriter.create(tmp_path / "c.h5", plan=[], layout=NINE_100, calibration={"taxel_min": np.zeros(18)})
    assert not (tmp_path / "c.h5").exists()


def test_26_textures_with_long_labels_round_trip_untruncated_with_stable_codes(tmp_path):
    order = list(LABELS_26)
    paths = []
    for k, seed in enumerate((1, 2)):
        random.Random(seed).shuffle(order)  # trials come in a different order in each session
        paths.append(tmp_path / f"t{k}.h5")
        w = SessionWriter.create(paths[-1], plan=_plan(order, 52), layout=NINE_100)  # textures from the labels
        assert len(w.textures) == 26
        w.write_trial(5, _trial(np.random.default_rng(k), NINE_100, 10))
    with open_session(paths[0]) as a, open_session(paths[1]) as b:
        assert a.textures == b.textures == texture_set_from_labels(LABELS_26)
        assert set(a.plan["texture"]) == set(LABELS_26)  # every label whole: "HB3" stays "HB3"
        assert a.plan["texture"].dtype.kind == "U" and a.plan["texture"].dtype.itemsize == 40 * 4
        for label in LABELS_26:  # codes come from the set, not from the order of the trials
            assert a.textures.code(label) == b.textures.code(label) == sorted(LABELS_26).index(label)
        assert a.trial(5).attrs["texture"] == a.plan["texture"][5]
    with h5py.File(paths[0], "r") as f:
        tex = f["plan"].dtype["texture"]
        assert h5py.check_string_dtype(tex).encoding == "utf-8" and h5py.check_string_dtype(tex).length is None
        assert {v.decode("utf-8") for v in f["plan"]["texture"]} == set(LABELS_26)
        assert TextureSet.from_json(f.attrs["texture_set"]).labels == tuple(sorted(LABELS_26))

    # an explicit set with groups: stored as given, codes = positions in it, labels in the set's spelling
    ts = TextureSet.from_dict({"name": "lab set", "textures": LABELS_26,
                               "groups": {"woven": ["Linen", "Canvas", "BeigeCotton"],
                                          "printed": [t for t in LABELS_26 if t not in ("Linen", "Canvas",
                                                                                       "BeigeCotton")]}})
    path = tmp_path / "groups.h5"
    w = SessionWriter.create(path, plan=_plan(["linen", "HB3", "草莓"], 3), textures=ts)
    assert w.plan["texture"].tolist() == ["Linen", "HB3", "草莓"]
    w.append_trial(dict(trial_id=None, texture="hb10", speed_mm_s=80, force_g=500, duration_s=1))
    with open_session(path) as s:
        assert s.textures == ts and s.textures.name == "lab set" and s.textures.has_groups
        assert s.textures.code("HB3") == 0 and s.textures.code("fabric-15") == 25
        assert s.textures.group_of("Linen") == "woven"
        assert list(s.plan["texture"]) == ["Linen", "HB3", "草莓", "HB10"]


def test_a_plan_label_outside_the_set_is_refused_before_the_file_exists(tmp_path):
    ts = TextureSet(["HB3", "Linen"], name="two")
    path = tmp_path / "x.h5"
    with pytest.raises(TextureSetError, match="HB4"):
        SessionWriter.create(path, plan=_plan(["HB3", "HB4"], 2), textures=ts)
    assert list(tmp_path.iterdir()) == []  # no file, no .creating leftover
    with pytest.raises(TextureSetError):  # the paper's set refuses a label outside A-P
        SessionWriter.create(path, plan=_plan(["A", "Q"], 2), textures=PAPER_TEXTURES)
    assert not path.exists()
    w = SessionWriter.create(path, plan=_plan(["HB3"], 1), textures=ts)
    with pytest.raises(TextureSetError, match="Canvas"):
        w.append_trial(dict(trial_id=None, texture="Canvas", speed_mm_s=1, force_g=1, duration_s=1))
    with open_session(path) as s:
        assert len(s.plan) == 1 and s.textures == ts


def test_a_trial_of_another_sensor_is_refused_and_nothing_is_written(tmp_path):
    rng = np.random.default_rng(3)
    path = tmp_path / "nine.h5"
    w = SessionWriter.create(path, plan=_plan(["A"], 3), layout=NINE_100)
    with pytest.raises(SessionError, match=r"18 channels at 1000 Hz.*9 channels at 100 Hz"):
        w.write_trial(0, TrialData(taxels=np.zeros((100, 18))))  # the paper's sensor
    with pytest.raises(SessionError, match=r"9 channels at 1000 Hz.*9 channels at 100 Hz"):
        w.write_trial(0, _trial(rng, NINE_100.with_rate(1000.0), 100))
    with pytest.raises(SessionError, match="18 channels"):  # a batch with a wrong trial in it: none of it lands
        w.write_trials([(0, _trial(rng, NINE_100, 50)), (1, TrialData(taxels=np.zeros((50, 18))))])
    assert w.completed_ids() == []
    with open_session(path) as s:
        assert s.completed_ids() == [] and list(s.plan["status"]) == [TrialStatus.PENDING] * 3
        assert "000000" not in s._f["trials"]
    # and a 9-channel trial into a paper session
    p18 = tmp_path / "paper.h5"
    w18 = SessionWriter.create(p18, plan=_plan(["A"], 1))
    assert w18.layout is PAPER_SENSOR
    with pytest.raises(SessionError, match=r"9 channels at 100 Hz.*18 channels at 1000 Hz"):
        w18.write_trial(0, _trial(rng, NINE_100, 10))


# -- schema 1/2 files -----------------------------------------------------------------------------------------------
_OLD_PLAN = np.dtype([("trial_id", "<u4"), ("texture", "S1"), ("speed_mm_s", "<f4"), ("force_g", "<f4"),
                      ("duration_s", "<f4"), ("profile", "S24"), ("ramp_start_mm_s", "<f4"),
                      ("ramp_end_mm_s", "<f4"), ("repeat", "<u4"), ("status", "u1")])


def _write_schema2(path, labels, *, n_samples=300, attrs=None, fill=None):
    """A session exactly as rigctl wrote schema 2 (before sensor_layout / texture_set): S1 labels, 18 columns at
    1 kHz, the constant taxel description on /trials; trial 0 complete, the others pending."""
    rng = np.random.default_rng(7)
    plan = np.zeros(len(labels), _OLD_PLAN)
    plan["trial_id"] = np.arange(len(labels))
    plan["texture"] = [t.encode() for t in labels]
    plan["speed_mm_s"], plan["force_g"], plan["duration_s"] = 80, 500, n_samples / 1000
    plan["profile"] = b"constant"
    plan["ramp_start_mm_s"] = plan["ramp_end_mm_s"] = np.nan
    plan["status"][0] = 1
    taxels = rng.integers(0, 1024, (n_samples, 18)).astype(np.uint16)
    if fill is not None:
        taxels[:, 16:] = fill
    with h5py.File(path, "w") as f:
        f.attrs.update({"schema_version": 2, "session_id": "0" * 36, "created_utc": "2026-11-20T10:00:00+00:00",
                        "rigctl_version": "0.1.0", "kind": "recorded", "rig_config": "{}", **(attrs or {})})
        g = f.create_group("protocol")
        g.create_dataset("source", data="name = 'old'", dtype=h5py.string_dtype("utf-8"))
        g.attrs.update({"name": "old", "format": "toml"})
        d = f.create_dataset("plan", data=plan, maxshape=(None,), chunks=(64,))
        d.attrs["status_enum"] = json.dumps({"pending": 0, "complete": 1, "failed": 2})
        tr = f.create_group("trials")
        tr.attrs["taxels_channels"] = "0-8 top layer (type I), 9-17 bottom layer (type II), row-major 3x3"
        tg = tr.create_group("000000")
        ds = tg.create_dataset("taxels", data=taxels, chunks=(n_samples, 18))
        ds.attrs.update({"rate_hz": 1000.0, "unit": "ADC counts", "adc_bits": 10, "starting_time": 0.0})
        for k, v in (("seq", np.arange(n_samples, dtype=np.uint16)), ("flags", np.zeros(n_samples, np.uint8)),
                     ("host_time_s", np.arange(n_samples) / 1000.0)):
            tg.create_dataset(k, data=v)
        for k in ("force_g", "force_time_s", "speed_mm_s", "speed_time_s"):
            tg.create_dataset(k, data=np.zeros(0))
        tg.attrs.update({"trial_id": 0, "texture": labels[0], "status": "complete", "n_samples": n_samples})
        c = f.create_group("calibration")
        c.create_dataset("taxel_min", data=np.arange(18.0))
        c.create_dataset("taxel_max", data=np.arange(18.0) + 900)
    return taxels


def test_a_schema_2_file_opens_as_the_paper_sensor_and_can_be_resumed(tmp_path):
    path = tmp_path / "old.h5"
    taxels = _write_schema2(path, ["B", "L", "P"])
    with open_session(path) as s:
        assert s.attrs["schema_version"] == 2
        assert s.layout is PAPER_SENSOR and s.textures is PAPER_TEXTURES
        assert list(s.plan["texture"]) == ["B", "L", "P"] and s.plan["profile"][0] == "constant"
        t = s.trial(0)
        assert t.layout is PAPER_SENSOR and t.rate_hz == 1000.0
        np.testing.assert_array_equal(t.taxels, taxels)
        np.testing.assert_array_equal(s.read_taxels([0]).data, taxels)  # the encoder's read path too
        assert s.calibration["taxel_min"].shape == (18,)
    # resuming an interrupted schema-2 session with this rigctl: same sensor, labels still fit
    w = SessionWriter.open(path, protocol_source="name = 'old'")
    assert w.layout is PAPER_SENSOR and w.pending_ids() == [1, 2]
    w.write_trial(1, TrialData(taxels=np.full((100, 18), 5)))
    w.append_trial(dict(trial_id=None, texture="C", speed_mm_s=80, force_g=500, duration_s=0.1))
    w.close()
    w2 = SessionWriter(path, compression=None)
    w2.textures = TextureSet(list(w2.textures.labels) + ["HB3"])  # even a set that has it
    with pytest.raises(SessionError, match="at most 1 byte"):  # the old fixed-length column cannot hold it
        w2.append_trial(dict(trial_id=None, texture="HB3", speed_mm_s=1, force_g=1, duration_s=1))
    w2.close()
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1] and list(s.plan["texture"]) == ["B", "L", "P", "C"]
        assert (s.trial(1).taxels == 5).all()
    # labels outside A-P: the set of the plan's labels
    other = tmp_path / "digits.h5"
    _write_schema2(other, ["1", "2", "1"])
    with open_session(other) as s:
        assert s.layout is PAPER_SENSOR and s.textures.labels == ("1", "2") and not s.textures.has_groups


def test_a_schema_2_file_encodes_like_its_trials(tmp_path):
    """An old (schema 2) session goes through the encoder's block read path: the features are those of its trial
    read the TrialData way and encoded by the batch encoder."""
    from rigctl.encoding.features import spike_features
    from rigctl.encoding.izhikevich import encode_ra, encode_sa
    from rigctl.encoding.normalise import TaxelRange
    from rigctl.encoding.pipeline import encode_session
    from rigctl.storage.encoded import open_encoded

    path = tmp_path / "old.h5"
    _write_schema2(path, ["B"], n_samples=600)
    with open_session(path) as s:
        x = s.trial(0).taxels
    rng_ = TaxelRange().update(x)
    want = spike_features(encode_sa(x, normalise=rng_), encode_ra(x, normalise=rng_), n_windows=6)
    out = encode_session(path, tmp_path / "old.enc.h5", variants=["original"], store_spikes=(), progress=None)
    with open_encoded(out) as f:
        np.testing.assert_array_equal(f.features("original"), want)


def test_a_schema_2_fabricslide_import_opens_with_its_16_present_channels(tmp_path):
    path = tmp_path / "fs.h5"
    present = np.array([True] * 16 + [False] * 2)
    taxels = _write_schema2(path, ["1", "4"], attrs={"kind": "fabricslide", "channel_present": present,
                                                    "texture_labels": json.dumps({"1": "BeigeCotton",
                                                                                  "4": "Linen"})}, fill=0)
    with open_session(path) as s:
        assert s.layout.n_channels == 16 and s.layout.sample_rate_hz == 1000.0 and s.layout.adc_bits == 10
        assert s.layout.channel_labels() == tuple(f"channel{k}" for k in range(1, 17))
        assert "FabricSlide" in s.layout.name
        from rigctl.storage.fabricslide import FABRICSLIDE_SENSOR
        assert s.layout == FABRICSLIDE_SENSOR  # the sensor a new FabricSlide import stores
        t = s.trial(0)
        assert t.layout == s.layout and t.taxels.shape == (300, 16)
        np.testing.assert_array_equal(t.taxels, taxels[:, :16])  # the absent (constant fill) columns dropped
        np.testing.assert_array_equal(s.read_taxels([0]).data, taxels[:, :16])
        np.testing.assert_array_equal(s.calibration["taxel_max"], np.arange(16.0) + 900)
        assert s.textures.labels == ("1", "4")
    with pytest.raises(SessionError, match="channel_present"):
        SessionWriter.open(path)


def test_block_reads_equal_trial_reads(tmp_path):
    """Session.read_taxels (the encoder's read path: one flat array, no TrialData) gives what trial() gives."""
    rng = np.random.default_rng(3)
    path = tmp_path / "s.h5"
    with SessionWriter.create(path, plan=_plan(["a", "b"], 5), layout=NINE_100,
                              textures=texture_set_from_labels(["a", "b"])) as w:
        for i, n in enumerate([40, 0, 75, 3, 60]):
            if i == 1:
                continue
            t = _trial(rng, NINE_100, n)
            t = TrialData(taxels=t.taxels, layout=NINE_100, dropped_frames=i, speed_mm_s=np.arange(i, dtype=float),
                          speed_time_s=np.arange(i) * 0.1)
            w.write_trial(i, t)
    with open_session(path) as s:
        ids = [4, 0, 3, 2]
        blk = s.read_taxels(ids, traces=True)
        assert blk.data.dtype == np.uint16 and blk.data.shape == (178, 9)
        for k, tid in enumerate(ids):
            tr = s.trial(tid)
            np.testing.assert_array_equal(blk.data[blk.starts[k]:blk.starts[k + 1]], tr.taxels)
            assert blk.dropped_frames[k] == tr.dropped_frames and blk.has_speed_trace[k] == (tid > 0)
            np.testing.assert_array_equal(blk.speed_traces[k][1], tr.speed_mm_s)
            np.testing.assert_array_equal(blk.speed_traces[k][0], tr.speed_time_s)
        with pytest.raises(KeyError):
            s.read_taxels([1])
    with h5py.File(path, "r+") as f:  # a value outside the 12-bit range: the trial is named
        f["/trials/000003/taxels"][1, 2] = 5000
    with open_session(path) as s, pytest.raises(SessionError, match="trial 3 is damaged"):
        s.read_taxels([0, 3])


def test_a_newer_schema_is_refused(tmp_path):
    path = tmp_path / "new.h5"
    SessionWriter.create(path, plan=_plan(["A"], 1))
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(SessionError, match="newer than this rigctl"):
        open_session(path)
    with pytest.raises(SessionError, match="newer than this rigctl"):
        SessionWriter.open(path)


def test_rigctl_info_shows_the_sensor_and_the_texture_set(tmp_path):
    from rigctl.cli import main

    path = tmp_path / "i.h5"
    ts = TextureSet.from_dict({"name": "lab", "textures": LABELS_26,
                               "groups": {"woven": LABELS_26[:13], "printed": LABELS_26[13:]}})
    w = SessionWriter.create(path, plan=_plan(LABELS_26, 26, duration_s=0.3), layout=NINE_100, textures=ts)
    w.write_trial(9, _trial(np.random.default_rng(1), NINE_100, 30))
    out = CliRunner().invoke(main, ["info", str(path)])
    assert out.exit_code == 0, out.output
    assert NINE_100.describe() in out.output and "9 channels" in out.output
    assert "lab: 26" in out.output and "woven: HB3 Linen" in out.output
    assert " " + "x" * 40 + " constant" in out.output  # the long label whole in the table
    out = CliRunner().invoke(main, ["info", "--json", str(path)])
    d = json.loads(out.output)
    assert d["sensor"]["n_channels"] == 9 and d["sensor"]["sample_rate_hz"] == 100.0
    assert d["sensor"]["description"] == NINE_100.describe()
    assert SensorLayout.from_dict(d["sensor"]["layout"]) == NINE_100
    assert d["texture_set"]["count"] == 26 and d["texture_set"]["name"] == "lab"
    assert d["texture_set"]["groups"] == {"woven": LABELS_26[:13], "printed": LABELS_26[13:]}
    assert d["trials"][9]["texture"] == "x" * 40 and d["trials"][9]["samples"] == 30


def test_reserved_attrs_and_a_wrong_layout_type_are_refused_without_a_file(tmp_path):
    path = tmp_path / "r.h5"
    with pytest.raises(ValueError, match="sensor_layout"):
        SessionWriter.create(path, plan=_plan(["A"], 1), attrs={"sensor_layout": "{}"})
    with pytest.raises(TypeError, match="SensorLayout"):
        SessionWriter.create(path, plan=_plan(["A"], 1), layout="3x3x2")
    assert list(tmp_path.iterdir()) == []
