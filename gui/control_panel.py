"""Rig control panel: drum speed and force setpoints within the controller's limits, run/stop/tare/home, the
controller state and fault bits in words, and live plots of load-cell force vs setpoint and drum speed vs target.

All drum calls go through :class:`rigctl_gui.workers.CommandExecutor` (a worker thread); the plots are redrawn from the
:class:`rigctl_gui.workers.StatusPoller` history by a QTimer.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from rigctl.core.drum import (
    MAX_FORCE_G,
    MAX_SPEED_MM_S,
    PROTOCOL_LIMITS,
    STATE_TEXT as STATE_WORDS,
    DrumLimits,
    DrumState,
    fault_advice as fault_meaning,
    status_line,
)
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, TextureSetError
from rigctl.operations import RigControl, setpoint_refusals
from rigctl_gui.colours import on_window
from rigctl_gui.live_items import cache_axes_and_title, mark_containers
from rigctl_gui.widgets import gap_breaks, keep_room, restyle, side_panel

__all__ = ["ControlPanel", "STATE_WORDS", "STATE_COLOURS", "fault_meaning", "drum_summary"]

#: the force and speed plots' smallest height together, px (each data area keeps ~80 px: its two-line legend, its axis
#: label)
PLOTS_MIN_PX = 300
#: the time axes of the force and speed plots show at least this much history, s
X_MIN_SPAN_S = 5.0
#: the status is polled at 10 Hz: a longer pause between two reads is an outage, drawn as a gap in the plots, s
GAP_S = 1.0
#: the colour each controller state is shown in (the words are the library's: rigctl.core.drum.STATE_TEXT)
STATE_COLOURS = {
    DrumState.IDLE: "#555",
    DrumState.HOMING: "#a60",
    DrumState.SEEKING_FORCE: "#a60",
    DrumState.FORCE_SETTLED: "#06a",
    DrumState.RUNNING: "#080",
    DrumState.FAULT: "#c00",
}


def drum_summary(poller, latch: str | None = None) -> tuple[str, str]:
    """The drum in one short line and its colour, for the top strip seen from every tab: ``("Drum: Running 80 mm/s,
    498 g", "#080")``, ``("Drum: FAULT, drivers off, pressing 508 g", "#c00")``, not responding or not connected
    (the library's words: :func:`rigctl.core.drum.status_line`, short). ``poller``: the rig's monitor (its latest
    status and link) or None; ``latch``: the library's latch label, if one is held."""
    if poller is None:
        return "Drum: not connected", "#555"
    if not poller.ok:
        return "Drum: NOT RESPONDING", "#c00"
    st = poller.latest
    if st is None:
        return "Drum: -", "#555"
    state = DrumState(int(st.state))
    word = status_line(st, latch, short=True)
    if int(st.faults) and state != DrumState.FAULT:
        word += " (fault latched)"
    return f"Drum: {word}", STATE_COLOURS.get(state, "#c00" if int(st.faults) else "#555")


class ControlPanel(QtWidgets.QWidget):
    """The rig control tab. Call :meth:`attach` with a connected :class:`rigctl_gui.workers.RigHandle`'s workers."""

    #: a manual setpoint was refused (the reason in words), for the window's event log
    refused = QtCore.Signal(str)
    #: an operator action was sent (in words: the setpoints applied, a command queued), for the event log
    acted = QtCore.Signal(str)
    #: a question for the operator: (title, text, yes, no, on_yes); the main window shows it non-modal
    question = QtCore.Signal(str, str, str, str, object)
    #: Clear fault was pressed: the main window opens the fault dialog (the one acknowledgement path: the fault
    #: named, a reason required, logged with the login name); nothing is cleared by the click itself
    acknowledge_wanted = QtCore.Signal()

    def __init__(self, parent=None):
        super().__init__(parent)
        self.poller = None
        self.commands = None
        self.drum = None
        self.ops: RigControl | None = None
        self._pending_plate: str | None = None  # the plate to mount once the operator agrees to stop the drum

        left = QtWidgets.QVBoxLayout()
        left.addWidget(self._build_setpoints())
        left.addWidget(self._build_commands())
        left.addWidget(self._build_state())
        left.addStretch(1)
        leftw = side_panel(left, 350)  # fixed width, scrolls when the window is short
        self._locked_by: str | None = None
        self._connected = False

        self._build_plots()

        lay = QtWidgets.QHBoxLayout(self)
        lay.addWidget(leftw)
        lay.addWidget(self.plots, 1)
        self.set_enabled(False)

    def _build_setpoints(self) -> QtWidgets.QGroupBox:
        """The speed and force setpoint boxes, the limits they are checked against and Apply."""
        # the boxes take any number typed (a value above the limits is shown as typed and refused visibly, never
        # cut to its first digits by the box's validator)
        self.speed = QtWidgets.QDoubleSpinBox(suffix=" mm/s", decimals=1, singleStep=10.0, maximum=99999.0)
        self.speed.setObjectName("speed_setpoint")
        self.force = QtWidgets.QDoubleSpinBox(suffix=" g", decimals=0, singleStep=50.0, maximum=99999.0)
        self.force.setObjectName("force_setpoint")
        self.limits_label = QtWidgets.QLabel()
        self.limits_label.setObjectName("setpoint_limits")
        self.setpoint_error = QtWidgets.QLabel("")
        self.setpoint_error.setObjectName("setpoint_error")
        # short lines without word wrap: a wrapped label in a form is squeezed in a short window
        self.setpoint_error.setStyleSheet(f"color: {on_window('#c00', self)}; font-weight: bold;")
        keep_room(self.setpoint_error, lines=2)  # its room is kept while hidden: the buttons below never move
        self.setpoint_error.hide()
        self.limits = PROTOCOL_LIMITS  # the controller's hard limits (DrumLimits), read at attach
        for box in (self.speed, self.force):
            box.setKeyboardTracking(False)
            box.setMinimumWidth(120)
            box.valueChanged.connect(self.check_setpoints)
        self.set_limits(MAX_SPEED_MM_S, MAX_FORCE_G)
        self.speed.setValue(80.0)
        self.force.setValue(500.0)
        self.apply_btn = QtWidgets.QPushButton("Apply setpoints")
        self.apply_btn.clicked.connect(self.apply_setpoints)

        form = QtWidgets.QFormLayout()
        form.addRow("Drum speed", self.speed)
        form.addRow("Contact force", self.force)
        form.addRow(self.limits_label)
        # in a box of its own: a QFormLayout drops a hidden widget's row whatever its size policy (Apply, Press and
        # Run moved down 38 px when a refusal showed); a box layout keeps the room (keep_room)
        holder = QtWidgets.QWidget()
        hold = QtWidgets.QVBoxLayout(holder)
        hold.setContentsMargins(0, 0, 0, 0)
        hold.addWidget(self.setpoint_error)
        form.addRow(holder)
        form.addRow("", self.apply_btn)
        setp = QtWidgets.QGroupBox("Setpoints")
        setp.setLayout(form)
        return setp

    def _build_commands(self) -> QtWidgets.QGroupBox:
        """The drum's command buttons and the plate chooser."""
        self.buttons = {}
        grid = QtWidgets.QGridLayout()
        for i, (name, label, tip) in enumerate(
            [
                ("press", "Press", "Engage the force loop: seek the force setpoint, then hold it"),
                ("run", "Run", "Start the drum at the speed setpoint (force loop holding)"),
                ("stop_drum", "Stop drum", "Decelerate the drum, keep holding the force"),
                ("tare", "Tare", "Zero the load cell (actuator released)"),
                ("home", "Home", "Drive the actuator to its home switch"),
                ("clear_fault", "Clear fault...", "Name the latched fault and acknowledge it with a reason (the fault "
                 "dialog); nothing moves until a separate start"),
            ]
        ):
            b = QtWidgets.QPushButton(label)
            b.setToolTip(tip)
            b.setObjectName(f"btn_{name}")
            b.clicked.connect(lambda _=False, n=name: self.command(n))
            self.buttons[name] = b
            grid.addWidget(b, i // 2, i % 2)
        self.plate = QtWidgets.QComboBox()
        self.plate.setObjectName("plate")
        self.textures: TextureSet | None = None
        self.set_textures(PAPER_TEXTURES)
        self.mount_btn = QtWidgets.QPushButton("Mount plate")
        self.mount_btn.setObjectName("btn_mount")
        self.mount_btn.clicked.connect(self.mount_plate)
        grid.addWidget(self.plate, 3, 0)
        grid.addWidget(self.mount_btn, 3, 1)
        cmds = QtWidgets.QGroupBox("Drum")
        cmds.setLayout(grid)
        return cmds

    def _build_state(self) -> QtWidgets.QGroupBox:
        """The controller's state, faults, readout and messages."""
        self.state_label = QtWidgets.QLabel("not connected")
        self.state_label.setObjectName("state_label")
        self.state_label.setWordWrap(True)
        self.state_label.setStyleSheet("font-size: 15px; font-weight: bold;")
        self.fault_label = QtWidgets.QLabel("Faults: -")
        self.fault_label.setWordWrap(True)
        self.readout = QtWidgets.QLabel("-")
        self.readout.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.message = QtWidgets.QLabel("")
        self.message.setWordWrap(True)
        sl = QtWidgets.QVBoxLayout()
        for w in (self.state_label, self.fault_label, self.readout, self.message):
            w.setTextFormat(QtCore.Qt.TextFormat.PlainText)  # device errors are shown whole ('<' included)
            sl.addWidget(w)
        state = QtWidgets.QGroupBox("Controller")
        state.setLayout(sl)
        return state

    def _build_plots(self) -> None:
        """Force vs setpoint and drum speed vs target, over time."""
        self.plots = pg.GraphicsLayoutWidget()
        self.force_plot = self.plots.addPlot(row=0, col=0, title="Load-cell force vs setpoint")
        self.force_plot.setLabel("left", "force (g)")
        self.force_plot.addLegend(offset=(5, 5))
        self.force_curve = self.force_plot.plot(pen=pg.mkPen("#1f77b4", width=2), name="measured")
        self.setpoint_curve = self.force_plot.plot(
            pen=pg.mkPen("#d62728", width=2, style=QtCore.Qt.PenStyle.DashLine), name="setpoint"
        )
        self.speed_plot = self.plots.addPlot(row=1, col=0, title="Drum surface speed")
        # the unit written out (no SI prefix: a drum at rest read "speed (mmm/s)" from -400 to 400)
        self.speed_plot.setLabel("left", "speed (mm/s)")
        self.speed_plot.setLabel("bottom", "time", units="s")
        self.speed_plot.addLegend(offset=(5, 5))
        self.speed_curve = self.speed_plot.plot(pen=pg.mkPen("#2ca02c", width=2), name="measured")
        self.target_curve = self.speed_plot.plot(
            pen=pg.mkPen("#ff7f0e", width=2, style=QtCore.Qt.PenStyle.DashLine), name="target"
        )
        for p in (self.force_plot, self.speed_plot):
            p.showGrid(x=True, y=True, alpha=0.3)
            # each refresh redraws the curves: the axes, their grid and the titles are drawn only when they change
            cache_axes_and_title(p)
        mark_containers(self.plots.ci)
        #: the time axes' span shown, s (:meth:`_set_x_range`)
        self._x_span_s = 0.0
        # each plot keeps room for its legend and its axis label (a shorter tab scrolls: at 1.5x on 1024x700 the
        # plots had 15 px and their axis labels ran into each other)
        self.plots.setMinimumHeight(PLOTS_MIN_PX)

    # ------------------------------------------------------------------------------------------------------
    def set_limits(self, speed_max_mm_s: float, force_max_g: float) -> None:
        """The controller's hard limits (its SPEED_LIMIT / FORCE_LIMIT). A setpoint is accepted when it is above 0
        and within both the rig's protocol range and these limits (:class:`rigctl.core.drum.DrumLimits`); others
        are refused with a message."""
        self.limits = DrumLimits(float(speed_max_mm_s), float(force_max_g))
        self.limits_label.setText(
            f"protocol range > 0 to {MAX_SPEED_MM_S:g} mm/s, > 0 to {MAX_FORCE_G:g} g\n"
            f"controller hard limits {speed_max_mm_s:g} mm/s, {force_max_g:g} g")
        self.limits_label.setToolTip(
            f"Accepted: speed above 0 and at most {self.accepted_max('speed'):g} mm/s, force above 0 and at most "
            f"{self.accepted_max('force'):g} g (the lower of the rig's protocol range and the controller's "
            "SPEED_LIMIT / FORCE_LIMIT registers). Anything else is refused and nothing is sent.")
        self.check_setpoints()

    def accepted_max(self, which: str) -> float:
        """The highest ``"speed"`` (mm/s) or ``"force"`` (g) setpoint accepted: the lower of both limits."""
        return (self.limits.speed_range() if which == "speed" else self.limits.force_range()).high

    def setpoint_problems(self) -> list[tuple[str, str]]:
        """Why the setpoints in the boxes cannot be sent, (short, full) per box (empty when they can): the
        library's policy (:func:`rigctl.operations.setpoint_refusals`)."""
        return [(r.short, r.full) for r in setpoint_refusals(self.limits, speed_mm_s=float(self.speed.value()),
                                                              force_g=float(self.force.value()))]

    def check_setpoints(self) -> bool:
        """Mark an out-of-range box red and say why under the boxes; True when both can be sent."""
        if not hasattr(self, "limits"):
            return True
        problems = self.setpoint_problems()
        for which, box in (("speed", self.speed), ("force", self.force)):
            bad = any(p[0].startswith(which) for p in problems)
            box.lineEdit().setStyleSheet("background: #fcc; color: #900; font-weight: bold;" if bad else "")
        self.setpoint_error.setText("\n".join(short for short, _ in problems))
        self.setpoint_error.setToolTip("\n".join(full for _, full in problems))
        self.setpoint_error.setVisible(bool(problems))
        return not problems

    def _refuse_setpoints(self) -> bool:
        """True (and the reason shown in the panel and reported) when the setpoints cannot be sent."""
        if self.check_setpoints():
            return False
        text = "; ".join(full for _, full in self.setpoint_problems()) + ": nothing sent"
        self.show_result(False, text)
        self.refused.emit(text)
        return True

    def set_textures(self, textures: TextureSet | None) -> None:
        """Offer the plates of ``textures`` (the rig's texture set; the paper's A-P by default). ``None`` (a rig
        whose operator mounts any plate): the plate box takes any label typed in."""
        self.textures = textures
        current = self.plate.currentText()
        self.plate.clear()
        self.plate.setEditable(textures is None)
        if textures is None:
            self.plate.setToolTip("Texture plate: type its label. The operator mounts it while the sensor is "
                                  "released, then presses the button.")
            self.plate.setEditText(current)
            return
        self.plate.addItems(list(textures.labels))
        if current in textures.labels:
            self.plate.setCurrentText(current)
        which = ("A-P (paper Fig. 2B)" if textures == PAPER_TEXTURES
                 else f"of the set {textures.name!r}" if textures.name else "of the rig's texture set")
        self.plate.setToolTip(f"Texture plate {which}. Simulated rig: mounts it. Real rig: the operator "
                              "mounts it while the sensor is released, then presses the button.")

    def _controls(self) -> list:
        return [self.apply_btn, self.mount_btn, self.plate, *self.buttons.values()]

    def set_enabled(self, on: bool) -> None:
        self._connected = on
        for w in self._controls():
            w.setEnabled(on and self._locked_by is None)

    def set_run_lock(self, reason: str | None) -> None:
        """While a protocol run owns the rig (running or paused) every manual command is disabled, its tooltip
        saying why (``reason``); ``None`` gives them back."""
        if reason == self._locked_by:
            return
        self._locked_by = reason
        for w in self._controls():
            tip = w.property("normal_tip")
            if tip is None:
                tip = w.toolTip()
                w.setProperty("normal_tip", tip)
            w.setToolTip(f"Disabled: {reason}" if reason else tip)
        self.set_enabled(self._connected)

    def attach(self, drum, poller, commands, control: RigControl | None = None) -> None:
        """Bind to a connected drum (read-only: a :class:`rigctl.operations.DrumView`), its status poller and
        command executor, and the open rig (a :class:`rigctl.operations.RigControl`) that the panel's commands go
        through."""
        self.drum, self.poller, self.commands = drum, poller, commands
        self.ops = control
        self.set_textures(PAPER_TEXTURES if control is None else control.textures)
        try:
            lim = drum.limits()
            self.set_limits(lim.speed_mm_s, lim.force_g)
        except Exception as exc:  # noqa: BLE001 - keep the defaults, say why
            self.message.setText(f"could not read the controller's limits: {exc}")
        self.set_enabled(True)

    def detach(self) -> None:
        self.drum = self.poller = self.commands = self.ops = None
        self.set_enabled(False)
        self.state_label.setText("not connected")

    # ------------------------------------------------------------------------------------------------------
    def _refused_by_run(self) -> bool:
        """True (and said in the panel) while a protocol run owns the rig (a shortcut may race the disabling)."""
        if self._locked_by is None:
            return False
        self.show_result(False, f"refused: {self._locked_by}")
        return True

    def apply_setpoints(self) -> None:
        if self.commands is None or self._refused_by_run() or self._refuse_setpoints():
            return
        speed, force = float(self.speed.value()), float(self.force.value())
        if self.ops is None:  # no rig attached: nothing to send to
            self.show_result(False, "refused: no rig connected")
            return
        self.commands.submit(f"set {speed:g} mm/s, {force:g} g", self.ops.apply_setpoints, speed, force)
        self.acted.emit(f"setpoints applied: speed {speed:g} mm/s, force {force:g} g")

    def command(self, name: str) -> None:
        """Queue a drum command. Run is :meth:`rigctl.operations.RigControl.run_at` (press until the force has
        settled, then run: the drum never turns before the sensor is loaded); Press presses to the force setpoint
        and waits for it to settle."""
        if self.commands is None or self._refused_by_run():
            return
        if name in ("run", "press"):
            if self._refuse_setpoints():
                return
            speed, force = float(self.speed.value()), float(self.force.value())
            if self.ops is None:  # no rig attached: nothing to press with
                self.show_result(False, f"{name} refused: no rig connected")
                return
            self.acted.emit(f"{name}: setpoints applied: speed {speed:g} mm/s, force {force:g} g")
            if name == "press":
                self.commands.submit(f"press to {force:g} g", self.ops.press, force)
            else:
                self.commands.submit(f"run at {speed:g} mm/s, {force:g} g", self.ops.run_at, speed, force)
            return
        if name == "clear_fault":  # one acknowledgement path: the fault dialog (fault named, a reason required)
            self.acknowledge_wanted.emit()
            return
        if name == "home" and self.ops is not None:  # the start: HOME and TARE (opening and acknowledging move nothing)
            self.commands.submit("home", self.ops.home)
            self.acted.emit("home sent")
            return
        if self.ops is None:
            self.show_result(False, f"{name.replace('_', ' ')} refused: no rig connected")
            return
        self.commands.submit(name.replace("_", " "), getattr(self.ops, name))  # the owner's (stop_drum, tare)
        self.acted.emit(f"{name.replace('_', ' ')} sent")

    def drum_turning(self) -> bool:
        """True when the newest status says the drum runs or moves (> 0.5 mm/s)."""
        st = self.poller.latest if self.poller is not None and self.poller.ok else None
        return st is not None and (int(st.state) == DrumState.RUNNING or abs(st.speed_mm_s) > 0.5)

    def mount_plate(self, label: str | None = None, *, confirmed: bool = False) -> None:
        """Release the sensor and mount texture plate ``label`` (:meth:`rigctl.operations.RigControl.mount_plate`;
        on hardware the operator has mounted it when pressing the button). The label is taken in the set's spelling
        (``"l"`` -> ``"L"``); a label the set does not have is refused in the panel's message line."""
        if self.commands is None or self.ops is None or self._refused_by_run():
            return
        label = label or self.plate.currentText()
        if self.textures is not None:
            try:
                label = self.textures.resolve(label)
            except TextureSetError as exc:
                self.show_result(False, str(exc))
                return
        self.plate.setCurrentText(label)
        if self.drum_turning() and not confirmed:
            self._pending_plate = label
            self.question.emit(
                "The drum is turning",
                f"The drum is turning. Mounting plate {label} stops it and releases the sensor first.",
                f"Stop the drum and mount {label}", "Cancel", self._mount_pending)
            return
        self.commands.submit(f"mount plate {label}", self.ops.mount_plate, label, lambda _msg: None)
        self.acted.emit(f"mount plate {label} sent")

    def _mount_pending(self) -> None:
        label, self._pending_plate = getattr(self, "_pending_plate", None), None
        if label is not None:
            self.mount_plate(label, confirmed=True)

    def _mark_stale(self, stale: bool) -> None:
        """Say on the plots that they are frozen while the drum controller does not answer."""
        if stale == getattr(self, "_stale", False):
            return
        self._stale = stale
        suffix = " - STALE: drum controller not responding" if stale else ""
        colour = "#c00" if stale else None
        self.force_plot.setTitle("Load-cell force vs setpoint" + suffix, color=colour)
        self.speed_plot.setTitle("Drum surface speed" + suffix, color=colour)

    def _set_x_range(self, span_s: float) -> None:
        """Both time axes from ``-S`` to 0 s (``S``: at least 5 s, whole seconds) so the ``span_s`` s of history all
        show; ``S`` changes only when the history no longer fits or has room for more than 2 s more, so the time
        axes (ticks, grid) are not drawn again at every refresh while the history grows or holds steady."""
        need = max(X_MIN_SPAN_S, span_s)
        if need <= self._x_span_s < need + 2.0:
            return
        self._x_span_s = float(np.ceil(need))
        for plot in (self.force_plot, self.speed_plot):  # no setXLink (crashes with PySide6 6.12)
            plot.setXRange(-self._x_span_s, 0.0, padding=0.02)

    def _set_y_ranges(self, h: np.ndarray) -> None:
        """y axes that never zoom into noise: speed from below 0 to at least the rig's top protocol speed, force
        from below 0 to at least 1.1x the highest value shown (a drum at rest shows a flat line at 0)."""
        with np.errstate(all="ignore"):
            spd = h[:, 3:5][np.isfinite(h[:, 3:5])]
            frc = h[:, 1:3][np.isfinite(h[:, 1:3])]
        s_lo = min(-5.0, float(spd.min()) - 5) if spd.size else -5.0
        s_hi = max(MAX_SPEED_MM_S, float(spd.max()) * 1.1) if spd.size else MAX_SPEED_MM_S
        f_lo = min(-20.0, float(frc.min()) * 1.1) if frc.size else -20.0
        f_hi = max(100.0, float(frc.max()) * 1.1) if frc.size else 100.0
        if getattr(self, "_y_ranges", None) != (s_lo, s_hi, f_lo, f_hi):
            self._y_ranges = (s_lo, s_hi, f_lo, f_hi)
            self.speed_plot.setYRange(s_lo, s_hi, padding=0)
            self.force_plot.setYRange(f_lo, f_hi, padding=0)

    def show_result(self, ok: bool, text: str) -> None:
        self.message.setStyleSheet("" if ok else f"color: {on_window('#c00', self)};")
        self.message.setText(text)

    def refresh(self) -> None:
        """Redraw from the poller (called by the main window's timer)."""
        p = self.poller
        if p is None:
            return
        h = p.history.snapshot()
        if len(h):
            # an outage (no status read for longer than GAP_S) is a gap in the curves, never a straight line
            h = gap_breaks(h, max_dt=GAP_S)
            t = h[:, 0] - np.nanmax(h[:, 0])
            for curve, col in ((self.force_curve, 1), (self.setpoint_curve, 2), (self.speed_curve, 3),
                               (self.target_curve, 4)):
                curve.setData(t, h[:, col], connect="finite")
            self._set_x_range(float(-np.nanmin(t)))
            self._set_y_ranges(h)
        st = p.latest
        self._mark_stale(not p.ok)
        if not p.ok:
            self.state_label.setText("Drum controller not responding")
            restyle(self.state_label, f"font-size: 15px; font-weight: bold; color: {on_window('#c00', self)};")
            return
        if st is None:
            return
        state = DrumState(int(st.state))
        latch = self.ops.latch if self.ops is not None else None
        self.state_label.setText(status_line(st, latch.label if latch is not None else None))
        restyle(self.state_label,
                f"font-size: 15px; font-weight: bold; color: {on_window(STATE_COLOURS.get(state, '#000'), self)};")
        faults = int(st.faults)
        if faults:
            self.fault_label.setText(f"Latched faults: {fault_meaning(faults)} The fault stays until you press "
                                     "Clear fault.")
            restyle(self.fault_label, f"color: {on_window('#c00', self)}; font-weight: bold;")
        else:
            self.fault_label.setText("Faults: none")
            restyle(self.fault_label, "")
        restyle(self.buttons["clear_fault"],
                "QPushButton { background: #fdd; color: #900; font-weight: bold; }" if faults else "")
        fw = ".".join(str(x) for x in st.firmware)
        self.readout.setText(
            f"force {st.force_g:7.1f} g (holding {st.force_setpoint_active_g:.0f} g)\n"
            f"speed {st.speed_mm_s:6.1f} mm/s (target {st.speed_target_mm_s:.1f})\n"
            f"drum {st.angle_deg:6.1f} deg, {st.revolutions} rev; actuator {st.actuator_mm:.2f} mm\n"
            f"firmware {fw}, heartbeat {st.heartbeat}\n"
            f"plate {(self.ops.plate if self.ops is not None else None) or 'unknown'}"
        )
