"""Rig calibration: the load cell (known mass) and the per-taxel normalisation; the rig config file that keeps both.

The rig config is a JSON file (default ``$XDG_CONFIG_HOME/rigctl/rig.json``, i.e. ``~/.config/rigctl/rig.json``;
overridden by the ``RIGCTL_CONFIG`` environment variable or an explicit path). :class:`rigctl.acquisition.rig.Rig`
loads it and every session file gets a copy (root attribute ``rig_config``, and the taxel normalisation in the
session's ``/calibration`` block). Layout::

    {"loadcell": {"counts_per_g": 420.1, "scale_x100": 42010, "mass_g": 500.0, "zero_raw": ..., "loaded_raw": ...,
                  "check_force_g": 499.6, "calibrated_utc": "..."},
     "taxel_normalisation": {"taxel_min": [18 numbers], "taxel_max": [18 numbers], "n_trials": 50,
                             "source": "calib.h5", "calibrated_utc": "..."}}

Load cell: with the actuator released, TARE, read the raw HX711 counts without and with a known mass; the scale is
``(loaded - zero) / mass`` counts per gram, written to the controller's signed 32-bit scale (LOADCELL_SCALE_X100_HI/
_LO: 1 to 100,000 counts/g, so 1-50 kg cells of 1-2 mV/V at gain 128 fit) and saved to EEPROM (SAVE_CALIBRATION). A
cell that reads negative under the mass is reported as reversed (mounted or wired the other way round), and
calibrated as negative only when the caller asks for it.

Taxel normalisation (paper, Materials and Methods: "the taxel readings were normalized between 0 and 1 on a
per-taxel basis", and for the real-time experiment "an initial dataset of 10 trials per texture was collected to get
the minimum and maximum values for each taxel"): the minimum and maximum ADC count of each taxel over a calibration
run's trials.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from rigctl.acquisition.motion import wait_released
from rigctl.acquisition.rigconfig import (  # noqa: F401 (re-exported: the config file API callers know from here)
    CalibrationError,
    _utc_now,
    config_path,
    default_config_path,
    load_rig_config,
    save_rig_config,
    update_rig_config,
)
from rigctl.core.drum import SCALE_CHECK_PCT, Fault, SetpointRangeError
from rigctl.core.interfaces import DrumController, DrumMonitor, MassPlacer
from rigctl.core.normalisation import TaxelRange

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------------------------------------
# Load cell
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class LoadCellCalibration:
    """Result of :func:`calibrate_loadcell`.

    Attributes
    ----------
    counts_per_g : float, HX711 counts per gram
    scale_x100 : int, the signed scale written to LOADCELL_SCALE_X100_HI/_LO (counts per g x 100)
    mass_g : float, the known mass used
    zero_raw, loaded_raw : float, mean raw HX711 counts without / with the mass
    check_force_g : float, the controller's FORCE_G reading with the mass after the new scale (should be ~mass_g)
    noise_counts : float, sd of the raw readings without the mass
    calibrated_utc : str
    contact_stiffness_g_per_mm : float, the contact's stiffness the probe measured with the verified scale and stored
        with the calibration (CALIBRATION_STIFFNESS_G_PER_MM, spec 2.12); 0: not measured (the stored one kept)
    """

    counts_per_g: float
    scale_x100: int
    mass_g: float
    zero_raw: float
    loaded_raw: float
    check_force_g: float
    noise_counts: float
    calibrated_utc: str
    contact_stiffness_g_per_mm: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


#: the press whose probe measures the contact's stiffness at calibration, g (the probe itself presses 50 g + 100 g;
#: a setpoint above that lets the probe finish: docs/wire-protocol.md 2.10-2.12)
CONTACT_PRESS_G = 300.0


def _clear_the_masss_own_trip(drum: DrumController, faults_before: Fault) -> None:
    """The reference mass read on the old scale may have tripped FORCE_LIMIT (a cell of another range: 500 g read as
    2,500 g) with the actuator at home; that latch, the calibration's own doing and nothing else, is cleared (logged)
    before the contact is pressed. Any other fault stays (the press is then refused: DrumError)."""
    st = drum.read_status()
    if st.faults == Fault.FORCE_LIMIT and not faults_before and abs(st.force_g) < 2 * drum.settle_band().force_tolerance_g:
        log.warning("the %s read on the old scale latched FORCE_LIMIT with the actuator home: cleared, the new scale "
                    "reads %.0f g now", "calibration mass", st.force_g)
        drum.clear_fault()


def _sleep(drum, s: float) -> None:
    """Wait ``s`` on the controller's clock (simulated time in-process), as the drum client's own waits do."""
    clock = getattr(drum, "clock", None)
    (clock.sleep if clock is not None else time.sleep)(s)


def _mean_raw(drum: DrumMonitor, n: int, interval_s: float) -> tuple[float, float, float]:
    raws, forces = [], []
    for _ in range(n):
        st = drum.read_status()
        raws.append(float(st.loadcell_raw))
        forces.append(float(st.force_g))
        _sleep(drum, interval_s)
    return float(np.mean(raws)), float(np.std(raws)), float(np.mean(forces))


def calibrate_loadcell(
    drum: DrumController,
    mass_g: float,
    *,
    place_mass: Callable[[float], Any],
    remove_mass: Callable[[float], Any] | None = None,
    n_readings: int = 25,
    interval_s: float = 0.02,
    settle_s: float = 0.5,
    save: bool = True,
    config_file: str | os.PathLike | Literal[False] | None = None,
    allow_negative: bool = False,
    contact_press_g: float | None = CONTACT_PRESS_G,
) -> LoadCellCalibration:
    """Calibrate the load cell with a known mass and write the scale to the drum controller.

    Steps: STOP (release the actuator; TARE is only allowed released), wait IDLE, TARE; mean raw HX711 counts
    without the mass; ``place_mass(mass_g)`` (the operator puts the mass on the load cell; in simulation the
    simulated rig adds it); mean raw counts with it; ``counts_per_g = (loaded - zero) / mass_g``;
    ``set_loadcell_scale(counts_per_g)`` (LOADCELL_SCALE_X100) and SAVE_CALIBRATION (EEPROM) when ``save``;
    read FORCE_G with the mass as a check; ``remove_mass(mass_g)``; then the contact's stiffness
    (:func:`store_contact_stiffness`): a press of ``contact_press_g`` on the mounted plate, its probe's stiffness
    measured with the verified scale, stored with the calibration (spec 2.12), SAVE_CALIBRATION.

    Parameters
    ----------
    drum : an open :class:`rigctl.core.interfaces.DrumController`
    mass_g : known mass, g (> 0)
    place_mass, remove_mass : callables that return once the mass is on / off the load cell
    n_readings, interval_s : raw readings averaged for each level, and their spacing (s)
    settle_s : wait after placing/removing the mass before reading, s (0.5: the HX711 settles 4 conversion periods
        after a step, 400 ms at 10 SPS; Avia HX711 datasheet)
    save : SAVE_CALIBRATION to the controller's EEPROM
    config_file : where to store the result in the rig config (``loadcell`` block); None = default path,
        False = do not store
    allow_negative : calibrate a cell that reads negative under the mass with a negative scale (else that is an
        error naming the reversed cell)
    contact_press_g : the press (g) whose probe measures the contact's stiffness with the verified scale, stored for
        the scale check of every later probe (spec 2.12; the controller must be homed, the plate mounted); None: the
        scale only, the stiffness stored before is kept

    Returns
    -------
    LoadCellCalibration

    Raises
    ------
    ValueError (mass <= 0), CalibrationError (no response to the mass, a reversed cell without ``allow_negative``,
    or a scale outside 1-100,000 counts/g), :class:`rigctl.devices.errors.DrumError` from the controller.
    """
    if not mass_g > 0:
        raise ValueError(f"mass_g must be > 0, got {mass_g}")
    wait_released(drum, timeout_s=30.0)
    faults_before = drum.read_status().faults
    _sleep(drum, settle_s)  # a load just taken off (a mass, a retract): the HX711 settles first, or the tare keeps it
    drum.tare()
    _sleep(drum, settle_s)
    zero, noise, _ = _mean_raw(drum, n_readings, interval_s)
    place_mass(mass_g)
    try:
        _sleep(drum, settle_s)  # the HX711 settles 4 conversion periods after the mass lands (50 / 400 ms)
        loaded, _, _ = _mean_raw(drum, n_readings, interval_s)
        delta = loaded - zero
        if abs(delta) <= max(10 * noise / np.sqrt(n_readings), 1.0):
            raise CalibrationError(
                f"the load cell did not respond to the {mass_g:g} g mass (raw {zero:.0f} -> {loaded:.0f} counts): "
                "is the mass on the load cell?")
        if delta < 0 and not allow_negative:
            raise CalibrationError(
                f"the load cell reads negative under the {mass_g:g} g mass (raw {zero:.0f} -> {loaded:.0f} counts): "
                "it is mounted or wired the other way round (swap its A+ and A- wires at the HX711, or turn it), "
                "or calibrate it as negative on purpose (allow_negative)")
        counts_per_g = delta / mass_g
        scale_x100 = int(round(counts_per_g * 100))
        try:
            drum.set_loadcell_scale(counts_per_g)
        except SetpointRangeError as exc:
            raise CalibrationError(f"{counts_per_g:.3f} counts/g is outside what the controller's load-cell scale "
                                   f"holds ({exc.low:g}-{exc.high:g} counts/g, either sign)") from None
        if save and contact_press_g is None:
            drum.save_calibration()
        _sleep(drum, settle_s)
        _, _, check = _mean_raw(drum, max(5, n_readings // 2), interval_s)
    finally:
        if remove_mass is not None:
            remove_mass(mass_g)
    stiffness = 0.0
    if contact_press_g is not None:
        _sleep(drum, settle_s)  # the mass just taken off: the HX711 settles before the probe reads the contact
        _clear_the_masss_own_trip(drum, faults_before)
        stiffness = store_contact_stiffness(drum, contact_press_g, save=save)
    result = LoadCellCalibration(
        counts_per_g=float(counts_per_g), scale_x100=scale_x100, mass_g=float(mass_g), zero_raw=zero,
        loaded_raw=loaded, check_force_g=check, noise_counts=noise, calibrated_utc=_utc_now(),
        contact_stiffness_g_per_mm=float(stiffness),
    )
    if config_file is not False:
        update_rig_config(config_file, loadcell=result.to_dict())
    return result


def store_contact_stiffness(drum: DrumController, press_g: float = CONTACT_PRESS_G, *, save: bool = True,
                            timeout_s: float = 60.0) -> float:
    """Measure the contact's stiffness with the scale in force and store it with the calibration (spec 2.12): only
    right after the scale was verified with a reference mass (:func:`calibrate_loadcell`), since every later probe is
    checked against it.

    The stored stiffness is cleared (no check against a contact measured with a scale that may have been wrong), a
    press of ``press_g`` (g) on the mounted plate probes it (CONTACT_STIFFNESS_G_PER_MM), the actuator is released,
    and the stiffness is written to CALIBRATION_STIFFNESS_G_PER_MM and, when ``save``, SAVE_CALIBRATION. One that
    differs from the one stored before by more than the check's tolerance is logged (the old scale or the contact
    was off). Returns g/mm.

    Raises CalibrationError (no stiffness measured: nothing stored), DrumError (not homed, a fault: the stored one
    restored)."""
    stored = drum.calibration_stiffness()
    drum.set_calibration_stiffness(0)
    try:
        drum.set_force(press_g)
        drum.press()
        drum.wait_force_settled(timeout_s=timeout_s)
        measured = float(drum.read_status().contact_stiffness_g_per_mm)
    except BaseException:
        drum.set_calibration_stiffness(stored)  # not measured: the check as it was (a latch stays for the operator)
        raise
    wait_released(drum, timeout_s=timeout_s)
    if not measured > 0:
        drum.set_calibration_stiffness(stored)
        raise CalibrationError("the press measured no contact stiffness: not stored")
    tol = 1.0 + SCALE_CHECK_PCT / 100.0
    if stored and not 1.0 / tol <= measured / stored <= tol:
        log.warning("the contact's stiffness stored with the calibration changes from %d to %.0f g/mm: the scale "
                    "calibrated before, or the contact (sensor, mount, plate material), was not the same", stored,
                    measured)
    drum.set_calibration_stiffness(measured)
    if save:
        drum.save_calibration()
    return measured


def simulated_mass(rig) -> tuple[Callable[[float], Any], Callable[[float], Any]]:
    """``(place_mass, remove_mass)`` callables for :func:`calibrate_loadcell` on a simulated rig.

    They rest a calibration mass on the simulated load cell through the rig's backend, when it is a
    :class:`rigctl.core.interfaces.MassPlacer` (the simulated, HIL and in-process backends). Raises
    CalibrationError on hardware (the operator places the mass: use a prompt).
    """
    backend = rig.backend
    if not isinstance(backend, MassPlacer):
        raise CalibrationError(f"this rig ({rig.mode}) has no simulated calibration mass: place the mass by hand "
                               "(prompt)")
    return (lambda g: backend.place_mass(g)), (lambda g: backend.place_mass(0.0))


# ----------------------------------------------------------------------------------------------------------------
# Taxel normalisation
# ----------------------------------------------------------------------------------------------------------------
#: the calibration's per-taxel normalisation is the one type of it, :class:`rigctl.core.normalisation.TaxelRange`
#: (``TaxelNormalisation(taxel_min, taxel_max, n_trials, source, calibrated_utc)``; the encoders take it as it is)
TaxelNormalisation = TaxelRange


def stored_taxel_range(host_config: dict, n_channels: int) -> TaxelRange | None:
    """The rig config's taxel normalisation (``taxel_normalisation`` block) as a :class:`TaxelRange`, or None when
    there is none or it was made for a sensor with another channel count than ``n_channels``."""
    block = host_config.get("taxel_normalisation")
    if not block or np.asarray(block.get("taxel_min", ())).size != int(n_channels):
        return None
    return TaxelRange.from_dict(block)


def taxel_normalisation(captures: Iterable[np.ndarray], *, source: str = "captures") -> TaxelNormalisation:
    """Per-taxel min/max over calibration captures.

    Parameters
    ----------
    captures : iterable of ``(n_i, n_channels)`` ADC-count arrays (one per trial; any channel count, the same in
        every capture: the first one decides)

    Raises
    ------
    ValueError if there are no samples or an array is not ``(n, n_channels)``.
    """
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    n = 0
    for cap in captures:
        a = np.asarray(cap)
        if lo is None and a.ndim == 2:
            lo, hi = np.full(a.shape[1], np.inf), np.full(a.shape[1], -np.inf)
        if lo is None or hi is None or a.ndim != 2 or a.shape[1] != len(lo):
            raise ValueError(f"a capture must be (n, {len(lo) if lo is not None else 'channels'}), got {a.shape}")
        if not a.size:
            continue
        lo = np.minimum(lo, a.min(axis=0))
        hi = np.maximum(hi, a.max(axis=0))
        n += 1
    if n == 0 or lo is None or hi is None:
        raise ValueError("no samples to normalise over")
    return TaxelRange(lo, hi, n, source, _utc_now())


def taxel_normalisation_from_session(path: str | os.PathLike, *, store: bool = False,
                                     config_file: str | os.PathLike | None = None) -> TaxelNormalisation:
    """Per-taxel min/max over every complete trial of a calibration session file.

    With ``store``, write it to the rig config (``taxel_normalisation`` block) so later sessions carry it.
    Raises ValueError if the session has no complete trial.
    """
    from rigctl.storage.session import open_session

    with open_session(path) as s:
        norm = taxel_normalisation((t.taxels for t in s.iter_trials()), source=str(path))
    if store:
        update_rig_config(config_file, taxel_normalisation=norm.to_dict())
    return norm


#: a taxel calibration run is refused when its median taxel spans less than this fraction of the ADC range (the drum
#: idle under a pressed or released sensor spans 15-17 counts of 1023: noise, which the encoder would turn into spikes)
MIN_TAXEL_SPAN_FRACTION = 0.05


def check_taxel_span(norm: TaxelNormalisation, adc_max: int, *,
                     min_fraction: float = MIN_TAXEL_SPAN_FRACTION) -> list[int]:
    """Refuse an implausible calibration run: one that did not press the sensor over textures.

    ``norm``'s per-taxel span (max - min, ADC counts) is compared with ``min_fraction * adc_max`` (51 counts for a
    10-bit sensor at the default 5 %). Returns the taxels below it (a few dead or untouched taxels are reported,
    not refused).

    Raises
    ------
    CalibrationError when the median taxel is below it (the message gives the spans and what was expected).
    """
    span = np.asarray(norm.taxel_max, float) - np.asarray(norm.taxel_min, float)
    need = min_fraction * float(adc_max)
    low = [int(i) for i in np.flatnonzero(span < need)]
    if float(np.median(span)) < need:
        raise CalibrationError(
            f"the calibration run spans only {span.min():.0f}-{span.max():.0f} ADC counts per taxel (median "
            f"{np.median(span):.0f}); at least {need:.0f} ({100 * min_fraction:g} % of 0-{adc_max}) is expected when "
            "the drum turns the textures under the pressed sensor: was the drum idle? Not stored")
    return low


def store_taxel_normalisation(norm: TaxelNormalisation, config_file: str | os.PathLike | None = None) -> dict:
    """Write ``norm`` as the rig config's ``taxel_normalisation``; the one it replaces (if any) is kept as
    ``taxel_normalisation_previous`` for :func:`undo_taxel_normalisation`. Returns the new config."""
    cfg = load_rig_config(config_file)
    if cfg.get("taxel_normalisation"):
        cfg["taxel_normalisation_previous"] = cfg["taxel_normalisation"]
    cfg["taxel_normalisation"] = norm.to_dict()
    save_rig_config(cfg, config_file)
    return cfg


def undo_taxel_normalisation(config_file: str | os.PathLike | None = None) -> dict:
    """Swap the rig config's taxel normalisation with the previous one (a second undo redoes); with no previous
    one the current is removed and kept as previous (the full ADC range is used). Returns the new config.

    Raises CalibrationError when there is neither a current nor a previous normalisation."""
    cfg = load_rig_config(config_file)
    cur, prev = cfg.pop("taxel_normalisation", None), cfg.pop("taxel_normalisation_previous", None)
    if cur is None and prev is None:
        raise CalibrationError("no taxel normalisation to undo")
    if prev is not None:
        cfg["taxel_normalisation"] = prev
    if cur is not None:
        cfg["taxel_normalisation_previous"] = cur
    save_rig_config(cfg, config_file)
    return cfg


def reset_taxel_normalisation(config_file: str | os.PathLike | None = None) -> dict:
    """Remove the rig config's taxel normalisation (the live encoder then uses the full ADC range), keeping it as
    ``taxel_normalisation_previous`` so :func:`undo_taxel_normalisation` brings it back. Returns the new config."""
    cfg = load_rig_config(config_file)
    cur = cfg.pop("taxel_normalisation", None)
    if cur is not None:
        cfg["taxel_normalisation_previous"] = cur
    save_rig_config(cfg, config_file)
    return cfg


def session_calibration_block(host_config: dict, n_channels: int | None = None) -> dict | None:
    """The ``/calibration`` block a session gets from a rig config: the taxel normalisation (arrays) plus the
    load-cell scale as attributes; None when the config holds neither.

    ``n_channels``: the session's taxel count (``rig.layout.n_channels``); a taxel normalisation made for another
    sensor (another channel count) is left out, with a warning, rather than failing the session.
    """
    out: dict[str, Any] = {}
    tn = host_config.get("taxel_normalisation")
    if tn and n_channels is not None and np.asarray(tn.get("taxel_min", ())).size != n_channels:
        log.warning("the rig config's taxel normalisation has %d taxels but the sensor has %d: not copied into the "
                    "session (calibrate the taxels of this sensor)", np.asarray(tn.get("taxel_min", ())).size,
                    n_channels)
        tn = None
    if tn:
        out["taxel_min"] = np.asarray(tn["taxel_min"], float)
        out["taxel_max"] = np.asarray(tn["taxel_max"], float)
        out["taxel_n_trials"] = int(tn.get("n_trials", 0))
        out["taxel_source"] = str(tn.get("source", ""))
        out["taxel_calibrated_utc"] = str(tn.get("calibrated_utc", ""))
    lc = host_config.get("loadcell")
    if lc:
        out["loadcell_counts_per_g"] = float(lc.get("counts_per_g", float("nan")))
        out["loadcell_mass_g"] = float(lc.get("mass_g", float("nan")))
        out["loadcell_calibrated_utc"] = str(lc.get("calibrated_utc", ""))
    return out or None
