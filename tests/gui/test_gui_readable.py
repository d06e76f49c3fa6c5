"""The app stays readable at Qt's 1.5x scale on a small screen and with a dark desktop palette (issue 38 part 8).

1.5x on a 1280x800 screen is a window of 853x533 of Qt's pixels (``QT_SCALE_FACTOR=1.5`` draws every one of them as
1.5 screen pixels; the layout is the same as at 1x in a window of that size, which is what these tests use: the
test process's QApplication is already made, and the factor is read only when one is made). There the Live view's
traces were squeezed to nothing by four title rows and four time axes, and its colour bar was pushed out of the
window by the traces' titles; the docs' screenshots (docs/gui.md) are taken at the real factor.

The dark palette is KDE Breeze Dark's (:func:`rigctl_gui.colours.dark_palette`): every text on screen is judged by
its WCAG contrast ratio (>= 4.5) against the background it is drawn on, measured on the rendered pixels of each
label, and from the colours of the event log's lines.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from PySide6 import QtCore, QtGui, QtWidgets

from rigctl_gui.colours import MIN_CONTRAST, contrast_ratio, dark_palette
from rigctl_gui.events import wait_for

from .conftest import holds_within

#: 1280x800 screen pixels at Qt's scale factor 1.5, in Qt's pixels
SCALED_1280x800 = (853, 533)
#: a whole 1024x700 screen at Qt's scale factor 1.5, in Qt's pixels: the window's smallest size must fit it
SCALED_1024x700 = (683, 466)


def _live_geometry(window, qapp, size):
    from rigctl_gui.live_view import MIN_TRACE_PX

    window.resize(*size)
    window.tabs.setCurrentWidget(window.live)
    live = window.live
    # the layout settles and the text is fitted (a loaded machine: up to 5 s; the assertions judge what it shows)
    wait_for(qapp, lambda: not live._fit_timer.isActive() and min(p.vb.height() for p in live.trace_plots)
             >= MIN_TRACE_PX, 5)
    wait_for(qapp, lambda: False, 0.2)
    return live


@pytest.mark.parametrize("size", [SCALED_1024x700, SCALED_1280x800, (1024, 700)],
                         ids=["1.5x-1024x700", "1.5x-1280x800", "1024x700"])
def test_the_live_view_keeps_readable_plots_and_its_colour_bar(inprocess_window, qapp, size):
    """Each trace plot's data area is at least 56 px tall and each raster's 36 px (the view scrolls below that),
    every title fits its plot, the raster's tick labels never overlap, and the colour bar with its labels lies
    inside the plots' widget."""
    from rigctl_gui.live_view import MIN_RASTER_PX, MIN_TRACE_PX

    live = _live_geometry(inprocess_window, qapp, size)
    try:
        assert [round(p.vb.height()) >= MIN_TRACE_PX for p in live.trace_plots] == [True] * len(live.trace_plots), \
            [p.vb.height() for p in live.trace_plots]
        assert all(p.vb.height() >= MIN_RASTER_PX - 0.5 for p in live.raster_plots.values()), \
            [p.vb.height() for p in live.raster_plots.values()]
        # the traces take a real share of what the tab shows (not 15 px of a 533-px window)
        shown = live.plot_scroll.viewport().height()
        assert sum(p.vb.height() for p in live.trace_plots) >= 0.3 * min(shown, live.gl.height())
        for p in live.time_plots:
            assert p.titleLabel.item.boundingRect().width() <= p.vb.width() + 1, p.titleLabel.text
        line = QtGui.QFontMetrics(live.gl.font()).height()
        for p in live.raster_plots.values():
            ticks = [t for t, _ in p.getAxis("left")._tickLevels[0]]
            px_per_taxel = p.vb.height() / live.sensor_layout.n_channels
            assert min(np.diff(ticks)) * px_per_taxel >= line, (ticks, p.vb.height())
        # the plots' widget fits the tab's width (it scrolls only vertically) and its contents fit the widget (a
        # title wider than its plot pushed the colour bar out of the window)
        assert live.gl.width() <= live.plot_scroll.viewport().width()
        assert live.gl.ci.geometry().width() <= live.gl.viewport().width() + 0.5
        view = QtCore.QRectF(live.gl.viewport().rect())
        bar = live.colour_bar
        r = live.gl.mapFromScene(bar.sceneBoundingRect()).boundingRect()
        assert view.contains(QtCore.QRectF(r)), (r, view)
        # the colour bar's labels as its axis draws them (the counts and "ADC counts"), each inside the widget
        img = QtGui.QImage(8, 8, QtGui.QImage.Format.Format_RGB32)
        painter = QtGui.QPainter(img)
        try:
            texts = bar.axis.generateDrawSpecs(painter)[2]
        finally:
            painter.end()
        values = [t for _, _, t in texts]
        assert {"0", "1000"} <= set(values), values
        for rect, _, text in texts:
            on_screen = live.gl.mapFromScene(bar.axis.mapRectToScene(rect)).boundingRect()
            assert view.contains(QtCore.QRectF(on_screen)), (text, on_screen, view)
        label = bar.getAxis("left").label  # "ADC counts", on the other side of the bar
        assert label.toPlainText().strip() == "ADC counts"
        on_screen = live.gl.mapFromScene(label.mapRectToScene(label.boundingRect())).boundingRect()
        assert label.isVisible() and view.contains(QtCore.QRectF(on_screen)), (on_screen, view)
        # rebuilt for a sensor (a board reconnected) with no resize: the taxel numbers stay hidden in small cells
        from rigctl_gui.live_view import MIN_LABELLED_CELL_PX

        layout, live.sensor_layout = live.sensor_layout, None
        live.set_layout(layout)
        wait_for(qapp, lambda: not live._fit_timer.isActive(), 5)
        wait_for(qapp, lambda: False, 0.2)
        cell = min(i.mapRectToScene(i.boundingRect()).width() / i.image.shape[1] for i in live.images)
        assert cell < MIN_LABELLED_CELL_PX and not any(t.isVisible() for t in live.taxel_labels), cell
    finally:
        inprocess_window.resize(1400, 900)


def _text_contrast(widget: QtWidgets.QWidget) -> float:
    """The contrast of ``widget``'s text as drawn: its most common pixel colour (the background) against the pixel
    farthest from it (a glyph's fully covered pixel has the text colour itself)."""
    img = widget.grab().toImage().convertToFormat(QtGui.QImage.Format.Format_RGB32)
    a = np.frombuffer(img.constBits(), np.uint32, img.width() * img.height()).copy()
    colours, counts = np.unique(a, return_counts=True)
    bg = QtGui.QColor.fromRgb(int(colours[counts.argmax()]))
    return max(contrast_ratio(QtGui.QColor.fromRgb(int(c)), bg) for c in colours)


@pytest.fixture
def dark(qapp):
    """The application in the dark palette for one test; the previous palette afterwards."""
    before = QtGui.QPalette(qapp.palette())
    qapp.setPalette(dark_palette())
    yield
    qapp.setPalette(before)


def test_every_label_is_readable_with_a_dark_palette(inprocess_window, qapp, dark):
    """With a dark palette and the drum running, every enabled label with text on the Rig control, Live view and
    Calibration tabs, the top strip and the status bar has a WCAG contrast ratio of at least 4.5."""
    w = inprocess_window
    w.control.command("run")
    try:
        assert wait_for(qapp, lambda: "Running" in w.drum_state.text(), 30), w.drum_state.text()
        from rigctl_gui.widgets import StatusText

        def unreadable() -> list[tuple[str, float]]:
            bad = []
            for label in [*w.findChildren(QtWidgets.QLabel), *w.findChildren(StatusText)]:
                if label.isVisible() and label.isEnabled() and label.text().strip() and label.width() > 4:
                    c = _text_contrast(label)
                    if c < MIN_CONTRAST:
                        bad.append((label.objectName() or label.text()[:40], round(c, 2)))
            return bad

        for tab in (w.control, w.live, w.calibration):
            w.tabs.setCurrentWidget(tab)
            wait_for(qapp, lambda: False, 1.0)  # state colours follow at the next refresh
            assert wait_for(qapp, lambda: not unreadable(), 5), (type(tab).__name__, unreadable())
        assert "Running" in w.drum_state.text()
    finally:
        w.control.command("stop")


@pytest.mark.parametrize("palette", ["light", "dark"])
def test_the_event_log_is_readable(qapp, palette):
    """Every fragment of the event log (time stamp, level, source, text of info, warning and error lines) has a
    contrast ratio of at least 4.5 against the log's background, in the style's palette and a dark one."""
    from rigctl_gui.messages import EventLog

    log = EventLog()
    if palette == "dark":
        log.setPalette(dark_palette())
    for level in (logging.INFO, logging.WARNING, logging.ERROR):
        log.add(level, "test", f"a {logging.getLevelName(level).lower()} line")
    view = log.view
    base, text = view.palette().color(QtGui.QPalette.ColorRole.Base), view.palette().color(QtGui.QPalette.ColorRole.Text)
    seen = []
    block = view.document().begin()
    while block.isValid():
        it = block.begin()
        while not it.atEnd():
            frag = it.fragment()
            fmt = frag.charFormat()
            colour = fmt.foreground().color() if fmt.hasProperty(QtGui.QTextFormat.Property.ForegroundBrush) else text
            seen.append((frag.text(), colour.name(), round(contrast_ratio(colour, base), 2)))
            it += 1
        block = block.next()
    assert len(seen) >= 9, seen
    assert all(c >= MIN_CONTRAST for _, _, c in seen), [s for s in seen if s[2] < MIN_CONTRAST]
    log.deleteLater()


def _overlaps(parent: QtWidgets.QWidget) -> list[tuple[str, str]]:
    """Pairs of visible sibling widgets under ``parent`` (at any depth) whose rectangles overlap, by name; a scroll
    area's or a tab bar's own parts, overlays (the stale marker) and hidden widgets are left out."""
    def name(w: QtWidgets.QWidget) -> str:
        text = w.text() if hasattr(w, "text") and callable(w.text) and isinstance(w.text(), str) else ""
        return f"{type(w).__name__}:{w.objectName() or text[:30]}"

    found = []
    for p in [parent, *parent.findChildren(QtWidgets.QWidget)]:
        if isinstance(p, (QtWidgets.QAbstractScrollArea, QtWidgets.QTabBar)) or not p.isVisible():
            continue
        kids = [k for k in p.findChildren(QtWidgets.QWidget, options=QtCore.Qt.FindChildOption.FindDirectChildrenOnly)
                if k.isVisible() and not k.isWindow() and k.objectName() != "stale_marker"
                and not k.objectName().startswith("qt_")]
        for i, a in enumerate(kids):
            for b in kids[i + 1:]:
                if a.geometry().intersects(b.geometry()):
                    found.append((name(a), name(b)))
    return found


def test_the_window_fits_a_1024x700_screen_at_1_5x(inprocess_window, qapp):
    """Issue 38: at 1.5x a 1024x700 screen is 683x466 of Qt's pixels and the window's smallest size was 794x519. Now
    the window's smallest size fits it, and at that size: STOP is whole; every tab's content gets at least its own
    smallest size (what does not fit scrolls, and the scroll bars reach all of it); no two widgets overlap; the Live
    view's bar takes two rows with every readout whole; the control plots keep their room (their axis labels ran
    into each other at 15 px); the calibration plot fits its widget; the analysis trial plots keep their room and
    their title; the source and a STOPPED run's long state are shown whole in the top strip; a refused setpoint
    moves neither Apply nor Press nor Run."""
    from rigctl_gui.control_panel import PLOTS_MIN_PX
    from rigctl_gui.widgets import FittedText

    w = inprocess_window
    width, height = SCALED_1024x700
    hint, smallest = w.minimumSizeHint(), w.minimumSize()
    assert hint.width() <= width and hint.height() <= height, hint
    assert smallest.width() <= width and smallest.height() <= height, smallest
    w.resize(width, height)
    try:
        wait_for(qapp, lambda: w.width() == width and w.height() == height, 5)
        assert (w.width(), w.height()) == SCALED_1024x700
        stop = QtCore.QRect(w.stop_btn.mapTo(w, QtCore.QPoint(0, 0)), w.stop_btn.size())
        assert w.rect().contains(stop) and (stop.width(), stop.height()) == (160, 48), stop
        # each check below judges the settled layout (holds_within: its events processed until it holds, a hang bound)
        for i in range(w.tabs.count()):
            w.tabs.setCurrentIndex(i)
            page, area = w.tabs.widget(i), w.tabs.area(i)  # (shown first: the Analysis tab is built on first show)
            name = w.tabs.tabText(i)

            def tab_fits(page=page, area=area, name=name) -> None:
                need = page.minimumSizeHint().expandedTo(page.minimumSize())
                assert page.width() >= need.width() and page.height() >= need.height(), (name, page.size(), need)
                view = area.viewport()
                assert area.horizontalScrollBar().maximum() >= page.width() - view.width(), name
                assert area.verticalScrollBar().maximum() >= page.height() - view.height(), name
                assert not _overlaps(page), (name, _overlaps(page))

            holds_within(qapp, tab_fits)
        assert not _overlaps(w.top_strip), _overlaps(w.top_strip)
        # the Live view: its bar on two rows, each readout given its whole width
        w.tabs.setCurrentWidget(w.live)
        live = w.live

        def live_bar_whole() -> None:
            assert live._bar2.indexOf(live.sensor_label) >= 0
            for label in (live.rate_label, live.sensor_label):
                assert label.width() >= label.sizeHint().width(), (label.objectName(), label.width())

        holds_within(qapp, live_bar_whole)
        # the control plots: their room, and their axis labels apart
        w.tabs.setCurrentWidget(w.control)
        c = w.control

        def control_plots_apart() -> None:
            assert c.plots.height() >= PLOTS_MIN_PX
            labels = [p.getAxis("left").label for p in (c.force_plot, c.speed_plot)]
            a, b = (lab.mapRectToScene(lab.boundingRect()) for lab in labels)
            assert not a.intersects(b), (a, b)

        holds_within(qapp, control_plots_apart)
        # the calibration plot (title, axes, bars) inside its widget
        w.tabs.setCurrentWidget(w.calibration)
        plot = w.calibration.norm_plot

        def calibration_plot_inside() -> None:
            shown = plot.mapFromScene(plot.plotItem.sceneBoundingRect()).boundingRect()
            assert plot.viewport().rect().adjusted(-1, -1, 1, 1).contains(shown), (shown, plot.viewport().rect())

        holds_within(qapp, calibration_plot_inside)
        # the analysis trial view: its plots whole (a trial's title inside, data areas of at least 36 px)
        an = w.analysis
        w.tabs.setCurrentWidget(an)
        an.views.setCurrentIndex(0)
        an.trial_plot.setTitle("Trial 4321: raw taxel readings")

        def trial_plots_whole() -> None:
            plots = [an.trial_plot, *(p for p, _ in an.trial_rasters.values())]
            assert all(p.vb.height() >= 36 for p in plots), [p.vb.height() for p in plots]
            title = an.trial_plot.titleLabel.item
            assert title.mapRectToScene(title.boundingRect()).right() <= an.trial_gl.viewport().width() + 1

        holds_within(qapp, trial_plots_whole)
        an.trial_plot.setTitle("Raw taxel readings")
        # the top strip's texts whole: the source, and beside it a stopped run's long state
        assert isinstance(w.source_label, FittedText)
        assert w.source_label.verticalScrollBar().maximum() == 0, w.source_label.text()
        # the drum's state at its longest usual length, whole in its bold font (it lost its start: measured in the
        # plain font)
        state = w.drum_state.text()
        w.drum_state.setText("Drum: Seeking force 120 mm/s, 1000 g")
        try:
            assert w.drum_state._shown() == w.drum_state.text(), (w.drum_state._shown(), w.drum_state.width())
        finally:
            w.drum_state.setText(state)
        run = w.protocol
        run.run_label.setText("Protocol screenshot_demo: STOPPED (the operator pressed STOP): the rig is at rest. "
                              "Resume records the discarded trial again, Abort ends the run - 3/16 done, ETA 0:21")
        run.run_strip.show()

        def texts_whole() -> None:
            for text in (run.run_label, w.source_label):
                assert text.verticalScrollBar().maximum() == 0, text.text()
                assert text.label.font().pixelSize() >= FittedText.MIN_PX

        try:
            holds_within(qapp, texts_whole)
        finally:
            run.run_strip.hide()
        # a refused setpoint moves none of Apply, Press, Run
        w.tabs.setCurrentWidget(w.control)
        holds_within(qapp, control_plots_apart)  # the tab's layout settled before the buttons are measured
        wait_for(qapp, lambda: False, 0.3)

        def tops():
            return [b.mapTo(w, b.rect().topLeft()).y() for b in (c.apply_btn, c.buttons["press"], c.buttons["run"])]

        before, speed, force = tops(), c.speed.value(), c.force.value()
        c.speed.setValue(5000.0)
        c.force.setValue(9000.0)
        c.apply_setpoints()

        def refused_shown() -> None:
            assert c.setpoint_error.isVisible() and "refused" in c.setpoint_error.text()

        holds_within(qapp, refused_shown)
        wait_for(qapp, lambda: False, 0.3)  # the layout's chance to move the buttons for the message
        assert tops() == before
        c.speed.setValue(speed)
        c.force.setValue(force)
    finally:
        w.resize(1400, 900)


@pytest.mark.parametrize("size", [(1024, 700), (1280, 800)], ids=["1024x700", "1280x800"])
def test_no_tab_scrolls_at_1x_on_the_usual_screens(inprocess_window, qapp, size):
    """The tabs' scroll areas (which let a 1024x700 screen at 1.5x hold the window) change nothing where the
    window has room: at 1024x700 and 1280x800 no tab's content scrolls, either way."""
    w = inprocess_window
    w.resize(*size)
    try:
        wait_for(qapp, lambda: (w.width(), w.height()) == size, 5)
        for i in range(w.tabs.count()):
            w.tabs.setCurrentIndex(i)
            wait_for(qapp, lambda: False, 0.2)
            area = w.tabs.area(i)
            bars = area.verticalScrollBar().maximum(), area.horizontalScrollBar().maximum()
            assert bars == (0, 0), (w.tabs.tabText(i), bars)
    finally:
        w.resize(1400, 900)
