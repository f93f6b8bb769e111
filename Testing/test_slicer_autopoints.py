"""The module's Auto button (issue 17) as Slicer runs it, through the harness of test_slicer_widget.py: it fills the
cardia and pylorus into the points node (movable, Unfold enabled) and warns when the points are unsure."""
import os

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
import slicer_harness  # noqa: E402

H = slicer_harness.require()
from slicer_harness import app as happ  # noqa: E402

qt, slicer = H.qt, H.slicer


@pytest.fixture(scope="module")
def module():
    happ.newScene()
    return happ.ModulePanel(os.path.join(ROOT, "StomachUnfold"), "StomachUnfold")


@pytest.fixture
def gui(module):
    scene, appLogic, logics = happ.newScene()
    module.widget, module.panel = None, None
    slicer.app.layoutManager().numberOfThreeDViews = 1
    widget = module.open()
    yield module, widget, scene
    if module.panel._entered:
        module.close()
    module.unload()


@pytest.fixture(scope="module")
def stomach():
    from StomachUnfoldEval.random_stomach import LABELS, random_stomach

    return random_stomach(0, size="tiny", labels=True), LABELS


def _points(node):
    out = {}
    for i in range(node.GetNumberOfControlPoints()):
        p = [0.0, 0.0, 0.0]
        node.GetNthControlPointPositionWorld(i, p)
        out[node.GetNthControlPointLabel(i)] = (np.array(p), node.GetNthControlPointLocked(i))
    return out


def test_auto_fills_movable_cardia_and_pylorus_near_the_true_ones(gui, stomach, monkeypatch):
    from StomachUnfoldLib.geometry import lps_to_ras

    module, widget, scene = gui
    (vol, truth, lab), _ = stomach
    node = widget.logic.volumeNodeFromVolume(vol, "r0")
    widget._parameterNode.inputVolume = node
    warnings = []
    monkeypatch.setattr(slicer.util, "warningDisplay", lambda *a, **k: warnings.append(a))
    assert not widget.ui.applyButton.enabled  # no points yet
    widget.ui.autoPointsButton.click()
    pts = _points(widget._parameterNode.pointsNode)
    assert set(pts) == {"cardia", "pylorus"} and warnings == []
    for name in ("cardia", "pylorus"):
        p, locked = pts[name]
        assert not locked
        assert np.linalg.norm(p - lps_to_ras(np.asarray(truth[f"{name}_lps"]))) <= 10.0
    assert widget.lastAutoPoints.confident and widget.ui.applyButton.enabled
    # a second click replaces the points instead of adding more
    widget.ui.autoPointsButton.click()
    assert widget._parameterNode.pointsNode.GetNumberOfControlPoints() == 2


def test_auto_warns_when_unsure_and_still_places_best_guesses(gui, stomach, monkeypatch):
    module, widget, scene = gui
    (vol, truth, lab), LABELS = stomach
    arr = np.array(vol.array)
    gas = lab == LABELS["lumen_air"]
    far = np.linalg.norm(vol.voxel_lps(gas) - np.asarray(truth["dome_top_lps"]), axis=1) > 30.0
    arr.reshape(-1)[np.nonzero(gas.reshape(-1))[0][far]] = 10  # little gas left: not distended
    widget._parameterNode.inputVolume = widget.logic.volumeNodeFromVolume(vol.with_array(arr), "littlegas")
    warnings = []
    monkeypatch.setattr(slicer.util, "warningDisplay", lambda *a, **k: warnings.append(a))
    widget.ui.autoPointsButton.click()
    assert len(warnings) == 1 and "unsure" in warnings[0][0]
    assert set(_points(widget._parameterNode.pointsNode)) == {"cardia", "pylorus"}
    assert not widget.lastAutoPoints.confident


def test_auto_reads_a_totalsegmentator_label_map_picked_as_the_mask(gui, stomach, monkeypatch):
    from StomachUnfoldEval.auto_points import totalseg_labels
    from StomachUnfoldLib.geometry import lps_to_ras

    module, widget, scene = gui
    (vol, truth, lab), _ = stomach
    seg = totalseg_labels(vol, lab, truth, "total")
    widget._parameterNode.inputVolume = widget.logic.volumeNodeFromVolume(vol, "r0")
    labelNode = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "total")
    labelNode.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(vol.index_to_ras_matrix))
    slicer.util.updateVolumeFromArray(labelNode, np.ascontiguousarray(seg))
    widget._parameterNode.maskNode = labelNode
    warnings = []
    monkeypatch.setattr(slicer.util, "warningDisplay", lambda *a, **k: warnings.append(a))
    before = {scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())}
    widget.ui.autoPointsButton.click()
    found = widget.lastAutoPoints
    assert found.source == "segmentation" and found.convention == "total" and warnings == []
    assert found.labels == {"stomach": 6, "esophagus": 15, "duodenum": 19}
    pts = _points(widget._parameterNode.pointsNode)
    assert np.linalg.norm(pts["cardia"][0] - lps_to_ras(np.asarray(truth["cardia_lps"]))) <= 10.0
    added = {scene.GetNthNode(i).GetClassName() for i in range(scene.GetNumberOfNodes())
             if scene.GetNthNode(i).GetID() not in before}
    assert all("Markups" in c for c in added), added  # only the new point list: no label map left behind
