"""The Slicer module's Logic against real MRML nodes (slicer-core wheel), headless.

``Testing/slicer_stubs`` supplies only ScriptedLoadableModule and parameterNodeWrapper, which the wheel
lacks; scene, nodes, storage, volume rendering and displayable managers are the real ones.
"""
import os
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(HERE, "slicer_stubs"))
sys.path.insert(0, os.path.join(ROOT, "StomachUnfold"))
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

slicer = pytest.importorskip("slicer")
import vtk  # noqa: E402

from StomachUnfoldLib.phantom import make_phantom  # noqa: E402

NOTES = os.path.join(ROOT, "..", "shared", "notes", "slicer_core_headless")


def make_scene():
    """A scene wired like Slicer's application: colours, markups, volumes and volume-rendering logics."""
    scene = slicer.vtkMRMLScene()
    slicer.mrmlScene = scene
    app = slicer.vtkSlicerApplicationLogic()
    app.SetMRMLScene(scene)
    app.GetColorLogic().SetMRMLScene(scene)
    app.GetColorLogic().AddDefaultColorNodes()
    app.SetSliceLogics(vtk.vtkCollection())
    app.SetViewLogics(vtk.vtkCollection())
    logics = {}
    for name, logic in (("Colors", slicer.vtkMRMLColorLogic()), ("Markups", slicer.vtkSlicerMarkupsLogic()),
                        ("Volumes", slicer.vtkSlicerVolumesLogic()),
                        ("VolumeRendering", slicer.vtkSlicerVolumeRenderingLogic())):
        logic.SetMRMLScene(scene)
        logic.SetMRMLApplicationLogic(app)
        app.SetModuleLogic(name, logic)
        logics[name] = logic
    return scene, app, logics


@pytest.fixture
def ctx():
    scene, app, logics = make_scene()
    import StomachUnfold as mod

    logic = mod.StomachUnfoldLogic()
    logic.volumeRenderingLogic = logics["VolumeRendering"]
    yield scene, app, logics, logic, mod
    scene.Clear(True)


@pytest.fixture(scope="module")
def phantom():
    return make_phantom("j", "tiny")


def _inputs(scene, logic, phantom, transform=None):
    ct, truth = phantom
    vol = logic.volumeNodeFromVolume(ct, "CT")
    pts = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "points")
    pts.AddControlPoint(vtk.vtkVector3d(*truth["cardia_ras"]), "cardia")
    pts.AddControlPoint(vtk.vtkVector3d(*truth["pylorus_ras"]), "pylorus")
    return vol, pts


def _scene_state(scene):
    return sorted((n.GetID(), n.GetName()) for n in
                  (scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())))


def test_node_geometry_round_trip(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    ct, truth = phantom
    vol = logic.volumeNodeFromVolume(ct, "CT")
    m = vtk.vtkMatrix4x4()
    vol.GetIJKToRASMatrix(m)
    ras = np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])
    assert np.allclose(ras, ct.index_to_ras_matrix)
    back = logic.volumeFromNode(vol)
    assert np.array_equal(back.array, ct.array)
    assert np.allclose(back.origin, ct.origin) and np.allclose(back.direction, ct.direction)
    assert np.allclose(back.spacing, ct.spacing)


def test_points_in_world_coordinates_under_a_transform(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    vol, pts = _inputs(scene, logic, phantom)
    t = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    m = vtk.vtkMatrix4x4()
    m.SetElement(0, 3, 10.0)
    t.SetMatrixTransformToParent(m)
    pts.SetAndObserveTransformNodeID(t.GetID())
    cardia, pylorus = logic.pointsFromMarkups(pts)
    assert np.allclose(cardia, np.array(phantom[1]["cardia_ras"]) + [10, 0, 0])
    pts.SetNthControlPointLabel(1, "antrum")
    with pytest.raises(ValueError, match="pylorus"):
        logic.pointsFromMarkups(pts)


def test_unfold_makes_nodes_and_leaves_inputs_alone(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    vol, pts = _inputs(scene, logic, phantom)
    before = slicer.util.arrayFromVolume(vol).copy()
    cardia, pylorus = logic.pointsFromMarkups(pts)
    out = logic.unfold(vol, cardia, pylorus, gridSize=3, wallThicknessMm=4.0)
    assert np.array_equal(slicer.util.arrayFromVolume(vol), before)
    v = out["volume"]
    assert v.GetName().startswith("CT_unfolded") and v.GetImageData() is not None
    # geometry: IJK-to-RAS of the output is the library's unfolded volume geometry in RAS
    res = logic.results[v.GetID()]
    m = vtk.vtkMatrix4x4()
    v.GetIJKToRASMatrix(m)
    assert np.allclose([[m.GetElement(r, c) for c in range(4)] for r in range(4)], res.unfolded.index_to_ras_matrix)
    assert np.array_equal(slicer.util.arrayFromVolume(v), res.unfolded.array)
    dn = logics["VolumeRendering"].GetFirstVolumeRenderingDisplayNode(v)
    assert dn is not None and dn.GetVisibility()
    assert dn.GetVolumePropertyNode().GetVolumeProperty().GetScalarOpacity().GetValue(-1000) == 0.0
    assert out["incision"].IsA("vtkMRMLMarkupsCurveNode") and out["incision"].GetNumberOfControlPoints() > 10
    assert out["centerline"].GetNumberOfControlPoints() > 10
    assert out["model"].GetPolyData().GetNumberOfPoints() > 100
    assert out["report"]["quality"]["grade"] in ("excellent", "good")
    # unique names on a second run
    out2 = logic.unfold(vol, cardia, pylorus, gridSize=3, wallThicknessMm=4.0)
    assert out2["volume"].GetName() != v.GetName()


def test_correspondence_both_ways_and_slice_jump(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    vol, pts = _inputs(scene, logic, phantom)
    out = logic.unfold(vol, *logic.pointsFromMarkups(pts), gridSize=3, wallThicknessMm=4.0)
    marker = np.array(phantom[1]["markers"][3]["ras"])
    there = logic.mapToUnfolded(out["volume"], marker)
    back = logic.mapToOriginal(out["volume"], there)
    assert np.allclose(back, marker, atol=1e-3)
    assert logic.mapToUnfolded(out["volume"], [999.0, 999.0, 999.0]) is None
    red = scene.AddNewNodeByClass("vtkMRMLSliceNode")
    red.SetLayoutName("Red")
    red.SetOrientationToAxial()
    logic.jumpSlicesTo(back)
    m = red.GetSliceToRAS()
    assert abs(m.GetElement(2, 3) - back[2]) < 1e-3


def test_error_and_cancel_leave_the_scene_as_it_was(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    vol, pts = _inputs(scene, logic, phantom)
    state = _scene_state(scene)
    cardia, pylorus = logic.pointsFromMarkups(pts)
    with pytest.raises(ValueError, match="outside the volume"):
        logic.unfold(vol, cardia + [0, 0, 900.0], pylorus, gridSize=3)
    assert _scene_state(scene) == state
    from StomachUnfoldLib.errors import Cancelled
    with pytest.raises(Cancelled):
        logic.unfold(vol, cardia, pylorus, gridSize=3, progress=lambda s, f: s != "unfolded volume")
    assert _scene_state(scene) == state
    # a failure while the output nodes are being made removes the ones already made
    orig = logic._curveNode
    logic._curveNode = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("disk full"))
    with pytest.raises(RuntimeError):
        logic.unfold(vol, cardia, pylorus, gridSize=3, wallThicknessMm=4.0)
    logic._curveNode = orig
    assert _scene_state(scene) == state


def test_parameter_node_run(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    vol, pts = _inputs(scene, logic, phantom)
    p = logic.getParameterNode()
    assert p.gridSize == 0  # automatic: cells of 5.6 mm, d = 3 on the 1.8 mm phantom
    p.inputVolume, p.pointsNode, p.wallThicknessMm = vol, pts, 4.0
    out = logic.unfoldFromParameterNode(p)
    assert p.outputVolume is out["volume"]
    assert out["report"]["model"]["grid_size_d"] == 3 and out["report"]["parameters"]["grid_size"] is None
    with pytest.raises(ValueError):
        logic.unfold(vol, [0, 0, 0], [1, 1, 1], notAParameter=3)


def test_label_map_mask_from_a_node(ctx, phantom):
    scene, app, logics, logic, mod = ctx
    ct, truth = phantom
    vol, pts = _inputs(scene, logic, phantom)
    lab = logic.volumeNodeFromVolume(ct.with_array((ct.array < -500).astype(np.uint8)), "label")
    mask = logic.maskFromNode(lab, logic.volumeFromNode(vol))
    assert mask.shape == ct.array.shape and mask.sum() == (ct.array < -500).sum()


def test_volume_rendered_view_png_is_not_blank(ctx, phantom, tmp_path):
    scene, app, logics, logic, mod = ctx
    vol, pts = _inputs(scene, logic, phantom)
    out = logic.unfold(vol, *logic.pointsFromMarkups(pts), gridSize=3, wallThicknessMm=4.0)
    png = render_view_png(scene, app, logics["VolumeRendering"], out["volume"], out["camera"],
                          str(tmp_path / "vr.png"), size=(400, 300))
    r = vtk.vtkPNGReader()
    r.SetFileName(png)
    r.Update()
    from vtk.util import numpy_support as ns
    a = ns.vtk_to_numpy(r.GetOutput().GetPointData().GetScalars()).reshape(300, 400, -1)
    lit = a[..., :3].sum(-1) > 30
    assert lit.mean() > 0.05  # not blank
    # the mucosa colour (pink: red above blue) dominates what is lit
    rgb = a[..., :3][lit].astype(float)
    assert np.mean(rgb[:, 0] > rgb[:, 2]) > 0.8


def render_view_png(scene, app, vr_logic, volume_node, camera, png, size=(600, 450)):
    """Render the volume-rendered unfolded volume through the MRML displayable managers (offscreen) to a PNG."""
    vr_logic.SetDefaultRenderingMethod("vtkMRMLCPURayCastVolumeRenderingDisplayNode")
    dn = vr_logic.GetFirstVolumeRenderingDisplayNode(volume_node)
    if not dn.IsA("vtkMRMLCPURayCastVolumeRenderingDisplayNode"):
        vpn = dn.GetVolumePropertyNode()
        scene.RemoveNode(dn)
        dn = vr_logic.CreateVolumeRenderingDisplayNode("vtkMRMLCPURayCastVolumeRenderingDisplayNode")
        scene.AddNode(dn)
        dn.SetAndObserveVolumePropertyNodeID(vpn.GetID())
        volume_node.AddAndObserveDisplayNodeID(dn.GetID())
    dn.SetVisibility(True)
    factory = slicer.vtkMRMLThreeDViewDisplayableManagerFactory.GetInstance()
    factory.SetMRMLApplicationLogic(app)
    for name in ("vtkMRMLVolumeRenderingDisplayableManager", "vtkMRMLCameraDisplayableManager",
                 "vtkMRMLViewDisplayableManager", "vtkMRMLModelDisplayableManager"):
        if not factory.IsDisplayableManagerRegistered(name):
            factory.RegisterDisplayableManager(name)
    ren = vtk.vtkRenderer()
    rw = vtk.vtkRenderWindow()
    rw.SetOffScreenRendering(1)
    rw.AddRenderer(ren)
    rw.SetSize(*size)
    iren = vtk.vtkRenderWindowInteractor()
    iren.SetRenderWindow(rw)
    iren.Initialize()
    group = slicer.vtkMRMLDisplayableManagerGroup()
    group.Initialize(factory, ren)
    view_logic = slicer.vtkMRMLViewLogic()
    view_logic.SetMRMLApplicationLogic(app)
    view_logic.SetMRMLScene(scene)
    view_node = scene.GetSingletonNode("1", "vtkMRMLViewNode") or view_logic.AddViewNode("1")
    view_node.SetBoxVisible(False)
    view_node.SetAxisLabelsVisible(False)
    view_node.SetBackgroundColor(0, 0, 0)
    view_node.SetBackgroundColor2(0, 0, 0)
    group.SetMRMLDisplayableNode(view_node)
    cam = ren.GetActiveCamera()
    cam.SetPosition(*camera["position"])
    cam.SetFocalPoint(*camera["focalPoint"])
    cam.SetViewUp(*camera["viewUp"])
    ren.ResetCameraClippingRange()
    rw.Render()
    w2i = vtk.vtkWindowToImageFilter()
    w2i.SetInput(rw)
    w2i.ReadFrontBufferOff()
    w2i.Update()
    wr = vtk.vtkPNGWriter()
    wr.SetFileName(png)
    wr.SetInputConnection(w2i.GetOutputPort())
    wr.Write()
    group.SetMRMLDisplayableNode(None)
    rw.Finalize()
    return png


def test_module_self_test_runs_headless(ctx):
    """The module's own ScriptedLoadableModuleTest (what Slicer --testing runs) passes on real MRML nodes."""
    scene, app, logics, logic, mod = ctx
    t = mod.StomachUnfoldTest()
    t.setUp = lambda: None  # the harness scene is already fresh; slicer.mrmlScene.Clear() also works
    t.runTest()
    names = [scene.GetNthNode(i).GetName() for i in range(scene.GetNumberOfNodes())]
    assert any(n.startswith("phantom_unfolded") for n in names)
