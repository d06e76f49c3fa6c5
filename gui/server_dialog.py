"""Attach to a running ``rigctl serve`` instead of owning the rig (Rig > Attach to a rigctl server...): the server's
rig status and run queue, queue the loaded protocol, pause / resume / abort a run, STOP (docs/serve.md).

A face on :class:`rigctl.server.ServerClient`, as the other tabs are on the operator layer: the server owns the rig,
this window only asks. While attached, the main window's STOP (button, Esc, menu) also sends STOP to the server.
"""

from __future__ import annotations

from typing import Any

from PySide6 import QtCore, QtWidgets

from rigctl_gui.messages import set_plain

#: the runs table's columns
RUN_COLUMNS = ("run", "protocol", "state", "trials", "output")


class ServerDialog(QtWidgets.QDialog):
    """The attach window. ``client_factory(url, token) -> ServerClient`` (tests inject one over an app in this
    process); ``protocol_source()`` -> the TOML text of the protocol loaded in the Protocol tab, or None."""

    def __init__(self, parent: Any = None, *, client_factory: Any = None, protocol_source: Any = None,
                 poll_ms: int = 1000) -> None:
        super().__init__(parent)
        self.setWindowTitle("rigctl server")
        self.client: Any = None
        self._factory = client_factory
        self._protocol_source = protocol_source or (lambda: None)
        self.url = QtWidgets.QLineEdit("http://127.0.0.1:8765")
        self.token = QtWidgets.QLineEdit()
        self.token.setEchoMode(QtWidgets.QLineEdit.EchoMode.Password)
        self.token.setPlaceholderText("token (blank: the one a server on this computer wrote)")
        self.attach_btn = QtWidgets.QPushButton("Attach")
        self.attach_btn.clicked.connect(self.attach)
        self.status = QtWidgets.QLabel("not attached")
        self.status.setWordWrap(True)
        self.table = QtWidgets.QTableWidget(0, len(RUN_COLUMNS))
        self.table.setHorizontalHeaderLabels(RUN_COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.out = QtWidgets.QLineEdit()
        self.out.setPlaceholderText("session name in the server's data folder (e.g. mouse1/s1.h5)")
        self.queue_btn = QtWidgets.QPushButton("Queue the loaded protocol")
        self.queue_btn.clicked.connect(self.queue_loaded)
        self.pause_btn = QtWidgets.QPushButton("Pause")
        self.resume_btn = QtWidgets.QPushButton("Resume")
        self.abort_btn = QtWidgets.QPushButton("Abort")
        self.release_btn = QtWidgets.QPushButton("Release queue")
        self.ack_btn = QtWidgets.QPushButton("Acknowledge fault...")
        self.ack_btn.setToolTip("The operator's acknowledgement of the server rig's latched fault (logged with your "
                                "name and reason); it clears the latch, it starts nothing")
        self.ack_btn.clicked.connect(self.acknowledge)
        #: () -> the acknowledgement's reason, or None (cancelled); a text dialog (tests replace it)
        self.ask_reason: Any = self._reason_dialog
        self.stop_btn = QtWidgets.QPushButton("STOP")
        self.stop_btn.setStyleSheet("background: #c00; color: white; font-weight: bold;")
        for b, what in ((self.pause_btn, "pause"), (self.resume_btn, "resume"), (self.abort_btn, "abort")):
            b.clicked.connect(lambda _=False, what=what: self.control(what))
        self.release_btn.clicked.connect(lambda _=False: self._ask(lambda c: c.release()))
        self.stop_btn.clicked.connect(self.stop)

        top = QtWidgets.QHBoxLayout()
        top.addWidget(QtWidgets.QLabel("Server"))
        top.addWidget(self.url, 2)
        top.addWidget(self.token, 1)
        top.addWidget(self.attach_btn)
        q = QtWidgets.QHBoxLayout()
        q.addWidget(self.out, 1)
        q.addWidget(self.queue_btn)
        ctl = QtWidgets.QHBoxLayout()
        for b in (self.pause_btn, self.resume_btn, self.abort_btn, self.release_btn, self.ack_btn, self.stop_btn):
            ctl.addWidget(b)
        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(top)
        lay.addWidget(self.status)
        lay.addWidget(self.table, 1)
        lay.addLayout(q)
        lay.addLayout(ctl)
        self.resize(760, 420)
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.refresh)
        self.timer.start(poll_ms)

    @property
    def attached(self) -> bool:
        return self.client is not None

    def attach(self) -> None:
        from rigctl.server.client import ServerClient, ServerError

        factory = self._factory or (lambda url, token: ServerClient(url, token=token or None))
        client = factory(self.url.text().strip(), self.token.text().strip())
        try:
            client.status()
        except ServerError as exc:
            set_plain(self.status, str(exc), error=True)
            return
        self.client = client
        self.refresh()

    def _ask(self, call: Any) -> Any:
        from rigctl.server.client import ServerError

        if self.client is None:
            set_plain(self.status, "attach to a server first", error=True)
            return None
        try:
            return call(self.client)
        except ServerError as exc:
            set_plain(self.status, str(exc), error=True)
            return None

    def selected_run(self) -> str | None:
        rows = self.table.selectionModel().selectedRows()
        if not rows:
            return None
        item = self.table.item(rows[0].row(), 0)
        return None if item is None else item.text()

    def control(self, what: str) -> None:
        """Pause, resume or abort the selected run (else the current one)."""
        run_id = self.selected_run() or self._current_id
        if run_id is None:
            set_plain(self.status, f"no run to {what}: select one", error=True)
            return
        if self._ask(lambda c: getattr(c, what)(run_id)) is not None:
            self.refresh()

    def queue_loaded(self) -> None:
        source, out = self._protocol_source(), self.out.text().strip()
        if not source or not out:
            set_plain(self.status, "load a protocol in the Protocol tab and give the output file", error=True)
            return
        if self._ask(lambda c: c.submit(out, toml=source)) is not None:
            self.refresh()

    def _reason_dialog(self) -> str | None:
        text, ok = QtWidgets.QInputDialog.getText(self, "Acknowledge the latched fault",
                                                  "What was checked (logged in the session):")
        return text.strip() if ok and text.strip() else None

    def acknowledge(self) -> None:
        """``POST /ack`` with the operator's reason and name (the server answers 409 when nothing is latched)."""
        import getpass

        reason = self.ask_reason()
        if reason and self._ask(lambda c: c.acknowledge(reason, by=getpass.getuser())) is not None:
            self.refresh()

    def stop(self) -> bool:
        """STOP on the server at once; True when it answered."""
        return self._ask(lambda c: c.stop()) is not None

    _current_id: str | None = None

    def refresh(self) -> None:
        if self.client is None:
            return
        from rigctl.server.client import ServerError

        try:
            st, runs = self.client.status(), self.client.runs()
        except ServerError as exc:
            set_plain(self.status, str(exc), error=True)
            return
        drum = (st.get("rig") or {}).get("drum") or {}
        cur = st.get("current_run")
        self._current_id = None if cur is None else cur["id"]
        trial = st.get("current_trial") or {}
        parts = [f"attached to {self.client.url}: {st['rig'].get('mode', '?')} rig",
                 f"drum {drum.get('state', '?')}, {drum.get('speed_mm_s', 0) or 0:.0f} mm/s, "
                 f"{drum.get('force_g', 0) or 0:.0f} g" if drum else st["rig"].get("drum_error", "drum ?"),
                 "queue HELD after STOP (Release queue)" if st.get("held") else "",
                 f"FAULT LATCHED: {latch['text']}" if (latch := st["rig"].get("latch")) else "",
                 f"running {cur['protocol_name']} trial {trial.get('trial_id', '?')} ({trial.get('texture', '?')})"
                 if cur else "no run"]
        set_plain(self.status, "; ".join(p for p in parts if p))
        selected = self.selected_run()
        self.table.setRowCount(len(runs))
        for r, run in enumerate(runs):
            values = (run["id"], run["protocol_name"], run["state"], f"{run['trials_done']}/{run['trials_total']}",
                      run["out"])
            for c, v in enumerate(values):
                self.table.setItem(r, c, QtWidgets.QTableWidgetItem(str(v)))
            if run["id"] == selected:
                self.table.selectRow(r)
