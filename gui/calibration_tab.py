"""placeholder"""
from PySide6 import QtWidgets


class CalibrationTab(QtWidgets.QWidget):
    def __init__(self, main, parent=None):
        super().__init__(parent)
        self.main = main

    def refresh(self):
        pass

    def rig_config(self):
        return None

    def taxel_range(self):
        return None

    def on_trial(self, planned, data):
        pass
