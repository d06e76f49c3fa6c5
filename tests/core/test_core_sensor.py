"""The sensor description: shapes, labels, JSON round trip, the board's identify reply, refusal of bad input."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.core import PAPER_FINGER, PAPER_SENSOR, LayoutError, SensorLayout, parse_layout


def test_paper_sensor_is_the_wire_layout():
    # docs/wire-protocol.md section 1: channels 0-8 top layer (type I), 9-17 bottom layer (type II), row-major 3x3
    assert PAPER_SENSOR.n_channels == 18 and PAPER_SENSOR.n_layers == 2
    assert list(PAPER_SENSOR.layer_channels("top")) == list(range(9))
    assert list(PAPER_SENSOR.layer_channels(1)) == list(range(9, 18))
    assert [la.receptor for la in PAPER_SENSOR.layers] == ["type I", "type II"]
    assert PAPER_SENSOR.channel_position(10) == (1, 0, 1)
    assert PAPER_SENSOR.sample_rate_hz == 1000.0 and PAPER_SENSOR.adc_max == 1023
    assert PAPER_FINGER.n_channels == 9 and PAPER_FINGER.n_layers == 1


@pytest.mark.parametrize("text, n, layers", [("3x3x2", 18, 2), ("3x3", 9, 1), ("4X4x1", 16, 1), ("2x5x3", 30, 3)])
def test_parse_layout(text, n, layers):
    lay = parse_layout(text, sample_rate_hz=100)
    assert (lay.n_channels, lay.n_layers, lay.sample_rate_hz) == (n, layers, 100.0)
    assert len(set(lay.channel_labels())) == n  # every channel has its own name


@pytest.mark.parametrize("text", ["3x", "0x3", "3x3x0", "three", "", "3*3"])
def test_parse_layout_refuses(text):
    with pytest.raises(LayoutError):
        parse_layout(text)


def test_json_round_trip_keeps_everything():
    lay = SensorLayout.grid(2, 2, 1, sample_rate_hz=250, adc_bits=12, pitch_mm=3.5,
                            channel_names=["a", "b", "c", "d"], name="lab sensor")
    back = SensorLayout.from_json(lay.to_json())
    assert back == lay and back.channel_labels() == ("a", "b", "c", "d")


def test_from_dict_refuses_inconsistent_counts():
    d = PAPER_SENSOR.to_dict()
    d["n_channels"] = 16
    with pytest.raises(LayoutError, match="n_channels=16"):
        SensorLayout.from_dict(d)
    with pytest.raises(LayoutError):
        SensorLayout.from_dict({"layers": [{"name": "x"}]})


def test_bad_values_refused():
    with pytest.raises(LayoutError):
        SensorLayout.grid(3, 3, sample_rate_hz=0)
    with pytest.raises(LayoutError):
        SensorLayout.grid(3, 3, adc_bits=17)
    with pytest.raises(LayoutError):
        SensorLayout.grid(3, 3, channel_names=["only one"])


def test_from_identify():
    # the Uno's banner fields (docs/wire-protocol.md 1.3)
    assert SensorLayout.from_identify({"ch": 18, "rate_hz": 1000, "bits": 10}) == PAPER_SENSOR
    nine = SensorLayout.from_identify({"ch": 9, "rate_hz": 100, "bits": 10})
    assert (nine.n_channels, nine.sample_rate_hz, nine.n_layers) == (9, 100.0, 1)
    explicit = SensorLayout.from_identify({"ch": 16, "rate_hz": 500, "bits": 12, "layout": "4x4x1"})
    assert (explicit.shape_text, explicit.adc_bits) == ("4x4x1", 12)
    with pytest.raises(LayoutError, match="ch=8"):
        SensorLayout.from_identify({"ch": 8, "layout": "3x3"})


def test_check_readings_names_shapes():
    PAPER_FINGER.check_readings(np.zeros((5, 9)))
    with pytest.raises(LayoutError, match=r"\(n_samples, 9\).*\(5, 18\)"):
        PAPER_FINGER.check_readings(np.zeros((5, 18)))
