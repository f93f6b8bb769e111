"""Render a preview of the module panel from StomachUnfold/Resources/UI/StomachUnfold.ui, without Slicer.

Slicer itself cannot be installed on our build machines, so this is not a screenshot of Slicer: the .ui is
loaded with plain Qt (PySide6, offscreen) and Slicer's own widgets are drawn by simple stand-ins
(``ctkCollapsibleButton`` as a titled box, ``qMRMLNodeComboBox`` as a combo box showing a node name,
``qSlicerMarkupsPlaceWidget`` as a place button). The layout, labels, defaults and tooltips are the .ui's.
The results text is filled from a real run's report.json, in the words the Widget uses.

    python -m venv /tmp/qt && /tmp/qt/bin/pip install PySide6-Essentials
    QT_QPA_PLATFORM=offscreen /tmp/qt/bin/python docs/make_panel_preview.py demo-out/unfold/report.json

PySide6 is only needed for this picture; it is not a dependency of the library or the module.
"""
import json
import os
import sys

from PySide6.QtCore import QFile, Qt
from PySide6.QtGui import QColor, QPainter, QPixmap
from PySide6.QtUiTools import QUiLoader
from PySide6.QtWidgets import QApplication, QComboBox, QGroupBox, QHBoxLayout, QToolButton, QWidget

HERE = os.path.dirname(os.path.abspath(__file__))
UI = os.path.join(HERE, "..", "StomachUnfold", "Resources", "UI", "StomachUnfold.ui")


class ctkCollapsibleButton(QGroupBox):  # noqa: N801 - the .ui's class name
    """Stand-in: a titled box (the title is set from the .ui's ``text`` property after loading)."""


class qMRMLWidget(QWidget):  # noqa: N801
    """Stand-in: a plain widget."""


class qSlicerWidget(QWidget):  # noqa: N801
    """Stand-in: a plain widget."""


class qMRMLNodeComboBox(QComboBox):  # noqa: N801
    """Stand-in: a combo box that shows one node name."""


class qSlicerMarkupsPlaceWidget(QWidget):  # noqa: N801
    """Stand-in: a place button and a delete button, as Slicer's place widget shows them."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.place = QToolButton(self)
        self.place.setText("Place")
        self.place.setCheckable(True)
        self.delete = QToolButton(self)
        self.delete.setText("Delete")
        lay.addWidget(self.place)
        lay.addWidget(self.delete)
        lay.addStretch(1)


def load_panel():
    """The module panel as built from the .ui file with the stand-ins."""
    loader = QUiLoader()
    for cls in (ctkCollapsibleButton, qMRMLWidget, qSlicerWidget, qMRMLNodeComboBox, qSlicerMarkupsPlaceWidget):
        loader.registerCustomWidget(cls)
    f = QFile(UI)
    f.open(QFile.ReadOnly)
    w = loader.load(f)
    f.close()
    for box in w.findChildren(QGroupBox):
        collapsed = bool(box.property("collapsed"))
        box.setTitle(("\u25b8 " if collapsed else "\u25be ") + str(box.property("text") or box.objectName()))
        if collapsed:
            for child in box.findChildren(QWidget):
                child.hide()
            box.setMinimumHeight(22)
            box.setMaximumHeight(22)
    return w


def fill(w, report, running: bool):
    """Set the panel to the state after (or during) a run of ``report``."""
    w.findChild(QComboBox, "inputSelector").addItem("StomachPhantom")
    w.findChild(QComboBox, "pointsSelector").addItem("StomachPhantom points")
    w.findChild(QComboBox, "maskSelector").addItem("None")
    w.findChild(QComboBox, "incisionComboBox").addItems(["greater", "lesser", "anterior", "posterior"])
    for name in ("cardiaPlaceWidget", "pylorusPlaceWidget"):
        pw = w.findChild(QWidget, name)
        pw.place.setText("Place  (1 point: " + name[:-11] + ")")
    p = report["parameters"]
    w.findChild(QWidget, "gridSizeSpinBox").setValue(int(p["grid_size"] or 0))  # 0: automatic
    w.findChild(QWidget, "kappaSpinBox").setValue(float(p["kappa"]))
    w.findChild(QWidget, "wallThicknessSpinBox").setValue(float(p["wall_thickness_mm"]))
    bar = w.findChild(QWidget, "progressBar")
    label = w.findChild(QWidget, "resultsLabel")
    if running:
        w.findChild(QWidget, "applyButton").setText("Cancel")
        bar.setValue(62)
        bar.setFormat("simulation: %p%")
        label.setText("No run yet.")
    else:
        bar.hide()
        q = report.get("quality", {})
        label.setText(f"{report['seconds']['total']:.1f} s, {report['iterations']} iterations, "
                      f"{report['model']['hexahedra']} hexahedra; grade {q.get('grade', '?')}, "
                      f"{100 * q.get('visible_fraction', 0):.0f}% of the mucosa visible")


def main(report_path, out_path):
    """Write a PNG with the panel while running (left) and after the run (right)."""
    app = QApplication.instance() or QApplication(sys.argv)
    with open(report_path) as f:
        report = json.load(f)
    shots = []
    for running in (True, False):
        w = load_panel()
        fill(w, report, running)
        w.resize(380, 620)
        w.show()
        app.processEvents()
        shots.append(w.grab())
    gap = 16
    out = QPixmap(sum(s.width() for s in shots) + gap, max(s.height() for s in shots))
    out.fill(QColor("white"))
    painter = QPainter(out)
    x = 0
    for s in shots:
        painter.drawPixmap(x, 0, s)
        x += s.width() + gap
    painter.setPen(Qt.gray)
    painter.end()
    out.save(out_path)
    print(out_path)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "demo-out/unfold/report.json",
         sys.argv[2] if len(sys.argv) > 2 else os.path.join(HERE, "images", "module_panel_preview.png"))
