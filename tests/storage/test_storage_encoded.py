"""rigctl.storage.encoded: the encoded file's writer and reader (round trip, schema version, refusals), files of
the unversioned schema 1 (as the pipeline wrote them before) and the variant registry."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.encoding.spikes import SpikeTrains
from rigctl.storage.encoded import (
    ALL_VARIANTS,
    ENCODED_SCHEMA_VERSION,
    MAIN_VARIANTS,
    REALTIME_VARIANTS,
    VARIANT_TITLES,
    VARIANTS,
    EncodedWriter,
    NotEncodedError,
    is_encoded_file,
    open_encoded,
    variant_info,
)

LAYOUT = SensorLayout.grid(4, 4, 1, sample_rate_hz=250.0, adc_bits=12, name="lab 4x4")
TEXTURES = TextureSet.from_dict({"name": "26 fabrics", "textures": [f"Fabric-{c}{c}{c}" for c in "ABCDEF"],
                                 "groups": {"plain": ["Fabric-AAA", "Fabric-BBB", "Fabric-CCC"],
                                            "twill": ["Fabric-DDD", "Fabric-EEE", "Fabric-FFF"]}})


def _trials(n=5):
    labels = [TEXTURES.labels[i % len(TEXTURES)] for i in range(n)]
    return {"trial_id": np.arange(10, 10 + n), "texture": labels,
            "speed_mm_s": np.where(np.arange(n) % 2, np.nan, 80.0), "force_g": np.full(n, 300.0),
            "profile": ["constant"] * (n - 1) + ["slow-to-fast ramp"], "duration_s": np.linspace(1, 2, n),
            "n_samples": (np.linspace(1, 2, n) * 250).astype(int)}


def _trains(rng, n_trials, n_trains):
    return SpikeTrains.from_lists([[np.sort(rng.uniform(0, 2, rng.integers(0, 6))) for _ in range(n_trains)]
                                   for _ in range(n_trials)])


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "e.h5"
    feats = rng.normal(size=(5, 32 * 8)).astype(np.float32)
    sp = [_trains(rng, 3, 32), _trains(rng, 2, 32)]
    table = np.zeros(4, dtype=[("texture", "U10"), ("speed_mm_s", "f4"), ("force_g", "f4"), ("taxel", "u2"),
                               ("coeff", "f8"), ("converged", "?")])
    table["texture"] = ["Fabric-AAA", "Fabric-AAA", "*", "*"]
    table["speed_mm_s"] = [80, np.nan, 80, np.nan]
    table["coeff"] = [1.0, 2.5, 1.0, 0.5]
    with EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials(), parameters={"window_s": 0.1},
                       attrs={"input_rate_hz": 250.0, "skipped_variants": {"speed_scaled": "no speed"}}) as w:
        assert not path.exists() and w.part.exists()  # written under .part until closed
        w.write_normalisation(np.zeros(16), np.full(16, 4095.0), source="test")
        w.write_force_coefficients(table, n_not_converged=1, n_coefficients=4)
        w.note_force_coefficients("not requested", label_free=True)
        w.write_features("original", 0, feats[:3])
        w.write_features("original", 3, feats[3:])
        w.add_spikes("original", 32, "SA then RA")
        for part in sp:
            w.append_spikes("original", part)
    assert path.exists() and not w.part.exists()
    assert is_encoded_file(path)
    with h5py.File(path, "r") as raw:  # labels are variable-length UTF-8 in the file, never fixed-width
        for name, col in (("trials", "texture"), ("trials", "group"), ("force_coefficients", "texture")):
            info = h5py.check_string_dtype(raw[name].dtype[col])
            assert info is not None and info.length is None and info.encoding == "utf-8"
    with open_encoded(path) as f:
        assert f.schema_version == ENCODED_SCHEMA_VERSION == 3
        assert f.attrs["kind"] == "rigctl encoded"
        assert f.layout == LAYOUT and f.textures == TEXTURES
        assert f.textures.group_of("Fabric-EEE") == "twill"
        assert f.variants == ("original",) and f.spike_variants == ("original",)
        assert f.n_trials == 5
        tr = f.trials
        assert list(tr["texture"]) == _trials()["texture"]  # multi-character labels, not truncated
        assert list(tr["group"]) == [TEXTURES.group_of(t) for t in _trials()["texture"]]
        np.testing.assert_array_equal(tr["trial_id"], np.arange(10, 15))
        np.testing.assert_array_equal(np.isnan(tr["speed_mm_s"]), np.arange(5) % 2 == 1)
        assert tr["profile"][-1] == "slow-to-fast ramp"
        np.testing.assert_array_equal(tr["n_samples"], _trials()["n_samples"])
        np.testing.assert_array_equal(f.features("original"), feats)
        assert f.feature_shape("original") == (5, 256)
        arrays = f.spikes("original")  # storage hands out plain arrays (it does not import the encoder)
        assert arrays.n_trains == 32 and arrays.spike_times.dtype == np.float64
        assert SpikeTrains(*arrays) == SpikeTrains.concatenate(sp)
        assert f.spike_trains_description("original") == "SA then RA"
        assert f.n_trains("original") == 32
        np.testing.assert_array_equal(f.normalisation["taxel_max"], np.full(16, 4095.0))
        fc = f.force_coefficients()
        assert list(fc["texture"]) == ["Fabric-AAA", "Fabric-AAA", "*", "*"]
        np.testing.assert_array_equal(fc["coeff"], table["coeff"])
        assert f.force_fit_stats()["n_not_converged"] == 1
        assert f.force_coefficients(label_free=True) is None
        assert f.attrs["force_coefficients_label_free_note"] == "not requested"
        assert f.parameters == {"window_s": 0.1}
        assert f.skipped_variants == {"speed_scaled": "no speed"}
        with pytest.raises(KeyError, match="speed_scaled"):
            f.features("speed_scaled")
        with pytest.raises(KeyError, match="no spike trains"):
            f.spikes("force_scaled")


def _tick_trains(rng, n_trials, n_trains, dt=1e-3):
    """Trains as the fused encoder makes them: times = sample * dt."""
    return SpikeTrains.from_lists([[np.unique(rng.integers(0, 3000, rng.integers(0, 8))) * dt
                                    for _ in range(n_trains)] for _ in range(n_trials)])


def test_spike_ticks_round_trip_bit_identical_and_shared_by_the_speed_scaled_twin(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "e.h5"
    parts = [_tick_trains(rng, 3, 4), _tick_trains(rng, 2, 4)]
    coef = [np.array([0.5, 1.0 / 3.0, 1.25]), np.array([0.7, 2.0 / 3.0])]  # eq. 2: speed / reference
    with EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
        w.add_spikes("original", 4, tick_s=1e-3)
        w.add_spikes("speed_scaled", 4, ticks_from="original")
        w.add_spikes("force_scaled", 4, tick_s=1e-3)
        w.add_spikes("speed_force_scaled", 4, tick_s=1e-3)  # its base is not stored: ticks of its own
        w.add_spikes("realtime_speed_scaled", 4)  # float64 times
        for part, c in zip(parts, coef):
            w.append_spikes("original", part)
            w.append_spikes("speed_scaled", part.scale_times(c), c)
            w.append_spikes("force_scaled", part)
            w.append_spikes("speed_force_scaled", part.scale_times(c), c)
            w.append_spikes("realtime_speed_scaled", part.scale_times(c))
    whole, c_all = SpikeTrains.concatenate(parts), np.concatenate(coef)
    with h5py.File(path, "r") as raw:
        assert raw["spikes/original/spike_ticks"].dtype == np.uint32
        assert "spike_ticks" not in raw["spikes/speed_scaled"] and raw["spikes/speed_scaled"].attrs["ticks_from"]
        assert raw["spikes/realtime_speed_scaled/spike_times"].dtype == np.float64
    with open_encoded(path) as f:
        assert SpikeTrains(*f.spikes("original")) == whole  # == compares times exactly
        assert SpikeTrains(*f.spikes("force_scaled")) == whole
        for v in ("speed_scaled", "speed_force_scaled", "realtime_speed_scaled"):
            assert SpikeTrains(*f.spikes(v)) == whole.scale_times(c_all), v
        for v in ("original", "speed_scaled", "realtime_speed_scaled"):  # a slice of trials reads only its rows
            full = SpikeTrains(*f.spikes(v))
            for sl in (slice(0, 1), slice(2, 4), slice(4, 5), slice(3, 3), slice(1, None)):
                rows = range(*sl.indices(5))
                assert SpikeTrains(*f.spikes(v, trials=sl)) == full.select_trials(list(rows)), (v, sl)
        with pytest.raises(ValueError, match="step"):
            f.spikes("original", trials=slice(0, 4, 2))


def test_spike_ticks_refusals(tmp_path):
    rng = np.random.default_rng(2)
    with EncodedWriter(tmp_path / "e.h5", layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
        with pytest.raises(ValueError, match="not a variant stored with ticks"):
            w.add_spikes("speed_scaled", 4, ticks_from="original")
        w.add_spikes("original", 4, tick_s=1e-3)
        with pytest.raises(ValueError, match="trains per trial"):
            w.add_spikes("speed_scaled", 6, ticks_from="original")
        w.add_spikes("speed_scaled", 4, ticks_from="original")
        on_grid = _tick_trains(rng, 2, 4)
        assert on_grid.spike_times.size
        off_grid = on_grid.with_times(on_grid.spike_times + 2.5e-4)
        with pytest.raises(ValueError, match="not multiples of tick_s"):
            w.append_spikes("original", off_grid)
        w.append_spikes("original", _tick_trains(np.random.default_rng(3), 2, 4))
        with pytest.raises(ValueError, match="not the same trains"):
            w.append_spikes("speed_scaled", _tick_trains(np.random.default_rng(4), 2, 4), 0.5)


def test_appended_ticks_store_what_appended_times_store(tmp_path):
    """``append_spike_ticks`` (the encoder's ticks of SA and RA joined, ``SpikeTrains.hstack_ticks``) writes the
    datasets ``append_spikes`` writes from the joined times, a speed-scaled twin's scale included; refusals."""
    rng = np.random.default_rng(6)
    parts = [(_tick_trains(rng, 3, 2), _tick_trains(rng, 3, 2)), (_tick_trains(rng, 2, 2), _tick_trains(rng, 2, 2))]
    coef = [np.array([0.5, 1.0 / 3.0, 1.25]), np.array([0.7, 2.0 / 3.0])]
    for how in ("times", "ticks"):
        with EncodedWriter(tmp_path / f"{how}.h5", layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
            w.add_spikes("original", 4, tick_s=1e-3)
            w.add_spikes("speed_scaled", 4, ticks_from="original")
            for (sa, ra), c in zip(parts, coef):
                if how == "times":
                    w.append_spikes("original", SpikeTrains.hstack([sa, ra]))
                    w.append_spikes("speed_scaled", SpikeTrains.hstack([sa, ra]).scale_times(c), c)
                else:
                    ticks, ends = SpikeTrains.hstack_ticks([sa, ra], 1e-3)
                    w.append_spike_ticks("original", ticks, ends)
                    w.append_spike_ticks("speed_scaled", ticks, ends, c)
    with h5py.File(tmp_path / "times.h5", "r") as a, h5py.File(tmp_path / "ticks.h5", "r") as b:
        for name in ("original/spike_ticks", "original/spike_times_index", "original/time_scale",
                     "speed_scaled/time_scale"):
            assert a[f"spikes/{name}"].dtype == b[f"spikes/{name}"].dtype
            np.testing.assert_array_equal(a[f"spikes/{name}"][()], b[f"spikes/{name}"][()], err_msg=name)
    sa, ra = parts[0]
    with pytest.raises(ValueError, match="not multiples of tick_s"):
        SpikeTrains.hstack_ticks([sa.with_times(sa.spike_times + 2.5e-4), ra], 1e-3)
    with pytest.raises(ValueError, match="same number of trials"):
        SpikeTrains.hstack_ticks([sa, parts[1][1]], 1e-3)
    ticks, ends = SpikeTrains.hstack_ticks([sa, ra], 1e-3)
    with EncodedWriter(tmp_path / "r.h5", layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
        w.add_spikes("original", 4, tick_s=1e-3)
        w.add_spikes("speed_scaled", 4, ticks_from="original")
        w.add_spikes("realtime_speed_scaled", 4)
        with pytest.raises(ValueError, match="uint32 ticks"):
            w.append_spike_ticks("original", ticks.astype(np.int64), ends)
        with pytest.raises(ValueError, match="uint32 ticks"):
            w.append_spike_ticks("realtime_speed_scaled", ticks, ends)
        with pytest.raises(ValueError, match="row ends"):
            w.append_spike_ticks("original", ticks, ends[:-1])
        w.append_spike_ticks("original", ticks, ends)
        with pytest.raises(ValueError, match="not the same trains"):
            w.append_spike_ticks("speed_scaled", ticks[:-1], np.minimum(ends, ticks.size - 1), 0.5)


def test_schema_2_float_spike_times_still_open(tmp_path):
    """Schema 2 wrote every variant's times as gzip float64 ``spike_times``: such a file reads as before."""
    rng = np.random.default_rng(5)
    path = tmp_path / "e.h5"
    st = _trains(rng, 5, 6)
    with EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
        w.write_features("original", 0, np.zeros((5, 12), np.float32))
        w.add_spikes("original", 6)  # no tick_s: the schema-2 layout
        w.append_spikes("original", st)
    with h5py.File(path, "r+") as raw:
        raw.attrs["schema_version"] = 2
        assert set(raw["spikes/original"]) == {"spike_times", "spike_times_index"}
    with open_encoded(path) as f:
        assert f.schema_version == 2
        assert SpikeTrains(*f.spikes("original")) == st


def test_writer_refusals(tmp_path):
    path = tmp_path / "e.h5"
    path.write_bytes(b"user data")
    with pytest.raises(FileExistsError):
        EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials())
    assert path.read_bytes() == b"user data"
    with pytest.raises(ValueError, match="not a rigctl encoded file"):  # only an encoded file is replaced
        EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials(), overwrite=True)
    assert path.read_bytes() == b"user data"
    path = tmp_path / "e2.h5"
    with EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
        w.write_features("original", 0, np.zeros((5, 3)))
    before = path.read_bytes()
    with pytest.raises(RuntimeError):
        with EncodedWriter(path, layout=LAYOUT, textures=TEXTURES, trials=_trials(), overwrite=True) as w:
            w.write_features("original", 0, np.zeros((5, 3)))
            raise RuntimeError("encoding failed")
    assert path.read_bytes() == before and not w.part.exists()  # nothing replaced, part file removed
    with pytest.raises(ValueError, match="entries"):
        EncodedWriter(tmp_path / "x.h5", layout=LAYOUT, textures=TEXTURES,
                      trials={"trial_id": [0, 1], "texture": ["Fabric-AAA"]})
    with EncodedWriter(tmp_path / "y.h5", layout=LAYOUT, textures=TEXTURES, trials=_trials()) as w:
        w.write_features("original", 0, np.zeros((2, 3)))
        with pytest.raises(ValueError, match="3"):
            w.write_features("original", 2, np.zeros((3, 4)))
        w.add_spikes("original", 32)
        with pytest.raises(ValueError, match="trains"):
            w.append_spikes("original", SpikeTrains.empty(1, 18))


def _write_schema1(path, labels, groups):
    """An encoded file as the pipeline wrote it before the schema was versioned (fixed-length byte strings, no
    layout, texture set or schema_version)."""
    n = len(labels)
    dt = np.dtype([("trial_id", "u4"), ("texture", "S8"), ("group", "S24"), ("speed_mm_s", "f4"),
                   ("force_g", "f4"), ("profile", "S24"), ("duration_s", "f4"), ("n_samples", "u4")])
    trials = np.zeros(n, dtype=dt)
    trials["trial_id"] = np.arange(n)
    trials["texture"] = [t.encode() for t in labels]
    trials["group"] = [g.encode() for g in groups]
    trials["speed_mm_s"] = 120.0
    trials["force_g"] = 500.0
    trials["profile"] = b"constant"
    trials["duration_s"] = 2.0
    trials["n_samples"] = 2000
    st = SpikeTrains.from_lists([[np.array([0.1 * (j + 1)]) for j in range(36)] for _ in range(n)])
    fc = np.zeros(2, dtype=[("texture", "S8"), ("speed_mm_s", "f4"), ("force_g", "f4"), ("taxel", "u2"),
                            ("coeff", "f8"), ("converged", "?")])
    fc["texture"] = [labels[0].encode()] * 2
    with h5py.File(path, "w") as f:
        f.create_dataset("trials", data=trials)
        f.create_dataset("features/original", data=np.ones((n, 2160), np.float32))
        f.create_dataset("features/speed_scaled", data=np.ones((n, 720), np.float32))
        g = f.create_group("spikes/original")
        g.create_dataset("spike_times", data=st.spike_times)
        g.create_dataset("spike_times_index", data=st.spike_times_index)
        g.attrs["n_trains"] = 36
        f.create_dataset("normalisation/taxel_min", data=np.zeros(18))
        f.create_dataset("normalisation/taxel_max", data=np.full(18, 1023.0))
        f.create_dataset("force_coefficients", data=fc)
        f.attrs["parameters"] = json.dumps({"fs_hz": 1000.0, "n_windows_unscaled": 60, "window_s": 0.1})
        f.attrs["variants"] = json.dumps(["original", "speed_scaled"])
        f.attrs["n_trials"] = n
        f.attrs["n_taxels"] = 18
    return st


def test_old_unversioned_file_opens(tmp_path):
    path = tmp_path / "old.h5"
    labels = list("ABLP")
    st = _write_schema1(path, labels, ["smooth", "circular ridges", "waves", "waves"])
    with open_encoded(path) as f:
        assert f.schema_version == 1
        assert f.layout.n_channels == 18 and f.layout.shape_text == PAPER_SENSOR.shape_text
        assert f.layout.sample_rate_hz == 1000.0
        assert f.textures is PAPER_TEXTURES
        assert f.resampling == {"input_rate_hz": 1000.0, "model_rate_hz": 1000.0, "resampled": False}
        assert f.variants == ("original", "speed_scaled")
        assert list(f.trials["texture"]) == labels and f.trials["texture"].dtype.kind == "U"
        assert list(f.trials["group"]) == ["smooth", "circular ridges", "waves", "waves"]
        assert f.features("original").shape == (4, 2160)
        assert SpikeTrains(*f.spikes("original")) == st
        assert list(f.force_coefficients()["texture"]) == ["A", "A"]
        assert f.n_trains("speed_scaled") == 36  # not stored: from the layout (SA + RA per taxel)
        assert f.skipped_variants == {}


def test_old_file_with_other_labels(tmp_path):
    path = tmp_path / "old_fabric.h5"
    _write_schema1(path, ["Linen", "Denim", "Linen"], ["", "", ""])
    with open_encoded(path) as f:
        assert f.textures.labels == ("Denim", "Linen") and not f.textures.has_groups
        assert list(f.trials["group"]) == ["", "", ""]


def test_not_encoded_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_encoded(tmp_path / "missing.h5")
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(NotEncodedError, match="not an HDF5 file"):
        open_encoded(text)
    assert not is_encoded_file(text)
    session = tmp_path / "session.h5"
    with h5py.File(session, "w") as f:
        f.create_dataset("plan", data=np.zeros(3))
    with pytest.raises(NotEncodedError, match="rigctl encode"):
        open_encoded(session)
    assert not is_encoded_file(session)
    newer = tmp_path / "newer.h5"
    with h5py.File(newer, "w") as f:
        f.create_group("features")
        f.attrs["schema_version"] = ENCODED_SCHEMA_VERSION + 1
    with pytest.raises(NotEncodedError, match="schema"):
        open_encoded(newer)


def test_variant_registry():
    assert MAIN_VARIANTS == ("original", "speed_scaled", "force_scaled", "speed_force_scaled")
    assert [VARIANT_TITLES[v] for v in MAIN_VARIANTS] == ["Original", "Speed Scaled", "Force Scaled",
                                                         "Speed and Force Scaled"]
    assert set(REALTIME_VARIANTS) < set(ALL_VARIANTS) and len(ALL_VARIANTS) == 8
    assert [v for v in ALL_VARIANTS if VARIANTS[v].speed_scaled] == [
        "speed_scaled", "speed_force_scaled", "speed_force_scaled_label_free", "realtime_speed_scaled"]
    assert VARIANTS["force_scaled_label_free"].label_free and VARIANTS["force_scaled_label_free"].force_scaled
    assert not VARIANTS["realtime_original"].main
    with pytest.raises(KeyError, match="original"):
        variant_info("nope")
