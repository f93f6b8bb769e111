"""The Slicer module's Logic against real MRML nodes (slicer-core wheel), headless.

The module is loaded over Slicer's real ScriptedLoadableModule and parameterNodeWrapper through
``Testing/slicer_harness`` (skips with the reason when ``../shared/slicer_python`` is absent); scene, nodes,
storage, volume rendering and displayable managers are the real ones. Input: the module's sample phantom.
"""
import os

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
import slicer_harness  # noqa: E402  (Testing/ is on sys.path, as for conftest)

slicer_harness.require()
import slicer
import vtk
from slicer_harness import app as happ

RUN = dict(gridSize=3, wallThicknessMm=4.0)


@pytest.fixture(scope="module")
def env():
    """One scene with the module loaded, the sample phantom, and one unfold shared by the tests."""
    scene, app, logics = happ.newScene()
    module = happ.ModulePanel(os.path.join(ROOT, "StomachUnfold"), "StomachUnfold")
    import SampleData

    vol, pts = SampleData.downloadSamples("StomachPhantom")
    logic = module.pythonModule.StomachUnfoldLogic()
    logic.volumeRenderingLogic = logics["VolumeRendering"]
    before = slicer.util.arrayFromVolume(vol).copy()
    out = logic.unfold(vol, *logic.pointsFromMarkups(pts), **RUN)
    return dict(scene=scene, app=app, logics=logics, mod=module.pythonModule, logic=logic, vol=vol, pts=pts,
                out=out, before=before)


def _scene_state(scene):
    return sorted((n.GetID(), n.GetName()) for n in
                  (scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())))


def test_node_geometry_round_trip(env):
    logic, vol = env["logic"], env["vol"]
    ct = logic.volumeFromNode(vol)
    node = logic.volumeNodeFromVolume(ct, "CT copy")
    m = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(m)
    assert np.allclose([[m.GetElement(r, c) for c in range(4)] for r in range(4)], ct.index_to_ras_matrix)
    back = logic.volumeFromNode(node)
    assert np.array_equal(back.array, ct.array)
    assert np.allclose(back.origin, ct.origin) and np.allclose(back.direction, ct.direction)
    assert np.allclose(back.spacing, ct.spacing)
    env["scene"].RemoveNode(node)


def test_points_in_world_coordinates_under_a_transform(env):
    scene, logic, pts = env["scene"], env["logic"], env["pts"]
    cardia0, _ = logic.pointsFromMarkups(pts)
    t = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    m = vtk.vtkMatrix4x4()
    m.SetElement(0, 3, 10.0)
    t.SetMatrixTransformToParent(m)
    pts.SetAndObserveTransformNodeID(t.GetID())
    try:
        cardia, pylorus = logic.pointsFromMarkups(pts)
        assert np.allclose(cardia, cardia0 + [10, 0, 0])
        pts.SetNthControlPointLabel(1, "antrum")
        with pytest.raises(ValueError, match="pylorus"):
            logic.pointsFromMarkups(pts)
    finally:
        pts.SetNthControlPointLabel(1, "pylorus")
        pts.SetAndObserveTransformNodeID(None)
        scene.RemoveNode(t)


def test_unfold_makes_nodes_and_leaves_inputs_alone(env):
    logic, vol, out, logics = env["logic"], env["vol"], env["out"], env["logics"]
    assert np.array_equal(slicer.util.arrayFromVolume(vol), env["before"])
    v = out["volume"]
    assert v.GetName().startswith("StomachPhantom_unfolded") and v.GetImageData() is not None
    res = logic.results[v.GetID()]
    m = vtk.vtkMatrix4x4()
    v.GetIJKToRASMatrix(m)
    assert np.allclose([[m.GetElement(r, c) for c in range(4)] for r in range(4)], res.unfolded.index_to_ras_matrix)
    assert np.array_equal(slicer.util.arrayFromVolume(v), res.unfolded.array)
    dn = logics["VolumeRendering"].GetFirstVolumeRenderingDisplayNode(v)
    assert dn is not None and dn.GetVisibility()
    assert dn.GetVolumePropertyNode().GetScalarOpacity().GetValue(-1000) == 0.0
    assert out["incision"].IsA("vtkMRMLMarkupsCurveNode") and out["incision"].GetNumberOfControlPoints() > 10
    assert out["centerline"].GetNumberOfControlPoints() > 10
    assert out["model"].GetPolyData().GetNumberOfPoints() > 100
    # the distortion map as a layer on the unfolded volume's grid: area scale, 1 where the view is true
    d = out["distortion"]
    area = slicer.util.arrayFromVolume(d)
    dm = res.distortion()
    assert area.shape == (1,) + res.unfolded.array.shape[1:]
    assert np.allclose(area[0][dm.covered], dm.area_scale[dm.covered]) and (area[0][~dm.covered] == 0).all()
    assert 0.5 < float(np.median(area[0][dm.covered])) < 2.0
    assert d.GetAttribute("StomachUnfold.distortionOf") == v.GetID()
    # shown as a layer over the unfolded volume in a slice view turned to the view's plane
    scene = slicer.mrmlScene
    sliceNode = scene.AddNewNodeByClass("vtkMRMLSliceNode")
    sliceNode.SetLayoutName("Test")
    composite = scene.AddNewNodeByClass("vtkMRMLSliceCompositeNode")
    composite.SetLayoutName("Test")
    try:
        assert logic.showDistortionLayer(sliceNode, v, d) is composite
        assert composite.GetBackgroundVolumeID() == v.GetID() and composite.GetForegroundVolumeID() == d.GetID()
        assert composite.GetForegroundOpacity() == 0.5
        normal = [sliceNode.GetSliceToRAS().GetElement(r, 2) for r in range(3)]
        k_axis = res.unfolded.index_to_ras_matrix[:3, 2] / np.linalg.norm(res.unfolded.index_to_ras_matrix[:3, 2])
        assert abs(abs(np.dot(normal, k_axis)) - 1.0) < 1e-6   # the slice plane is the view's (i, j) plane
    finally:
        scene.RemoveNode(composite)
        scene.RemoveNode(sliceNode)
    assert out["report"]["quality"]["grade"] in ("excellent", "good")
    import json

    assert json.loads(v.GetAttribute("StomachUnfold.report"))["quality"]["grade"] == out["report"]["quality"]["grade"]


def test_correspondence_both_ways_and_slice_jump(env):
    scene, logic, out = env["scene"], env["logic"], env["out"]
    from StomachUnfoldLib.geometry import lps_to_ras

    mesh = logic.results[out["volume"].GetID()].mesh
    mucosa = lps_to_ras(mesh.rest_lps[mesh.surface[len(mesh.surface) // 3][0]])
    there = logic.mapToUnfolded(out["volume"], mucosa)
    back = logic.mapToOriginal(out["volume"], there)
    assert np.allclose(back, mucosa, atol=0.5)
    assert logic.mapToUnfolded(out["volume"], [999.0, 999.0, 999.0]) is None
    red = scene.AddNewNodeByClass("vtkMRMLSliceNode")
    red.SetLayoutName("RedTest")
    red.SetOrientationToAxial()
    logic.jumpSlicesTo(back)
    assert abs(red.GetSliceToRAS().GetElement(2, 3) - back[2]) < 1e-3
    scene.RemoveNode(red)


def test_error_and_cancel_leave_the_scene_as_it_was(env):
    scene, logic, vol, pts = env["scene"], env["logic"], env["vol"], env["pts"]
    state = _scene_state(scene)
    cardia, pylorus = logic.pointsFromMarkups(pts)
    with pytest.raises(ValueError, match="outside the volume"):
        logic.unfold(vol, cardia + [0, 0, 900.0], pylorus, gridSize=3)
    assert _scene_state(scene) == state
    from StomachUnfoldLib.errors import Cancelled

    with pytest.raises(Cancelled):
        logic.unfold(vol, cardia, pylorus, gridSize=3, progress=lambda s, f: f < 0.1)
    assert _scene_state(scene) == state

    class DiskFull(RuntimeError):
        pass

    # a failure while the output nodes are being made removes the ones already made
    result = next(iter(logic.results.values()))
    orig = logic._curveNode
    logic._curveNode = lambda *a, **k: (_ for _ in ()).throw(DiskFull("disk full"))
    try:
        with pytest.raises(DiskFull):
            logic._makeOutputNodes(result, "again")
    finally:
        logic._curveNode = orig
    assert _scene_state(scene) == state


def test_parameter_node_run(env):
    logic, vol, pts = env["logic"], env["vol"], env["pts"]
    p = logic.getParameterNode()
    assert p.gridSize == 0  # automatic: cells of 5.6 mm, d = 3 on the 1.8 mm phantom
    params = logic.unfoldParameters(**{n: getattr(p, n) for n in env["mod"].PARAMETER_MAP})
    assert params.grid_size is None and params.method == p.method
    with pytest.raises(ValueError):
        logic.unfold(vol, [0, 0, 0], [1, 1, 1], notAParameter=3)
    with pytest.raises(ValueError, match="select an input CT"):
        logic.unfoldFromParameterNode(p)


def test_label_map_mask_from_a_node(env):
    scene, logic, vol = env["scene"], env["logic"], env["vol"]
    ct = logic.volumeFromNode(vol)
    lab = logic.volumeNodeFromVolume(ct.with_array((ct.array < -500).astype(np.uint8)), "label")
    mask = logic.maskFromNode(lab, ct)
    assert mask.shape == ct.array.shape and mask.sum() == (ct.array < -500).sum()
    scene.RemoveNode(lab)


def test_volume_rendered_view_png_is_not_blank(env, tmp_path):
    scene, app, logics, out = env["scene"], env["app"], env["logics"], env["out"]
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


def _segmentation(scene, logic, ct, labels, name):
    """A segmentation node imported from a label array on the CT's grid (one segment per label value)."""
    lab = logic.volumeNodeFromVolume(ct.with_array(labels.astype(np.uint8)), "lab")
    lab2 = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "lab2")
    lab2.SetAndObserveImageData(lab.GetImageData())
    m = vtk.vtkMatrix4x4()
    lab.GetIJKToRASMatrix(m)
    lab2.SetIJKToRASMatrix(m)
    seg = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", name)
    assert slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(lab2, seg)
    seg.CreateDefaultDisplayNodes()
    for node in (lab, lab2):
        scene.RemoveNode(node)
    return seg


def test_segmentation_masks_empty_several_or_chosen_segment(env):
    scene, logic, vol, pts = env["scene"], env["logic"], env["vol"], env["pts"]
    ct = logic.volumeFromNode(vol)
    cardia, pylorus = logic.pointsFromMarkups(pts)
    empty = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "empty")
    state = _scene_state(scene)
    with pytest.raises(ValueError, match="empty holds no segment"):
        logic.unfold(vol, cardia, pylorus, maskNode=empty, **RUN)
    assert _scene_state(scene) == state
    gas = ct.array < -500
    two = _segmentation(scene, logic, ct, gas + 2 * (ct.array > 200), "two")
    state = _scene_state(scene)
    with pytest.raises(ValueError, match=r"two has 2 visible segments.*maskSegmentId"):
        logic.unfold(vol, cardia, pylorus, maskNode=two, **RUN)
    with pytest.raises(ValueError, match="no segment 'nonsense'"):
        logic.maskFromNode(two, ct, "nonsense")
    assert _scene_state(scene) == state
    first = two.GetSegmentation().GetNthSegmentID(0)
    assert logic.maskFromNode(two, ct, first).sum() == gas.sum()
    two.GetDisplayNode().SetSegmentVisibility(two.GetSegmentation().GetNthSegmentID(1), False)
    assert logic.maskFromNode(two, ct).sum() == gas.sum()  # the one visible segment
    assert _scene_state(scene) == state
    for node in (empty, two):
        scene.RemoveNode(node)


@pytest.mark.parametrize("bad", [None, "abc", [1.0, 2.0], [0.0, float("nan"), 1.0]])
def test_points_that_are_not_three_numbers_give_a_clear_error(env, bad):
    scene, logic, vol, pts = env["scene"], env["logic"], env["vol"], env["pts"]
    state = _scene_state(scene)
    _, pylorus = logic.pointsFromMarkups(pts)
    with pytest.raises(ValueError, match="cardiaRAS must be three finite numbers"):
        logic.unfold(vol, bad, pylorus, **RUN)
    assert _scene_state(scene) == state


def test_a_point_not_placed_is_not_used(env):
    logic, pts = env["logic"], env["pts"]
    p = [0.0, 0.0, 0.0]
    pts.GetNthControlPointPosition(0, p)
    label = pts.GetNthControlPointLabel(0)
    pts.UnsetNthControlPointPosition(0)
    try:
        with pytest.raises(ValueError, match=label):
            logic.pointsFromMarkups(pts)
    finally:
        pts.SetNthControlPointPosition(0, *p)
    assert np.allclose(logic.pointsFromMarkups(pts)[0 if label == "cardia" else 1], p)


def test_a_batch_of_the_scenes_volumes_writes_the_command_lines_outputs(env, tmp_path):
    scene, logic, vol, pts = env["scene"], env["logic"], env["vol"], env["pts"]
    before = _scene_state(scene)
    seen = []
    rows = logic.unfoldBatch([(vol, pts)], str(tmp_path / "out"), method="cylindrical",
                             progress=lambda stage, fraction: seen.append(fraction))
    assert [r["status"] for r in rows] == ["ok"], rows
    assert rows[0]["case"] == vol.GetName() and rows[0]["method"] == "cylindrical"
    assert os.path.exists(tmp_path / "out" / vol.GetName() / "view.png")
    assert os.path.exists(tmp_path / "out" / "summary.csv") and seen[-1] == 1.0
    assert _scene_state(scene) == before  # files only, no node
    again = logic.unfoldBatch([(vol, pts)], str(tmp_path / "out"), method="cylindrical")
    assert again[0]["reused"] is True  # the same CT and points: done, reused
