"""The module as Slicer runs it: real ScriptedLoadableModule, parameterNodeWrapper, SampleData and i18n from
Slicer 5.10.0, real Qt (PySide6, offscreen), real MRML; stand-ins only for the C++ CTK/qMRML widgets and
slicer.app (``Testing/slicer_harness``). Issue 13: each test names the defect it covers.
"""
import os
import re
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
import slicer_harness  # noqa: E402  (Testing/ is on sys.path, as for conftest)

H = slicer_harness.require()
from slicer_harness import app as happ

qt, slicer = H.qt, H.slicer
import vtk

SAMPLE_DIR = os.path.join(ROOT, "StomachUnfold", "Resources", "SampleData")
RUN = dict(gridSize=3, wallThicknessMm=4.0)


def sceneState(scene):
    """(ID, class, name) of every node: what a run or a cancel must leave unchanged."""
    return sorted((n.GetID(), n.GetClassName(), n.GetName()) for n in
                  (scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())))


@pytest.fixture(scope="module")
def module():
    """The module loaded once per test file, as Slicer loads it at start-up (startupCompleted emitted)."""
    happ.newScene()
    return happ.ModulePanel(os.path.join(ROOT, "StomachUnfold"), "StomachUnfold")


@pytest.fixture
def gui(module):
    """A fresh scene and a fresh module panel (Widget set up and entered) on it."""
    scene, appLogic, logics = happ.newScene()
    module.widget, module.panel = None, None
    slicer.app.layoutManager().numberOfThreeDViews = 1
    slicer.app.processEventsFlags.clear()
    widget = module.open()
    yield module, widget, scene
    if module.panel._entered:
        module.close()
    module.unload()


def loadSample():
    """The sample phantom and its points through the real SampleData module."""
    import SampleData

    nodes = SampleData.downloadSamples("StomachPhantom")
    return nodes[0], nodes[1]


def progressDialogs():
    return [w for w in qt.QApplication.topLevelWidgets() if isinstance(w, qt.QProgressDialog) and w.visible]


# ---------------------------------------------------------------- defect 1: VTKObservationMixin
def test_widget_sets_up_over_the_real_base_class(gui):
    """Defect 1: setup() uses addObserver; the real ScriptedLoadableModuleWidget has none without the mixin."""
    module, widget, scene = gui
    assert isinstance(widget, slicer.util.VTKObservationMixin)
    assert widget.hasObserver(scene, scene.StartCloseEvent, widget.onSceneStartClose)
    assert widget.ui.applyButton.text == "Unfold"


# ---------------------------------------------------------------- defect 2 and the method choice
def test_incision_and_method_are_choices_in_their_combo_boxes(gui):
    """Defect 2: a str bound to a QComboBox needs Choice; the combos list the choices and drive the parameter."""
    module, widget, scene = gui
    combo = widget.ui.incisionComboBox
    items = [combo.itemText(i) for i in range(combo.count)]
    assert items == list(module.pythonModule.INCISION_SIDES)
    combo.currentIndex = items.index("lesser")
    assert widget._parameterNode.incision == "lesser"
    methods = [widget.ui.methodComboBox.itemText(i) for i in range(widget.ui.methodComboBox.count)]
    from StomachUnfoldLib.params import parameter_specs

    assert methods == list(next(s for s in parameter_specs() if s.name == "method").choices)
    assert widget.ui.methodComboBox.currentText == widget._parameterNode.method == module.pythonModule.DEFAULT_METHOD


# ---------------------------------------------------------------- defect 3
def test_mask_selector_offers_the_concrete_mask_classes(gui):
    """Defect 3: the mask parameter is a union of concrete node classes (vtkMRMLNode is abstract)."""
    module, widget, scene = gui
    assert list(widget.ui.maskSelector.nodeTypes) == ["vtkMRMLSegmentationNode", "vtkMRMLLabelMapVolumeNode"]
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "stomach")
    widget.ui.maskSelector.setCurrentNode(seg)
    assert widget._parameterNode.maskNode is seg


# ---------------------------------------------------------------- defect 4
def test_sample_data_is_registered_and_downloads_through_sample_data(gui):
    """Defect 4: the source registers at start-up and SampleData.downloadSamples loads the CT and its points."""
    import SampleData

    source = SampleData.SampleDataLogic.sourceForSampleName(SampleData.SampleDataLogic(), "StomachPhantom")
    assert source is not None and all(u.startswith("file://") for u in source.uris)
    volume, points = loadSample()
    assert volume.IsA("vtkMRMLScalarVolumeNode") and volume.GetImageData().GetScalarTypeAsString() == "short"
    labels = {points.GetNthControlPointLabel(i) for i in range(points.GetNumberOfControlPoints())}
    assert labels == {"cardia", "pylorus"}
    assert sum(os.path.getsize(os.path.join(SAMPLE_DIR, f)) for f in os.listdir(SAMPLE_DIR)) < 2 * 2**20


# ---------------------------------------------------------------- defect 5
BLOCKER = r"""
import sys, importlib.abc
BLOCKED = ("skimage", "tqdm", "matplotlib", "dask", "distributed", "pandas", "StomachUnfoldEval")
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (not bundled with Slicer)", name=name)
sys.meta_path.insert(0, Block())
import SimpleITK as sitk, numpy as np
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.io import read_volume, cardia_pylorus_from_markups
from StomachUnfoldLib.pipeline import unfold, UnfoldParameters
ct = read_volume(sys.argv[1])
cardia, pylorus = cardia_pylorus_from_markups(sys.argv[2])
r = unfold(ct, cardia, pylorus, UnfoldParameters(grid_size=3, wall_thickness_mm=4.0, max_iterations=3, quality=False))
print("OK", r.unfolded.array.shape)
"""


def test_library_runs_on_what_slicer_bundles(module):
    """Defect 5: the library imports and unfolds with only numpy, scipy, SimpleITK and vtk (no skimage, tqdm)."""
    out = subprocess.run([sys.executable, "-c", BLOCKER, os.path.join(SAMPLE_DIR, "StomachPhantom.nrrd"),
                          os.path.join(SAMPLE_DIR, "StomachPhantomPoints.mrk.json")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "OK" in out.stdout, out.stderr[-2000:]
    assert module.pythonModule.missingPackages() == []


def test_missing_package_is_offered_for_pip_install_after_confirmation(gui, monkeypatch):
    """Defect 5: a missing package is offered for slicer.util.pip_install (the network stands in as a recorder)."""
    module, widget, scene = gui
    installed = []
    monkeypatch.setitem(module.pythonModule.REQUIRED_PACKAGES, "no_such_package_xyz", "no-such-package-xyz")
    monkeypatch.setattr(slicer.util, "pip_install", lambda req, **kw: installed.append(req))
    assert widget._ensureDependencies() is False  # testing mode: Slicer's confirmation answers "no"
    assert installed == []
    asked = []
    monkeypatch.setattr(slicer.util, "confirmOkCancelDisplay", lambda text, **kw: asked.append(text) or True)
    assert widget._ensureDependencies() is False  # the user said OK; still missing after the (recorded) install
    assert installed == ["no-such-package-xyz"] and "no-such-package-xyz" in asked[0]
    # from a source tree without the library installed: the repository itself is offered, without its deps
    monkeypatch.setattr(module.pythonModule, "libraryAvailable", lambda: False)
    installed.clear()
    widget._ensureDependencies()
    assert installed[-1] == f'--no-deps "{ROOT}"'
    assert module.pythonModule.librarySourceTree() == ROOT


# ---------------------------------------------------------------- defects 6 and 7: Cancel
def _clickCancel():
    dialogs = progressDialogs()
    assert dialogs, "no progress dialog is shown while unfolding"
    button = next(b for b in dialogs[0].findChildren(qt.QPushButton) if b.text == "Cancel")
    button.click()


def test_cancel_click_cancels_the_run_and_leaves_the_scene(gui, monkeypatch):
    """Defects 6, 7: a click on Cancel reaches the run, which stops without an error pop-up or new nodes."""
    module, widget, scene = gui
    volume, points = loadSample()
    widget._parameterNode.inputVolume, widget._parameterNode.pointsNode = volume, points
    assert widget.ui.applyButton.enabled
    errors = []
    monkeypatch.setattr(slicer.util, "errorDisplay", lambda *a, **k: errors.append(a))
    monkeypatch.setattr(slicer.app, "testingEnabled", lambda: False)  # as for a user: errors would pop up
    state = sceneState(scene)
    slicer.app.queueUserInput(_clickCancel)  # the user clicks Cancel as soon as the dialog lets input in
    widget.ui.applyButton.click()
    assert sceneState(scene) == state
    assert errors == [] and widget.ui.resultsLabel.text.startswith("Cancelled")
    flags = slicer.app.processEventsFlags  # one processEvents per progress report
    assert not any(f & qt.QEventLoop.ExcludeUserInputEvents for f in flags)
    assert 0 < len(flags) < 5, "the run went on after Cancel"
    assert progressDialogs() == [] and widget.ui.applyButton.enabled


# ---------------------------------------------------------------- defect 8
def test_spin_boxes_keep_the_panel_ranges_and_special_text(gui):
    """Defect 8: WithinRange keeps the .ui ranges and the "automatic" text; out-of-range values are refused."""
    module, widget, scene = gui
    ui, p = widget.ui, widget._parameterNode
    assert (ui.gridSizeSpinBox.minimum, ui.gridSizeSpinBox.maximum) == (0, 32)
    assert ui.gridSizeSpinBox.specialValueText == "automatic (5.6 mm)" and ui.gridSizeSpinBox.value == 0
    assert (ui.kappaSpinBox.minimum, ui.kappaSpinBox.maximum) == (0.01, 10.0)
    assert (ui.maxIterationsSpinBox.minimum, ui.maxIterationsSpinBox.maximum) == (1, 10000)
    with pytest.raises(ValueError):
        p.kappa = -0.5
    with pytest.raises(ValueError):
        p.gridSize = -3
    ui.kappaSpinBox.value = 0.2
    assert p.kappa == pytest.approx(0.2)


def test_parameter_node_agrees_with_the_core_parameter_specs(module):
    """The panel's defaults are the core's (gridSize 0 = automatic) and its ranges lie inside the core's."""
    from StomachUnfoldLib.params import parameter_specs

    mod = module.pythonModule
    specs = {s.name: s for s in parameter_specs()}
    from slicer.parameterNodeWrapper import findFirstAnnotation, splitAnnotations

    for name, core in mod.PARAMETER_MAP.items():
        info = mod.StomachUnfoldParameterNode.allParameters[name]
        spec = specs[core]
        default = info.default.value
        assert default == (spec.default if spec.default is not None else 0), name
        within = findFirstAnnotation(splitAnnotations(info.unalteredType)[1], slicer.parameterNodeWrapper.WithinRange)
        if within is not None and spec.lo is not None:
            lo = within.minimum if not (name == "gridSize" and within.minimum == 0) else 1
            assert lo >= spec.lo and (lo > spec.lo or not spec.lo_open) and within.maximum <= spec.hi, name
    mod.StomachUnfoldLogic.unfoldParameters(**{n: mod.StomachUnfoldParameterNode.allParameters[n].default.value
                                                for n in mod.PARAMETER_MAP}).validate()


# ---------------------------------------------------------------- defect 9
def _connectionCounts(widget):
    sig = qt.SIGNAL("valueChanged(double)")
    return (len(widget.Observations), len(widget._parameterNode._parameterGUIs),
            widget.ui.kappaSpinBox.receivers(sig))


def test_enter_exit_and_scene_close_ten_times_leave_no_extra_observers_or_nodes(gui):
    """Defect 9: connectGui is undone in exit() and on scene close; nothing piles up; Unfold follows the inputs."""
    module, widget, scene = gui
    assert not widget.ui.applyButton.enabled  # no inputs yet
    counts, state = _connectionCounts(widget), sceneState(scene)
    for _ in range(10):
        module.close()
        assert len(widget._parameterNode._parameterGUIs) == 0
        module.open()
    assert _connectionCounts(widget) == counts and sceneState(scene) == state
    for _ in range(10):
        scene.Clear(0)
    assert _connectionCounts(widget) == counts
    module.close()
    for _ in range(10):
        scene.Clear(0)  # closed while another module is shown: no GUI connection is made
    assert widget._parameterNode is None or len(widget._parameterNode._parameterGUIs) == 0
    module.open()
    assert _connectionCounts(widget) == counts
    volume, points = loadSample()
    module.close()
    module.open()  # entering picks the loaded CT and its points
    assert widget._parameterNode.inputVolume is volume and widget._parameterNode.pointsNode is points
    assert widget.ui.applyButton.enabled
    points.SetNthControlPointLabel(1, "antrum")
    assert not widget.ui.applyButton.enabled and "pylorus" in widget.ui.applyButton.toolTip
    module.close()
    module.unload()  # application exit: cleanup() removes every observer and GUI connection
    assert widget.Observations == [] and widget._parameterNode is None


# ---------------------------------------------------------------- defect 10
def test_opening_the_module_adds_only_its_parameter_node(module):
    """Defect 10: opening the module adds no points node (only the parameter node)."""
    scene, appLogic, logics = happ.newScene()
    before = sceneState(scene)
    module.widget = None
    module.open()
    added = sorted(set(sceneState(scene)) - set(before))
    assert [c for _, c, _ in added] == ["vtkMRMLScriptedModuleNode"]
    module.close()


def test_segmentation_mask_leaves_no_temporary_nodes(gui):
    """Defect 10: exporting a segmentation mask leaves no label map, display node or colour table behind."""
    module, widget, scene = gui
    volume, points = loadSample()
    logic = widget.logic
    ct = logic.volumeFromNode(volume)
    label = logic.volumeNodeFromVolume(ct.with_array((ct.array < -500).astype(np.uint8)), "label")
    label2 = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "lab")
    label2.SetAndObserveImageData(label.GetImageData())
    m = vtk.vtkMatrix4x4()
    label.GetIJKToRASMatrix(m)
    label2.SetIJKToRASMatrix(m)
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "seg")
    assert slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(label2, seg)
    state = sceneState(scene)
    mask = logic.maskFromNode(seg, ct)
    assert sceneState(scene) == state
    assert mask.sum() == (ct.array < -500).sum()


def test_transfer_functions_go_through_the_volume_property_node(module):
    """Defect 10: the mucosa transfer functions are set on the property node, in one modification."""
    node = slicer.vtkMRMLVolumePropertyNode()
    events = []
    node.AddObserver(vtk.vtkCommand.ModifiedEvent, lambda c, e: events.append(e))
    module.pythonModule.setMucosaTransferFunctions(node)
    assert node.GetScalarOpacity().GetValue(-1000) == 0.0 and node.GetScalarOpacity().GetValue(-100) > 0.9
    assert node.GetColor().GetSize() == 6 and len(events) == 1


def test_no_3d_view_fails_before_any_output(gui):
    """Defect 10: with no 3D view in the layout, Unfold says so and makes no node."""
    module, widget, scene = gui
    volume, points = loadSample()
    widget._parameterNode.inputVolume, widget._parameterNode.pointsNode = volume, points
    slicer.app.layoutManager().numberOfThreeDViews = 0
    state = sceneState(scene)
    with pytest.raises(ValueError, match="3D view"):
        widget.onApplyButton()
    assert sceneState(scene) == state


# ---------------------------------------------------------------- defect 11
def _arm(widget, which):
    w = getattr(widget.ui, f"{which}PlaceWidget")
    w.placeButton().click()
    assert w.placeModeEnabled
    return w


def test_place_buttons_label_the_placed_point_single_placement(gui):
    """Defect 11: single placement; the new point (not necessarily the last) gets the label; re-placing replaces."""
    module, widget, scene = gui
    points = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "P")
    points.AddControlPoint(vtk.vtkVector3d(1, 2, 3), "note")
    points.UnsetNthControlPointPosition(0)  # an unplaced point first: a click fills it, as Slicer does
    points.AddControlPoint(vtk.vtkVector3d(5, 5, 5), "other")
    widget.ui.pointsSelector.setCurrentNode(points)
    w = _arm(widget, "cardia")
    assert w.placeMultipleMarkups == slicer.qSlicerMarkupsPlaceWidget.ForcePlaceSingleMarkup
    assert not w.interactionNode().GetPlaceModePersistence()
    assert happ.clickInView([10.0, 20.0, 30.0]) == 0
    assert points.GetNthControlPointLabel(0) == "cardia" and points.GetNthControlPointLabel(1) == "other"
    assert not w.placeModeEnabled  # single placement: place mode ends after one point
    _arm(widget, "cardia")
    happ.clickInView([11.0, 21.0, 31.0])
    qt.QApplication.processEvents()  # the older "cardia" is removed after the event, not inside it
    labels = [points.GetNthControlPointLabel(i) for i in range(points.GetNumberOfControlPoints())]
    assert labels.count("cardia") == 1
    p = [0.0] * 3
    points.GetNthControlPointPositionWorld(labels.index("cardia"), p)
    assert p == [11.0, 21.0, 31.0]


def test_previous_points_node_is_no_longer_observed(gui):
    """Defect 11: after switching the points node, the old one's placements are not labelled any more."""
    module, widget, scene = gui
    old = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "old")
    new = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "new")
    widget.ui.pointsSelector.setCurrentNode(old)
    widget.ui.pointsSelector.setCurrentNode(new)
    _arm(widget, "pylorus")
    old.AddControlPoint(vtk.vtkVector3d(1, 1, 1), "x")
    assert old.GetNthControlPointLabel(0) == "x"
    happ.clickInView([2.0, 2.0, 2.0])
    assert new.GetNthControlPointLabel(0) == "pylorus"


# ---------------------------------------------------------------- defect 12
class _Translator(qt.QTranslator):
    def translate(self, context, sourceText, disambiguation=None, n=-1):
        return "Magen entfalten" if (context, sourceText) == ("StomachUnfold", "Stomach Unfold") else None


def test_conventions_translation_help_link_contributors_and_sys_path(module):
    """Defect 12: strings go through slicer.i18n, help links the documentation, contributors are
    "Name (Organisation)", and importing the module leaves sys.path alone."""
    translator = _Translator()
    qt.QCoreApplication.installTranslator(translator)
    try:
        p = happ._ModuleParent(module.parent.path)
        module.pythonModule.StomachUnfold(p)
        assert p.title == "Magen entfalten"
    finally:
        qt.QCoreApplication.removeTranslator(translator)
    assert re.search(r'<a href="https?://[^"]+">', p.helpText)
    assert all(re.fullmatch(r"[^()]+ \([^()]+\)", c) for c in p.contributors)
    saved = list(sys.path)
    sys.path[:] = [s for s in sys.path if os.path.abspath(s or ".") != ROOT]
    try:
        before = list(sys.path)
        import importlib.util

        spec = importlib.util.spec_from_file_location("StomachUnfold_reimport", module.parent.path)
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
        assert sys.path == before
    finally:
        sys.path[:] = saved


# ---------------------------------------------------------------- a whole run, linked reading, the self-test
def test_unfold_in_the_gui_then_linked_findings_both_ways(gui):
    """Unfold from the panel (camera reset incl. clipping range), then a finding placed on either view shows in
    the other; one placed on the unfolded view jumps the CT slices to its original location."""
    module, widget, scene = gui
    volume, points = loadSample()
    p = widget._parameterNode
    p.inputVolume, p.pointsNode, p.gridSize, p.wallThicknessMm = volume, points, 3, 4.0
    camera = slicer.modules.cameras.logic().GetViewActiveCameraNode(
        slicer.app.layoutManager().threeDWidget(0).mrmlViewNode())
    resets = []
    camera.AddObserver(camera.ResetCameraClippingEvent, lambda c, e: resets.append(e))
    widget.ui.applyButton.click()
    assert p.outputVolume is not None and widget.ui.resultsLabel.text.split(";")[0].endswith(" s")
    assert resets and np.allclose(camera.GetFocalPoint(), widget.logic.viewerCamera(p.outputVolume)["focalPoint"])
    assert widget.ui.findingsCollapsibleButton.enabled
    # the distortion map is shown as a layer over the unfolded volume in the yellow view; the CT stays in red
    yellow = scene.GetSingletonNode("Yellow", "vtkMRMLSliceCompositeNode")
    red = scene.GetSingletonNode("Red", "vtkMRMLSliceCompositeNode")
    assert yellow.GetBackgroundVolumeID() == p.outputVolume.GetID()
    assert scene.GetNodeByID(yellow.GetForegroundVolumeID()).GetAttribute("StomachUnfold.distortionOf") == \
        p.outputVolume.GetID()
    assert red.GetBackgroundVolumeID() != p.outputVolume.GetID()
    assert "within 10 %" in widget.ui.resultsLabel.text
    result = widget.logic.results[p.outputVolume.GetID()]
    from StomachUnfoldLib.geometry import lps_to_ras

    mucosa = lps_to_ras(result.mesh.rest_lps[result.mesh.surface[len(result.mesh.surface) // 2][0]])
    # CT -> unfolded
    _arm(widget, "ctFinding")
    happ.clickInView(mucosa)
    assert p.unfoldedFindings.GetNumberOfControlPoints() == 1
    there = [0.0] * 3
    p.unfoldedFindings.GetNthControlPointPositionWorld(0, there)
    assert np.allclose(there, widget.logic.mapToUnfolded(p.outputVolume, mucosa), atol=1e-3)
    # unfolded -> CT, with a slice jump
    _arm(widget, "unfoldedFinding")
    happ.clickInView(there)
    assert p.ctFindings.GetNumberOfControlPoints() == 2
    back = [0.0] * 3
    p.ctFindings.GetNthControlPointPositionWorld(1, back)
    assert np.allclose(back, mucosa, atol=0.5)
    red = scene.GetSingletonNode("Red", "vtkMRMLSliceNode")
    assert abs(red.GetSliceToRAS().GetElement(2, 3) - back[2]) < 1e-3


def test_the_run_s_warnings_are_listed_in_the_panel_and_logged(gui, caplog):
    """The cardia and pylorus clicked the wrong way round: the run exchanges them, and the panel says so."""
    module, widget, scene = gui
    volume, points = loadSample()
    a, b = [0.0] * 3, [0.0] * 3
    points.GetNthControlPointPositionWorld(0, a)
    points.GetNthControlPointPositionWorld(1, b)
    points.SetNthControlPointPositionWorld(0, *b)
    points.SetNthControlPointPositionWorld(1, *a)
    p = widget._parameterNode
    p.inputVolume, p.pointsNode, p.gridSize, p.wallThicknessMm = volume, points, 3, 4.0
    with caplog.at_level("WARNING"):
        widget.ui.applyButton.click()
    assert p.outputVolume is not None
    text = widget.ui.resultsLabel.text
    assert "\nWarnings:\n- " in text and "probably swapped and have been exchanged" in text
    assert any("probably swapped" in r.getMessage() for r in caplog.records)


def test_module_self_test_passes_over_the_real_base_classes(module):
    """What ``Slicer --testing`` runs: slicer.selfTests["StomachUnfold"] (sample data through SampleData)."""
    happ.newScene()
    slicer.selfTests["StomachUnfold"](msec=10)


# ---------------------------------------------------------------- the stand-ins follow the real headers
HEADERS = {  # Q_PROPERTY names and signals, from Slicer's and CTK's headers
    "qMRMLNodeComboBox": (
        {"currentNodeID", "currentNodeId", "nodeTypes", "showHidden", "showChildNodeTypes", "hideChildNodeTypes",
         "baseName", "noneEnabled", "addEnabled", "removeEnabled", "editEnabled", "renameEnabled",
         "interactionNodeSingletonTag", "selectNodeUponCreation", "noneDisplay", "sizeAdjustPolicy"},
        {"currentNodeChanged", "currentNodeIDChanged", "nodeActivated", "nodeAdded", "nodeAddedByUser",
         "nodeAddedByUserAction", "nodeAboutToBeRemoved", "currentNodeRenamed", "nodeAboutToBeEdited"}),
    "qSlicerMarkupsPlaceWidget": (
        {"buttonsVisible", "deleteAllControlPointsOptionVisible", "unsetLastControlPointOptionVisible",
         "unsetAllControlPointsOptionVisible", "placeMultipleMarkups", "nodeColor", "defaultNodeColor",
         "currentNodeActive", "placeModeEnabled", "placeModePersistency", "deleteAllMarkupsOptionVisible"},
        {"activeMarkupsPlaceModeChanged", "activeMarkupsFiducialPlaceModeChanged", "mrmlSceneChanged"}),
    "ctkCollapsibleButton": (
        {"collapsed", "collapsedHeight", "contentsFrameShape", "contentsFrameShadow", "contentsLineWidth",
         "contentsMidLineWidth", "buttonTextAlignment", "indicatorAlignment"},
        {"contentsCollapsed"}),
}


@pytest.mark.parametrize("name", sorted(HEADERS))
def test_stand_ins_have_the_properties_and_signals_of_the_real_headers(name):
    """Each stand-in declares the header's Q_PROPERTYs and signals, and no signal or property the header lacks."""
    cls = getattr(slicer, name, None) or getattr(H.ctk, name)
    props, signals = HEADERS[name]
    mo = cls.staticMetaObject
    base = mo.superClass()
    while base.className().startswith(("qMRML", "qSlicer", "ctk")):
        base = base.superClass()
    own = {mo.property(i).name() for i in range(base.propertyCount(), mo.propertyCount())}
    ownSignals = {bytes(mo.method(i).name()).decode() for i in range(base.methodCount(), mo.methodCount())
                  if mo.method(i).methodType() == qt.QMetaMethod.Signal}
    assert props <= own and own <= props | {"isEntered"}, own ^ props
    assert ownSignals == signals, ownSignals ^ signals


# --- the Auto button (issue 17): fills movable cardia and pylorus points, warns when unsure --------------------

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


def _totalseg_label_node(widget, scene, vol, truth, lab):
    """The input volume set from ``vol`` and a TotalSegmentator-like label map node of its stomach (v2 numbers)."""
    from StomachUnfoldEval.auto_points import totalseg_labels

    widget._parameterNode.inputVolume = widget.logic.volumeNodeFromVolume(vol, "r0")
    labelNode = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "total")
    labelNode.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(vol.index_to_ras_matrix))
    slicer.util.updateVolumeFromArray(labelNode, np.ascontiguousarray(totalseg_labels(vol, lab, truth, "total")))
    return labelNode


def _click_auto(widget, scene, maskNode, monkeypatch):
    """Pick ``maskNode`` as the mask and press Auto: (the found points, warnings shown, classes of nodes added)."""
    widget._parameterNode.maskNode = maskNode
    warnings = []
    monkeypatch.setattr(slicer.util, "warningDisplay", lambda *a, **k: warnings.append(a))
    before = {scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())}
    widget.ui.autoPointsButton.click()
    added = {scene.GetNthNode(i).GetClassName() for i in range(scene.GetNumberOfNodes())
             if scene.GetNthNode(i).GetID() not in before}
    return widget.lastAutoPoints, warnings, added


def test_auto_reads_a_totalsegmentator_label_map_picked_as_the_mask(gui, stomach, monkeypatch):
    from StomachUnfoldLib.geometry import lps_to_ras

    module, widget, scene = gui
    (vol, truth, lab), _ = stomach
    labelNode = _totalseg_label_node(widget, scene, vol, truth, lab)
    found, warnings, added = _click_auto(widget, scene, labelNode, monkeypatch)
    assert found.source == "segmentation" and found.convention == "total" and warnings == []
    assert found.labels == {"stomach": 6, "esophagus": 15, "duodenum": 19}
    pts = _points(widget._parameterNode.pointsNode)
    assert np.linalg.norm(pts["cardia"][0] - lps_to_ras(np.asarray(truth["cardia_lps"]))) <= 10.0
    assert all("Markups" in c for c in added), added  # only the new point list: no label map left behind


def test_auto_reads_a_segmentation_by_segment_name_and_terminology(gui, stomach, monkeypatch):
    """A segmentation node (as SlicerTotalSegmentator makes): organs by segment name or SNOMED terminology code; a
    hidden segment before them must not shift which exported label is which."""
    from StomachUnfoldLib.geometry import lps_to_ras

    module, widget, scene = gui
    (vol, truth, lab), _ = stomach
    labelNode = _totalseg_label_node(widget, scene, vol, truth, lab)
    segNode = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "TotalSegmentator")
    assert slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelNode, segNode)
    scene.RemoveNode(labelNode)
    segNode.CreateDefaultDisplayNodes()
    segmentation = segNode.GetSegmentation()
    byValue = {segmentation.GetNthSegment(i).GetLabelValue(): segmentation.GetNthSegmentID(i)
               for i in range(segmentation.GetNumberOfSegments())}
    assert {1, 5, 6, 15, 19} <= set(byValue)
    segmentation.GetSegment(byValue[6]).SetName("stomach")
    oesophagus = segmentation.GetSegment(byValue[15])
    oesophagus.SetName("Segment_3")  # known by its terminology code only
    oesophagus.SetTerminology("Segmentation category and type - 3D Slicer General Anatomy list~SCT^123037004^"
                              "Anatomical Structure~SCT^32849002^Esophagus~^^~Anatomic codes - DICOM master list~^^~^^")
    segmentation.GetSegment(byValue[19]).SetName("duodenum")
    segNode.GetDisplayNode().SetSegmentVisibility(byValue[1], False)  # the spleen, first in order, hidden
    found, warnings, added = _click_auto(widget, scene, segNode, monkeypatch)
    assert found.source == "segmentation" and found.convention == "names" and warnings == [], found.evidence
    assert set(found.labels) == {"stomach", "esophagus", "duodenum"}
    pts = _points(widget._parameterNode.pointsNode)
    for name in ("cardia", "pylorus"):
        assert np.linalg.norm(pts[name][0] - lps_to_ras(np.asarray(truth[f"{name}_lps"]))) <= 10.0
    assert all("Markups" in c for c in added), added
