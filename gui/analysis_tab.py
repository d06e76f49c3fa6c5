"""Offline analysis tab: open a session or encoded file, browse its trials (raw traces, a heat map per taxel layer
and SA/RA rasters of any trial, shaped by the file's sensor layout: any channel count, layers and rate), encode
and run the paper's analyses in a background process with progress and cancel
(:mod:`rigctl.encoding.pipeline`, :mod:`rigctl.analysis`), plot accuracy vs PCs with error bars for the four
variants (Fig. 3), the Table 1 grid and confusion matrices; export figures (PNG/SVG) and tables (CSV); train the
texture classifier used by the real-time classification view."""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from rigctl.core import PAPER_SENSOR, SensorLayout
from rigctl.core.errors import describe_error
from rigctl_gui.colours import ERROR, on_window
from rigctl_gui.messages import escaped as _html  # a '<' in an error would cut a rich-text label short
from rigctl_gui.staged import StagedBuild, StagedWidget
from rigctl_gui.widgets import add_taxel_numbers, side_panel
from rigctl_gui.workers import Job, ProcessJob

#: an exported PNG is rendered at least this wide (px)
EXPORT_PNG_WIDTH_PX = 1600
#: the trial view's left axes are this wide (px), so readings, SA and RA share one data area and time axis
TRIAL_AXIS_PX = 56
#: the accuracy and confusion plots' smallest height, px: a shorter tab scrolls (at 1.5x on a 1024x700 screen the plots
#: were squeezed to a few px and their tick labels overlapped)
RESULT_PLOT_MIN_PX = 200
#: the trial view's plots' smallest size, px (beside the 230-px heat maps; at 1.5x on a 1024x700 screen they had 70 px,
#: their data areas 14 px wide and ~20 px tall, the title cut): a smaller tab scrolls
TRIAL_PLOTS_MIN_PX = (300, 340)
#: Fig. 3 / report colours per variant
VARIANT_COLOURS = {"original": "#000000", "speed_scaled": "#1f77b4", "force_scaled": "#d62728",
                   "speed_force_scaled": "#2ca02c"}


def file_kind(path: str) -> str:
    """"encoded" (an encoded file, :mod:`rigctl.storage.encoded`), "session" (a session file,
    :mod:`rigctl.storage.session`), or "unknown"."""
    from rigctl.storage.encoded import is_encoded_file
    from rigctl.storage.session import open_session

    if is_encoded_file(path):
        return "encoded"
    try:
        with open_session(path):
            return "session"
    except Exception:  # noqa: BLE001 - anything that is not a session
        return "unknown"


class _Views(QtWidgets.QTabWidget):
    """The result views, without height-for-width: a tab widget's is its pages' *preferred* height (their plots'
    480 px), and the main window's page scroll area took it as the tab's smallest height, so the Analysis tab
    scrolled at 1024x700 and 1280x800 with a file open."""

    def hasHeightForWidth(self) -> bool:  # noqa: N802 - Qt override
        return False


class AnalysisTab(StagedWidget, QtWidgets.QWidget):
    """The offline analysis tab; ``main`` is the :class:`rigctl_gui.app.MainWindow`."""

    heat_bar: pg.ColorBarItem  # the heat maps' one colour bar (:meth:`_build_trial_view`)

    #: a staged build (``staged=True``) has finished: every view exists (GUI thread)
    built = QtCore.Signal()

    def __init__(self, main, parent=None, *, staged=False):  # (staged: bool; the body is left unchecked, as before)
        super().__init__(parent)
        self.main = main
        self._staged: StagedBuild | None = None  # the staged build (``staged=True``)
        self.path: str | None = None
        self.kind: str | None = None
        self.encoded_path: str | None = None
        self.results = None
        self.job = None
        self._job_kind = ""
        self._trial_job: Job | None = None
        self._verdict_job: Job | None = None  # the trial validator's verdicts on the open session (off this thread)
        self._wanted_tid: int | None = None  # the selected trial: the plot follows it (rapid browsing)
        self.shown_tid: int | None = None  # the trial the plots show
        self._session_range = None
        self.sensor_layout: SensorLayout = PAPER_SENSOR  # the open file's sensor (shapes the trial view)

        self.views = _Views()
        self._lay = lay = QtWidgets.QHBoxLayout(self)
        lay.addWidget(self.views, 1)
        if staged:  # one plot per pass of the event loop (the whole tab held the GUI thread ~0.7-1.6 s: issue 51)
            self._staged = StagedBuild(self._view_steps(), self)
            self._staged.done.connect(self.built)
        else:
            for _ in self._view_steps():
                pass

    def _view_steps(self) -> Iterator[None]:
        """The controls, then the result views, built in steps (a yield after each plot); the controls stay disabled
        until every view exists."""
        self._leftw = leftw = self._build_controls()
        self._lay.insertWidget(0, leftw)
        leftw.setEnabled(False)
        yield
        yield from self._build_trial_tab()
        self._build_accuracy_tab()
        yield
        self._build_table1_tab()
        yield
        self._build_confusion_tab()
        self._leftw.setEnabled(True)
        self._update_buttons()

    def _build_controls(self) -> QtWidgets.QWidget:
        """The left panel: file, trials, the analyses' options and buttons, the model trainer, the exports."""
        self.open_btn = QtWidgets.QPushButton("Open session / encoded file...")
        self.open_btn.clicked.connect(self._browse)
        self.file_label = QtWidgets.QLabel("no file")
        self.file_label.setWordWrap(True)
        self.trials = QtWidgets.QTableWidget(0, 5)
        self.trials.setHorizontalHeaderLabels(["trial", "texture", "speed", "force", "status"])
        self.trials.verticalHeader().setVisible(False)
        self.trials.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.trials.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.SingleSelection)
        self.trials.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.trials.itemSelectionChanged.connect(self._trial_selected)

        self.repeats = QtWidgets.QSpinBox(minimum=1, maximum=100, value=5)
        self.n_pcs = QtWidgets.QSpinBox(minimum=1, maximum=200, value=50)
        self.per_texture = QtWidgets.QSpinBox(minimum=2, maximum=5000, value=500)
        self.do_cv = QtWidgets.QCheckBox("Textures and groups (Fig. 3A-B)")
        self.do_cv.setChecked(True)
        self.do_extra = QtWidgets.QCheckBox("Speed/force extrapolation (Fig. 3C-F)")
        self.do_extra.setChecked(True)
        opts = QtWidgets.QFormLayout()
        opts.addRow("Repetitions", self.repeats)
        opts.addRow("PCs 1..", self.n_pcs)
        opts.addRow("Trials per texture", self.per_texture)
        opts.addRow("Test folds", self._build_cv_groups())
        opts.addRow(self.do_cv)
        opts.addRow(self.do_extra)
        self.encode_btn = QtWidgets.QPushButton("Encode")
        self.encode_btn.setToolTip("Encode the session into SA/RA spike trains and features (rigctl encode)")
        self.encode_btn.clicked.connect(self.encode)
        self.run_btn = QtWidgets.QPushButton("Run analyses")
        self.run_btn.clicked.connect(self.run_analyses)
        self.cancel_btn = QtWidgets.QPushButton("Cancel")
        self.cancel_btn.clicked.connect(self.cancel)
        btns = QtWidgets.QHBoxLayout()
        for b in (self.encode_btn, self.run_btn, self.cancel_btn):
            btns.addWidget(b)
        self.progress = QtWidgets.QProgressBar()
        self.status = QtWidgets.QLabel("")
        self.status.setObjectName("analysis_status")
        self.status.setWordWrap(True)

        self.model_variant = QtWidgets.QComboBox()
        from rigctl.storage.encoded import MAIN_VARIANTS, REALTIME_VARIANTS

        # the variant registry's names (rigctl.storage.encoded), the paper's default model variant first
        self.model_variant.addItems(sorted(MAIN_VARIANTS + REALTIME_VARIANTS, key=lambda v: v != "speed_scaled"))
        self.model_pcs = QtWidgets.QSpinBox(minimum=1, maximum=200, value=25)
        self.train_btn = QtWidgets.QPushButton("Train model for the real-time view")
        self.train_btn.clicked.connect(self.train_model)
        mf = QtWidgets.QFormLayout()
        mf.addRow("Features", self.model_variant)
        mf.addRow("PCs", self.model_pcs)
        mf.addRow(self.train_btn)
        model_box = QtWidgets.QGroupBox("Texture classifier (PCA + LDA)")
        model_box.setLayout(mf)

        self.export_png = QtWidgets.QPushButton("View PNG...")
        self.export_svg = QtWidgets.QPushButton("View SVG...")
        for b in (self.export_png, self.export_svg):
            b.setToolTip("Save the view shown on the right (trial, accuracy vs PCs, Table 1 or confusion)")
        self.export_csv = QtWidgets.QPushButton("Tables CSV...")
        self.export_png.clicked.connect(lambda: self.export_figure("png"))
        self.export_svg.clicked.connect(lambda: self.export_figure("svg"))
        self.export_csv.clicked.connect(self._export_csv_dialog)
        ex = QtWidgets.QHBoxLayout()
        for b in (self.export_png, self.export_svg, self.export_csv):
            ex.addWidget(b)

        left = QtWidgets.QVBoxLayout()
        left.addWidget(self.open_btn)
        left.addWidget(self.file_label)
        left.addWidget(self.trials, 1)
        og = QtWidgets.QGroupBox("Analyses")
        ol = QtWidgets.QVBoxLayout(og)
        ol.addLayout(opts)
        ol.addLayout(btns)
        ol.addWidget(self.progress)
        ol.addWidget(self.status)
        left.addWidget(og)
        left.addWidget(model_box)
        left.addLayout(ex)
        self.trials.setMinimumHeight(170)  # several rows even in a short window (the panel scrolls instead)
        return side_panel(left, 400)

    def _build_trial_tab(self) -> Iterator[None]:
        """The trial view: raw traces and SA/RA rasters (left), one heat map per taxel layer (right); in steps."""
        # trial view: raw traces and SA/RA rasters (left), one heat map per taxel layer (right)
        trialw = QtWidgets.QWidget()
        tlay = QtWidgets.QHBoxLayout(trialw)
        self.trial_gl = pg.GraphicsLayoutWidget()
        self.trial_gl.setMinimumSize(*TRIAL_PLOTS_MIN_PX)
        self.trial_busy = QtWidgets.QProgressBar()  # indeterminate while a trial is read and encoded
        self.trial_busy.setRange(0, 0)
        self.trial_busy.setMaximumHeight(14)
        self.trial_busy.setTextVisible(False)
        self.trial_busy_label = QtWidgets.QLabel("")
        self.trial_busy_label.setObjectName("trial_busy")
        # wrapped: unwrapped, the first trial's long note asked for ~850 px and grew a 1280 px window to ~1490 px
        self.trial_busy_label.setWordWrap(True)
        self.trial_plot = self.trial_gl.addPlot(row=0, col=0, title="Raw taxel readings")
        self.trial_plot.setLabel("left", "ADC counts")
        # one time axis for readings, SA and RA: left axes of one width (the same data area), one x range
        self.trial_plot.getAxis("left").setWidth(TRIAL_AXIS_PX)
        self.trial_curves: list = []
        self.trial_rasters = {}
        yield
        for row, (key, title, colour) in enumerate([("sa", "SA spikes", "#1f77b4"), ("ra", "RA spikes", "#d62728")],
                                                   start=1):
            p = self.trial_gl.addPlot(row=row, col=0, title=title)
            p.setLabel("left", "taxel")
            p.getAxis("left").setWidth(TRIAL_AXIS_PX)
            c = pg.PlotCurveItem(pen=pg.mkPen(colour, width=1), connect="pairs")
            p.addItem(c)
            self.trial_rasters[key] = (p, c)
            yield
        self.trial_rasters["ra"][0].setLabel("bottom", "time in trial (s)")
        self.heat_gl = pg.GraphicsLayoutWidget()
        self.heat_gl.setFixedWidth(230)
        self.heat_plots: list = []  # (PlotItem, ImageItem) per layer
        tleft = QtWidgets.QVBoxLayout()
        busy_row = QtWidgets.QHBoxLayout()
        busy_row.addWidget(self.trial_busy_label, 3)
        busy_row.addWidget(self.trial_busy, 1)
        tleft.addLayout(busy_row)
        tleft.addWidget(self.trial_gl, 1)
        tlay.addLayout(tleft, 1)
        tlay.addWidget(self.heat_gl)
        self._set_trial_busy(None)
        self.views.addTab(trialw, "Trial")
        yield from self._trial_view_steps(PAPER_SENSOR)

    def _build_accuracy_tab(self) -> None:
        """Accuracy vs number of PCs (Fig. 3), one curve per variant of the chosen task."""
        accw = QtWidgets.QWidget()
        al = QtWidgets.QVBoxLayout(accw)
        self.task_combo = QtWidgets.QComboBox()
        self.task_combo.currentIndexChanged.connect(self._draw_curves)
        al.addWidget(self.task_combo)
        self.acc_plot = pg.PlotWidget(title="Accuracy vs number of PCs")
        self.acc_plot.setLabel("left", "accuracy (%)")
        self.acc_plot.setLabel("bottom", "number of PCs")
        self.acc_plot.showGrid(x=True, y=True, alpha=0.3)
        self.acc_plot.addLegend(offset=(-10, -10), labelTextSize="8pt")
        self.acc_plot.setMinimumHeight(RESULT_PLOT_MIN_PX)
        # the long description in a wrapping label: a plot title wider than the view set the plot's minimum width
        # and cut the title, the legend and the x axis at 1024x700
        self.acc_info = QtWidgets.QLabel("")
        self.acc_info.setWordWrap(True)
        al.addWidget(self.acc_info)
        al.addWidget(self.acc_plot, 1)
        self.views.addTab(accw, "Accuracy vs PCs (Fig. 3)")

    def _build_table1_tab(self) -> None:
        """Table 1: accuracy (%) of each task and variant at a chosen number of PCs."""
        tw = QtWidgets.QWidget()
        tl = QtWidgets.QVBoxLayout(tw)
        self.table_pcs = QtWidgets.QSpinBox(minimum=1, maximum=200, value=50)
        self.table_pcs.valueChanged.connect(self._fill_table)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(QtWidgets.QLabel("Accuracy (%) at PCs"))
        row.addWidget(self.table_pcs)
        row.addStretch(1)
        tl.addLayout(row)
        self.table1 = QtWidgets.QTableWidget(0, 0)
        self.table1.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        tl.addWidget(self.table1, 1)
        self.warn_label = QtWidgets.QLabel("")
        self.warn_label.setWordWrap(True)
        tl.addWidget(self.warn_label)
        self.views.addTab(tw, "Table 1")

    def _build_confusion_tab(self) -> None:
        """The confusion matrix of a chosen task and variant (rows: true, columns: predicted)."""
        cw = QtWidgets.QWidget()
        cl = QtWidgets.QVBoxLayout(cw)
        crow = QtWidgets.QHBoxLayout()
        self.conf_task = QtWidgets.QComboBox()
        self.conf_variant = QtWidgets.QComboBox()
        self.conf_task.currentIndexChanged.connect(self._draw_confusion)
        self.conf_variant.currentIndexChanged.connect(self._draw_confusion)
        crow.addWidget(self.conf_task)
        crow.addWidget(self.conf_variant)
        cl.addLayout(crow)
        # the long description lives in a wrapping label: a plot title wider than the view pushes the colour bar
        # out of the widget (pyqtgraph's title sets the minimum width of the plot's column)
        self.conf_info = QtWidgets.QLabel("rows: true, columns: predicted; row-normalised")
        self.conf_info.setWordWrap(True)
        cl.addWidget(self.conf_info)
        self.conf_plot = pg.PlotWidget(title="Confusion matrix")
        self.conf_plot.setMinimumHeight(RESULT_PLOT_MIN_PX)
        self.conf_plot.setAspectLocked(True)
        self.conf_plot.invertY(True)
        self.conf_img = pg.ImageItem(axisOrder="row-major")
        self.conf_img.setLookupTable(pg.colormap.get("viridis").getLookupTable(nPts=256))
        self.conf_plot.addItem(self.conf_img)
        self.conf_bar = pg.ColorBarItem(values=(0, 1), colorMap=pg.colormap.get("viridis"), interactive=False,
                                        colorMapMenu=False, width=14, label="fraction of the true class")
        self.conf_bar.setImageItem(self.conf_img, insert_in=self.conf_plot.plotItem)
        self.conf_plot.setLabel("left", "true")
        self.conf_plot.setLabel("bottom", "predicted")
        self.conf_counts: list = []  # a TextItem per cell: the trial count
        cl.addWidget(self.conf_plot, 1)
        self.views.addTab(cw, "Confusion")

    # ------------------------------------------------------------------------------------------------------
    # file and trials
    # ------------------------------------------------------------------------------------------------------
    def _build_trial_view(self, layout: SensorLayout) -> None:
        """One trace per channel, raster rows per channel and a heat map per layer (rows x cols) of ``layout``; the
        sensor shown already (another file of it): its plots again, emptied."""
        for _ in self._trial_view_steps(layout):
            pass

    def _trial_view_steps(self, layout: SensorLayout) -> Iterator[None]:
        """:meth:`_build_trial_view` in steps (a yield after each heat map)."""
        if layout == self.sensor_layout and self.heat_plots:
            for c in self.trial_curves:
                c.setData([], [])
            for la, (_, img) in zip(layout.layers, self.heat_plots):
                img.setImage(np.zeros((la.rows, la.cols)))
            self.heat_bar.setLevels((0, layout.adc_max))
            self.heat_bar.getAxis("left").setLabel("mean ADC counts")
            return
        self.sensor_layout = layout
        n = layout.n_channels
        for c in self.trial_curves:
            self.trial_plot.removeItem(c)
        self.trial_curves = [self.trial_plot.plot(pen=pg.mkPen(pg.intColor(k, max(n, 2)), width=1))
                             for k in range(n)]
        for p, _ in self.trial_rasters.values():
            p.setYRange(-0.5, n - 0.5, padding=0)
        self.trial_plot.setLabel("bottom", f"time in trial (s), {layout.sample_rate_hz:g} Hz")
        self.heat_gl.clear()
        self.heat_plots = []
        cmap = pg.colormap.get("viridis")
        lut = cmap.getLookupTable(nPts=256)
        for i, la in enumerate(layout.layers):
            p = self.heat_gl.addPlot(row=i, col=0, title=f"{la.name} ({la.receptor})" if la.receptor else la.name)
            p.setAspectLocked(True)
            p.invertY(True)
            p.hideAxis("bottom")
            p.hideAxis("left")
            p.setMouseEnabled(x=False, y=False)
            img = pg.ImageItem(np.zeros((la.rows, la.cols)), axisOrder="row-major")
            img.setLookupTable(lut)
            p.addItem(img)
            p.setRange(xRange=(0, la.cols), yRange=(0, la.rows), padding=0)
            p.disableAutoRange()
            if la.n_channels <= 64:  # each taxel's number in its cell
                add_taxel_numbers(p, la.rows, la.cols, layout.layer_channels(i).start)
            self.heat_plots.append((p, img))
            yield
        # one colour bar for every map: mean ADC counts of the trial (an encoded file without its session: SA
        # spike counts)
        self.heat_bar = pg.ColorBarItem(values=(0, layout.adc_max), colorMap=cmap, interactive=False,
                                        colorMapMenu=False, width=10, label="mean ADC counts")
        self.heat_gl.addItem(self.heat_bar, row=0, col=1, rowspan=max(1, len(layout.layers)))

    def _browse(self):
        from rigctl_gui.dialogs import choose_path  # non-modal: STOP stays usable

        return choose_path(self, "open", "Open", self._session_dir(), "HDF5 (*.h5 *.hdf5)", self.open)

    def _session_dir(self) -> str:
        """Where the Open dialog starts: the last file opened here, else the sessions' output folder, else the working
        folder; never empty (an empty start opened Qt's last-visited folder: protocols/ after a protocol was
        opened)."""
        for key in ("dirs/analysis", "dirs/output"):
            d = str(self.main.settings.value(key, "") or "")
            if d and os.path.isdir(d):
                return d
        return os.getcwd()

    def open(self, path: str) -> None:
        """Show a session or encoded file's trials."""
        try:
            kind = file_kind(path)
        except Exception as exc:  # noqa: BLE001
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>cannot open {_html(path)}: {_html(exc)}</span>")
            return
        if kind == "unknown":
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>{_html(path)} is neither a session nor an encoded "
                                "file</span>")
            return
        self.main.settings.setValue("dirs/analysis", os.path.dirname(path))
        self.path, self.kind = path, kind
        self.encoded_path = path if kind == "encoded" else None
        self._session_range = None
        self._wanted_tid = self.shown_tid = None
        rows, layout = self._trial_rows()
        self._build_trial_view(layout)
        for _p, raster in self.trial_rasters.values():  # the previous file's trial is not this file's
            raster.setData([], [])
        self.trial_plot.setTitle("Raw taxel readings")
        self.trials.clearSelection()  # a row selected in the previous file would not show its trial here
        self.trials.setRowCount(len(rows))
        for r, vals in enumerate(rows):
            for c, v in enumerate(vals):
                self.trials.setItem(r, c, QtWidgets.QTableWidgetItem(str(v)))
        self.trials.resizeColumnsToContents()
        self.file_label.setText(f"<b>{os.path.basename(path)}</b> ({kind}, {len(rows)} trials; sensor "
                                f"{layout.shape_text}, {layout.n_channels} taxels, {layout.sample_rate_hz:g} Hz)")
        self.status.setText("select a trial to see it; Encode / Run analyses for the paper's results")
        self._verdict_job = _verdicts_job(path) if kind == "session" else None
        self._update_buttons()

    def _show_verdicts(self, job: Job) -> None:
        """The trial validator's verdicts (:func:`_verdicts_job`) in the table: an excluded trial's status reads
        ``excluded``, its reason in the cell's tooltip; nothing when the session was closed or another opened."""
        self._verdict_job = None
        if job.error or job.path != self.path:
            return
        cells = ((r, self.trials.item(r, 0)) for r in range(self.trials.rowCount()))
        rows = {int(item.text()): r for r, item in cells if item is not None}
        for tid, why in job.result.items():
            if tid in rows:
                item = QtWidgets.QTableWidgetItem("excluded")
                item.setToolTip(f"trial {tid} is excluded: {why}")
                self.trials.setItem(rows[tid], 4, item)

    def _trial_rows(self) -> tuple[list[tuple], SensorLayout]:
        """Table rows (trial, texture, speed, force, status) and the file's sensor layout (a file is open)."""
        assert self.path is not None
        if self.kind == "session":
            from rigctl.storage.session import TrialStatus, open_session

            with open_session(self.path) as s:
                plan = s.plan
                rows = [(int(r["trial_id"]), _txt(r["texture"]), f"{float(r['speed_mm_s']):g}",
                         f"{float(r['force_g']):g}", TrialStatus(int(r["status"])).name.lower()) for r in plan]
                return rows, s.layout
        from rigctl.storage.encoded import open_encoded

        with open_encoded(self.path) as ef:  # every column of rigctl.storage.encoded.TRIAL_COLUMNS is there
            cols, layout = ef.trials, ef.layout
        return [(int(tid), tex, f"{spd:g}", f"{frc:g}", "encoded") for tid, tex, spd, frc in
                zip(cols["trial_id"], cols["texture"], cols["speed_mm_s"], cols["force_g"])], layout

    def _trial_selected(self) -> None:
        rows = self.trials.selectionModel().selectedRows()
        if rows:
            self.show_trial(rows[0].row())

    def show_trial(self, row: int) -> None:
        """Draw trial ``row`` of the table: raw readings (session) and SA/RA rasters (encoded in a thread for a
        session file, read from ``/spikes`` for an encoded file).

        The plot always ends on the selected trial: while one trial is being read, a newer selection is remembered
        and read next (the trials browsed past in between are skipped), and a finished trial that is no longer
        selected is not drawn."""
        item = self.trials.item(row, 0)
        if self.path is None or item is None:
            return
        self._wanted_tid = int(item.text())
        if self._trial_job is None:
            self._start_trial_job(self._wanted_tid)

    def _start_trial_job(self, tid: int) -> None:
        path, kind = self.path, self.kind
        assert path is not None  # show_trial starts a job only with a file open
        first = self._session_range is None and kind == "session"

        def work(job):
            import numpy as np

            if kind == "session":  # the library encodes it (rigctl.operations.trial_spikes)
                from rigctl.operations import session_taxel_range, trial_spikes

                rng = self._session_range
                if rng is None:  # the session's per-taxel range (paper: over the whole dataset), read once
                    rng = self._session_range = session_taxel_range(path)
                t = trial_spikes(path, tid, taxel_range=rng)
                return (t.readings, t.sa, t.ra, t.duration_s, "")
            from rigctl.encoding.spikes import SpikeTrains
            from rigctl.storage.encoded import open_encoded

            with open_encoded(path) as ef:
                i = int(np.flatnonzero(ef.trials["trial_id"] == tid)[0])
                # SA + RA trains of a variant whose spikes are stored (the real-time variants hold SA only)
                have = [v for v in ef.spike_variants if not v.startswith("realtime")]
                if not have:
                    raise ValueError(f"{os.path.basename(path)} stores no SA/RA spike trains (encoded with --no-spikes?): "
                                     "open its session file to see this trial's spikes")
                name = "original" if "original" in have else have[0]
                st = SpikeTrains(*ef.spikes(name, trials=slice(i, i + 1)))  # this trial's rows only
                duration_s = float(ef.trials["duration_s"][i])
            x, note = _source_readings(path, tid)
            if x is not None:
                duration_s = len(x) / self.sensor_layout.sample_rate_hz
            n_tr = st.n_trains
            half = n_tr // 2
            return (x, [st.train(0, k) for k in range(half)], [st.train(0, half + k) for k in range(half)],
                    duration_s, note)

        self._trial_job = Job(work, name="trial")
        self._trial_job.tid = tid
        self._trial_job.path = path
        self._trial_job.start()
        self._set_trial_busy(f"trial {tid}: reading and encoding"
                             + (" (the first trial also takes each taxel's range over the whole session and "
                                "compiles the encoder: a few seconds)" if first else "") + "...")
        self.views.setCurrentIndex(0)

    def _set_trial_busy(self, text: str | None) -> None:
        """Show (``text``) or hide (None) the trial view's busy indicator."""
        self.trial_busy_label.setText(text or "")
        self.trial_busy.setVisible(text is not None)
        self.trial_busy_label.setVisible(text is not None)

    def _trial_finished(self, job: Job) -> None:
        """A trial job ended: draw it if it is still the selected trial of the open file, else read the selected
        one."""
        self._trial_job = None
        if job.path == self.path and job.tid == self._wanted_tid:
            self._set_trial_busy(None)
            self._draw_trial(job)
        elif self._wanted_tid is not None:
            self._start_trial_job(self._wanted_tid)
        else:
            self._set_trial_busy(None)

    def _draw_trial(self, job: Job) -> None:
        if job.error:  # (an excluded trial: the validator's reason) the view shows no other trial in its place
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>trial {job.tid}: {_html(job.error)}</span>")
            self.shown_tid = None
            for c in self.trial_curves:
                c.setData([], [])
            return
        self.shown_tid = job.tid
        x, sa, ra, duration_s, note = job.result
        layout = self.sensor_layout
        if x is not None:
            t = np.arange(len(x)) / layout.sample_rate_hz
            for k, c in enumerate(self.trial_curves):
                c.setData(t, x[:, k])
            mean = np.asarray(x, float).mean(axis=0)
            levels, label = (0.0, float(layout.adc_max)), "mean ADC counts"
            values = mean
        else:
            for c in self.trial_curves:
                c.setData([], [])
            # no readings: the heat maps show each taxel's SA spike count
            values = np.array([len(v) for v in sa], float)
            levels, label = (0.0, max(1.0, float(values.max()) if values.size else 1.0)), "SA spikes in the trial"
        if len(values) == layout.n_channels:
            for li, (la, (_, img)) in enumerate(zip(layout.layers, self.heat_plots)):
                ch = layout.layer_channels(li)
                img.setImage(values[ch.start:ch.stop].reshape(la.rows, la.cols), levels=levels)
        self.heat_bar.setLevels(levels)
        self.heat_bar.getAxis("left").setLabel(label)  # (where the constructor put it)
        # one x range for readings, SA and RA: the whole trial (set, never each plot's own auto range)
        if not duration_s or not np.isfinite(duration_s):
            ends = [float(v.max()) for v in (*sa, *ra) if len(v)]
            duration_s = max(ends) if ends else 1.0
        for p in (self.trial_plot, *(q for q, _ in self.trial_rasters.values())):
            p.disableAutoRange(axis="x")
            p.setXRange(0.0, float(duration_s), padding=0.01)
        self.trial_x_range = (0.0, float(duration_s))
        for key, trains in (("sa", sa), ("ra", ra)):
            ts = np.concatenate(trains) if trains else np.zeros(0)
            rows = np.concatenate([np.full(len(v), k, float) for k, v in enumerate(trains)]) if trains else ts
            seg = np.empty((2 * len(ts), 2))
            seg[0::2, 0] = seg[1::2, 0] = ts
            seg[0::2, 1] = rows - 0.4
            seg[1::2, 1] = rows + 0.4
            self.trial_rasters[key][1].setData(seg[:, 0], seg[:, 1], connect="pairs")
        self.trial_plot.setTitle(f"Trial {job.tid}: raw taxel readings" + (f" ({note})" if note else ""))
        n_sa, n_ra = sum(len(v) for v in sa), sum(len(v) for v in ra)
        self.status.setText(f"trial {job.tid}: {n_sa} SA and {n_ra} RA spikes")

    # ------------------------------------------------------------------------------------------------------
    # background work
    # ------------------------------------------------------------------------------------------------------
    def _busy(self) -> bool:
        return self.job is not None and not self.job.done

    def encode(self) -> None:
        from rigctl_gui.analysis_jobs import encoded_path_for

        if self.kind != "session" or self._busy() or self.path is None:
            return
        out = encoded_path_for(self.path)
        self._start(ProcessJob("rigctl_gui.analysis_jobs:encode", session_path=self.path, out_path=out), "encoding")

    def _build_cv_groups(self) -> QtWidgets.QWidget:
        """How the textures/groups folds split the trials (``rigctl analyze --cv-groups``): random trials, or whole
        recordings / sessions / time blocks of each recording held out together (train and test never share one)."""
        self.cv_groups = QtWidgets.QComboBox()
        for text, spec in (("random trials", None), ("whole recordings", "recording"),
                           ("whole sessions", "session"), ("time blocks", "block")):
            self.cv_groups.addItem(text, spec)
        self.cv_groups.setToolTip("Random folds over trials from one recording measure how well a recording "
                                  "recognises itself; holding out whole recordings, sessions or time blocks keeps "
                                  "each on one side of every split (rigctl analyze --cv-groups)")
        self.cv_blocks = QtWidgets.QSpinBox(minimum=2, maximum=20, value=4)
        self.cv_blocks.setSuffix(" per recording")
        self.cv_blocks.setEnabled(False)
        self.cv_groups.currentIndexChanged.connect(
            lambda _i: self.cv_blocks.setEnabled(self.cv_groups.currentData() == "block"))
        box = QtWidgets.QWidget()
        row = QtWidgets.QHBoxLayout(box)
        row.setContentsMargins(0, 0, 0, 0)
        row.addWidget(self.cv_groups, 1)
        row.addWidget(self.cv_blocks)
        return box

    def cv_groups_spec(self) -> str | None:
        """The chosen split as ``--cv-groups`` spells it (None: random trials)."""
        spec = self.cv_groups.currentData()
        return f"block:{self.cv_blocks.value()}" if spec == "block" else spec

    def run_analyses(self) -> None:
        if self.path is None or self._busy():
            return
        spec = self.cv_groups_spec()
        self._start(ProcessJob("rigctl_gui.analysis_jobs:analyse", path=self.encoded_path or self.path,
                               cv=self.do_cv.isChecked(), extrapolation=self.do_extra.isChecked(),
                               repeats=self.repeats.value(), n_pcs=self.n_pcs.value(),
                               per_texture=self.per_texture.value(), cv_groups=spec), "analyses")
        if self.do_cv.isChecked() and spec:
            self._log(f"textures/groups test folds hold out {self.cv_groups.currentText()} ({spec})")

    def train_model(self) -> None:
        path = self.encoded_path
        if path is None or self._busy():
            self.status.setText("encode the file first (or open an encoded file)")
            return
        self._start(ProcessJob("rigctl_gui.analysis_jobs:train_classifier", path=path,
                               variant=self.model_variant.currentText(), n_pcs=self.model_pcs.value()), "training")

    def _log(self, text: str, *, error: bool = False) -> None:
        """Into the main window's event log (every job and export is logged)."""
        import logging

        notify = getattr(self.main, "notify", None)
        if notify is not None:
            notify(text, level=logging.ERROR if error else logging.INFO, source="analysis")

    def _start(self, job, kind: str) -> None:
        self._log(f"{kind} started ({os.path.basename(str(self.encoded_path or self.path))})")
        self.job, self._job_kind = job, kind
        self.progress.setRange(0, 0)  # busy from the first moment (spawning the worker takes seconds)
        self.status.setText(f"{kind}: starting...")
        job.start()
        self._update_buttons()

    def cancel(self) -> None:
        if self._busy():
            self.job.cancel()
            self.status.setText(f"{self._job_kind} cancelled")
            self._log(f"{self._job_kind} cancelled")
            self.job = None
        self.progress.setRange(0, 100)
        self.progress.setValue(0)
        self._update_buttons()

    def refresh(self) -> None:
        """Pull the trial job and the background job (the main window's timer calls this). Whatever a finished job
        brings, the outcome is shown in the tab and the panel is never left busy: an error while showing a result
        is reported in the status line, not raised into the event loop."""
        if self.building:  # (a staged build: nothing to pull yet)
            return
        vj = self._verdict_job
        if vj is not None and vj.done:
            self._show_verdicts(vj)
        tj = self._trial_job
        if tj is not None and tj.done:
            try:
                self._trial_finished(tj)
            except Exception as exc:  # noqa: BLE001 - shown in the window; the tab stays usable
                self._set_trial_busy(None)
                self._error(f"trial {tj.tid} could not be shown", exc)
        job = self.job
        if job is None:
            return
        job.poll()
        self._show_progress(job)
        if not job.done:
            self.status.setText(f"{self._job_kind}: {_html(job.message)}")
            return
        self.job = None
        try:
            self._finish_job(job)
        except Exception as exc:  # noqa: BLE001 - shown in the window; the tab stays usable
            self._error(f"{self._job_kind}: the result could not be shown", exc)
        finally:
            self.progress.setRange(0, 100)
            self._update_buttons()

    def _show_progress(self, job) -> None:
        """A busy bar that moves: indeterminate until the job reports a fraction (model training reports none)."""
        if job.fraction > 0:
            self.progress.setRange(0, 100)
            # 100 % only once the job is done (its last stage, e.g. fitting force coefficients, reports no fraction)
            self.progress.setValue(min(99, int(100 * job.fraction)))
        else:
            self.progress.setRange(0, 0)

    def _error(self, what: str, exc: BaseException) -> None:
        import logging

        logging.getLogger(__name__).error("%s", what, exc_info=exc)
        self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>{_html(what)}: {_html(describe_error(exc))}</span>")

    def _finish_job(self, job) -> None:
        if self._job_kind != "analyses" or job.error:  # analyses: logged by show_results, as the panel says
            self._log(f"{self._job_kind} failed: {job.error}" if job.error else f"{self._job_kind} finished"
                      + (f": {job.result}" if isinstance(job.result, str) else ""), error=bool(job.error))
        if job.error:
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>{self._job_kind} failed: {_html(job.error)}</span>")
        elif self._job_kind == "encoding":
            self.encoded_path = job.result
            self.status.setText(f"encoded into {_html(job.result)}")
        elif self._job_kind == "analyses":
            results, self.encoded_path = job.result
            self.progress.setRange(0, 100)
            self.progress.setValue(100)
            self.show_results(results)
        elif self._job_kind == "training":
            self.progress.setRange(0, 100)
            self.progress.setValue(100)
            saved = job.result
            self.status.setText(f"trained a model, saved to {_html(saved)}; loading it for the real-time view")

            def loaded(model) -> None:
                clf = model[-1]
                self.status.setText(f"trained a {clf.variant} PCA+LDA pipeline ({clf.n_pcs_} PCs, {len(clf.classes_)} "
                                    f"textures), saved to {_html(saved)}; the real-time view uses it")

            self.main.classify.load_model(saved, on_loaded=loaded)

    def _update_buttons(self) -> None:
        busy = self._busy()
        self.encode_btn.setEnabled(not busy and self.kind == "session")
        self.run_btn.setEnabled(not busy and self.path is not None)
        self.train_btn.setEnabled(not busy and self.path is not None)
        self.cancel_btn.setEnabled(busy)
        for b in (self.export_png, self.export_svg):  # the trial view can be exported before any analysis
            b.setEnabled(self.path is not None)
        self.export_csv.setEnabled(self.results is not None)

    # ------------------------------------------------------------------------------------------------------
    # results
    # ------------------------------------------------------------------------------------------------------
    def show_results(self, res) -> None:
        """Show analysis results (:class:`rigctl.analysis.results.TaskResults`); results without a single curve (a
        file too small for any task, e.g. one trial) leave the previous results and say why in the status line."""
        from rigctl.analysis.results import task_title

        tasks = [t for t, by_v in res.curves.items() if by_v]
        if not tasks:
            why = "; ".join(res.warnings) or "the tasks produced no results"
            name = os.path.basename(str(self.encoded_path or self.path))
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>no analysis could run on {_html(name)}: {_html(why)}</span>")
            self._log(f"no analysis could run on {name}: {why}", error=True)
            return
        self.results = res
        for combo in (self.task_combo, self.conf_task):
            combo.blockSignals(True)
            combo.clear()
            for t in tasks:
                combo.addItem(task_title(t), t)
            combo.blockSignals(False)
        from rigctl.analysis.data import variant_title

        variants = sorted({v for by_v in res.curves.values() for v in by_v}, key=_variant_order)
        self.conf_variant.blockSignals(True)
        self.conf_variant.clear()
        for v in variants:  # the paper's names shown, the registry's kept as data
            self.conf_variant.addItem(variant_title(v), v)
        self.conf_variant.blockSignals(False)
        n_max = max(c.acc.shape[1] for by_v in res.curves.values() for c in by_v.values())
        self.table_pcs.setMaximum(n_max)
        self.table_pcs.setValue(min(self.table_pcs.value(), n_max))
        self._draw_curves()
        self._fill_table()
        self._draw_confusion()
        self.warn_label.setText("<br>".join(res.warnings))
        self.views.setCurrentIndex(1)
        n = sum(len(v) for v in res.curves.values())
        done = (f"analyses done: {len(tasks)} task(s), {n} curves"
                + (f"; {len(res.warnings)} note(s) under Table 1" if res.warnings else ""))
        self.status.setText(done)
        self._log(done)

    def _draw_curves(self) -> None:
        from rigctl.analysis.data import variant_title
        from rigctl.analysis.results import task_title

        self.acc_plot.clear()
        legend = self.acc_plot.plotItem.legend
        if legend is not None:
            legend.clear()
        res, task = self.results, self.task_combo.currentData()
        if res is None or task is None:
            return
        for v in sorted(res.curves[task], key=_variant_order):
            c = res.curves[task][v]
            colour = VARIANT_COLOURS.get(v, "#888")
            x, m, s = c.pcs.astype(float), 100 * c.mean, 100 * c.sd
            self.acc_plot.addItem(pg.ErrorBarItem(x=x, y=m, height=2 * s, pen=pg.mkPen(colour, width=1), beam=0.3))
            self.acc_plot.plot(x, m, pen=pg.mkPen(colour, width=2), symbol="o", symbolSize=4, symbolBrush=colour,
                               symbolPen=None, name=variant_title(v))
        from rigctl.analysis import report

        chance = report.chance_pct(res, task)
        self.acc_chance = pg.InfiniteLine(pos=chance, angle=0, pen=pg.mkPen("#888", width=1, style=QtCore.Qt.PenStyle.DotLine),
                                          label=f"chance {chance:.1f} %", labelOpts={"position": 0.95, "color": "#888"})
        self.acc_plot.addItem(self.acc_chance)
        self.acc_plot.setTitle(f"{task_title(task)}")
        self.acc_info.setText(f"Accuracy vs number of PCs: mean, {report.ERROR_BARS}; {report.n_text(res, task)}; "
                              f"dotted: chance (1 / classes = {chance:.1f} %)")

    def _fill_table(self) -> None:
        from rigctl.analysis import report
        from rigctl.analysis.data import variant_title
        from rigctl.analysis.results import task_title

        res = self.results
        if res is None:
            return
        grid = report.table1(res, self.table_pcs.value())
        variants = sorted({v for row in grid.values() for v in row}, key=_variant_order)
        self.table1.setRowCount(len(grid))
        self.table1.setColumnCount(len(variants))
        # two-line headers: the whole grid fits the view at 1024x700 (one-line names cut off the last column)
        self.table1.setHorizontalHeaderLabels([_two_lines(variant_title(v), 12) for v in variants])
        self.table1.setVerticalHeaderLabels([task_title(t).replace(" (Fig.", "\n(Fig.") for t in grid])
        for r, (_task, row) in enumerate(grid.items()):
            for c, v in enumerate(variants):
                if v in row:
                    mu, sd = row[v]
                    text = f"{mu:.1f} +- {sd:.1f}" if np.isfinite(mu) else "-"  # no test trials: never "nan"
                    self.table1.setItem(r, c, QtWidgets.QTableWidgetItem(text))
        self.table1.resizeColumnsToContents()
        self.table1.resizeRowsToContents()

    def _draw_confusion(self) -> None:
        """The confusion matrix of the chosen task and variant: colour = fraction of the true class (row-normalised,
        with a colour bar), each cell's trial count written in it, the paper's names for task and variant."""
        from rigctl.analysis import report
        from rigctl.analysis.data import variant_title
        from rigctl.analysis.results import task_title

        for t in self.conf_counts:
            self.conf_plot.removeItem(t)
        self.conf_counts = []
        res = self.results
        task, v = self.conf_task.currentData(), self.conf_variant.currentData()
        if res is None or task is None or v not in res.curves.get(task, {}):
            self.conf_img.clear()
            return
        c = res.curves[task][v]
        counts = np.asarray(c.confusion)
        cm = counts.astype(float) / np.maximum(counts.sum(axis=1, keepdims=True), 1)
        self.conf_img.setImage(cm, levels=(0, 1))
        ax = [(i + 0.5, str(lab)) for i, lab in enumerate(c.classes)]
        self.conf_plot.getAxis("bottom").setTicks([ax])
        self.conf_plot.getAxis("left").setTicks([ax])
        if len(c.classes) <= 30:  # beyond that the numbers no longer fit their cells
            for (r, k), n in np.ndenumerate(counts):
                t = pg.TextItem(str(int(n)), color="k" if cm[r, k] > 0.6 else "w", anchor=(0.5, 0.5))
                t.setPos(k + 0.5, r + 0.5)
                self.conf_plot.addItem(t)
                self.conf_counts.append(t)
        self._fit_conf_counts()
        # a classifier off its training manifold piles its predictions on one class
        pile = report.prediction_collapse(res, tasks=(task,)).get(task, {}).get(v)
        pile_text = ("no test trials" if pile is None else f"most predicted: {pile.top_class}, "
                     f"{100 * pile.top_share:.0f} % of the test trials (even: {100 * pile.even_share:.0f} %)")
        self.conf_plot.setTitle(f"{task_title(task)}, {variant_title(v)}")
        self.conf_info.setText(f"Confusion at {c.confusion_pcs} PCs (rows true, columns predicted; colour: fraction "
                               f"of the true class; trials summed over {c.acc.shape[0]} repetitions); {pile_text}")

    def _fit_conf_counts(self) -> None:
        """Size the confusion counts to their cells (three-digit counts spilled into the next cell): the largest
        font, up to 10 px, whose widest count takes at most 85 % of a cell's width on screen and whose line fits its
        height; the counts are hidden when a cell is too small for 5 px."""
        if not getattr(self, "conf_counts", None):  # (a staged build: not there yet)
            return
        n = max(1, self.conf_img.image.shape[0] if self.conf_img.image is not None else 1)
        vb = self.conf_plot.plotItem.vb
        cell_px = abs(vb.mapViewToScene(QtCore.QPointF(1, 0)).x() - vb.mapViewToScene(QtCore.QPointF(0, 0)).x())
        if not cell_px > 0:  # not laid out yet
            cell_px = min(vb.width(), vb.height()) / n
        widest = max((t.textItem.toPlainText() for t in self.conf_counts), key=len)
        font = self.conf_counts[0].textItem.font()
        size = 10
        while size >= 5:
            font.setPixelSize(size)
            fm = QtGui.QFontMetrics(font)
            if fm.horizontalAdvance("8" * len(widest)) <= 0.85 * cell_px and fm.height() <= cell_px:
                break
            size -= 1
        for t in self.conf_counts:
            t.setVisible(size >= 5)
            if size >= 5:
                f = t.textItem.font()
                f.setPixelSize(size)
                t.setFont(f)

    def resizeEvent(self, ev):  # noqa: N802 - Qt override
        super().resizeEvent(ev)
        QtCore.QTimer.singleShot(0, self._fit_conf_counts)  # once the plot has its new size

    # ------------------------------------------------------------------------------------------------------
    # export
    # ------------------------------------------------------------------------------------------------------
    def export_figure(self, fmt: str, path: str | None = None) -> str | None:
        """Save the view now shown (the trial, accuracy vs PCs, Table 1 or the confusion matrix: what you see is
        what is exported) as PNG (rendered at least :data:`EXPORT_PNG_WIDTH_PX` wide) or SVG (QSvgGenerator:
        pyqtgraph 0.14's SVG exporter fails on Qt 6.11 paths).

        A path without an extension gets ``.png`` / ``.svg`` (:func:`export_path`); another extension, or an
        existing file the added extension would replace, is refused with a message. Returns the path written, or
        None (refused, cancelled, or the file could not be written: the status line says which)."""
        from PySide6 import QtGui
        from PySide6.QtSvg import QSvgGenerator

        view = self.views.tabText(self.views.currentIndex())
        if path is None:  # ask (non-modal: STOP stays usable); the export runs when a name is chosen
            from rigctl_gui.dialogs import choose_path

            choose_path(self, "save", f"Export the {view} view", self._export_dir(), f"{fmt.upper()} (*.{fmt})",
                        lambda chosen: self.export_figure(fmt, chosen))
            return None
        try:
            path = export_path(path, fmt)
        except ValueError as exc:
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>not saved: {_html(exc)}</span>")
            return None
        page = self.views.currentWidget()
        size = page.size()
        if fmt == "png":
            scale = max(1.0, EXPORT_PNG_WIDTH_PX / max(size.width(), 1))
            img = QtGui.QImage(int(size.width() * scale), int(size.height() * scale), QtGui.QImage.Format.Format_ARGB32)
            img.fill(QtGui.QColor("white"))
            painter = QtGui.QPainter(img)
            painter.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing)
            painter.scale(scale, scale)
            page.render(painter, QtCore.QPoint(0, 0))
            painter.end()
            img.save(path)
        else:
            gen = QSvgGenerator()
            gen.setFileName(path)
            gen.setSize(size)
            gen.setViewBox(QtCore.QRect(0, 0, size.width(), size.height()))
            gen.setTitle(view)
            painter = QtGui.QPainter(gen)
            page.render(painter, QtCore.QPoint(0, 0))
            painter.end()
        if not os.path.isfile(path) or os.path.getsize(path) == 0:
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>could not write {_html(path)}</span>")
            return None
        self.status.setText(f"saved the {_html(view)} view to {_html(path)}")
        self._log(f"the {view} view exported to {path}")
        return path

    def _export_dir(self) -> str:
        return os.path.dirname(self.encoded_path or self.path or "") or ""

    def _export_csv_dialog(self) -> None:
        from rigctl_gui.dialogs import choose_path  # non-modal: STOP stays usable

        choose_path(self, "save", "Export tables", self._export_dir(), "CSV (*.csv)", self.export_csv_to)

    def export_csv_to(self, path: str) -> list[str]:
        """Write the curves (long format, :func:`rigctl.analysis.report.to_csv`) to ``path`` and the Table 1 grid
        to ``<path stem>_table1.csv``; returns both paths."""
        import csv

        from rigctl.analysis import report

        try:
            path = export_path(path, "csv")
        except ValueError as exc:
            self.status.setText(f"<span style='color:{on_window(ERROR, self)}'>not saved: {_html(exc)}</span>")
            return []
        with open(path, "w", newline="") as f:
            f.write(report.to_csv(self.results))
        grid = report.table1(self.results, self.table_pcs.value())
        tpath = os.path.splitext(path)[0] + "_table1.csv"
        with open(tpath, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["task", "variant", "n_pcs", "mean_percent", "sd_percent"])
            for task, row in grid.items():
                for v, (mu, sd) in row.items():
                    w.writerow([task, v, self.table_pcs.value(), f"{mu:.3f}", f"{sd:.3f}"])
        self.status.setText(f"saved {path} and {tpath}")
        self._log(f"tables exported to {path} and {tpath}")
        return [path, tpath]


def _two_lines(text: str, longest: int) -> str:
    """``text`` broken at its last space when it is longer than ``longest`` characters (a table header)."""
    if len(text) <= longest or " " not in text:
        return text
    head, _, tail = text.rpartition(" ")
    return f"{head}\n{tail}"


def _verdicts_job(path: str) -> Job:
    """A started job whose result is the trial validator's excluded trials of session ``path`` (id -> reason,
    :func:`rigctl.storage.validate.usable_trials`, the check every command makes): it reads the session, so not on
    the GUI thread."""
    def work(_job: Job) -> dict[int, str]:
        from rigctl.storage.session import open_session
        from rigctl.storage.validate import usable_trials

        with open_session(path) as s:
            return dict(usable_trials(s).excluded)

    job = Job(work, name="verdicts")
    job.path = path
    job.start()
    return job


def _source_readings(encoded_path: str, tid: int) -> tuple[np.ndarray | None, str]:
    """The raw readings of trial ``tid`` from the session an encoded file was encoded from
    (:func:`rigctl.analysis.model.session_of`: its ``source_session``, else a file of that name beside it), and a
    note for the plot's title ("" when found; else why there are none)."""
    from rigctl.analysis.model import session_of
    from rigctl.storage.session import open_session

    try:
        session, _params = session_of(encoded_path)
        with open_session(session) as s:
            return s.usable_trial(int(tid)).taxels, ""  # the one validator: an excluded trial's readings not shown
    except FileNotFoundError:
        return None, "its session file is not found: open the session to see them"
    except Exception as exc:  # noqa: BLE001 - the spikes are still shown; the title says why there are no readings
        return None, f"not read from the session: {describe_error(exc)}"


def export_path(path: str, fmt: str) -> str:
    """The file an export of format ``fmt`` ("png", "svg", "csv") writes for the chosen ``path``: ``path`` itself
    when it ends in ``.fmt`` (any case), ``path + ".fmt"`` when it has no extension.

    Raises ValueError (the message says why) for another extension (``fig.jpg`` is not written as PNG) and when the
    added extension names a file that exists (the user chose ``fig``, not to replace ``fig.png``)."""
    root, ext = os.path.splitext(path)
    if ext.lower() == f".{fmt}":
        return path
    if ext:
        raise ValueError(f"{os.path.basename(path)} does not end in .{fmt}: choose a .{fmt} file name")
    out = f"{path}.{fmt}"
    if os.path.exists(out):
        raise ValueError(f"{os.path.basename(out)} already exists: choose it by name to replace it")
    return out


def _txt(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _variant_order(v: str) -> int:
    from rigctl.analysis.data import VARIANTS

    order = list(VARIANTS)
    return order.index(v) if v in order else len(order)
