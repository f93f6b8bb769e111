"""Render the module panel to docs/images/module_panel.png through the test harness (not a Slicer screenshot).

The module is loaded as Slicer loads it, over Slicer's real ScriptedLoadableModule, parameterNodeWrapper and
SampleData (``$STOMACHUNFOLD_SHARED/slicer_python/v5.10.0``) with real Qt (PySide6, offscreen) and real MRML;
what stands in for Slicer's C++ are the CTK/qMRML widgets (``Testing/slicer_harness``: collapsible buttons,
node selectors, place widgets) and ``slicer.app``. The panel shows the sample phantom after one Unfold.

    .venv/bin/python docs/make_panel_preview.py [out.png]
"""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
OUT = os.path.join(HERE, "images", "module_panel.png")


def main(out=OUT, width=420):
    """Load the module, the sample phantom, run Unfold from the panel and save the panel as a PNG (pixels)."""
    sys.path.insert(0, os.path.join(ROOT, "Testing"))
    import slicer_harness

    reason = slicer_harness.skipReason()
    if reason:
        raise SystemExit(reason)
    h = slicer_harness.install()
    from slicer_harness import app

    import SampleData

    app.newScene()
    module = app.ModulePanel(os.path.join(ROOT, "StomachUnfold"), "StomachUnfold")
    widget = module.open()
    volume, points = SampleData.downloadSamples("StomachPhantom")
    module.close()
    module.open()
    p = widget._parameterNode
    p.gridSize, p.wallThicknessMm = 3, 4.0
    widget.ui.applyButton.click()
    panel = module.panel
    panel.resize(width, 10)
    panel.show()
    for _ in range(3):
        h.qt.QApplication.processEvents()
    panel.resize(width, panel.sizeHint().height() + 10)
    h.qt.QApplication.processEvents()
    os.makedirs(os.path.dirname(out), exist_ok=True)
    if not panel.grab().save(out):
        raise SystemExit(f"could not write {out}")
    return out


if __name__ == "__main__":
    print(main(*sys.argv[1:]))
