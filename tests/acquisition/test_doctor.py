"""rigctl doctor: the measurements on known signals, the checks on the in-process rig (healthy and with injected
faults), the report stored in the rig config, and the CLI (usage errors, a port without permission)."""

from __future__ import annotations

import json
import os
import subprocess
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from rigctl import firmware
from rigctl.acquisition import doctor
from rigctl.acquisition.doctor.base import NOT_OPENED
from rigctl.acquisition.doctor.measure import clock_error_ppm, crosstalk, step_response
from rigctl.acquisition.rigconfig import RigConfigError, load_rig_config, validate_rig_config
from rigctl.core.drum import DrumState
from rigctl.core.faults import parse_fault
from rigctl.rigs import WATCHDOG_MS, open_rig
from rigctl.simulation.model import DrumConfig, MechanicsConfig, RigConfig


# ------------------------------------------------------------------------------------------------ measurements
def _second_order(t, sp, zeta, wn):
    wd = wn * np.sqrt(1 - zeta ** 2)
    return sp * (1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / np.sqrt(1 - zeta ** 2) * np.sin(wd * t)))


def test_step_response_of_a_damped_second_order_step():
    t = np.arange(0, 6, 0.02)
    zeta = 0.4
    f = _second_order(t, 500.0, zeta, 2 * np.pi * 1.0)
    x = f / 250.0  # 250 g/mm
    r = step_response(t, f, x, 500.0, 15.0)
    expected = 100 * np.exp(-np.pi * zeta / np.sqrt(1 - zeta ** 2))  # 25.4 %
    assert r.overshoot_pct == pytest.approx(expected, abs=1.0)
    assert r.settled and 0.5 < r.settling_time_s < 2.0
    assert r.stiffness_g_per_mm == pytest.approx(250.0, rel=0.01)
    assert r.residual_pp_g < 15


def test_step_response_of_a_sustained_oscillation_does_not_settle():
    t = np.arange(0, 6, 0.02)
    f = 500 + 185 * np.sin(2 * np.pi * 3 * t)  # +-185 g, the 80 SPS figure
    r = step_response(t, f, f / 1500, 500.0, 15.0)
    assert not r.settled
    assert r.residual_pp_g == pytest.approx(370, rel=0.05)


def test_crosstalk_finds_a_bleeding_pair_and_nothing_in_independent_noise():
    rng = np.random.default_rng(1)
    s = np.round(500 + 1.6 * rng.standard_normal((10_000, 18)))
    c, noise = crosstalk(s)
    assert np.nanmax(c) < 0.05
    bled = s.copy()
    bled[:, 4] = np.round(0.8 * s[:, 4] + 0.2 * bled[:, 3])  # 20 % of taxel 3 left in taxel 4 (47 kOhm)
    c, _ = crosstalk(bled)
    j, i = np.unravel_index(int(np.nanargmax(c)), c.shape)
    assert {j, i} == {3, 4}
    assert c[4, 3] == c[3, 4] == pytest.approx(0.2 / np.hypot(0.8, 0.2), abs=0.03)


def test_clock_error_ppm():
    assert clock_error_ppm(1000.5, 1000.0) == pytest.approx(500.0)


# ------------------------------------------------------------------------------------------------ on a rig
def _run(tmp_path, config=None, names=None):
    cfg_path = tmp_path / "rig.json"
    ctx = doctor.DoctorContext("inprocess", opener=lambda: open_rig("inprocess", config=config, seed=3,
                                                                    host_config_path=cfg_path),
                               config_path=cfg_path, rest_s=3.0)
    report = doctor.run_doctor(doctor.select(names), ctx)
    return report, {r.name: r for r in report.results}


def test_the_healthy_inprocess_rig_passes_and_the_report_is_stored(tmp_path):
    report, by = _run(tmp_path)
    assert report.ok, [r.line() for r in report.results if r.status == "fail"]
    for name in ("link", "controller-faults", "firmware-version", "hx711-rate", "loadcell-zero", "noise-floor",
                 "crosstalk", "uno-clock", "loadcell-polarity", "force-step", "drum-speed", "drum-direction"):
        assert by[name].status == "pass", by[name].line()
    # the virtual Mega reports the installed sources' build id (as if flashed by rigctl); the virtual Uno none, named
    own = firmware.build_id()
    assert by["firmware-build"].status == "pass" and by["firmware-build"].values["mega_build"] == own
    assert "taxel streamer (uno) reports no build id" in by["firmware-build"].summary
    assert by["port-permissions"].status == "skip"  # the in-process rig has no ports
    assert by["force-step"].values["settling_time_s"] < doctor.drum_checks.MAX_SETTLING_S
    doctor.save_report(report, tmp_path / "rig.json")
    stored = load_rig_config(tmp_path / "rig.json")["doctor"]["inprocess"]
    assert stored["checked_utc"] == report.checked_utc and stored["ok"] is True
    assert [c["name"] for c in stored["checks"]] == doctor.check_names()
    again = doctor.last_report("inprocess", tmp_path / "rig.json")
    assert again is not None and [r.status for r in again.results] == [r.status for r in report.results]


def test_a_reversed_load_cell_fails_polarity_with_the_fix(tmp_path):
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=-420.0))
    report, by = _run(tmp_path, cfg, ["link", "loadcell-polarity"])
    r = by["loadcell-polarity"]
    assert r.status == "fail", r.line()
    assert "swap" in r.fix and "A+/A-" in r.fix
    assert r.values["lowest_force_g"] < -30
    assert not report.ok


def _run_service(tmp_path, config, names):
    from rigctl.operations import RigSource, doctor as run

    report = run(RigSource("inprocess"), config=config, seed=3, host_config_path=tmp_path / "rig.json", rest_s=3.0,
                 checks=names, save=False)
    return report, {r.name: r for r in report.results}


def test_a_reversed_actuator_fails_the_direction_check_with_the_fix(tmp_path):
    """Issue 39: the actuator's coil pair swapped. Opening the rig moves nothing (controller-faults, which runs
    before the checks that move, finds nothing latched); the doctor's start HOMEs before the first check that moves,
    HOME's direction proof latches ACTUATOR_DIRECTION (the rig stays open with it latched for the operator), and the
    direction check says how to fix it; the healthy rig passes it."""
    cfg = RigConfig(mechanics=MechanicsConfig(actuator_reversed=True))
    report, by = _run_service(tmp_path, cfg, ["actuator-direction", "controller-faults"])
    r = by["actuator-direction"]
    assert r.status == "fail" and "swap one coil pair" in r.fix, r.line()
    assert by["controller-faults"].status == "pass", by["controller-faults"].line()  # before the start's HOME
    _, by = _run_service(tmp_path, None, ["actuator-direction"])
    assert by["actuator-direction"].status == "pass", by["actuator-direction"].line()


def test_a_10_sps_hx711_fails_its_check_with_the_rate_pin_fix(tmp_path):
    """The simulated HX711 at 10 SPS on a controller set for 80: the controller latches HX711_RATE, the doctor opens
    the rig without clearing it and names the RATE pin; the checks that would move the rig skip."""
    cfg = RigConfig(mechanics=MechanicsConfig(hx711_rate_sps=10.0))
    report, by = _run_service(tmp_path, cfg, ["link", "controller-faults", "hx711-rate", "force-step"])
    assert by["link"].status == "pass"
    assert by["hx711-rate"].status == "fail" and "RATE pin high" in by["hx711-rate"].fix
    assert by["hx711-rate"].values["hx711_rate_sps"] == pytest.approx(10.0, rel=0.05)
    assert by["controller-faults"].status == "fail" and "HX711_RATE" in by["controller-faults"].summary
    assert by["force-step"].status == "skip"
    _, healthy = _run_service(tmp_path, None, ["hx711-rate"])
    assert healthy["hx711-rate"].status == "pass", healthy["hx711-rate"].line()


def test_a_drum_driver_at_8_microsteps_fails_the_index_speed_check(tmp_path):
    _, by = _run_service(tmp_path, RigConfig(drum=DrumConfig(driver_microsteps=8)), ["drum-speed"])
    r = by["drum-speed"]
    assert r.status == "fail" and "16 microsteps" in r.fix
    assert r.values["speed_at_40_mm_s"] == pytest.approx(80.0, rel=0.02)
    assert r.values["steps_per_rev_at_40_mm_s"] == 1600
    _, healthy = _run_service(tmp_path, None, ["drum-speed"])
    assert healthy["drum-speed"].status == "pass", healthy["drum-speed"].line()
    assert healthy["drum-speed"].values["speed_at_120_mm_s"] == pytest.approx(120.0, rel=0.02)


def test_the_load_cell_scale_is_compared_with_the_rig_configs_calibration(tmp_path):
    from rigctl.acquisition.rigconfig import save_rig_config

    save_rig_config({"loadcell": {"counts_per_g": 420.0, "scale_x100": 42000}}, tmp_path / "rig.json")
    _, by = _run_service(tmp_path, None, ["loadcell-scale"])
    assert by["loadcell-scale"].status == "pass", by["loadcell-scale"].line()
    save_rig_config({"loadcell": {"counts_per_g": 500.0, "scale_x100": 50000}}, tmp_path / "rig.json")
    _, by = _run_service(tmp_path, None, ["loadcell-scale"])
    r = by["loadcell-scale"]
    assert r.status == "fail" and r.values["board_counts_per_g"] == 420.0 and "calibrat" in r.fix


def test_the_reference_mass_check_reads_a_known_mass_and_the_stored_stiffness(tmp_path):
    """Issue 75 item 6: the doctor's bring-up puts the reference mass on the cell (the simulated rig's model does)
    and compares the reading with it; a load cell of half the gain its calibration says fails with the fix (a wrong
    scale the EEPROM and the rig config agree on, which loadcell-scale cannot see); so does a rig whose calibration
    stores no contact stiffness (the check of every press is off)."""
    _, by = _run_service(tmp_path, None, ["reference-mass"])
    r = by["reference-mass"]
    assert r.status == "pass" and abs(r.values["off_pct"]) < 1 and r.values["stored_stiffness_g_per_mm"] > 0, r.line()
    half = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=210.0))  # the factory's 420 counts/g: reads 1/2
    _, by = _run_service(tmp_path, half, ["reference-mass"])
    r = by["reference-mass"]
    assert r.status == "fail" and r.values["read_g"] == pytest.approx(250, abs=10) and "reference mass" in r.fix


def test_firmware_build_against_the_installed_sources():
    """Each board's build id (the Mega's BUILD_ID_0 .. _2 registers, wire-protocol 2.2; the Uno's banner build=, 1.4)
    against the installed sources' digest: equal -> pass; another -> fail naming the board's flash command; a Uno
    without one (a simulated Uno) -> named; a Mega without one (build 0: the Arduino IDE, make BUILD_ID=) -> fail."""
    from types import SimpleNamespace

    own = firmware.build_id()
    other = "0123456789ab" if own != "0123456789ab" else "ba9876543210"

    def check(mega, uno):
        rig = SimpleNamespace(drum=SimpleNamespace(read_status=lambda: SimpleNamespace(build_id=mega)),
                              stream=SimpleNamespace(banner={"build": uno}))
        return doctor.run_doctor(doctor.select(["firmware-build"]), doctor.DoctorContext("hardware", rig=rig)).results[0]

    assert check(own, own).status == "pass"
    r = check(own, None)
    assert r.status == "pass" and r.values == {"mega_build": own, "uno_build": None, "sources_digest": firmware.source_digest()}
    assert "uno) reports no build id" in r.summary
    for mega, uno, board in ((other, own, "mega"), (own, other.upper(), "uno"), (other, None, "mega")):
        r = check(mega, uno)
        assert r.status == "fail", r.line()
        assert f"rigctl firmware --flash PORT --board {board}" in r.fix and f"({board}) runs build {other}" in r.summary
    r = check(other, other)
    assert "--board mega" in r.fix and "--board uno" in r.fix
    for uno in (None, own):
        r = check(None, uno)
        assert r.status == "fail" and "(mega) runs build 0" in r.summary and "--board mega" in r.fix, r.line()


def test_the_inprocess_mega_flashed_from_other_sources_fails_the_build_check():
    """The virtual Mega reports the installed sources' build id; given another (a board flashed from other sources of
    the same version), the doctor fails naming the flash command; given none (build 0: the Arduino IDE, make
    BUILD_ID=), it fails too."""
    own = firmware.build_id()
    other = "0123456789ab" if own != "0123456789ab" else "ba9876543210"
    with open_rig("inprocess", seed=3) as rig:
        def check():
            ctx = doctor.DoctorContext("inprocess", rig=rig)
            return doctor.run_doctor(doctor.select(["firmware-build"]), ctx).results[0]

        assert rig.drum.read_status().build_id == own
        assert check().status == "pass"
        rig.backend.controller.build_id = other
        r = check()
        assert r.status == "fail" and r.values["mega_build"] == other, r.line()
        assert r.fix == "flash the installed firmware: rigctl firmware --flash PORT --board mega"
        rig.backend.controller.build_id = None
        assert rig.drum.read_status().build_id is None
        r = check()
        assert r.status == "fail" and "runs build 0" in r.summary and r.fix.endswith("--board mega"), r.line()


def test_a_mega_flashed_before_the_build_id_registers_is_told_to_flash(monkeypatch):
    """A controller whose input registers end at INDEX_COUNT (firmware built before BUILD_ID_0 .. _2) answers the
    status read with exception 02: the host says what to do, not just the exception."""
    from pymodbus.constants import ExcCodes

    from rigctl.core.drum import DrumError
    from rigctl.devices import wire

    with open_rig("inprocess", seed=3) as rig:
        ctl = rig.backend.controller
        full = ctl._read

        def older(func_code, address, count):  # the register span of the firmware before
            if func_code == 4 and address + count > int(wire.InputRegister.INDEX_COUNT) + 1:
                return ExcCodes.ILLEGAL_ADDRESS
            return full(func_code, address, count)

        monkeypatch.setattr(ctl, "_read", older)
        with pytest.raises(DrumError, match=r"older than the installed sources; flash them: rigctl firmware --flash"):
            rig.drum.read_status()
        monkeypatch.setattr(ctl, "_read", full)
        assert rig.drum.read_status().build_id == firmware.build_id()


def test_a_stored_report_is_schema_checked():
    good = {"checked_utc": "2026-01-01T00:00:00+00:00", "rig": "sim", "ok": True,
            "checks": [{"name": "link", "status": "pass", "summary": "ok", "values": {"x": [1, 2.5], "y": None}}]}
    validate_rig_config({"doctor": {"sim": good}})
    bad = json.loads(json.dumps(good))
    bad["checks"][0]["status"] = "maybe"
    with pytest.raises(RigConfigError, match="doctor.sim"):
        validate_rig_config({"doctor": {"sim": bad}})
    with pytest.raises(RigConfigError, match="unknown key"):
        validate_rig_config({"doctor": {"bench": good}})


# ------------------------------------------------------------------------------------------------ CLI
RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)


def _rigctl(*args, timeout_s: float = 120, **kw):
    return subprocess.run([*RIGCTL, *args], capture_output=True, text=True, timeout=timeout_s, **kw)


def test_cli_usage_errors_exit_2():
    p = _rigctl("doctor", "--check", "bogus", "--no-save")
    assert p.returncode == 2 and "unknown check 'bogus'" in p.stderr
    p = _rigctl("doctor", "--drum-port", "/dev/null", "--no-save")
    assert p.returncode == 2 and "both --drum-port and --taxel-port" in p.stderr
    p = _rigctl("doctor", "--hil-bootloaders", "--sim", "--no-save")
    assert p.returncode == 2 and "choose one of --sim, --hil and --inprocess" in p.stderr
    assert "Traceback" not in p.stderr


def _as_unprivileged_user(args: list[str]) -> tuple[int, str]:
    """``rigctl ARGS`` in a forked child that dropped root for the user nobody (65534): the interpreter's own files
    may be unreadable for nobody, so the child runs the already imported CLI instead of a new interpreter."""
    import tempfile

    from click.testing import CliRunner

    import rigctl.cli.doctor  # noqa: F401 - imported before the fork: nobody may not read the sources' folders
    from rigctl.cli import main

    # the user's folders (config, state, cache) in a folder nobody may use, as a real user's own would be; and the
    # command run once before the fork, as root, to import every module its path loads (the interpreter's library
    # may be unreadable for nobody: 'No module named queue'); its result is not judged
    home = tempfile.mkdtemp(prefix="rigctl-nobody-")
    os.chmod(home, 0o777)
    env = {"HOME": home, "XDG_CONFIG_HOME": home, "XDG_STATE_HOME": home, "XDG_CACHE_HOME": home,
           "RIGCTL_CONFIG": os.path.join(home, "rig.json")}
    CliRunner().invoke(main, args, env=env)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 99
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            res = CliRunner().invoke(main, args, env=env)
            os.write(w, res.output.encode())
            code = res.exit_code
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as f:
        out = f.read()
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status), out


def test_a_port_without_permission_fails_with_the_dialout_fix(tmp_path):
    """Two ptys (the boards' ports) that only root may open; the doctor runs as an unprivileged user (or, when the
    tests do not run as root, on ports chmod 000)."""
    fds, names = [], []
    for _ in range(2):
        m, s = os.openpty()
        fds += [m, s]
        names.append(os.ttyname(s))
    try:
        args = ["doctor", "--drum-port", names[0], "--taxel-port", names[1], "--check", "port-permissions", "--json",
                "--no-save"]
        if os.getuid() == 0:
            for n in names:
                os.chown(n, 0, 0)
                os.chmod(n, 0o600)
            code, out = _as_unprivileged_user(args)
        else:
            for n in names:
                os.chmod(n, 0)
            p = _rigctl(*args, env={**os.environ, "HOME": str(tmp_path)})
            code, out = p.returncode, p.stdout
        assert code == 1, out
        rep = json.loads(out[out.index("{"):])
        (check,) = rep["checks"]
        assert check["status"] == "fail" and names[0] in check["summary"], check
        assert "usermod -aG" in check["fix"] and "log out" in check["fix"]
    finally:
        for fd in fds:
            os.close(fd)


def test_cli_doctor_inprocess_passes_and_stores_the_dated_report(tmp_path):
    """`rigctl doctor` as a process, on the in-process rig (its checks' logic; the same command on the firmware under
    simavr, over ptys, is test_cli_doctor_hil_passes): a line per check, the summary, the report stored under the
    rig's kind with its date."""
    cfg = tmp_path / "rig.json"
    p = _rigctl("doctor", "--inprocess", "--rest-s", "3", "--config", str(cfg), "--save",
                env={**os.environ, "HOME": str(tmp_path)})
    assert p.returncode == 0, p.stdout + p.stderr
    assert "NOT_HOMED" not in p.stderr and "EEPROM" not in p.stderr, p.stderr  # no alarm above a passing report
    lines = p.stdout.splitlines()
    # a line a check, but consecutive skips for one reason, which share a line ("SKIP  a, b (2 checks): why")
    named = [n for line in lines[:-1] for n in line.split(":")[0].split(None, 1)[1].split(" (")[0].split(", ")]
    assert sorted(named) == sorted(doctor.check_names()), p.stdout
    assert all(line.split()[0] in ("PASS", "SKIP") for line in lines[:-1]), p.stdout
    assert lines[-1].startswith("inprocess rig:") and "0 failed" in lines[-1]
    stored = load_rig_config(cfg)["doctor"]["inprocess"]
    assert stored["ok"] is True and stored["rig"] == "inprocess"
    assert abs(datetime.fromisoformat(stored["checked_utc"]) - datetime.now(UTC)) < timedelta(minutes=5)
    assert {c["name"]: c["status"] for c in stored["checks"]}["force-step"] == "pass"


def test_cli_doctor_writes_the_rig_config_only_with_save(tmp_path):
    """Without --save the report is printed, never stored: the rig config is not created (issue 38: doctor on a real rig
    wrote ~/.config/rigctl/rig.json unasked)."""
    from click.testing import CliRunner

    from rigctl.cli import main

    cfg = tmp_path / "rig.json"
    r = CliRunner().invoke(main, ["doctor", "--inprocess", "--check", "link", "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[-1] == "inprocess rig: 1 passed, 0 failed, 0 skipped" and not cfg.exists()


@pytest.mark.hil
@pytest.mark.slow
def test_cli_doctor_hil_passes(tmp_path):
    """Every check on the firmware under simavr: ~45 s of the firmware's time (the drum-speed check waits two index
    edges at 40 mm/s, 7.9 s a revolution), 100-130 s on a loaded 2-core machine; nothing fails, what the simulator
    cannot show is a skip with its reason."""
    cfg = tmp_path / "rig.json"
    p = _rigctl("doctor", "--hil", "--rest-s", "2", "--config", str(cfg), "--json", "--save", timeout_s=280,
                env={**os.environ, "HOME": str(tmp_path)})
    assert p.returncode == 0, p.stdout + p.stderr
    rep = json.loads(p.stdout)
    by = {c["name"]: c for c in rep["checks"]}
    assert not [n for n, c in by.items() if c["status"] == "fail"], by
    for name in ("port-permissions", "link", "firmware-version", "firmware-build", "controller-faults", "reset-cause",
                 "e-stop",
                 "hx711-rate", "loadcell-zero", "reference-mass", "noise-floor", "crosstalk", "loadcell-polarity",
                 "force-step", "drum-speed",
                 "drum-direction"):
        assert by[name]["status"] == "pass", by[name]
    # both images under simavr were built by rigctl from the installed sources: both boards report their build id
    assert by["firmware-build"]["values"]["mega_build"] == by["firmware-build"]["values"]["uno_build"] == \
        firmware.build_id()
    assert load_rig_config(cfg)["doctor"]["hil"]["ok"] is True


@pytest.mark.hil
def test_cli_doctor_hil_with_the_real_bootloaders(tmp_path):
    """--hil-bootloaders: both boards run their real bootloaders (stk500v2, optiboot) and reset when the doctor opens
    their ports, as real boards do. The Mega's HX711 kept converting through the reset and the bootloader's 0.8 s, so
    the sketch's first reading had waited: timed from it, the rate read 95.4 SPS for the 80 SPS part (firmware before
    the rate was timed from the second edge; past the 20 % tolerance in a third of boots on a bench)."""
    p = _rigctl("doctor", "--hil-bootloaders", "--rest-s", "2", "--json", "--no-save", "--check", "link",
                "--check", "reset-cause", "--check", "hx711-rate", "--check", "firmware-build",
                env={**os.environ, "HOME": str(tmp_path)})
    assert p.returncode == 0, p.stdout + p.stderr
    by = {c["name"]: c for c in json.loads(p.stdout)["checks"]}
    assert by["link"]["status"] == "pass", by["link"]
    # the stk500v2 bootloader clears MCUSR before the sketch reads it: the cause is unknown, never a false one
    assert by["reset-cause"]["values"]["reset_cause"] == [], by["reset-cause"]
    assert by["hx711-rate"]["values"]["hx711_rate_sps"] == pytest.approx(80.0, rel=0.01), by["hx711-rate"]
    # the Uno's banner (build=) and the Mega's BUILD_ID registers name the sources they were built from: those installed
    assert by["firmware-build"]["status"] == "pass", by["firmware-build"]
    assert by["firmware-build"]["values"]["mega_build"] == by["firmware-build"]["values"]["uno_build"]


@pytest.mark.hil
def test_a_high_impedance_taxel_does_not_bleed_into_its_neighbours_under_simavr(tmp_path):
    """The simavr harness's multiplexer RC model with one taxel at 1 MOhm (the firmware settles 47 kOhm). The
    firmware discharges the mux node and the sample-and-hold to 0 V before each input (issue 39 item 4,
    docs/firmware.md): the slow taxel reads low (its node charges from 0 V for 17 us of a 39 us time constant), but
    it neither carries its scan neighbour's reading nor lends its own: the crosstalk check passes, taxel 4 inside its
    bound. (The firmware that switched straight from one input to the next failed this check: 4 shared its
    neighbour's changes.)"""
    cfg = tmp_path / "rig.json"

    watchdog_ms = []

    def opener():
        rig = open_rig("hil", host_config_path=cfg)
        watchdog_ms.append(rig.drum.settings()["WATCHDOG_MS"])
        rig.backend.sim.set_taxel_ohm(1e6, taxel=4)
        return rig

    ctx = doctor.DoctorContext("hil", opener=opener, config_path=cfg, rest_s=3.0)
    by = {r.name: r for r in doctor.run_doctor(doctor.select(["link", "crosstalk"]), ctx).results}
    r = by["crosstalk"]
    assert r.status == "pass", r.line()
    assert r.values["per_taxel_max"][4] <= r.values["bound"]
    # the HIL rig writes its own host watchdog (rigs.WATCHDOG_MS: 5 s while the host leaves the controller unfed
    # for over 1 s in places, issue 55 item 6)
    assert watchdog_ms == [WATCHDOG_MS["hil"]] == [5000]


@pytest.mark.hil
def test_a_10_sps_hx711_fails_its_check_on_the_firmware_under_simavr(tmp_path):
    """The harness's HX711 at 10 SPS (RATE pin low) on the firmware set for 80: the firmware times the rate at boot
    and latches HX711_RATE; the doctor reports the rate it measured and names the RATE pin."""
    from rigctl.operations import RigSource, doctor as run

    cfg = RigConfig(mechanics=MechanicsConfig(hx711_rate_sps=10.0))
    report = run(RigSource("hil"), config=cfg, host_config_path=tmp_path / "rig.json", rest_s=2.0, save=False,
                 checks=["link", "controller-faults", "hx711-rate"])
    by = {r.name: r for r in report.results}
    assert by["link"].status == "pass", by["link"].line()
    r = by["hx711-rate"]
    assert r.status == "fail" and "RATE pin high" in r.fix, r.line()
    assert r.values["hx711_rate_sps"] == pytest.approx(10.0, rel=0.02)
    assert by["controller-faults"].status == "fail" and "HX711_RATE" in by["controller-faults"].summary


@pytest.mark.hil
def test_a_reversed_load_cell_fails_polarity_on_the_firmware_under_simavr(tmp_path):
    cfg = tmp_path / "rig.json"
    reversed_cell = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=-420.0))
    ctx = doctor.DoctorContext("hil", opener=lambda: open_rig("hil", host_config_path=cfg, config=reversed_cell),
                               config_path=cfg, rest_s=3.0)
    by = {r.name: r for r in doctor.run_doctor(doctor.select(["link", "loadcell-polarity"]), ctx).results}
    r = by["loadcell-polarity"]
    assert r.status == "fail" and "A+/A-" in r.fix, r.line()
    # the evidence: the firmware's own fault (it trips at once and backs off: a host polling late, on a loaded machine,
    # never sees the negative force), or the negative force the host saw before any fault
    assert "LOADCELL_REVERSED" in r.summary or r.values["lowest_force_g"] < -30, r.line()


def test_serial_numbers_on_hardware_ports(monkeypatch, tmp_path):
    """The boards' USB serial numbers from pyserial's port list (replaced here: no USB boards on this machine): both
    known -> pass; a CH340 clone without one -> fail naming the port; swapped roles -> fail."""
    from rigctl.acquisition.doctor import host_checks
    from rigctl.devices.ports import PortInfo

    drum, taxel = tmp_path / "ttyACM0", tmp_path / "ttyACM1"
    drum.touch()
    taxel.touch()

    def listing(*boards):
        return lambda include_all=False: [PortInfo(str(p), 1, 2, desc, board, sn) for p, desc, board, sn in boards]

    def run():
        ctx = doctor.DoctorContext("hardware", opener=lambda: None, drum_port=str(drum), taxel_port=str(taxel))
        return doctor.run_doctor(doctor.select(["serial-numbers"]), ctx).results[0]

    monkeypatch.setattr(host_checks, "find_ports", listing((drum, "Arduino Mega 2560 R3", "mega", "A1"),
                                                           (taxel, "Arduino Uno R3", "uno", "B2")))
    r = run()
    assert r.status == "pass" and r.values == {"drum_serial_number": "A1", "taxel_serial_number": "B2"}
    monkeypatch.setattr(host_checks, "find_ports", listing((drum, "Arduino Mega 2560 R3", "mega", "A1"),
                                                           (taxel, "CH340 USB-serial", None, None)))
    r = run()
    assert r.status == "fail" and str(taxel) in r.summary and "udev-rules" in r.fix
    monkeypatch.setattr(host_checks, "find_ports", listing((drum, "Arduino Uno R3", "uno", "A1"),
                                                           (taxel, "Arduino Mega 2560 R3", "mega", "B2")))
    r = run()
    assert r.status == "fail" and "swap" in r.fix


def test_a_firmware_build_mismatch_is_refused_at_open_unless_allowed(monkeypatch, tmp_path):
    """Issue 39 item 6: every open compares the boards' builds with the installed sources: a Mega flashed from other
    sources is refused with one line naming both builds and the flash command; --allow-firmware-mismatch opens it
    with a warning; the doctor opens it anyway (its firmware-build check reports it)."""
    from click.testing import CliRunner

    from rigctl.acquisition.rig import FirmwareMismatch
    from rigctl.cli import main
    from rigctl.simulation import controller

    own = firmware.build_id()
    other = "0123456789ab" if own != "0123456789ab" else "ba9876543210"
    monkeypatch.setattr(controller, "installed_build_id", lambda: other)
    with pytest.raises(FirmwareMismatch) as exc:
        open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json")
    line = str(exc.value)
    assert "\n" not in line and other in line and own in line and "rigctl firmware --flash" in line
    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json", allow_firmware_mismatch=True) as rig:
        assert any(other in w for w in rig.warnings)
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    args = ["acquire", "quick_check", "--inprocess", "--out", str(tmp_path / "a.h5"), "--quiet"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code != 0 and "rigctl firmware --flash" in result.output and "Traceback" not in result.output
    report, by = _run_service(tmp_path, None, ["firmware-build"])
    assert by["firmware-build"].status == "fail" and other in by["firmware-build"].summary


def test_a_drum_controller_below_the_safety_floor_is_never_run_even_when_a_mismatch_is_allowed(monkeypatch, tmp_path):
    """Issue 75 item 6: ``--allow-firmware-mismatch`` runs another build (developers), never an image below the
    safety floor (:data:`rigctl.firmware.MEGA_SAFETY_FLOOR`): the installed sources' controller opened under a floor
    one minor version above it is refused with one line naming both versions, allowed or not, and the acquire CLI
    says that line; at the floor it opens. The rule itself: below, at, above, none reported, no Mega."""
    from click.testing import CliRunner

    from rigctl.acquisition.rig import FirmwareMismatch
    from rigctl.cli import main

    runs = firmware.source_versions()["mega"]
    assert firmware.MEGA_SAFETY_FLOOR <= runs  # the installed sources are at or above their own floor
    above = (runs[0], runs[1] + 1)
    assert firmware.below_safety_floor({"mega": runs, "uno": None}) is None
    assert firmware.below_safety_floor({"uno": (1, 0)}) is None
    assert "reports no firmware version" in firmware.below_safety_floor({"mega": None})
    monkeypatch.setattr(firmware, "MEGA_SAFETY_FLOOR", above)
    for allow in (False, True):
        with pytest.raises(FirmwareMismatch) as exc:
            open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json", allow_firmware_mismatch=allow)
        line = str(exc.value)
        assert "\n" not in line and f"runs firmware {runs[0]}.{runs[1]}" in line, line
        assert f"safety floor {above[0]}.{above[1]}" in line and "rigctl firmware --flash PORT --board mega" in line
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    args = ["acquire", "quick_check", "--inprocess", "--allow-firmware-mismatch", "--out", str(tmp_path / "a.h5"),
            "--quiet"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code != 0 and "safety floor" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "a.h5").exists()
    monkeypatch.setattr(firmware, "MEGA_SAFETY_FLOOR", runs)
    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json") as rig:
        assert rig.drum.read_status().firmware == runs


def test_row_correlations_tell_the_drum_direction_on_a_periodic_texture():
    """The back row repeats the front one ``lag`` samples later when the drum turns forwards; a 15 mm ridge period
    correlates again one period away, outside the two windows searched (pure: no rig)."""
    from rigctl.acquisition.doctor.measure import row_correlations

    t = np.arange(2000) / 1000.0
    ridges = lambda x: np.sign(np.sin(2 * np.pi * x / 15.0))  # noqa: E731 - 15 mm ridges
    front, back = ridges(40.0 * t), ridges(40.0 * t - 10.0)  # 40 mm/s, rows 10 mm apart: 250 samples
    fwd, bwd = row_correlations(np.c_[front, front], np.c_[back, back], 250)
    assert fwd > 0.95 and bwd < 0.5  # the square ridges 20 +- 2 mm off: 3 mm out of phase at best
    fwd, bwd = row_correlations(back, front, 250)  # the drum turning backwards: the back row leads
    assert bwd > 0.95 and fwd < 0.5
    with pytest.raises(ValueError):
        row_correlations(front[:600], back[:600], 250)


def test_a_reversed_drum_fails_the_direction_check_with_the_fix(tmp_path, monkeypatch):
    """Issue 39 item 1: the drum's coil pair swapped (``--inject reversed-drum``): the index and the speed marks pass
    at the right speed, the taxels show the back row leading; the check fails with the fix, the healthy rig passes."""
    from click.testing import CliRunner

    from rigctl.cli import main

    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    args = ["doctor", "--inprocess", "--check", "drum-direction", "--no-save"]
    bad = CliRunner().invoke(main, [*args, "--inject", "reversed-drum@0"])
    assert bad.exit_code == 1 and "FAIL  drum-direction" in bad.output and "swap one coil pair of the drum" in bad.output
    good = CliRunner().invoke(main, args)
    assert good.exit_code == 0 and "PASS  drum-direction" in good.output, good.output


def test_a_drum_controller_without_a_build_id_is_refused_at_open_in_one_line(monkeypatch, tmp_path):
    """Issue 55 item 5: a Mega reporting build 0 (BUILD_ID_0 .. _2 all 0: an image built by the Arduino IDE or
    ``make BUILD_ID=``) cannot be told from any other sources: every open refuses it with one line naming build 0, the
    firmware versions this rigctl knows and the flash command (the old code opened it silently); the acquire CLI says
    that line, no traceback; --allow-firmware-mismatch (developers) opens it with a warning."""
    from click.testing import CliRunner

    from rigctl.acquisition.rig import FirmwareMismatch
    from rigctl.cli import main
    from rigctl.simulation import controller

    monkeypatch.setattr(controller, "installed_build_id", lambda: None)
    with pytest.raises(FirmwareMismatch) as exc:
        open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json")
    line = str(exc.value)
    versions = firmware.source_versions()
    assert "\n" not in line and "the Mega runs firmware" in line and "build 0" in line, line
    assert f"mega firmware {'.'.join(map(str, versions['mega']))} build {firmware.build_id()}" in line, line
    assert "rigctl firmware --flash PORT --board mega" in line and "--allow-firmware-mismatch" in line
    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json", allow_firmware_mismatch=True) as rig:
        assert any("build 0" in w and "allowed" in w for w in rig.warnings), rig.warnings
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    args = ["acquire", "quick_check", "--inprocess", "--out", str(tmp_path / "a.h5"), "--quiet"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code != 0 and "build 0" in result.output and "Traceback" not in result.output
    assert len([ln for ln in result.output.splitlines() if "build 0" in ln]) == 1, result.output
    assert not (tmp_path / "a.h5").exists()


def test_a_reversed_cell_after_a_reset_under_load_is_named_and_its_advice_never_crushes(tmp_path):
    """Issue 55 item 4: a load cell reversed (A+/A- swapped) and the controller reset while pressing 1000 g: HOME
    backs off, the reversed cell reads that as a rise and ACTUATOR_DIRECTION latches. The old advice everywhere was
    "swap one coil pair of the actuator", which then drove HOME into the sensor (13,304 g on the bench). Now the latch
    text, the controller's fault advice and the doctor name the load cell as a cause, the doctor presses the cell
    (a mass on the simulated one) before it advises anything and, the press reading as a fall, advises the cell's
    wires and not the coils; following that advice HOMEs without pressing past 1.1 x FORCE_LIMIT (true force)."""
    from rigctl.acquisition.safety import latch_from_faults
    from rigctl.core.drum import CRUSH_NOTE, Fault, ResetCause, fault_advice
    from rigctl.core.faults import parse_fault

    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json") as rig:
        eng = rig.backend.engine
        model = eng.model
        peak = [0.0]
        step = eng.controller.control_period

        def control_period(n_ms):  # the true contact force after every control period (the truth log's column)
            step(n_ms)
            peak[0] = max(peak[0], model.contact_force_g)

        eng.controller.control_period = control_period
        rig.press(1000)
        eng.faults.apply_fault(parse_fault("reversed-cell@1"), True)  # swapped and reset in the same instant
        eng.controller.reset(ResetCause.EXTERNAL)
        # a reset under load: the controller latches it itself (RESET, firmware 1.5, issue 76); acknowledged, nothing
        # moves, and the doctor's check HOMEs from NOT_HOMED
        assert Fault.RESET in rig.drum.read_status().faults
        rig.acknowledge("the reset under load checked", by="pytest")
        ctx = doctor.DoctorContext("inprocess", rig=rig)
        r = doctor.run_doctor(doctor.select(["actuator-direction"]), ctx).results[0]
        st = rig.drum.read_status()
        # firmware 1.2 (docs/wire-protocol.md 2.11): HOME's direction check is sign-free (|raw - zero| from the tare
        # stored with the calibration), so the reversed cell is no longer taken for a reversed actuator: HOME backs
        # off, the load falls, the rig homes, and the doctor's direction check passes
        assert Fault.ACTUATOR_DIRECTION not in st.faults and st.homed, st
        assert r.status == "pass", r.line()
        # where ACTUATOR_DIRECTION does latch (a reversed motor; a cell reversed on an older record), its words
        fault = int(Fault.ACTUATOR_DIRECTION)
        for text in (latch_from_faults(fault).describe(), fault_advice(fault)):
            assert "load cell" in text and "by hand" in text and "FORCE_G" in text, text
        assert CRUSH_NOTE in fault_advice(fault)
        from types import SimpleNamespace

        from rigctl_gui.fault_dialog import latch_of  # the GUI's latched-fault dialog: the same words

        title, _detail, todo = latch_of(SimpleNamespace(latch=latch_from_faults(fault)), fault)
        assert "load cell reversed" in title and "by hand" in todo and "FORCE_G" in todo, (title, todo)
        # the GUI renders the owner's latch and derives none of its own from raw bits (issue 76, c010060)
        assert latch_of(SimpleNamespace(latch=None), fault) == ("no fault", "", "")
        # the cell's own check names it
        p = doctor.run_doctor(doctor.select(["loadcell-polarity"]), ctx).results[0]
        assert p.status == "fail", p.line()
        # the advice followed: the cell's wires swapped back, the latch acknowledged, HOME
        eng.faults.apply_fault(parse_fault("reversed-cell@1"), False)
        if rig.drum.read_status().faults:
            rig.drum.clear_fault()
        # the back-off from the press is still under way (controller.c: HOME from IDLE only with the cell unloaded, so
        # a HOME at once is refused; the old Python copy's back-off had ended by then)
        rig.drum.wait_released(timeout_s=15.0)
        rig.drum.home()
        st = rig.drum.wait_state([DrumState.IDLE], timeout_s=30.0)
        assert st.homed and not int(st.faults), st
        assert peak[0] <= 1.1 * 1500, peak[0]


def test_a_reversed_actuator_from_power_on_is_told_from_a_reversed_cell(tmp_path):
    """The power-on cases still tell the two apart: reversed-actuator@0 fails actuator-direction, and the hand press
    reading as a rise, the doctor advises the coil swap; reversed-cell@0 passes it (HOME drives the right way) and
    fails loadcell-polarity."""
    from rigctl.operations import RigSource, doctor as run

    def checks(fault, names):
        report = run(RigSource("inprocess", inject=(parse_fault(fault),)), seed=3,
                     host_config_path=tmp_path / "rig.json", rest_s=3.0, checks=names, save=False)
        return {r.name: r for r in report.results}

    by = checks("reversed-actuator@0", ["actuator-direction"])
    r = by["actuator-direction"]
    assert r.status == "fail" and "the actuator turns the wrong way" in r.summary and "swap one coil pair" in r.fix
    assert r.values["hand_press_change_g"] > 100, r.line()
    by = checks("reversed-cell@0", ["actuator-direction", "loadcell-polarity"])
    assert by["actuator-direction"].status == "pass", by["actuator-direction"].line()
    assert by["loadcell-polarity"].status == "fail" and "A+/A-" in by["loadcell-polarity"].fix


def test_a_named_check_that_could_not_run_exits_1(tmp_path):
    """`rigctl doctor --check drum-speed` with the e-stop pressed (issue 76): the check cannot run (the controller is
    in FAULT), so the command exits 1 and names it; `doctor && acquire` never reads a check not done as OK (the old
    code: every selected check skipped, exit 0). `--check e-stop` then fails outright (the input reads open)."""
    from click.testing import CliRunner

    from rigctl.cli import main

    args = ["doctor", "--inprocess", "--inject", "estop@0+600", "--no-save", "--config", str(tmp_path / "rig.json")]
    r = CliRunner().invoke(main, [*args, "--check", "drum-speed"])
    assert r.exit_code == 1, r.output
    assert "SKIP  drum-speed" in r.output and "not checked: drum-speed could not run" in r.output, r.output
    e = CliRunner().invoke(main, [*args, "--check", "e-stop"])
    assert e.exit_code == 1 and "FAIL  e-stop" in e.output, e.output


def test_the_report_says_which_checks_could_not_run():
    """not_run: every skip of a named check; of the whole list, only the rig not opening or a cancel."""
    rep = doctor.DoctorReport("2026-01-01T00:00:00+00:00", "sim", [
        doctor.CheckResult("link", "skip", f"{NOT_OPENED} (port busy)"),
        doctor.CheckResult("usb-serial", "skip", "simulated boards on ptys have no USB serial number"),
        doctor.CheckResult("e-stop", "pass", "released")])
    assert [r.name for r in rep.not_run(named=False)] == ["link"]
    assert [r.name for r in rep.not_run(named=True)] == ["link", "usb-serial"]


def test_skips_for_one_reason_share_one_line():
    """Issue 79 item 7: a rig that did not open printed its reason on 16 SKIP lines; consecutive skips for one reason
    now share a line naming every check, other lines print as they come."""
    from rigctl.cli.doctor import _SkipFolder

    out: list[str] = []
    folder = _SkipFolder(out.append)
    why = "the rig did not open (port busy)"
    results = [doctor.CheckResult("link", "fail", "no answer", fix="free the port"),
               *(doctor.CheckResult(n, "skip", why) for n in ("drum-speed", "force-step", "e-stop")),
               doctor.CheckResult("usb-serial", "skip", "simulated boards have no USB serial number"),
               doctor.CheckResult("hx711-rate", "pass", "80 SPS")]
    for r in results:
        folder.add(r)
    folder.flush()
    assert out == ["FAIL  link: no answer -> fix: free the port",
                   f"SKIP  drum-speed, force-step, e-stop (3 checks): {why}",
                   "SKIP  usb-serial: simulated boards have no USB serial number",
                   "PASS  hx711-rate: 80 SPS"]
