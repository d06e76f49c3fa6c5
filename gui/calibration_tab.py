"""Calibration tab: load-cell calibration with a known mass and per-taxel normalisation, both through
:mod:`rigctl.acquisition.calibration` (run in a worker thread). Results go into the rig config file, which the
acquisition copies into every session file; the taxel normalisation also feeds the live encoder at once.

The normalisation has one min/max per taxel of the connected sensor (``layout.n_channels`` of the stream's
:class:`rigctl.core.sensor.SensorLayout`, default the paper's 18); a stored normalisation for another channel count
is shown as not matching and not used."""

from __future__ import annotations

import threading

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from rigctl.core.errors import describe_error
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl_gui.colours import ERROR, on_window
from rigctl_gui.messages import escaped
from rigctl_gui.widgets import keep_room, side_panel
from rigctl_gui.workers import Job


def axis_layers(layout: SensorLayout) -> str:
    """The taxel spans of the layers for an axis label: ``"0-8 top, 9-17 bottom"`` for the paper's sensor,
    ``"0-8"`` for a single unnamed layer."""
    parts = []
    for i, la in enumerate(layout.layers):
        ch = layout.layer_channels(i)
        span = f"{ch.start}-{ch.stop - 1}" if len(ch) > 1 else f"{ch.start}"
        parts.append(span if la.name in ("", "taxels") else f"{span} {la.name}")
    return ", ".join(parts)



def _stiffness_words(loadcell: dict) -> str:
    """What the calibration stored of the contact (docs/wire-protocol.md 2.12): every probe's stiffness is compared
    with it (LOADCELL_SCALE outside 0.87-1.15), or none is stored and the reading's scale goes unchecked."""
    k = float(loadcell.get("contact_stiffness_g_per_mm") or 0.0)
    if k > 0:
        return f"contact {k:,.0f} g/mm (each press's probe is checked against it)"
    return "no contact stiffness stored: the scale is not checked at each press (calibrate with the plate mounted)"

class CalibrationTab(QtWidgets.QWidget):
    """The calibration tab; ``main`` is the :class:`rigctl_gui.app.MainWindow`."""

    def __init__(self, main, parent=None):
        super().__init__(parent)
        self.main = main
        self.handle = None
        self.sensor_layout: SensorLayout = PAPER_SENSOR
        self.job: Job | None = None
        self._mass_event = threading.Event()

        # --- load cell ---
        self.mass = QtWidgets.QDoubleSpinBox(suffix=" g", decimals=1, minimum=1.0, maximum=2000.0, value=500.0)
        self.mass.setObjectName("calibration_mass")
        self.loadcell_btn = QtWidgets.QPushButton("Calibrate load cell")
        self.loadcell_btn.clicked.connect(self.calibrate_loadcell)
        self.mass_prompt = QtWidgets.QFrame()
        self.mass_prompt.setStyleSheet("QFrame { background: #ffd; border: 1px solid #aa0; } QLabel { color: #000; }")
        self.mass_label = QtWidgets.QLabel()
        mass_ok = QtWidgets.QPushButton("Mass is on the load cell")
        mass_ok.clicked.connect(self._mass_placed)
        ml = QtWidgets.QHBoxLayout(self.mass_prompt)
        ml.addWidget(self.mass_label, 1)
        ml.addWidget(mass_ok)
        keep_room(self.mass_prompt)  # its room is kept: nothing below moves when it asks for the mass
        self.mass_prompt.hide()
        self.loadcell_info = QtWidgets.QLabel("-")
        self.loadcell_info.setWordWrap(True)
        lf = QtWidgets.QFormLayout()
        lf.addRow("Known mass", self.mass)
        lf.addRow("", self.loadcell_btn)
        lf.addRow(self.mass_prompt)
        lf.addRow("Stored", self.loadcell_info)
        lc = QtWidgets.QGroupBox("Load cell: tare, place a known mass, compute and write the scale")
        lc.setLayout(lf)

        # --- taxel normalisation ---
        self.norm_seconds = QtWidgets.QDoubleSpinBox(suffix=" s", decimals=0, minimum=1, maximum=600, value=10)
        self.norm_btn = QtWidgets.QPushButton("Record calibration run")
        self.norm_btn.setToolTip("Capture the live stream for this long (run the drum over the textures meanwhile) "
                                 "and take each taxel's min/max")
        self.norm_btn.clicked.connect(self.record_normalisation)
        self.from_session_btn = QtWidgets.QPushButton("From a session file...")
        self.from_session_btn.clicked.connect(self.normalisation_from_session)
        self.undo_btn = QtWidgets.QPushButton("Undo")
        self.undo_btn.setToolTip("Go back to the previous taxel normalisation (again: redo)")
        self.undo_btn.clicked.connect(self.undo_normalisation)
        self.reset_btn = QtWidgets.QPushButton("Reset")
        self.reset_btn.setToolTip("No taxel normalisation: the live encoder uses the full ADC range (Undo brings "
                                  "the current one back)")
        self.reset_btn.clicked.connect(self.reset_normalisation)
        self.norm_info = QtWidgets.QLabel("-")
        self.norm_info.setWordWrap(True)
        self.norm_plot = pg.PlotWidget()
        # the title in a wrapping label: as the plot's own title it set the plot's smallest width and was cut (with
        # the last bars) where the tab is narrow (1.5x on 1024x700)
        self.norm_title = QtWidgets.QLabel("Per-taxel range (ADC counts)")
        self.norm_title.setWordWrap(True)
        self.norm_title.setAlignment(QtCore.Qt.AlignmentFlag.AlignHCenter)
        self.norm_plot.setMinimumHeight(120)
        self.norm_bars = pg.BarGraphItem(x=np.arange(1), y0=np.zeros(1), height=np.zeros(1), width=0.7,
                                         brush="#1f77b4")
        self.norm_plot.addItem(self.norm_bars)
        self.set_layout(PAPER_SENSOR)
        nf = QtWidgets.QGridLayout()
        nf.addWidget(QtWidgets.QLabel("Calibration run"), 0, 0)
        nf.addWidget(self.norm_seconds, 0, 1)
        nf.addWidget(self.norm_btn, 0, 2)
        nf.addWidget(self.from_session_btn, 1, 1, 1, 2)
        nf.addWidget(self.undo_btn, 2, 1)
        nf.addWidget(self.reset_btn, 2, 2)
        nf.addWidget(QtWidgets.QLabel("Stored"), 3, 0, QtCore.Qt.AlignTop)
        nf.addWidget(self.norm_info, 3, 1, 1, 2)
        tn = QtWidgets.QGroupBox("Taxel normalisation")
        tn.setToolTip("Per-taxel min/max of a calibration run (paper, real-time experiment)")
        tn.setLayout(nf)
        lc.setTitle("Load cell")
        lc.setToolTip("Tare, place a known mass, compute and write the scale")

        self.progress = QtWidgets.QProgressBar()
        self.status = QtWidgets.QLabel("")
        self.status.setObjectName("calibration_status")
        self.status.setWordWrap(True)
        self.config_label = QtWidgets.QLabel("")
        self.config_label.setWordWrap(True)

        # left: the controls in a panel of fixed width (it scrolls when the window is short); right: the plot
        left = QtWidgets.QVBoxLayout()
        left.addWidget(self.config_label)
        left.addWidget(lc)
        left.addWidget(tn)
        left.addWidget(self.progress)
        left.addWidget(self.status)
        left.addStretch(1)
        lay = QtWidgets.QHBoxLayout(self)
        lay.addWidget(side_panel(left, 420))
        right = QtWidgets.QVBoxLayout()
        right.addWidget(self.norm_title)
        right.addWidget(self.norm_plot, 1)
        lay.addLayout(right, 1)
        self._enable(False)

    # ------------------------------------------------------------------------------------------------------
    def set_layout(self, layout: SensorLayout) -> None:
        """Show the per-taxel range of ``layout.n_channels`` taxels on 0-``layout.adc_max`` counts."""
        self.sensor_layout = layout
        n = layout.n_channels
        self.norm_plot.setLabel("bottom", f"taxel ({axis_layers(layout)})")
        self.norm_plot.setYRange(0, layout.adc_max)
        self.norm_bars.setOpts(x=np.arange(n), y0=np.zeros(n), height=np.zeros(n))

    def attach(self, handle, layout: SensorLayout | None = None) -> None:
        """Bind to an open rig; ``layout`` defaults to the taxel stream's (the paper's sensor without one)."""
        self.handle = handle
        self.set_layout(layout or getattr(handle.taxels, "layout", None) or PAPER_SENSOR)
        self._enable(True)
        self.show_config()

    def detach(self) -> None:
        self.handle = None
        self._enable(False)

    def _enable(self, on: bool) -> None:
        busy = self.job is not None and not self.job.done
        for b in (self.loadcell_btn, self.norm_btn):
            b.setEnabled(on and not busy)
        self._sync_undo()

    def _run_owns_rig(self) -> bool:
        protocol = getattr(self.main, "protocol", None)
        return bool(getattr(protocol, "running", False))

    def _sync_undo(self) -> None:
        """Undo / Reset: enabled when there is something to go back to, no calibration is running and no protocol
        run owns the rig (a session's calibration must not change under it)."""
        busy = self.job is not None and not self.job.done
        locked = self._run_owns_rig()
        cur, prev = getattr(self, "_stored", (False, False))
        self.undo_btn.setEnabled(not busy and not locked and (cur or prev))
        self.reset_btn.setEnabled(not busy and not locked and cur)
        for b in (self.undo_btn, self.reset_btn):
            if b.property("normal_tip") is None:
                b.setProperty("normal_tip", b.toolTip())
            tip = "Disabled while a protocol run owns the rig" if locked else b.property("normal_tip")
            if b.toolTip() != tip:  # a tooltip set, even to the same text, is an event through the app's filters
                b.setToolTip(tip)

    def _config(self) -> dict:
        from rigctl.acquisition.calibration import load_rig_config

        try:
            return load_rig_config(self.main.rig_config_path())
        except Exception as exc:  # noqa: BLE001 - a corrupt config is shown, not fatal
            self.status.setText(f"rig config: {exc}")
            return {}

    def taxel_range(self, control=None, layout: SensorLayout | None = None):
        """The stored per-taxel normalisation as a :class:`rigctl.core.normalisation.TaxelRange`, or None (none
        stored, or stored for another channel count than ``layout``'s, default this tab's layout)."""
        from rigctl.acquisition.calibration import stored_taxel_range

        layout = layout or self.sensor_layout
        config = control.host_config if control is not None and control.taxel_normalisation() else self._config()
        return stored_taxel_range(config, layout.n_channels)

    def show_config(self) -> None:
        from rigctl.acquisition.calibration import config_path

        cfg = self._config()
        self.config_label.setText(f"Rig config file: <code>{config_path(self.main.rig_config_path())}</code> "
                                  "(copied into every session file)")
        lc = cfg.get("loadcell")
        self.loadcell_info.setText(
            f"{lc['counts_per_g']:.2f} counts/g from a {lc['mass_g']:g} g mass (check reading "
            f"{lc.get('check_force_g', float('nan')):.1f} g), {lc.get('calibrated_utc', '')}; " + _stiffness_words(lc)
            if lc else "not calibrated (the controller's EEPROM scale is used)"
        )
        tn = cfg.get("taxel_normalisation")
        n = self.sensor_layout.n_channels
        if tn and len(tn["taxel_min"]) != n:
            self.norm_bars.setOpts(y0=np.zeros(n), height=np.zeros(n))
            self.norm_info.setText(f"stored for {len(tn['taxel_min'])} taxels, but this sensor has {n}: not used; "
                                   f"the live encoder uses the full ADC range 0-{self.sensor_layout.adc_max}")
        elif tn:
            lo, hi = np.asarray(tn["taxel_min"], float), np.asarray(tn["taxel_max"], float)
            self.norm_bars.setOpts(y0=lo, height=hi - lo)
            self.norm_info.setText(f"{tn.get('n_trials', 0)} capture(s) from {tn.get('source', '?')}, "
                                   f"{tn.get('calibrated_utc', '')}; span {np.min(hi - lo):.0f}-{np.max(hi - lo):.0f}"
                                   " counts")
        else:
            self.norm_bars.setOpts(y0=np.zeros(n), height=np.zeros(n))
            self.norm_info.setText(f"none: the live encoder uses the full ADC range 0-{self.sensor_layout.adc_max}")
        prev = cfg.get("taxel_normalisation_previous")
        if prev:
            self.norm_info.setText(self.norm_info.text() + f"<br>previous (Undo): {prev.get('source', '?')}, "
                                   f"{prev.get('calibrated_utc', '')}")
        self._stored = (bool(tn), bool(prev))
        self._enable(self.handle is not None)

    # ------------------------------------------------------------------------------------------------------
    def calibrate_loadcell(self) -> None:
        from rigctl.operations import calibrate_loadcell

        h = self.handle
        if h is None or (self.job is not None and not self.job.done):
            return
        mass = float(self.mass.value())
        # a simulated rig rests the mass itself; on hardware the operator is asked
        place, remove = (None, None) if h.is_simulated else (self._prompt_place, self._prompt_remove)
        cfg_path = self.main.rig_config_path()

        def work(job):
            job.progress(0.1, "taring and reading the empty load cell...")
            return calibrate_loadcell(h.control, mass, place_mass=place, remove_mass=remove, config_file=cfg_path)

        self._start(Job(work, name="loadcell"), "load-cell calibration")

    def _prompt_place(self, mass_g):
        self._mass_event.clear()
        self.job.events.put(f"Place the {mass_g:g} g mass on the load cell, then confirm.")
        self._mass_event.wait()

    def _prompt_remove(self, mass_g):
        self.job.events.put(f"Remove the {mass_g:g} g mass.")

    def _mass_placed(self) -> None:
        self.mass_prompt.hide()
        self._mass_event.set()

    def record_normalisation(self) -> None:
        from rigctl.operations import record_taxel_normalisation

        h = self.handle
        if h is None or (self.job is not None and not self.job.done):
            return
        seconds = float(self.norm_seconds.value())
        cfg_path = self.main.rig_config_path()

        def work(job):
            return record_taxel_normalisation(
                h.control, seconds, config_file=cfg_path, cancel=job.cancel,
                progress=lambda f: job.progress(f, "capturing the calibration run..."))

        self._start(Job(work, name="normalisation"), "taxel normalisation")

    def normalisation_from_session(self):
        from rigctl_gui.dialogs import choose_path  # non-modal: STOP stays usable

        start = str(self.main.settings.value("dirs/output", ""))
        return choose_path(self, "open", "Calibration session", start, "Sessions (*.h5)",
                           self.normalisation_from_file)

    def normalisation_from_file(self, path: str) -> None:
        from rigctl.acquisition import calibration as cal
        from rigctl.operations import store_taxel_normalisation

        cfg_path = self.main.rig_config_path()
        h = self.handle
        layout = self.sensor_layout

        def work(job):
            return store_taxel_normalisation(cal.taxel_normalisation_from_session(path), layout,
                                             config_file=cfg_path, control=getattr(h, "control", None))

        self._start(Job(work, name="normalisation"), "taxel normalisation")

    def undo_normalisation(self) -> None:
        """Back to the previous taxel normalisation (a second Undo redoes); the live encoder follows at once."""
        from rigctl.acquisition import calibration as cal

        self._change_config(cal.undo_taxel_normalisation, "taxel normalisation: back to the previous one")

    def reset_normalisation(self) -> None:
        """No taxel normalisation (full ADC range); Undo brings it back; the live encoder follows at once."""
        from rigctl.acquisition import calibration as cal

        self._change_config(cal.reset_taxel_normalisation,
                            f"taxel normalisation reset: the live encoder uses the full ADC range "
                            f"0-{self.sensor_layout.adc_max}")

    def _change_config(self, fn, done: str) -> None:
        if (self.job is not None and not self.job.done) or self._run_owns_rig():
            return
        cfg_path = self.main.rig_config_path()
        try:
            cfg = fn(cfg_path)
        except Exception as exc:  # noqa: BLE001 - shown; the stored calibration is unchanged
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>{escaped(describe_error(exc))}</span>")
            return
        if self.handle is not None:
            self.handle.control.host_config = cfg
        self.status.setText(done)
        self._apply_to_encoder()
        self.show_config()

    def _apply_to_encoder(self) -> None:
        enc = getattr(self.main, "encoder", None)
        if enc is not None:
            enc.set_normaliser(self.taxel_range())

    def _start(self, job: Job, what: str) -> None:
        self.job = job
        self._what = what
        self.status.setText(f"{what}: running...")
        job.start()
        self._enable(self.handle is not None)

    def refresh(self) -> None:
        self._sync_undo()
        job = self.job
        if job is None:
            return
        while not job.events.empty():
            self.mass_label.setText(job.events.get())
            self.mass_prompt.show()
        self.progress.setValue(int(100 * job.fraction))
        if not job.done:
            if job.message:
                self.status.setText(f"{self._what}: {job.message}")
            return
        self.job = None
        self.mass_prompt.hide()
        if job.error:
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>{self._what} failed: {escaped(job.error)}</span>")
        else:
            self.progress.setValue(100)
            r = job.result
            if hasattr(r, "counts_per_g"):
                self.status.setText(f"load cell: {r.counts_per_g:.2f} counts/g written to the controller; with "
                                    f"the {r.mass_g:g} g mass it now reads {r.check_force_g:.1f} g")
            else:
                low = r.low_taxels
                self.status.setText(f"taxel normalisation stored ({r.norm.n_trials} capture(s)); the live encoder uses "
                                    "it from now on (Undo goes back)"
                                    + (f"; taxels {', '.join(map(str, low))} barely moved: check them" if low else ""))
                self._apply_to_encoder()
        self.show_config()
        self._enable(self.handle is not None)
