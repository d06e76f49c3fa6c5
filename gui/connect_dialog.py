"""Connect dialog: choose the simulated rig (default), two serial ports found by VID/PID
(:func:`rigctl.devices.ports.find_ports`), a replay (a session file or a FabricSlide folder), or the rig's own
firmware under simavr (hardware-in-the-loop, optionally with the boards' real bootloaders), or a plugin's rig (an
installed entry point of the group ``rigctl.rigs``, :mod:`rigctl.core.rig_plugins`, with its ``KEY=VALUE`` options).
The choice persists in QSettings and is the source the app opens at its next start. The dialog is non-modal (STOP stays usable,
:func:`rigctl_gui.dialogs.show_dialog`) and refuses OK, saying why, for a source that cannot be opened."""

from __future__ import annotations

import os
import shlex

from PySide6 import QtCore, QtWidgets

from rigctl.core.rig_plugins import rig_entries
from rigctl_gui.colours import ERROR, on_window
from rigctl_gui.dialogs import choose_path
from rigctl_gui.workers import RigSource


def _text(value: object) -> str | None:
    """A QSettings string value, or None for a missing or empty one."""
    return str(value) if value else None


def plugin_rigs() -> list[str]:
    """The installed plugins' rigs (not rigctl's own), by name; no plugin is imported."""
    return [name for name, entry in rig_entries().items() if not entry.builtin]


def parse_rig_options(text: str) -> dict[str, str]:
    """``KEY=VALUE KEY=VALUE`` (shell quoting for values with spaces) -> a dict; ValueError naming a bad word."""
    out: dict[str, str] = {}
    for word in shlex.split(text or ""):
        key, sep, value = word.partition("=")
        if not sep or not key:
            raise ValueError(f"rig option {word!r}: give KEY=VALUE")
        out[key] = value
    return out


def format_rig_options(options: dict[str, str]) -> str:
    return " ".join(f"{k}={shlex.quote(v)}" for k, v in options.items())


def load_source(settings: QtCore.QSettings) -> RigSource:
    """The last source chosen (the simulated rig when none was saved, or the saved kind is unknown: a plugin
    uninstalled since)."""
    kind = str(settings.value("source/kind", "sim"))
    try:
        return RigSource(
            kind=kind,
            drum_port=_text(settings.value("source/drum_port", None)),
            taxel_port=_text(settings.value("source/taxel_port", None)),
            replay_dir=_text(settings.value("source/replay_dir", None)),
            bootloaders=kind == "hil" and str(settings.value("source/bootloaders", "false")).lower() == "true",
            motion=_text(settings.value("source/motion", None)) if kind == "handheld" else None,
            options=parse_rig_options(str(settings.value("source/rig_options", "") or "")) if kind in plugin_rigs()
            else {},
        )
    except ValueError:
        return RigSource()


def save_source(settings: QtCore.QSettings, src: RigSource) -> None:
    settings.setValue("source/kind", src.kind)
    settings.setValue("source/drum_port", src.drum_port or "")
    settings.setValue("source/taxel_port", src.taxel_port or "")
    settings.setValue("source/replay_dir", src.replay_dir or "")
    settings.setValue("source/bootloaders", "true" if src.bootloaders else "false")
    settings.setValue("source/rig_options", format_rig_options(src.options))
    settings.setValue("source/motion", src.motion or "")


def source_problem(source: RigSource) -> str | None:
    """Why ``source`` cannot be opened, found before trying (None when it may be)."""
    if source.kind == "replay":
        if not source.replay_dir:
            return "choose a session file or a FabricSlide folder to replay (Connect...)"
        if not os.path.exists(source.replay_dir):
            return f"the replay source {source.replay_dir} does not exist (Connect... to choose another)"
    if source.kind == "hil":
        from rigctl.firmware import missing_build_tools

        missing = missing_build_tools()
        if missing:
            return (f"the firmware under simavr needs {', '.join(missing)}: install the AVR toolchain and simavr "
                    "(Debian: gcc-avr avr-libc arduino-core-avr simavr libsimavr-dev make pkg-config)")
    if source.is_hardware and not (source.drum_port and source.taxel_port):
        return "choose both serial ports: the drum controller's and the taxel board's (Connect...)"
    return None


def list_ports():
    """Serial ports with their VID:PID and board guess; [] (with the reason) when the library cannot list them."""
    try:
        from rigctl.devices.ports import find_ports

        return find_ports(), None
    except Exception as exc:  # noqa: BLE001 - shown in the dialog
        return [], str(exc)


class ConnectDialog(QtWidgets.QDialog):
    """Pick a rig source. :meth:`source` returns the choice as a :class:`rigctl_gui.workers.RigSource`."""

    def __init__(self, current: RigSource, parent=None):
        super().__init__(parent)
        self.setWindowTitle("Connect to the rig")
        self.sim = QtWidgets.QRadioButton("Simulated rig (virtual boards on ptys, physical model)")
        self.serial = QtWidgets.QRadioButton("Real rig on serial ports")
        self.replay = QtWidgets.QRadioButton("Replay (a recorded session file or FabricSlide directory through the "
                                             "simulated rig)")
        self.hil = QtWidgets.QRadioButton("Firmware under simavr (hardware-in-the-loop: the rig's own Mega and Uno "
                                          "images on simulated boards, built on first use)")
        self.hil_bootloaders = QtWidgets.QCheckBox("with the boards' real bootloaders (each connect resets them, as "
                                                   "USB does on a bench)")
        self.hil_bootloaders.setChecked(current.bootloaders)
        self.hil_bootloaders.toggled.connect(self._bootloaders_toggled)
        plugins = plugin_rigs()
        self.plugin = QtWidgets.QRadioButton("Plugin rig (your own hardware: an installed rigctl.rigs backend; "
                                             "`rigctl rigs` lists them)")
        self.plugin_name = QtWidgets.QComboBox()
        self.plugin_name.addItems(plugins)
        self.plugin_options = QtWidgets.QLineEdit(format_rig_options(current.options))
        self.plugin_options.setPlaceholderText("options: KEY=VALUE KEY=VALUE (e.g. port=/dev/ttyUSB0 drum=inprocess)")
        if current.kind in plugins:
            self.plugin_name.setCurrentText(current.kind)
        if not plugins:
            self.plugin.setEnabled(False)
            self.plugin.setToolTip("no plugin rig is installed (docs/guides/my-hardware.md writes one)")
        for widget in (self.plugin_name, self.plugin_options):
            widget.setEnabled(bool(plugins))
        self.drum_port = QtWidgets.QComboBox(editable=True)
        self.taxel_port = QtWidgets.QComboBox(editable=True)
        self.refresh_btn = QtWidgets.QPushButton("Rescan ports")
        self.refresh_btn.clicked.connect(self.rescan)
        self.port_info = QtWidgets.QLabel()
        self.port_info.setWordWrap(True)
        self.replay_dir = QtWidgets.QLineEdit(current.replay_dir or "")
        browse = QtWidgets.QPushButton("Folder...")
        browse.setToolTip("a FabricSlide directory")
        browse.clicked.connect(self._browse)
        browse_file = QtWidgets.QPushButton("Session file...")
        browse_file.setToolTip("a session file (.h5) of any sensor: rigctl acquire or rigctl import output")
        browse_file.clicked.connect(self._browse_file)

        form = QtWidgets.QFormLayout()
        form.addRow("Drum controller (Mega, Modbus)", self.drum_port)
        form.addRow("Taxel streamer (Uno)", self.taxel_port)
        form.addRow(self.refresh_btn, self.port_info)
        ports = QtWidgets.QGroupBox()
        ports.setLayout(form)
        rl = QtWidgets.QHBoxLayout()
        rl.addWidget(self.replay_dir, 1)
        rl.addWidget(browse)
        rl.addWidget(browse_file)

        self.problem = QtWidgets.QLabel("")
        self.problem.setObjectName("connect_problem")
        self.problem.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.problem.setWordWrap(True)
        self.problem.setStyleSheet(f"color: {on_window(ERROR, self)}; font-weight: bold;")
        self.problem.hide()
        button = QtWidgets.QDialogButtonBox.StandardButton
        buttons = QtWidgets.QDialogButtonBox(button.Ok | button.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(self.sim)
        lay.addWidget(self.serial)
        lay.addWidget(ports)
        lay.addWidget(self.replay)
        lay.addLayout(rl)
        lay.addWidget(self.hil)
        hl = QtWidgets.QHBoxLayout()
        hl.addSpacing(24)
        hl.addWidget(self.hil_bootloaders, 1)
        lay.addLayout(hl)
        lay.addWidget(self.plugin)
        pl = QtWidgets.QHBoxLayout()
        pl.addSpacing(24)
        pl.addWidget(self.plugin_name)
        pl.addWidget(self.plugin_options, 1)
        lay.addLayout(pl)
        lay.addWidget(self.problem)
        lay.addWidget(buttons)

        {"hardware": self.serial, "replay": self.replay, "hil": self.hil,
         **{name: self.plugin for name in plugins}}.get(current.kind, self.sim).setChecked(True)
        self.rescan(current)

    def rescan(self, current: RigSource | None = None) -> None:
        ports, err = list_ports()
        for box in (self.drum_port, self.taxel_port):
            box.clear()
        for p in ports:
            vidpid = f"{p.vid:04X}:{p.pid:04X}" if p.vid is not None and p.pid is not None else "no VID:PID"
            text = f"{p.device}  [{vidpid}] {p.description or ''}"
            if p.board:
                text += f"  (looks like the {p.board})"
            self.drum_port.addItem(text, p.device)
            self.taxel_port.addItem(text, p.device)
        # preselect by board guess, then by the saved ports
        for box, board, saved in (
            (self.drum_port, "mega", current.drum_port if current else None),
            (self.taxel_port, "uno", current.taxel_port if current else None),
        ):
            for i, p in enumerate(ports):
                if p.board == board:
                    box.setCurrentIndex(i)
            if saved:
                i = box.findData(saved)
                if i >= 0:
                    box.setCurrentIndex(i)
                else:
                    box.setEditText(saved)
        self.port_info.setText(err or f"{len(ports)} serial port(s) found")

    def _bootloaders_toggled(self, on: bool) -> None:
        if on:  # the bootloaders are the firmware under simavr's
            self.hil.setChecked(True)

    def _browse(self) -> QtWidgets.QFileDialog:
        return choose_path(self, "dir", "FabricSlide directory", self.replay_dir.text(), "", self._replay_chosen)

    def _browse_file(self) -> QtWidgets.QFileDialog:
        return choose_path(self, "open", "Session file to replay", self.replay_dir.text(),
                           "Session files (*.h5 *.hdf5);;All files (*)", self._replay_chosen)

    def _replay_chosen(self, path: str) -> None:
        self.replay_dir.setText(path)
        self.replay.setChecked(True)

    def accept(self) -> None:
        """OK: refused (the reason shown in the dialog) when the chosen source cannot be opened."""
        try:
            problem = source_problem(self.source())
        except ValueError as exc:  # a rig option that is no KEY=VALUE, or a name rigctl keeps
            problem = str(exc)
        if problem:
            self.problem.setText(problem)
            self.problem.show()
            return
        super().accept()

    @staticmethod
    def _port(box: QtWidgets.QComboBox) -> str | None:
        data = box.currentData()
        text = box.currentText().split()[0] if box.currentText().strip() else None
        return data if data and box.currentText().startswith(str(data)) else text

    def source(self) -> RigSource:
        """The source chosen; ValueError for a plugin's options that are not ``KEY=VALUE`` words."""
        if self.plugin.isChecked() and self.plugin_name.currentText():
            return RigSource(self.plugin_name.currentText(), options=parse_rig_options(self.plugin_options.text()))
        if self.serial.isChecked():
            return RigSource("hardware", drum_port=self._port(self.drum_port), taxel_port=self._port(self.taxel_port))
        if self.replay.isChecked():
            return RigSource("replay", replay_dir=self.replay_dir.text() or None)
        if self.hil.isChecked():
            return RigSource("hil", bootloaders=self.hil_bootloaders.isChecked())
        return RigSource("sim")
