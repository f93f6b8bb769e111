"""Render the Slicer module's output headless (real MRML nodes, slicer-core wheel) for the README.

Run: .venv/bin/python docs/make_slicer_images.py  ->  docs/images/slicer_volume_rendering.png
"""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "Testing"))

import test_slicer_logic as t  # noqa: E402  (sets up the stand-ins and the module path)
import vtk  # noqa: E402

from StomachUnfoldLib.phantom import make_phantom  # noqa: E402


def main():
    scene, app, logics = t.make_scene()
    import StomachUnfold as mod

    logic = mod.StomachUnfoldLogic()
    logic.volumeRenderingLogic = logics["VolumeRendering"]
    ct, truth = make_phantom("j", "small", rugae=True)
    vol = logic.volumeNodeFromVolume(ct, "StomachPhantom")
    pts = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "points")
    pts.AddControlPoint(vtk.vtkVector3d(*truth["cardia_ras"]), "cardia")
    pts.AddControlPoint(vtk.vtkVector3d(*truth["pylorus_ras"]), "pylorus")
    out = \
        logic.unfold(vol, *logic.pointsFromMarkups(pts), grid_mm=5.0, wall_thickness_mm=4.0)
    png = os.path.join(ROOT, "docs", "images", "slicer_volume_rendering.png")
    t.render_view_png(scene, app, logics["VolumeRendering"], out["volume"], out["camera"], png, size=(800, 600))
    print(png, out["report"]["quality"]["grade"])


if __name__ == "__main__":
    main()
