"""Text colours that follow the palette: the app's state colours (error red, running green, amber, grey) are
chosen for a light window and made readable on whatever background a panel has (a dark desktop palette too), by
the WCAG contrast ratio (:func:`contrast_ratio`, at least :data:`MIN_CONTRAST` for text, as WCAG's AA level asks).

:func:`dark_palette` is a dark desktop palette (KDE Breeze Dark's colours) for the screenshots and the tests; the
app itself takes whatever palette the desktop gives it.
"""

from __future__ import annotations

import functools

from PySide6 import QtGui, QtWidgets

#: the app's error red (on a light window; :func:`on_window` makes it readable on any)
ERROR = "#c00"
#: the smallest contrast ratio of text against its background (WCAG 2 AA, normal text)
MIN_CONTRAST = 4.5


def _luminance(c: QtGui.QColor) -> float:
    """WCAG relative luminance of ``c`` (0 black .. 1 white)."""
    def lin(v: float) -> float:
        return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4

    return 0.2126 * lin(c.redF()) + 0.7152 * lin(c.greenF()) + 0.0722 * lin(c.blueF())


def contrast_ratio(a: QtGui.QColor | str, b: QtGui.QColor | str) -> float:
    """WCAG contrast ratio of two colours, 1 (the same) .. 21 (black on white)."""
    la, lb = sorted((_luminance(QtGui.QColor(a)), _luminance(QtGui.QColor(b))), reverse=True)
    return (la + 0.05) / (lb + 0.05)


def readable(colour: str, background: QtGui.QColor | str, min_ratio: float = MIN_CONTRAST) -> str:
    """``colour`` (a name or ``#rgb``) as a ``#rrggbb`` text colour readable on ``background``: itself when its
    contrast ratio is at least ``min_ratio``, else the same hue made lighter (on a dark background) or darker (on a
    light one) until it is. The app asks this for its state colours several times a second: each answer is
    worked out once per colour, background and ratio."""
    return _readable(colour, QtGui.QColor(background).rgba(), min_ratio)


@functools.lru_cache(maxsize=512)
def _readable(colour: str, background_rgba: int, min_ratio: float) -> str:
    c, bg = QtGui.QColor(colour), QtGui.QColor.fromRgba(background_rgba)
    if contrast_ratio(c, bg) >= min_ratio:
        return c.name()
    h, s, lightness = c.hslHueF(), c.hslSaturationF(), c.lightnessF()
    up = _luminance(bg) < 0.18  # a dark background: lighter text
    for k in range(1, 21):
        v = lightness + (1 - lightness) * k / 20 if up else lightness * (1 - k / 20)
        cand = QtGui.QColor.fromHslF(max(h, 0.0), s, v)
        if contrast_ratio(cand, bg) >= min_ratio:
            return cand.name()
    return "#ffffff" if up else "#000000"


def on_window(colour: str, widget: QtWidgets.QWidget | None = None) -> str:
    """``colour`` readable as text on ``widget``'s window background (the application's when None)."""
    pal = widget.palette() if widget is not None else QtWidgets.QApplication.palette()
    return readable(colour, pal.color(QtGui.QPalette.ColorRole.Window))


def dark_palette() -> QtGui.QPalette:
    """A dark desktop palette (KDE Breeze Dark's colours), as a user's dark theme gives the app."""
    pal = QtGui.QPalette()
    roles = QtGui.QPalette.ColorRole
    for role, colour in [(roles.Window, "#2a2e32"), (roles.WindowText, "#fcfcfc"), (roles.Base, "#1b1e20"),
                         (roles.AlternateBase, "#232629"), (roles.Text, "#fcfcfc"), (roles.Button, "#31363b"),
                         (roles.ButtonText, "#fcfcfc"), (roles.ToolTipBase, "#31363b"),
                         (roles.ToolTipText, "#fcfcfc"), (roles.Highlight, "#3daee9"),
                         (roles.HighlightedText, "#fcfcfc"), (roles.Link, "#1d99f3"), (roles.BrightText, "#ffffff"),
                         (roles.PlaceholderText, "#a1a9b1"), (roles.Light, "#40464c"), (roles.Midlight, "#373c41"),
                         (roles.Mid, "#2c3034"), (roles.Dark, "#1b1e20"), (roles.Shadow, "#0e0f10")]:
        pal.setColor(role, QtGui.QColor(colour))
    for role, colour in [(roles.WindowText, "#6e7175"), (roles.Text, "#6e7175"), (roles.ButtonText, "#6e7175")]:
        pal.setColor(QtGui.QPalette.ColorGroup.Disabled, role, QtGui.QColor(colour))
    return pal
