"""StomachUnfold: virtual unfolded views of the stomach, a 3D Slicer scripted module.

Two clicks (cardia, pylorus) and Unfold: the stomach wall is cut open along an incision line and spread
flat (Oda et al.), and shown as a new volume rendered in 3D. The work is done by ``StomachUnfoldLib``
(pure Python); this file only converts MRML nodes to arrays and back (Logic) and holds the GUI (Widget).
Coordinates: MRML nodes are RAS (world), the library works in LPS; the conversion is in ``volumeFromNode``.
"""
import logging
import os
import sys

import numpy as np
import vtk

import slicer
from slicer.ScriptedLoadableModule import (ScriptedLoadableModule, ScriptedLoadableModuleLogic,
                                           ScriptedLoadableModuleTest, ScriptedLoadableModuleWidget)

# From the source tree ("Add module path" pointing at this folder) the library sits one level up.
_HERE = os.path.dirname(os.path.abspath(__file__))
for _candidate in (_HERE, os.path.dirname(_HERE)):
    if os.path.isdir(os.path.join(_candidate, "StomachUnfoldLib")) and _candidate not in sys.path:
        sys.path.insert(0, _candidate)

try:  # Slicer >= 5.4; not in the slicer-core wheel used by the headless tests
    from slicer.parameterNodeWrapper import parameterNodeWrapper
except ImportError:  # pragma: no cover - the stand-in used in the tests provides it
    parameterNodeWrapper = None

INCISION_SIDES = ("greater", "lesser", "anterior", "posterior")


#
# Module
#
class StomachUnfold(ScriptedLoadableModule):
    """Module description shown in Slicer."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "Stomach Unfold"
        self.parent.categories = ["Gastrointestinal"]
        self.parent.dependencies = []
        self.parent.contributors = ["StomachUnfold developers"]
        self.parent.helpText = (
            "Virtual unfolded view of the stomach from CT (Oda et al., semi-automated VU view generation). "
            "Select the CT, place the cardia and the pylorus, press Unfold. The unfolded volume is rendered "
            "from the viewer's side with the mucosa facing you. For a stomach without gas give a stomach "
            "segmentation or label volume.")
        self.parent.acknowledgementText = (
            "Method: M. Oda et al., Semi-Automated Virtual Unfolded View Generation Method of Stomach from CT "
            "Volumes. Computation: StomachUnfoldLib (NumPy/SciPy).")
        if hasattr(slicer, "app") and hasattr(slicer.app, "connect"):
            slicer.app.connect("startupCompleted()", registerSampleData)


def _phantomSampleLoader(*args, **kwargs):
    """Make the synthetic stomach phantom (no download) and load it, with its cardia/pylorus points."""
    from StomachUnfoldLib.phantom import make_phantom

    ct, truth = make_phantom("j", "small")
    logic = StomachUnfoldLogic()
    volumeNode = logic.volumeNodeFromVolume(ct, "StomachPhantom")
    points = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "StomachPhantomPoints")
    points.AddControlPoint(vtk.vtkVector3d(*truth["cardia_ras"]), "cardia")
    points.AddControlPoint(vtk.vtkVector3d(*truth["pylorus_ras"]), "pylorus")
    return [volumeNode]


def registerSampleData():
    """Register the synthetic stomach phantom in the Sample Data module (generated locally, nothing downloaded)."""
    try:
        import SampleData
    except ImportError:
        return
    iconsPath = os.path.join(_HERE, "Resources", "Icons")
    SampleData.SampleDataLogic.registerCustomSampleDataSource(
        category="StomachUnfold", sampleName="StomachPhantom",
        thumbnailFileName=os.path.join(iconsPath, "StomachUnfold.png"),
        uris=None, fileNames=None, nodeNames="StomachPhantom",
        customDownloader=_phantomSampleLoader)


#
# Parameter node
#
def _makeParameterNodeClass():
    if parameterNodeWrapper is None:
        return None

    @parameterNodeWrapper
    class StomachUnfoldParameterNode:
        """Saved with the scene (.mrb): inputs, parameters and the last output of a run."""

        inputVolume: slicer.vtkMRMLScalarVolumeNode
        pointsNode: slicer.vtkMRMLMarkupsFiducialNode
        maskNode: slicer.vtkMRMLNode = None
        gridSize: int = 0  # d in voxels; 0: automatic, cells of DEFAULT_CELL_MM (5.6 mm, the paper's d = 8 at 0.7 mm)
        kappa: float = 0.5
        incision: str = "greater"
        wallThicknessMm: float = 5.0
        beta: float = 0.25
        gamma: float = 0.5
        timeStep: float = 1.0
        springStiffness: float = 1.0
        damping: float = 0.5
        maxIterations: int = 300
        outputVolume: slicer.vtkMRMLScalarVolumeNode = None

    return StomachUnfoldParameterNode


StomachUnfoldParameterNode = _makeParameterNodeClass()

#: parameter-node field -> UnfoldParameters field
PARAMETER_MAP = {"gridSize": "grid_size", "kappa": "kappa", "incision": "incision",
                 "wallThicknessMm": "wall_thickness_mm", "beta": "beta", "gamma": "gamma", "timeStep": "time_step",
                 "springStiffness": "spring_stiffness", "damping": "damping", "maxIterations": "max_iterations"}


#
# Logic
#
class StomachUnfoldLogic(ScriptedLoadableModuleLogic):
    """Converts MRML nodes to arrays, runs StomachUnfoldLib, returns new nodes. No Qt; usable from the console.

    Example (Python console)::

        logic = slicer.util.getModuleLogic("StomachUnfold")  # or StomachUnfoldLogic()
        out = logic.unfold(getNode("CT"), cardiaRAS=[-31, 0, 73], pylorusRAS=[58, 0, -28], kappa=0.5)
        out["volume"], out["report"]["quality"]["grade"]
    """

    def __init__(self, scene=None):
        ScriptedLoadableModuleLogic.__init__(self)
        self.scene = scene
        self.volumeRenderingLogic = None  # set by tests or found in slicer.modules
        self.results = {}  # unfolded volume node ID -> UnfoldResult (for the correspondence)

    # ------------------------------------------------------------------ helpers
    def _scene(self):
        return self.scene if self.scene is not None else slicer.mrmlScene

    def getParameterNode(self):
        """The module's parameter node wrapped for typed access (Slicer >= 5.4)."""
        if StomachUnfoldParameterNode is None:
            raise RuntimeError("parameterNodeWrapper is not available in this Slicer")
        return StomachUnfoldParameterNode(super().getParameterNode())

    @staticmethod
    def _worldMatrix(node):
        """4x4 numpy matrix from the node's parent transform to world (identity if none); error if non-linear."""
        parent = node.GetParentTransformNode()
        m = vtk.vtkMatrix4x4()
        if parent is not None:
            if not parent.IsTransformToWorldLinear():
                raise ValueError(f"{node.GetName()} is under a non-linear transform; harden the transform first")
            parent.GetMatrixTransformToWorld(m)
        return np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])

    def volumeFromNode(self, volumeNode):
        """Library Volume (LPS geometry, array [k, j, i]) from a scalar volume node, parent transform applied.

        The array is a copy: the node is never modified.
        """
        from StomachUnfoldLib.geometry import Volume

        if volumeNode is None or volumeNode.GetImageData() is None:
            raise ValueError("select an input CT volume that holds image data")
        if volumeNode.GetImageData().GetNumberOfScalarComponents() != 1:
            raise ValueError(f"{volumeNode.GetName()} has several components per voxel; select a scalar CT volume")
        arr = np.array(slicer.util.arrayFromVolume(volumeNode), copy=True)
        ijkToRas = vtk.vtkMatrix4x4()
        volumeNode.GetIJKToRASMatrix(ijkToRas)
        m = self._worldMatrix(volumeNode) @ np.array([[ijkToRas.GetElement(r, c) for c in range(4)] for r in range(4)])
        lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ m
        A = lps[:3, :3]
        spacing = np.linalg.norm(A, axis=0)
        direction = A / spacing[None, :]
        if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4):
            raise ValueError(f"{volumeNode.GetName()} is sheared (non-orthogonal axes); resample it first")
        return Volume(arr, spacing, lps[:3, 3], direction)

    def volumeNodeFromVolume(self, volume, name, scene=None):
        """New scalar volume node (unique name) holding a library Volume (LPS geometry converted to RAS)."""
        scene = scene or self._scene()
        node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", scene.GenerateUniqueName(name))
        self._setVolumeGeometry(node, volume)
        slicer.util.updateVolumeFromArray(node, np.ascontiguousarray(volume.array))
        node.CreateDefaultDisplayNodes()
        return node

    @staticmethod
    def _setVolumeGeometry(node, volume):
        ras = volume.index_to_ras_matrix
        node.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(ras))

    def pointsFromMarkups(self, pointsNode):
        """Cardia and pylorus positions (RAS world mm) from the control points labelled 'cardia' and 'pylorus'."""
        if pointsNode is None:
            raise ValueError("place the cardia and pylorus points first")
        found = {}
        for i in range(pointsNode.GetNumberOfControlPoints()):
            label = (pointsNode.GetNthControlPointLabel(i) or "").strip().lower()
            if label in ("cardia", "pylorus"):
                if label in found:
                    raise ValueError(f"two control points are labelled '{label}'; keep one")
                p = [0.0, 0.0, 0.0]
                pointsNode.GetNthControlPointPositionWorld(i, p)
                found[label] = np.array(p)
        missing = [n for n in ("cardia", "pylorus") if n not in found]
        if missing:
            raise ValueError(f"no control point labelled {' or '.join(missing)} in {pointsNode.GetName()}; "
                             "place both points (the labels tell which is which)")
        return found["cardia"], found["pylorus"]

    def maskFromNode(self, maskNode, referenceVolume):
        """Bool stomach mask on the reference Volume's grid from a label map volume or a segmentation node."""
        from StomachUnfoldLib.io import read_label_volume

        if maskNode is None:
            return None
        scene = self._scene()
        tmp = None
        try:
            if maskNode.IsA("vtkMRMLSegmentationNode"):
                tmp = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode")
                logic = slicer.vtkSlicerSegmentationsModuleLogic()
                if not logic.ExportVisibleSegmentsToLabelmapNode(maskNode, tmp):
                    raise ValueError(f"could not export {maskNode.GetName()} to a label map")
                labelNode = tmp
            elif maskNode.IsA("vtkMRMLScalarVolumeNode"):
                labelNode = maskNode
            else:
                raise ValueError(f"{maskNode.GetName()} is neither a segmentation nor a label map volume")
            return read_label_volume(self.volumeFromNode(labelNode), referenceVolume)
        finally:
            if tmp is not None:
                scene.RemoveNode(tmp)

    # ------------------------------------------------------------------ the run
    def unfold(self, volumeNode, cardiaRAS, pylorusRAS, maskNode=None, progress=None, **params):
        """Unfold the stomach of ``volumeNode`` between two RAS points (mm); returns a dict of new nodes and the report.

        ``params`` are StomachUnfoldLib.pipeline.UnfoldParameters fields (snake_case) or this module's
        parameter names (gridSize: d in voxels, 0 or None for cells of 5.6 mm; kappa, incision, wallThicknessMm,
        beta, gamma, timeStep, springStiffness, damping, maxIterations). ``progress(stage, fraction)`` may return False to cancel. On error or
        cancel no node is left in the scene and the input nodes are unchanged.
        """
        from StomachUnfoldLib.geometry import ras_to_lps
        from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

        kwargs = {PARAMETER_MAP.get(k, k): v for k, v in params.items()}
        if kwargs.get("grid_size") == 0:  # the panel's "automatic" cell size
            kwargs["grid_size"] = None
        try:
            unfoldParams = UnfoldParameters(**kwargs)
        except TypeError as e:
            raise ValueError(f"unknown parameter: {e}") from None
        ct = self.volumeFromNode(volumeNode)
        mask = self.maskFromNode(maskNode, ct)
        result = unfold(ct, ras_to_lps(np.asarray(cardiaRAS, float)), ras_to_lps(np.asarray(pylorusRAS, float)),
                        unfoldParams, mask=mask, progress=progress)
        return self._makeOutputNodes(result, volumeNode.GetName())

    def unfoldFromParameterNode(self, parameterNode=None, progress=None):
        """Run with the inputs and parameters of a (wrapped) parameter node; stores the output volume in it."""
        p = parameterNode or self.getParameterNode()
        if p.inputVolume is None:
            raise ValueError("select an input CT volume")
        cardia, pylorus = self.pointsFromMarkups(p.pointsNode)
        params = {name: getattr(p, name) for name in PARAMETER_MAP}
        out = self.unfold(p.inputVolume, cardia, pylorus, maskNode=p.maskNode, progress=progress, **params)
        p.outputVolume = out["volume"]
        return out

    def _makeOutputNodes(self, result, baseName):
        """Create the output nodes all together; remove every one of them if any step fails."""
        scene = self._scene()
        created = []
        try:
            vol = self.volumeNodeFromVolume(result.unfolded, f"{baseName}_unfolded", scene)
            created.append(vol)
            vol.SetAttribute("StomachUnfold.report", _json(result.report))
            created += self._showVolumeRendering(vol)
            inc = self._curveNode(result.incision_lps, f"{baseName}_incision", (1.0, 0.3, 0.2))
            created.append(inc)
            cl = self._curveNode(result.centerline_lps, f"{baseName}_centerline", (0.2, 0.8, 1.0))
            created.append(cl)
            model = self._modelNode(result.deformed_vertices, result.hexes, f"{baseName}_unfolded_wall")
            created.append(model)
        except Exception:
            for node in reversed(created):
                self._removeWithDisplays(node)
            raise
        self.results[vol.GetID()] = result
        return {"volume": vol, "incision": inc, "centerline": cl, "model": model, "report": result.report,
                "camera": self.viewerCamera(vol)}

    def _removeWithDisplays(self, node):
        """Remove a node made by a run together with its display and storage nodes."""
        scene = self._scene()
        if node is None or not scene.IsNodePresent(node):
            return
        if node.IsA("vtkMRMLDisplayableNode"):
            for i in reversed(range(node.GetNumberOfDisplayNodes())):
                dn = node.GetNthDisplayNode(i)
                if dn is not None and scene.IsNodePresent(dn):
                    scene.RemoveNode(dn)
        if node.IsA("vtkMRMLStorableNode") and node.GetStorageNode() is not None:
            scene.RemoveNode(node.GetStorageNode())
        scene.RemoveNode(node)

    def _curveNode(self, points_lps, name, color):
        from StomachUnfoldLib.geometry import lps_to_ras

        scene = self._scene()
        node = scene.AddNewNodeByClass("vtkMRMLMarkupsCurveNode", scene.GenerateUniqueName(name))
        pts = vtk.vtkPoints()
        for p in lps_to_ras(np.asarray(points_lps, float)):
            pts.InsertNextPoint(*p)
        node.SetControlPointPositionsWorld(pts)
        node.SetLocked(True)
        node.CreateDefaultDisplayNodes()
        dn = node.GetDisplayNode()
        if dn is not None:
            dn.SetSelectedColor(*color)
            dn.SetColor(*color)
            dn.SetPointLabelsVisibility(False)
        return node

    def _modelNode(self, vertices_lps, hexes, name):
        from StomachUnfoldLib.wall_model import model_to_vtk

        scene = self._scene()
        grid = model_to_vtk(vertices_lps, hexes, frame="RAS")
        surface = vtk.vtkGeometryFilter()
        surface.SetInputData(grid)
        surface.Update()
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", scene.GenerateUniqueName(name))
        node.SetAndObservePolyData(surface.GetOutput())
        node.CreateDefaultDisplayNodes()
        dn = node.GetDisplayNode()
        if dn is not None:
            dn.SetColor(0.9, 0.6, 0.55)
            dn.SetOpacity(0.3)
            dn.SetVisibility(False)
        return node

    # ------------------------------------------------------------------ display
    def _vrLogic(self):
        if self.volumeRenderingLogic is not None:
            return self.volumeRenderingLogic
        modules = getattr(slicer, "modules", None)
        if modules is not None and hasattr(modules, "volumerendering"):
            return modules.volumerendering.logic()
        return None

    def _showVolumeRendering(self, volumeNode):
        """Volume-render the unfolded volume with the mucosa transfer function; returns the nodes it created."""
        vr = self._vrLogic()
        if vr is None:
            logging.warning("volume rendering logic not available; the unfolded volume is not rendered")
            return []
        displayNode = vr.CreateDefaultVolumeRenderingNodes(volumeNode)
        mucosaVolumeProperty(displayNode.GetVolumePropertyNode().GetVolumeProperty())
        displayNode.SetVisibility(True)
        return [displayNode.GetVolumePropertyNode(), displayNode.GetROINode() if hasattr(displayNode, "GetROINode")
                else None, displayNode]

    @staticmethod
    def viewerCamera(volumeNode, distanceFactor=2.2):
        """Camera (RAS mm) looking down -k at the unfolded volume: position, focal point and view-up (+j)."""
        m = vtk.vtkMatrix4x4()
        volumeNode.GetIJKToRASMatrix(m)
        M = np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])
        dims = np.array(volumeNode.GetImageData().GetDimensions(), float)
        centre = (M @ np.r_[(dims - 1) / 2.0, 1.0])[:3]
        k = M[:3, 2] / np.linalg.norm(M[:3, 2])
        j = M[:3, 1] / np.linalg.norm(M[:3, 1])
        extent = float(np.max((dims - 1) * np.linalg.norm(M[:3, :3], axis=0)))
        return {"position": (centre + distanceFactor * extent * k).tolist(), "focalPoint": centre.tolist(),
                "viewUp": j.tolist()}

    @staticmethod
    def applyCamera(cameraNode, camera):
        """Point a camera node (e.g. the 3D view's) at the unfolded volume from the viewer's side."""
        cameraNode.SetPosition(*camera["position"])
        cameraNode.SetFocalPoint(*camera["focalPoint"])
        cameraNode.SetViewUp(*camera["viewUp"])

    # ------------------------------------------------------------------ correspondence
    def mapToOriginal(self, unfoldedVolumeNode, pointRAS):
        """Map a point (RAS mm) of an unfolded volume back into the original CT (RAS mm); None if off the wall."""
        return self._map(unfoldedVolumeNode, pointRAS, "to_original")

    def mapToUnfolded(self, unfoldedVolumeNode, pointRAS):
        """Map a point (RAS mm) of the original CT into the unfolded volume (RAS mm); None if off the wall."""
        return self._map(unfoldedVolumeNode, pointRAS, "to_unfolded")

    def _map(self, unfoldedVolumeNode, pointRAS, direction):
        from StomachUnfoldLib.geometry import lps_to_ras, ras_to_lps

        result = self.results.get(unfoldedVolumeNode.GetID())
        if result is None:
            raise ValueError(f"{unfoldedVolumeNode.GetName()} was not made in this session; its correspondence "
                             "is not available")
        f = getattr(result.correspondence, direction)
        p = f(ras_to_lps(np.asarray(pointRAS, float))[None])[0]
        return None if not np.all(np.isfinite(p)) else lps_to_ras(p)

    def jumpSlicesTo(self, pointRAS):
        """Centre every slice view of the scene on a point (RAS mm)."""
        slicer.vtkMRMLSliceNode.JumpAllSlices(self._scene(), *[float(v) for v in pointRAS])


def mucosaVolumeProperty(volumeProperty, thresholdHU=-400.0):
    """Fill a vtkVolumeProperty for the unfolded view: air clear, mucosa opaque pink, dense markers yellow."""
    opacity = vtk.vtkPiecewiseFunction()
    opacity.AddPoint(-1024, 0.0)
    opacity.AddPoint(thresholdHU - 100, 0.0)
    opacity.AddPoint(thresholdHU + 150, 0.85)
    opacity.AddPoint(300, 0.95)
    opacity.AddPoint(3071, 1.0)
    color = vtk.vtkColorTransferFunction()
    color.AddRGBPoint(-1024, 0.0, 0.0, 0.0)
    color.AddRGBPoint(thresholdHU, 0.75, 0.42, 0.38)
    color.AddRGBPoint(60, 0.93, 0.62, 0.58)
    color.AddRGBPoint(200, 0.98, 0.8, 0.6)
    color.AddRGBPoint(400, 1.0, 0.95, 0.45)
    color.AddRGBPoint(3071, 1.0, 1.0, 0.8)
    volumeProperty.SetScalarOpacity(opacity)
    volumeProperty.SetColor(color)
    volumeProperty.ShadeOn()
    volumeProperty.SetAmbient(0.3)
    volumeProperty.SetDiffuse(0.7)
    volumeProperty.SetSpecular(0.2)
    volumeProperty.SetInterpolationTypeToLinear()
    return volumeProperty


def _json(obj):
    import json

    from StomachUnfoldLib.pipeline import _json_default

    return json.dumps(obj, default=_json_default)


#
# Widget
#
class StomachUnfoldWidget(ScriptedLoadableModuleWidget):
    """Thin GUI: inputs, two place buttons, parameters, Unfold/Cancel with progress, results."""

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        self.logic = None
        self._parameterNode = None
        self._running = False
        self._cancelRequested = False
        self._nextLabel = None

    def setup(self):
        import qt  # noqa: F401  (GUI only)

        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(self.resourcePath("UI/StomachUnfold.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = StomachUnfoldLogic()
        self.ui.incisionComboBox.addItems(list(INCISION_SIDES))
        self.ui.cardiaPlaceWidget.setMRMLScene(slicer.mrmlScene)
        self.ui.pylorusPlaceWidget.setMRMLScene(slicer.mrmlScene)
        self.ui.cardiaPlaceWidget.placeButton().connect("clicked(bool)", lambda on: self._armLabel("cardia", on))
        self.ui.pylorusPlaceWidget.placeButton().connect("clicked(bool)", lambda on: self._armLabel("pylorus", on))
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.pointsSelector.connect("currentNodeChanged(vtkMRMLNode*)", self._onPointsNodeChanged)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.initializeParameterNode()
        self.ui.progressBar.hide()

    def cleanup(self):
        self.removeObservers()

    def enter(self):
        self.initializeParameterNode()

    def onSceneStartClose(self, caller, event):
        self._parameterNode = None

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self):
        self._parameterNode = self.logic.getParameterNode()
        if not self._parameterNode.inputVolume:
            first = slicer.mrmlScene.GetFirstNodeByClass("vtkMRMLScalarVolumeNode")
            if first:
                self._parameterNode.inputVolume = first
        if not self._parameterNode.pointsNode:
            node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "StomachPoints")
            self._parameterNode.pointsNode = node
        self._parameterNode.connectGui(self.ui)
        self._onPointsNodeChanged(self._parameterNode.pointsNode)

    def _onPointsNodeChanged(self, node):
        for w in (self.ui.cardiaPlaceWidget, self.ui.pylorusPlaceWidget):
            w.setCurrentNode(node)
        if node is not None:
            self.addObserver(node, slicer.vtkMRMLMarkupsNode.PointPositionDefinedEvent, self._onPointPlaced)

    def _armLabel(self, label, on):
        """The next point placed gets this label; an earlier point with the label is replaced."""
        self._nextLabel = label if on else None

    def _onPointPlaced(self, caller, event):
        if self._nextLabel is None:
            return
        n = caller.GetNumberOfControlPoints()
        for i in reversed(range(n - 1)):
            if (caller.GetNthControlPointLabel(i) or "").lower() == self._nextLabel:
                caller.RemoveNthControlPoint(i)
        caller.SetNthControlPointLabel(caller.GetNumberOfControlPoints() - 1, self._nextLabel)
        self._nextLabel = None

    def _progress(self, stage, fraction):
        import qt

        self.ui.progressBar.setValue(int(100 * fraction))
        self.ui.progressBar.setFormat(f"{stage}: %p%")
        slicer.app.processEvents(qt.QEventLoop.ExcludeUserInputEvents | qt.QEventLoop.AllEvents)
        return not self._cancelRequested

    def onApplyButton(self):
        """Unfold, or cancel a run in progress (the button turns into Cancel while running)."""
        import qt

        if self._running:
            self._cancelRequested = True
            return
        self._running, self._cancelRequested = True, False
        self.ui.applyButton.text = "Cancel"
        self.ui.progressBar.show()
        try:
            with slicer.util.tryWithErrorDisplay("Unfolding failed.", waitCursor=True):
                out = self.logic.unfoldFromParameterNode(self._parameterNode, progress=self._progress)
                r = out["report"]
                q = r.get("quality", {})
                self.ui.resultsLabel.text = (
                    f"{r['seconds']['total']:.1f} s, {r['iterations']} iterations, {r['model']['hexahedra']} "
                    f"hexahedra; grade {q.get('grade', '?')}, {100 * q.get('visible_fraction', 0):.0f}% of the "
                    "mucosa visible")
                viewNode = slicer.app.layoutManager().threeDWidget(0).mrmlViewNode()
                cameraNode = slicer.modules.cameras.logic().GetViewActiveCameraNode(viewNode)
                StomachUnfoldLogic.applyCamera(cameraNode, out["camera"])
        finally:
            self._running = False
            self.ui.applyButton.text = "Unfold"
            self.ui.progressBar.hide()


#
# Test (runs inside Slicer: Slicer --no-main-window --testing --python-code "...")
#
class StomachUnfoldTest(ScriptedLoadableModuleTest):
    """Loads the phantom, places the points, runs the Logic and checks the outputs."""

    def setUp(self):
        slicer.mrmlScene.Clear()

    def runTest(self):
        self.setUp()
        self.test_unfold_phantom()

    def test_unfold_phantom(self):
        from StomachUnfoldLib.phantom import make_phantom

        ct, truth = make_phantom("j", "tiny")
        logic = StomachUnfoldLogic()
        volumeNode = logic.volumeNodeFromVolume(ct, "phantom")
        points = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "points")
        points.AddControlPoint(vtk.vtkVector3d(*truth["cardia_ras"]), "cardia")
        points.AddControlPoint(vtk.vtkVector3d(*truth["pylorus_ras"]), "pylorus")
        cardia, pylorus = logic.pointsFromMarkups(points)
        out = logic.unfold(volumeNode, cardia, pylorus, gridSize=3, wallThicknessMm=4.0)
        self.assertIsNotNone(out["volume"].GetImageData())
        self.assertGreater(out["report"]["iterations"], 0)
        self.assertIn(out["report"]["quality"]["grade"], ("excellent", "good"))
        self.assertGreater(out["incision"].GetNumberOfControlPoints(), 10)
        self.delayDisplay("StomachUnfold test passed")
