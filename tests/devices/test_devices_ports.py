"""Boards found by USB serial number, exclusive opens, and `rigctl udev-rules`."""

from __future__ import annotations

import os
from types import SimpleNamespace

import pytest
import serial
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.devices import ports
from rigctl.devices.drum import DrumClient, resets_on_open
from rigctl.devices.errors import DrumError, TaxelStreamError
from rigctl.devices.taxel_stream import TaxelStream

MEGA_SERIAL, UNO_SERIAL = "95530343834351A0C1E1", "7543334343135170A0B0"


def _comport(device, vid, pid, serial_number):
    return SimpleNamespace(device=device, vid=vid, pid=pid, serial_number=serial_number, description="Arduino")


@pytest.fixture
def enumerated(monkeypatch):
    """pyserial's port list, replaced: ``enumerated[:] = [...]`` re-enumerates the USB bus."""
    listed: list = []
    monkeypatch.setattr(ports.list_ports, "comports", lambda: list(listed))
    return listed


def test_a_board_named_by_serial_number_is_found_wherever_it_enumerates(enumerated, mega, tmp_path):
    link = tmp_path / "ttyACM7"
    os.symlink(mega.path, link)
    enumerated[:] = [_comport(str(link), 0x2341, 0x0042, MEGA_SERIAL), _comport("/dev/null", 0x2341, 0x0043, UNO_SERIAL)]
    assert ports.resolve_port(f"serial:{MEGA_SERIAL}") == str(link)
    assert ports.resolve_port("/dev/ttyACM0") == "/dev/ttyACM0"
    # on the board's clock (a name by serial number is a real USB board's, found on the wall clock; this one is the
    # virtual Mega's, whose clock the test hands in: a starved host pauses the board, and the answer timeout judges it)
    with DrumClient(f"serial:{MEGA_SERIAL}", timeout_s=0.5, retries=2, clock=mega.clock) as drum:
        assert drum.read_status().firmware[0] >= 1
        assert ports.is_exclusive(drum._client.socket)
        # the USB link drops and the board comes back as another ttyACM: the next request finds it by its number
        drum._client.close()
        os.unlink(link)
        moved = tmp_path / "ttyACM9"
        os.symlink(mega.path, moved)
        enumerated[:] = [_comport("/dev/null", 0x2341, 0x0043, UNO_SERIAL), _comport(str(moved), 0x2341, 0x0042,
                                                                                       MEGA_SERIAL)]
        assert drum.read_status().firmware[0] >= 1
        assert drum._client.comm_params.host == str(moved)


def test_a_board_opened_by_path_is_reopened_by_its_serial_number_so_boards_cannot_swap(enumerated, mega, uno, tmp_path):
    acm0, acm1 = tmp_path / "ttyACM0", tmp_path / "ttyACM1"
    os.symlink(mega.path, acm0)
    os.symlink(uno.path, acm1)
    enumerated[:] = [_comport(str(acm0), 0x2341, 0x0042, MEGA_SERIAL), _comport(str(acm1), 0x2341, 0x0043, UNO_SERIAL)]
    with DrumClient(str(acm0), timeout_s=0.5, retries=2) as drum:
        assert drum.clock is mega.clock  # on the board's clock, found by the link (the Uno is only a name here)
        drum.read_status()
        # both boards re-enumerate in the other order: ttyACM0 is now the Uno
        drum._client.close()
        os.unlink(acm0)
        os.unlink(acm1)
        os.symlink(uno.path, acm0)
        os.symlink(mega.path, acm1)
        enumerated[:] = [_comport(str(acm0), 0x2341, 0x0043, UNO_SERIAL),
                         _comport(str(acm1), 0x2341, 0x0042, MEGA_SERIAL)]
        assert drum.read_status().firmware[0] >= 1  # the Mega, found as ttyACM1
        assert drum._client.comm_params.host == str(acm1)
        # and it is unplugged: no reopen of whatever holds a name now
        drum._client.close()
        enumerated[:] = [_comport(str(acm0), 0x2341, 0x0043, UNO_SERIAL)]
        with pytest.raises(DrumError, match="USB serial number"):
            drum.read_status()


def test_a_board_that_is_not_connected_is_a_clear_error(enumerated):
    with pytest.raises(ports.PortNotFound, match="no serial port with USB serial number 'X1'"):
        ports.resolve_port("serial:X1")
    with pytest.raises(DrumError, match="X1"):
        DrumClient("serial:X1").open()
    with pytest.raises(TaxelStreamError, match="X1"):
        TaxelStream("serial:X1", banner_timeout_s=0.2).open()


def test_the_taxel_stream_holds_its_port_exclusively(clocked_uno):
    uno = clocked_uno
    with TaxelStream(uno.path) as stream:
        assert stream.clock is uno.clock  # the banner wait on the board's clock
        assert ports.is_exclusive(stream._serial)
        # a cooperating second client is refused (pyserial's advisory lock)
        with pytest.raises(serial.SerialException):
            serial.Serial(uno.path, exclusive=True)


def test_only_a_real_serial_device_resets_on_open(tmp_path):
    a, b = os.openpty()
    try:
        assert not resets_on_open(os.ttyname(b))  # a pty has no DTR line
    finally:
        os.close(a)
        os.close(b)
    assert resets_on_open(str(tmp_path / "ttyACM0"))  # cannot be checked: assume the board resets
    assert DrumClient("/dev/ttyACM0").boot_wait_s > 0  # a real port: the Mega's boot window is waited out


def test_udev_rules_name_each_board_by_serial_number_and_keep_modemmanager_away(enumerated):
    enumerated[:] = [_comport("/dev/ttyACM0", 0x2341, 0x0043, UNO_SERIAL), _comport("/dev/ttyACM1", 0x2341, 0x0042,
                                                                                     MEGA_SERIAL)]
    r = CliRunner().invoke(main, ["udev-rules"])
    assert r.exit_code == 0, r.output
    rules = [line for line in r.output.splitlines() if line and not line.startswith("#")]
    assert len(rules) == 2
    drum = next(line for line in rules if "rigctl-drum" in line)
    taxel = next(line for line in rules if "rigctl-taxel" in line)
    assert f'ATTRS{{serial}}=="{MEGA_SERIAL}"' in drum and 'ATTRS{idProduct}=="0042"' in drum
    assert f'ATTRS{{serial}}=="{UNO_SERIAL}"' in taxel
    for line in rules:
        assert 'ENV{ID_MM_DEVICE_IGNORE}="1"' in line and 'GROUP="dialout"' in line and 'SUBSYSTEM=="tty"' in line


def test_clones_need_their_serial_numbers_given(enumerated):
    enumerated[:] = [_comport("/dev/ttyUSB0", 0x1A86, 0x7523, "A1"), _comport("/dev/ttyUSB1", 0x1A86, 0x7523, "B2")]
    r = CliRunner().invoke(main, ["udev-rules"])
    assert r.exit_code == 1 and "no rig board found" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(main, ["udev-rules", "--drum-serial", "B2", "--taxel-serial", "A1"])
    assert r.exit_code == 0
    assert 'ATTRS{serial}=="B2", SYMLINK+="rigctl-drum"' in r.output
    assert 'ATTRS{idVendor}=="1a86"' in r.output
    r = CliRunner().invoke(main, ["udev-rules", "--drum-serial", 'B2"; RUN+="x', "--taxel-serial", "A1"])
    assert r.exit_code == 2 and "cannot match" in r.output  # a usage error: the option named
