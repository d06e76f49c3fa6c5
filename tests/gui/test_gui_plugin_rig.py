"""The Connect dialog opens a plugin's rig (issue 38 part 6): the out-of-tree CSV taxel board
(tests/plugins/rigctl-csvboard, pip-installed into a folder on sys.path: tests/conftest.py's installed_plugins) is
offered under "Plugin rig" with its options; a malformed option is refused in the dialog, saying why; accepted, the
app opens it (the board's 4 taxels at 200 Hz on the in-process simulated drum) and the choice persists, options
included."""

from __future__ import annotations

from rigctl_gui.events import wait_for


def test_the_connect_dialog_opens_a_plugin_rig(qapp, gui_home, installed_plugins, tmp_path):
    from PySide6 import QtWidgets

    from rigctl_gui.app import MainWindow, make_settings
    from rigctl_gui.connect_dialog import load_source
    from rigctl_gui.workers import RigSource

    board = tmp_path / "board.csv"
    board.write_text("\n".join(",".join(str((i * 7) % 900 + 10 * c) for c in range(4)) for i in range(400)) + "\n")
    w = MainWindow(RigSource("sim"), autoconnect=False)
    try:
        dlg = w.choose_source()
        assert dlg.plugin.isEnabled() and not dlg.plugin.isChecked()
        assert sorted(dlg.plugin_name.itemText(i) for i in range(dlg.plugin_name.count())) == ["broken", "csvboard"]
        dlg.plugin.setChecked(True)
        dlg.plugin_name.setCurrentText("csvboard")
        dlg.plugin_options.setText(f"file={board} drum")  # not KEY=VALUE
        dlg.accept()
        assert dlg.result() != QtWidgets.QDialog.Accepted and "give KEY=VALUE" in dlg.problem.text()
        dlg.plugin_options.setText(f"file='{board}' drum=inprocess")
        chosen = RigSource("csvboard", options={"file": str(board), "drum": "inprocess"})
        assert dlg.source() == chosen
        dlg.accept()  # the app connects to it
        assert wait_for(qapp, lambda: w.handle is not None or "Could not" in w.banner.text, 60), w.banner.text
        assert w.handle is not None, w.banner.text
        assert w.source == chosen and "csvboard rig (file=" in w.source_label.text()
        layout = w.handle.taxels.layout
        assert (layout.n_channels, layout.sample_rate_hz) == (4, 200.0)
        assert load_source(make_settings()) == chosen  # the next start opens it again
    finally:
        w.close()
        w.deleteLater()
        qapp.processEvents()
