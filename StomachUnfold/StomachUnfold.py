"""StomachUnfold: virtual unfolded views of the stomach, a 3D Slicer scripted module.

Two clicks (cardia, pylorus) and Unfold: the stomach wall is cut open along an incision line and spread
flat (Oda et al.), and shown as a new volume rendered in 3D. The work is done by ``StomachUnfoldLib``
(pure Python on what Slicer bundles: NumPy, SciPy, SimpleITK, VTK); this file converts MRML nodes to arrays
and back (Logic) and holds the GUI (Widget). Coordinates: MRML nodes are RAS (world), the library works in
LPS; the conversion is in ``volumeFromNode``.
"""
import hashlib
import json
import logging
import os
import pathlib
from typing import Annotated, Optional, Union

import numpy as np
import slicer
import vtk
from slicer import (
    vtkMRMLLabelMapVolumeNode,
    vtkMRMLMarkupsFiducialNode,
    vtkMRMLScalarVolumeNode,
    vtkMRMLSegmentationNode,
)
from slicer.i18n import tr as _
from slicer.i18n import translate
from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper
from slicer.ScriptedLoadableModule import (
    ScriptedLoadableModule,
    ScriptedLoadableModuleLogic,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
)
from slicer.util import VTKObservationMixin

try:  # the one definition of the choices is the library's
    from StomachUnfoldLib.methods import method_names
    from StomachUnfoldLib.params import DEFAULT_METHOD, INCISION_SIDES
    METHOD_NAMES = tuple(method_names())
except ImportError:  # not installed yet: Unfold offers to install it (then Slicer restarts with the real choices)
    DEFAULT_METHOD = "massspring"
    INCISION_SIDES, METHOD_NAMES = ("greater",), (DEFAULT_METHOD,)

# TODO(lead): the project's public address once published; docs/slicer.md is the page this points at.
DOCUMENTATION_URL = "https://github.com/StomachUnfold/StomachUnfold/blob/main/docs/slicer.md"
SAMPLE_FILES = (("StomachPhantom.nrrd", "StomachPhantom", "VolumeFile"),
                ("StomachPhantomPoints.mrk.json", "StomachPhantomPoints", "MarkupsFile"))
#: Python packages the library needs; import name -> pip requirement (all bundled with Slicer today).
REQUIRED_PACKAGES = {"numpy": "numpy", "scipy": "scipy", "SimpleITK": "SimpleITK", "vtk": "vtk"}


#
# Module
#
class StomachUnfold(ScriptedLoadableModule):
    """Module description shown in Slicer."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = _("Stomach Unfold")
        self.parent.categories = [translate("qSlicerAbstractCoreModule", "Gastrointestinal")]
        self.parent.dependencies = []
        self.parent.contributors = ["StomachUnfold developers (StomachUnfold project)"]
        self.parent.helpText = _(
            "Virtual unfolded view of the stomach from CT (Oda et al., semi-automated virtual unfolded view "
            "generation). Select the CT, place the cardia and the pylorus, press Unfold. The unfolded volume "
            "is rendered from the viewer's side with the mucosa facing you. For a stomach without gas give a "
            "stomach segmentation or label map.") + "<p>" + _(
            "See the {link_start}module documentation{link_end}.").format(
            link_start=f'<a href="{DOCUMENTATION_URL}">', link_end="</a>") + "</p>"
        self.parent.acknowledgementText = _(
            "Method: M. Oda et al., Semi-Automated Virtual Unfolded View Generation Method of Stomach from CT "
            "Volumes. Computation: StomachUnfoldLib (NumPy, SciPy, SimpleITK, VTK).")
        slicer.app.connect("startupCompleted()", registerSampleData)


def _fileSha256(path):
    """SHA256 hex digest of a file (for Sample Data's cache check)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def registerSampleData():
    """Register the stomach phantom shipped in Resources/SampleData (a file:// source) with Sample Data."""
    import SampleData

    resources = os.path.join(os.path.dirname(__file__), "Resources")
    dataDir = os.path.join(resources, "SampleData")
    paths = [os.path.join(dataDir, name) for name, _node, _type in SAMPLE_FILES]
    SampleData.SampleDataLogic.registerCustomSampleDataSource(
        category="StomachUnfold", sampleName="StomachPhantom",
        thumbnailFileName=os.path.join(resources, "Icons", "StomachUnfold.png"),
        uris=[pathlib.Path(p).as_uri() for p in paths],
        fileNames=[name for name, _node, _type in SAMPLE_FILES],
        nodeNames=[node for _name, node, _type in SAMPLE_FILES],
        loadFileTypes=[t for _name, _node, t in SAMPLE_FILES],
        checksums=[f"SHA256:{_fileSha256(p)}" for p in paths])


#
# Parameter node
#
@parameterNodeWrapper
class StomachUnfoldParameterNode:
    """Saved with the scene (.mrb): inputs, parameters (ranges as in the panel) and the outputs of the last run."""

    inputVolume: vtkMRMLScalarVolumeNode
    pointsNode: vtkMRMLMarkupsFiducialNode
    # typing.Union, not "|": the real parameterNodeWrapper checks typing.get_origin(...) == typing.Union
    maskNode: Optional[Union[vtkMRMLSegmentationNode, vtkMRMLLabelMapVolumeNode]]  # noqa: UP007, UP045
    method: Annotated[str, Choice(METHOD_NAMES)] = DEFAULT_METHOD
    gridSize: Annotated[int, WithinRange(0, 32)] = 0  # d in voxels; 0: automatic, cells of 5.6 mm
    kappa: Annotated[float, WithinRange(0.01, 10.0)] = 0.5
    incision: Annotated[str, Choice(INCISION_SIDES)] = "greater"
    wallThicknessMm: Annotated[float, WithinRange(0.5, 30.0)] = 5.0
    beta: Annotated[float, WithinRange(0.001, 0.5)] = 0.25
    gamma: Annotated[float, WithinRange(0.001, 1.0)] = 0.5
    timeStep: Annotated[float, WithinRange(0.01, 100.0)] = 1.0
    springStiffness: Annotated[float, WithinRange(0.01, 100.0)] = 1.0
    damping: Annotated[float, WithinRange(0.0, 100.0)] = 0.5
    maxIterations: Annotated[int, WithinRange(1, 10000)] = 300
    maskSegmentId: str = ""  # the stomach's segment of a segmentation mask ("": its only visible segment)
    outputVolume: vtkMRMLScalarVolumeNode
    ctFindings: vtkMRMLMarkupsFiducialNode
    unfoldedFindings: vtkMRMLMarkupsFiducialNode


#: parameter-node field -> UnfoldParameters keyword
PARAMETER_MAP = {"method": "method", "gridSize": "grid_size", "kappa": "kappa", "incision": "incision",
                 "wallThicknessMm": "wall_thickness_mm", "beta": "beta", "gamma": "gamma", "timeStep": "time_step",
                 "springStiffness": "spring_stiffness", "damping": "damping", "maxIterations": "max_iterations"}


def missingPackages():
    """Pip requirements of the packages the library needs that this Python cannot import (empty if none)."""
    import importlib.util

    return [req for name, req in REQUIRED_PACKAGES.items() if importlib.util.find_spec(name) is None]


def libraryAvailable():
    """True when StomachUnfoldLib can be imported."""
    import importlib.util

    try:
        return importlib.util.find_spec("StomachUnfoldLib") is not None
    except (ImportError, ValueError):
        return False


def librarySourceTree():
    """The repository root when this module runs from a source tree beside StomachUnfoldLib, else None."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if os.path.isfile(os.path.join(root, "StomachUnfoldLib", "__init__.py")) and os.path.isfile(
            os.path.join(root, "pyproject.toml")):
        return root
    return None


def _jsonDefault(o):
    """JSON for NumPy scalars/arrays and objects with to_dict (the report before it has to_json)."""
    if hasattr(o, "to_dict"):
        return o.to_dict()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def reportToJson(report):
    """The run's report as a JSON string."""
    if hasattr(report, "to_json"):
        return report.to_json()
    return json.dumps(report, default=_jsonDefault)


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
        """scene: the MRML scene to work in (default slicer.mrmlScene at each call)."""
        ScriptedLoadableModuleLogic.__init__(self)
        self.scene = scene
        self.volumeRenderingLogic = None  # found in slicer.modules unless set
        self.results = {}  # unfolded volume node ID -> UnfoldResult (for the correspondence)

    # ------------------------------------------------------------------ helpers
    def _scene(self):
        return self.scene if self.scene is not None else slicer.mrmlScene

    def getParameterNode(self):
        """The module's parameter node wrapped for typed access."""
        return StomachUnfoldParameterNode(super().getParameterNode())

    @staticmethod
    def _worldMatrix(node):
        """4x4 numpy matrix from the node's parent transform to world (identity if none); error if non-linear."""
        parent = node.GetParentTransformNode()
        m = vtk.vtkMatrix4x4()
        if parent is not None:
            if not parent.IsTransformToWorldLinear():
                raise ValueError(_("{name} is under a non-linear transform; harden the transform first").format(
                    name=node.GetName()))
            parent.GetMatrixTransformToWorld(m)
        return np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])

    def volumeFromNode(self, volumeNode):
        """Library Volume (LPS geometry, array [k, j, i]) from a scalar volume node, parent transform applied.

        The array is a copy: the node is never modified.
        """
        from StomachUnfoldLib.geometry import Volume

        if volumeNode is None or volumeNode.GetImageData() is None:
            raise ValueError(_("select an input CT volume that holds image data"))
        if volumeNode.GetImageData().GetNumberOfScalarComponents() != 1:
            raise ValueError(_("{name} has several components per voxel; select a scalar CT volume").format(
                name=volumeNode.GetName()))
        arr = np.array(slicer.util.arrayFromVolume(volumeNode), copy=True)
        ijkToRas = vtk.vtkMatrix4x4()
        volumeNode.GetIJKToRASMatrix(ijkToRas)
        m = self._worldMatrix(volumeNode) @ np.array([[ijkToRas.GetElement(r, c) for c in range(4)] for r in range(4)])
        lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ m
        A = lps[:3, :3]
        spacing = np.linalg.norm(A, axis=0)
        direction = A / spacing[None, :]
        if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4):
            raise ValueError(_("{name} is sheared (non-orthogonal axes); resample it first").format(
                name=volumeNode.GetName()))
        return Volume(arr, spacing, lps[:3, 3], direction)

    def volumeNodeFromVolume(self, volume, name, scene=None):
        """New scalar volume node (unique name) holding a library Volume (LPS geometry converted to RAS)."""
        scene = scene or self._scene()
        node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", scene.GenerateUniqueName(name))
        node.SetIJKToRASMatrix(slicer.util.vtkMatrixFromArray(volume.index_to_ras_matrix))
        slicer.util.updateVolumeFromArray(node, np.ascontiguousarray(volume.array))
        node.CreateDefaultDisplayNodes()
        return node

    def pointsFromMarkups(self, pointsNode):
        """Cardia and pylorus positions (RAS world mm) from the control points labelled 'cardia' and 'pylorus'."""
        if pointsNode is None:
            raise ValueError(_("place the cardia and pylorus points first"))
        found = {}
        for i in range(pointsNode.GetNumberOfControlPoints()):
            if pointsNode.GetNthControlPointPositionStatus(i) != pointsNode.PositionDefined:
                continue
            label = (pointsNode.GetNthControlPointLabel(i) or "").strip().lower()
            if label in ("cardia", "pylorus"):
                if label in found:
                    raise ValueError(_("two control points are labelled '{label}'; keep one").format(label=label))
                p = [0.0, 0.0, 0.0]
                pointsNode.GetNthControlPointPositionWorld(i, p)
                found[label] = np.array(p)
        missing = [n for n in ("cardia", "pylorus") if n not in found]
        if missing:
            raise ValueError(_("no control point labelled {labels} in {name}; place both points (the labels tell "
                               "which is which)").format(labels=" / ".join(missing), name=pointsNode.GetName()))
        return found["cardia"], found["pylorus"]

    def maskFromNode(self, maskNode, referenceVolume, segmentId=None):
        """Bool stomach mask on the reference Volume's grid from a label map volume or a segmentation node.

        Of a segmentation, the segment ``segmentId`` is used, else its one visible segment; several visible
        segments and none chosen, no segment, or an empty one give a ValueError saying what to do. The export goes
        through a temporary label map; every node it adds to the scene (the label map, its display node, a colour
        table) is removed again, also on error.
        """
        from StomachUnfoldLib.io import read_label_volume

        if maskNode is None:
            return None
        scene = self._scene()
        if maskNode.IsA("vtkMRMLSegmentationNode"):
            chosen = self._maskSegment(maskNode, segmentId)
            before = {scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())}
            try:
                tmp = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode")
                ids = vtk.vtkStringArray()
                ids.InsertNextValue(chosen)
                if (not slicer.vtkSlicerSegmentationsModuleLogic.ExportSegmentsToLabelmapNode(maskNode, ids, tmp)
                        or tmp.GetImageData() is None):
                    raise ValueError(_("the segment '{segment}' of {name} is empty or has no label map; paint the "
                                       "stomach into it, or choose another segment").format(
                        segment=maskNode.GetSegmentation().GetSegment(chosen).GetName(), name=maskNode.GetName()))
                return read_label_volume(self.volumeFromNode(tmp), referenceVolume)
            finally:
                added = [scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())]
                for node in reversed([n for n in added if n.GetID() not in before]):
                    scene.RemoveNode(node)
        if maskNode.IsA("vtkMRMLScalarVolumeNode"):
            return read_label_volume(self.volumeFromNode(maskNode), referenceVolume)
        raise ValueError(_("{name} is neither a segmentation nor a label map volume").format(name=maskNode.GetName()))

    def labelsFromNode(self, maskNode, referenceVolume):
        """(int label array on the reference Volume's grid, {label value: segment name and terminology} or None)
        from a multi-label map volume or a segmentation node (exported as maskFromNode does; the scene is kept)."""
        from StomachUnfoldLib.landmarks import labels_on_grid

        if maskNode is None:
            return None, None
        if maskNode.IsA("vtkMRMLSegmentationNode"):
            scene = self._scene()
            before = {scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())}
            try:
                tmp = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode")
                if not slicer.vtkSlicerSegmentationsModuleLogic.ExportVisibleSegmentsToLabelmapNode(maskNode, tmp):
                    raise ValueError(_("could not export {name} to a label map").format(name=maskNode.GetName()))
                seg = maskNode.GetSegmentation()
                display = maskNode.GetDisplayNode()
                # the export numbers the visible segments 1, 2, ... in the segmentation's order
                visible = [seg.GetNthSegmentID(i) for i in range(seg.GetNumberOfSegments())
                           if display is None or display.GetSegmentVisibility(seg.GetNthSegmentID(i))]
                names = {}
                for value, segmentId in enumerate(visible, start=1):
                    segment = seg.GetSegment(segmentId)
                    term = ""
                    if hasattr(segment, "GetTerminology"):
                        term = segment.GetTerminology() or ""
                    else:
                        tag = vtk.mutable("") if hasattr(vtk, "mutable") else None
                        if tag is not None and segment.GetTag("TerminologyEntry", tag):
                            term = str(tag)
                    names[value] = f"{segment.GetName()} {term}".strip()
                return labels_on_grid(self.volumeFromNode(tmp), referenceVolume), names
            finally:
                added = [scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())]
                for node in reversed([n for n in added if n.GetID() not in before]):
                    scene.RemoveNode(node)
        return labels_on_grid(self.volumeFromNode(maskNode), referenceVolume), None

    def autoPoints(self, volumeNode, pointsNode, maskNode=None):
        """Find the cardia and pylorus (StomachUnfoldLib.landmarks) and put them into ``pointsNode`` as control points
        labelled 'cardia' and 'pylorus' (RAS world mm; earlier ones with those labels replaced); the AutoPoints."""
        from StomachUnfoldLib.geometry import lps_to_ras
        from StomachUnfoldLib.landmarks import find_points

        ct = self.volumeFromNode(volumeNode)
        labels, names = self.labelsFromNode(maskNode, ct)
        found = find_points(ct, labels, names)
        for label, p in (("cardia", found.cardia_lps), ("pylorus", found.pylorus_lps)):
            for i in reversed(range(pointsNode.GetNumberOfControlPoints())):
                if (pointsNode.GetNthControlPointLabel(i) or "").strip().lower() == label:
                    pointsNode.RemoveNthControlPoint(i)
            index = pointsNode.AddControlPointWorld(vtk.vtkVector3d(*lps_to_ras(p)), label)
            pointsNode.SetNthControlPointLocked(index, False)
        return found

    @staticmethod
    def _maskSegment(segmentationNode, segmentId=None):
        """The ID of the stomach segment of a segmentation node: ``segmentId``, else its only visible segment."""
        seg = segmentationNode.GetSegmentation()
        ids = [seg.GetNthSegmentID(i) for i in range(seg.GetNumberOfSegments())]
        name = segmentationNode.GetName()
        if not ids:
            raise ValueError(_("{name} holds no segment; segment the stomach first, or clear the mask").format(
                name=name))
        listing = ", ".join(f"'{seg.GetSegment(i).GetName()}' ({i})" for i in ids[:12])
        if segmentId:
            if segmentId not in ids:
                raise ValueError(_("{name} has no segment '{segment}'; it holds {listing}").format(
                    name=name, segment=segmentId, listing=listing))
            return segmentId
        display = segmentationNode.GetDisplayNode()
        visible = [i for i in ids if display is None or display.GetSegmentVisibility(i)]
        if len(visible) != 1:
            raise ValueError(_("{name} has {n} visible segments ({listing}); choose the stomach's segment "
                               "(maskSegmentId) or show only it").format(name=name, n=len(visible), listing=listing))
        return visible[0]

    @staticmethod
    def _pointRAS(value, name):
        """A point as a float array of three finite RAS mm; ValueError naming it otherwise (None, text, 2 values)."""
        try:
            p = np.asarray(value, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            p = None
        if value is None or isinstance(value, str) or p is None or p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(_("{name} must be three finite numbers R, A, S in mm, got {value!r}").format(
                name=name, value=value))
        return p

    @staticmethod
    def unfoldParameters(**params):
        """StomachUnfoldLib UnfoldParameters from snake_case keywords or this module's parameter names."""
        from StomachUnfoldLib.pipeline import UnfoldParameters

        kwargs = {PARAMETER_MAP.get(k, k): v for k, v in params.items()}
        if kwargs.get("grid_size") == 0:  # the panel's "automatic" cell size
            kwargs["grid_size"] = None
        try:
            return UnfoldParameters(**kwargs)
        except TypeError as e:
            raise ValueError(_("unknown parameter: {error}").format(error=e)) from None

    # ------------------------------------------------------------------ the run
    def unfold(self, volumeNode, cardiaRAS, pylorusRAS, maskNode=None, progress=None, maskSegmentId=None, **params):
        """Unfold the stomach of ``volumeNode`` between two RAS points (mm); returns a dict of new nodes and the report.

        ``params`` are StomachUnfoldLib UnfoldParameters keywords (snake_case) or this module's parameter
        names (method, gridSize: d in voxels, 0 or None for cells of 5.6 mm; kappa, incision, wallThicknessMm,
        beta, gamma, timeStep, springStiffness, damping, maxIterations). ``progress(stage, fraction)`` may
        return False to cancel (raises StomachUnfoldLib.errors.Cancelled). On error or cancel no node is left
        in the scene and the input nodes are unchanged. ``maskSegmentId``: the stomach's segment of a segmentation
        ``maskNode`` (default: its only visible segment).
        """
        from StomachUnfoldLib.geometry import ras_to_lps
        from StomachUnfoldLib.pipeline import unfold

        cardia, pylorus = self._pointRAS(cardiaRAS, "cardiaRAS"), self._pointRAS(pylorusRAS, "pylorusRAS")
        unfoldParams = self.unfoldParameters(**params)
        ct = self.volumeFromNode(volumeNode)
        mask = self.maskFromNode(maskNode, ct, maskSegmentId)
        result = unfold(ct, ras_to_lps(cardia), ras_to_lps(pylorus), unfoldParams, mask=mask, progress=progress)
        return self._makeOutputNodes(result, volumeNode.GetName())

    def unfoldFromParameterNode(self, parameterNode=None, progress=None):
        """Run with the inputs and parameters of a (wrapped) parameter node; stores the output volume in it."""
        p = parameterNode or self.getParameterNode()
        if p.inputVolume is None:
            raise ValueError(_("select an input CT volume"))
        cardia, pylorus = self.pointsFromMarkups(p.pointsNode)
        params = {name: getattr(p, name) for name in PARAMETER_MAP}
        out = self.unfold(p.inputVolume, cardia, pylorus, maskNode=p.maskNode, progress=progress,
                          maskSegmentId=p.maskSegmentId or None, **params)
        p.outputVolume = out["volume"]
        return out

    # ------------------------------------------------------------------ a batch (the command line's `batch`)
    def unfoldBatch(self, cases, outputDir, progress=None, sweep=None, **params):
        """Unfold several CTs into ``outputDir/NAME/`` (the command line's output files) and write its summary.

        ``cases``: a folder (every NAME.nrrd / .nii.gz / .mha with a NAME.mrk.json beside it), a manifest .csv,
        or a list of (volumeNode, pointsNode) pairs of this scene, saved first into ``outputDir/inputs/``. The
        cases run here one after the other (Slicer has no Dask), done ones are reused on a rerun; ``params``
        as for :meth:`unfold`; ``progress(stage, fraction)`` is called as cases finish. Returns the summary
        rows (``status`` ok or error with its message); no node is added to the scene.
        """
        import os

        from StomachUnfoldLib.batch import manifest_from_folder, read_manifest, run_batch
        from StomachUnfoldLib.geometry import ras_to_lps
        from StomachUnfoldLib.io import write_markups_fiducials, write_volume

        base = self.unfoldParameters(**params).flat()
        if isinstance(cases, str):
            jobs = read_manifest(cases) if cases.lower().endswith(".csv") else manifest_from_folder(cases)
        else:
            folder = os.path.join(outputDir, "inputs")
            for volumeNode, pointsNode in cases:
                name = volumeNode.GetName()
                cardia, pylorus = self.pointsFromMarkups(pointsNode)
                write_volume(self.volumeFromNode(volumeNode), os.path.join(folder, name + ".nrrd"))
                write_markups_fiducials(os.path.join(folder, name + ".mrk.json"),
                                        {"cardia": ras_to_lps(cardia), "pylorus": ras_to_lps(pylorus)}, name)
            jobs = manifest_from_folder(folder)
        return run_batch(jobs, outputDir, sweep=sweep, progress=progress, base_params=base)

    def _makeOutputNodes(self, result, baseName):
        """Create the output nodes all together; remove every one of them if any step fails."""
        scene = self._scene()
        before = {scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())}
        try:
            vol = self.volumeNodeFromVolume(result.unfolded, f"{baseName}_unfolded", scene)
            vol.SetAttribute("StomachUnfold.report", reportToJson(result.report))
            self._showVolumeRendering(vol)
            inc = self._curveNode(result.incision_lps, f"{baseName}_incision", (1.0, 0.3, 0.2))
            cl = self._curveNode(result.centerline_lps, f"{baseName}_centerline", (0.2, 0.8, 1.0))
            model = self._modelNode(result, f"{baseName}_unfolded_wall")
            distortion = self._distortionNode(result, f"{baseName}_distortion", vol)
        except Exception:
            added = [scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())]
            for node in reversed([n for n in added if n.GetID() not in before]):
                scene.RemoveNode(node)
            raise
        self.results[vol.GetID()] = result
        return {"volume": vol, "incision": inc, "centerline": cl, "model": model, "distortion": distortion,
                "report": result.report, "camera": self.viewerCamera(vol)}

    def showDistortionLayer(self, sliceNode, unfoldedNode, distortionNode, opacity=0.5):
        """Show the unfolded volume in one slice view, turned to its own (i, j) plane at the mucosa, with the
        distortion map over it as the foreground layer (``opacity`` 0-1); returns the slice composite node."""
        scene = self._scene()
        composite = None
        for i in range(scene.GetNumberOfNodesByClass("vtkMRMLSliceCompositeNode")):
            node = scene.GetNthNodeByClass(i, "vtkMRMLSliceCompositeNode")
            if node.GetLayoutName() == sliceNode.GetLayoutName():
                composite = node
                break
        if composite is None:
            raise ValueError(_("no slice view {name} to show the distortion map in").format(
                name=sliceNode.GetLayoutName()))
        composite.SetBackgroundVolumeID(unfoldedNode.GetID())
        composite.SetForegroundVolumeID(distortionNode.GetID())
        composite.SetForegroundOpacity(float(opacity))
        sliceNode.RotateToVolumePlane(distortionNode)
        bounds = [0.0] * 6
        distortionNode.GetRASBounds(bounds)
        centre = [(bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2, (bounds[4] + bounds[5]) / 2]
        sliceNode.JumpSliceByCentering(*centre)
        return composite

    def _distortionNode(self, result, name, unfoldedNode):
        """Scalar volume of the view's area scale (view area / mucosa area; 1 = true) on the unfolded volume's (i, j)
        grid, one slice at the mucosa: shown as a layer over the unfolded volume, it tells where lengths and areas
        measured on the view can be trusted (the worst length scale is in the node attribute and distortion.nrrd)."""
        from StomachUnfoldLib.distortion import area_scale_volume

        dmap = result.distortion()
        node = self.volumeNodeFromVolume(area_scale_volume(result.unfolded, dmap), name)
        node.SetAttribute("StomachUnfold.distortionOf", unfoldedNode.GetID())
        node.SetAttribute("StomachUnfold.trustedFraction", f"{dmap.summary().get('trusted_fraction', 0.0):.4f}")
        dn = node.GetDisplayNode()
        if dn is not None:
            scene = self._scene()
            colour = scene.GetNodeByID("vtkMRMLColorTableNodeFileDivergingBlueRed.txt") or \
                scene.GetNodeByID("vtkMRMLColorTableNodeRainbow")
            if colour is not None:
                dn.SetAndObserveColorNodeID(colour.GetID())
            dn.AutoWindowLevelOff()
            dn.SetWindowLevel(1.0, 1.0)  # area scale 0.5 (blue, shrunk) .. 1 (true) .. 1.5 (red, enlarged)
        return node

    def _curveNode(self, points_lps, name, color):
        """A locked markups curve through points (LPS mm, shown in RAS)."""
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

    def _modelNode(self, result, name):
        """Model node of the unfolded wall (the method's cells' outer surface, hidden by default)."""
        from StomachUnfoldLib.wall_model import model_to_vtk

        mesh = getattr(result, "mesh", None)
        if mesh is not None:
            vertices, cells = mesh.unfolded_lps, mesh.cells
        else:  # library before the methods registry
            vertices, cells = result.deformed_vertices, result.hexes
        grid = model_to_vtk(vertices, cells, frame="RAS")
        surface = vtk.vtkGeometryFilter()
        surface.SetInputData(grid)
        surface.Update()
        scene = self._scene()
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
        """Volume-render the unfolded volume with the mucosa transfer function (set through the property node)."""
        vr = self._vrLogic()
        if vr is None:
            logging.warning("volume rendering logic not available; the unfolded volume is not rendered")
            return None
        displayNode = vr.CreateDefaultVolumeRenderingNodes(volumeNode)
        setMucosaTransferFunctions(displayNode.GetVolumePropertyNode())
        displayNode.SetVisibility(True)
        return displayNode

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
        """Point a camera node at the unfolded volume from the viewer's side (RAS mm) and reset its clipping range."""
        cameraNode.SetPosition(*camera["position"])
        cameraNode.SetFocalPoint(*camera["focalPoint"])
        cameraNode.SetViewUp(*camera["viewUp"])
        cameraNode.ResetClippingRange()

    # ------------------------------------------------------------------ correspondence
    def mapToOriginal(self, unfoldedVolumeNode, pointRAS):
        """Map a point (RAS mm) of an unfolded volume back into the original CT (RAS mm); None if off the wall."""
        return self._map(unfoldedVolumeNode, pointRAS, "to_original")

    def mapToUnfolded(self, unfoldedVolumeNode, pointRAS):
        """Map a point (RAS mm) of the original CT into the unfolded volume (RAS mm); None if off the wall."""
        return self._map(unfoldedVolumeNode, pointRAS, "to_unfolded")

    def _map(self, unfoldedVolumeNode, pointRAS, direction):
        from StomachUnfoldLib.geometry import lps_to_ras, ras_to_lps

        result = self.results.get(unfoldedVolumeNode.GetID()) if unfoldedVolumeNode is not None else None
        if result is None:
            name = unfoldedVolumeNode.GetName() if unfoldedVolumeNode is not None else "?"
            raise ValueError(_("{name} was not made in this session; its correspondence is not available").format(
                name=name))
        f = getattr(result.correspondence, direction)
        p = f(ras_to_lps(np.asarray(pointRAS, float))[None])[0]
        return None if not np.all(np.isfinite(p)) else lps_to_ras(p)

    def linkPoint(self, unfoldedVolumeNode, sourceNode, index, targetNode, direction):
        """Copy control point ``index`` of sourceNode into targetNode mapped through the correspondence.

        direction: "to_original" (source on the unfolded view, target in the CT) or "to_unfolded". The copy
        keeps the label. Returns the mapped position (RAS mm), or None when the point is off the wall.
        """
        p = [0.0, 0.0, 0.0]
        sourceNode.GetNthControlPointPositionWorld(index, p)
        q = self._map(unfoldedVolumeNode, p, direction)
        if q is None:
            return None
        label = sourceNode.GetNthControlPointLabel(index)
        j = targetNode.AddControlPointWorld(vtk.vtkVector3d(*[float(v) for v in q]), label)
        targetNode.SetNthControlPointDescription(j, f"linked:{sourceNode.GetNthControlPointID(index)}")
        return q

    def jumpSlicesTo(self, pointRAS):
        """Centre every slice view of the scene on a point (RAS mm)."""
        slicer.vtkMRMLSliceNode.JumpAllSlices(self._scene(), *[float(v) for v in pointRAS])


def setMucosaTransferFunctions(volumePropertyNode, thresholdHU=-400.0):
    """Set the unfolded view's transfer functions on a volume property node (HU): air clear, mucosa pink, markers yellow."""
    # a wide ramp over the air/mucosa edge (-800 .. -100 HU at the default threshold): a step at the threshold
    # renders the sampled surface's iso-lines as terraces (docs/images/view_before_after_vr.png)
    opacity = vtk.vtkPiecewiseFunction()
    opacity.AddPoint(-1024, 0.0)
    opacity.AddPoint(thresholdHU - 400, 0.0)
    opacity.AddPoint(thresholdHU + 100, 0.6)
    opacity.AddPoint(thresholdHU + 300, 0.95)
    opacity.AddPoint(3071, 1.0)
    color = vtk.vtkColorTransferFunction()
    color.AddRGBPoint(-1024, 0.0, 0.0, 0.0)
    color.AddRGBPoint(thresholdHU, 0.75, 0.42, 0.38)
    color.AddRGBPoint(60, 0.93, 0.62, 0.58)
    color.AddRGBPoint(200, 0.98, 0.8, 0.6)
    color.AddRGBPoint(400, 1.0, 0.95, 0.45)
    color.AddRGBPoint(3071, 1.0, 1.0, 0.8)
    wasModifying = volumePropertyNode.StartModify()
    volumePropertyNode.SetScalarOpacity(opacity)
    volumePropertyNode.SetColor(color)
    prop = volumePropertyNode.GetVolumeProperty()
    prop.ShadeOn()
    prop.SetAmbient(0.3)
    prop.SetDiffuse(0.7)
    prop.SetSpecular(0.2)
    prop.SetInterpolationTypeToLinear()
    volumePropertyNode.EndModify(wasModifying)
    return volumePropertyNode


#
# Widget
#
class StomachUnfoldWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """Thin GUI: inputs, two place buttons, parameters, Unfold with a progress dialog (Cancel), results, findings."""

    def __init__(self, parent=None) -> None:
        """Called when the user opens the module the first time and the widget is initialized."""
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._pointsNode = None
        self._armedLabel = None
        self._knownPointIDs = {}
        self._keepPointID = {}
        self._findingNodes = []
        self._linking = False
        self._running = False
        self.lastAutoPoints = None  # the AutoPoints of the last Auto click
        self._progressDialog = None

    def setup(self) -> None:
        """Called when the user opens the module the first time and the widget is initialized."""
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(self.resourcePath("UI/StomachUnfold.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = StomachUnfoldLogic()

        for w in (self.ui.cardiaPlaceWidget, self.ui.pylorusPlaceWidget, self.ui.ctFindingPlaceWidget,
                  self.ui.unfoldedFindingPlaceWidget):
            w.placeMultipleMarkups = slicer.qSlicerMarkupsPlaceWidget.ForcePlaceSingleMarkup
            w.activeMarkupsPlaceModeChanged.connect(self._onPlaceModeChanged)
        self.ui.cardiaPlaceWidget.placeButton().connect("clicked(bool)", lambda on: self._armLabel("cardia", on))
        self.ui.pylorusPlaceWidget.placeButton().connect("clicked(bool)", lambda on: self._armLabel("pylorus", on))
        self.ui.pointsSelector.connect("currentNodeChanged(vtkMRMLNode*)", self._onPointsNodeChanged)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.autoPointsButton.connect("clicked(bool)", self.onAutoPointsButton)

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.initializeParameterNode()

    def cleanup(self) -> None:
        """Called when the application closes and the module widget is destroyed."""
        self.setParameterNode(None)
        self.removeObservers()

    def enter(self) -> None:
        """Called each time the user opens this module."""
        self.initializeParameterNode()

    def exit(self) -> None:
        """Called each time the user opens a different module: stop reacting to the parameter node and points."""
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
        self._observePointsNode(None)
        self._observeFindings([])

    def onSceneStartClose(self, caller, event) -> None:
        """Called just before the scene is closed."""
        self.setParameterNode(None)
        self._observePointsNode(None)
        self._observeFindings([])

    def onSceneEndClose(self, caller, event) -> None:
        """Called just after the scene is closed."""
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self) -> None:
        """Ensure the parameter node exists and is observed; pick existing inputs (never adds nodes but it)."""
        self.setParameterNode(self.logic.getParameterNode())
        p = self._parameterNode
        if not p.inputVolume:
            for node in slicer.util.getNodesByClass("vtkMRMLScalarVolumeNode"):
                if not node.IsA("vtkMRMLLabelMapVolumeNode") and node.GetAttribute("StomachUnfold.report") is None:
                    p.inputVolume = node
                    break
        if not p.pointsNode:
            for node in slicer.util.getNodesByClass("vtkMRMLMarkupsFiducialNode"):
                labels = {(node.GetNthControlPointLabel(i) or "").lower() for i in range(node.GetNumberOfControlPoints())}
                if {"cardia", "pylorus"} & labels:
                    p.pointsNode = node
                    break
        self._onPointsNodeChanged(p.pointsNode)
        self._observeFindings([n for n in (p.ctFindings, p.unfoldedFindings) if n is not None])

    def setParameterNode(self, inputParameterNode) -> None:
        """Set and observe the parameter node; the GUI connection's tag is kept so that it can be undone."""
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            if self.hasObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply):
                self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
        self._parameterNode = inputParameterNode
        if self._parameterNode:
            self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
            self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
        self._checkCanApply()

    def _checkCanApply(self, caller=None, event=None) -> None:
        """Enable Unfold when a CT and both labelled points are there; the tooltip says what is missing."""
        p = self._parameterNode
        reason = None
        if self._running:
            reason = _("Unfolding is running")
        elif not p or not p.inputVolume:
            reason = _("Select the CT volume")
        else:
            try:
                self.logic.pointsFromMarkups(p.pointsNode)
            except ValueError as e:
                reason = str(e)
        self.ui.applyButton.enabled = reason is None
        self.ui.applyButton.toolTip = reason or _("Unfold the stomach between the cardia and the pylorus")

    # ------------------------------------------------------------------ points
    def _observePointsNode(self, node):
        """Observe one points node (the previous one's observers are removed)."""
        if self._pointsNode is not None:
            for event in (slicer.vtkMRMLMarkupsNode.PointPositionDefinedEvent,
                          slicer.vtkMRMLMarkupsNode.PointRemovedEvent,
                          slicer.vtkMRMLMarkupsNode.PointModifiedEvent):
                for method in (self._onPointPlaced, self._checkCanApply):
                    if self.hasObserver(self._pointsNode, event, method):
                        self.removeObserver(self._pointsNode, event, method)
        self._pointsNode = node
        if node is not None:
            self._rememberPoints(node)
            self.addObserver(node, slicer.vtkMRMLMarkupsNode.PointPositionDefinedEvent, self._onPointPlaced)
            self.addObserver(node, slicer.vtkMRMLMarkupsNode.PointRemovedEvent, self._checkCanApply)
            self.addObserver(node, slicer.vtkMRMLMarkupsNode.PointModifiedEvent, self._checkCanApply)

    def _onPointsNodeChanged(self, node):
        for w in (self.ui.cardiaPlaceWidget, self.ui.pylorusPlaceWidget):
            w.setCurrentNode(node)
        if node is not self._pointsNode:
            self._observePointsNode(node)
        self._checkCanApply()

    def _rememberPoints(self, node):
        self._knownPointIDs[node.GetID()] = {node.GetNthControlPointID(i) for i in range(node.GetNumberOfControlPoints())
                                             if node.GetNthControlPointPositionStatus(i) == node.PositionDefined}

    def _newlyDefinedPoints(self, node):
        """Indices of the control points defined since the node was last looked at (any position in the list)."""
        known = self._knownPointIDs.get(node.GetID(), set())
        new = [i for i in range(node.GetNumberOfControlPoints())
               if node.GetNthControlPointPositionStatus(i) == node.PositionDefined
               and node.GetNthControlPointID(i) not in known]
        self._rememberPoints(node)
        return new

    def _armLabel(self, label, on):
        """The next point placed gets this label; an earlier point with the label is replaced."""
        self._armedLabel = label if on else None

    def _onPlaceModeChanged(self, on):
        if not on:
            self._armedLabel = None

    def _onPointPlaced(self, caller, event):
        """Label the newly placed point; older points with that label are removed after the event has been handled."""
        new = self._newlyDefinedPoints(caller)
        label = self._armedLabel
        if label is None or not new:
            self._checkCanApply()
            return
        index = new[-1]
        keepID = caller.GetNthControlPointID(index)
        caller.SetNthControlPointLabel(index, label)
        self._armedLabel = None
        self._keepPointID[(caller.GetID(), label)] = keepID  # the latest placement wins
        import qt

        qt.QTimer.singleShot(0, lambda node=caller, lab=label: self._removeOlder(node, lab))

    def _removeOlder(self, node, label):
        """Remove the points labelled ``label`` but the latest placed one (run after the point event)."""
        keepID = self._keepPointID.pop((node.GetID(), label), None)
        if keepID is None or not slicer.mrmlScene.IsNodePresent(node):
            return
        for i in reversed(range(node.GetNumberOfControlPoints())):
            if (node.GetNthControlPointLabel(i) or "").lower() == label and node.GetNthControlPointID(i) != keepID:
                node.RemoveNthControlPoint(i)
        self._rememberPoints(node)
        self._checkCanApply()

    # ------------------------------------------------------------------ findings (linked reading)
    def _observeFindings(self, nodes):
        for node in self._findingNodes:
            if self.hasObserver(node, slicer.vtkMRMLMarkupsNode.PointPositionDefinedEvent, self._onFindingPlaced):
                self.removeObserver(node, slicer.vtkMRMLMarkupsNode.PointPositionDefinedEvent, self._onFindingPlaced)
        self._findingNodes = list(nodes)
        for node in self._findingNodes:
            self._rememberPoints(node)
            self.addObserver(node, slicer.vtkMRMLMarkupsNode.PointPositionDefinedEvent, self._onFindingPlaced)
        p = self._parameterNode
        if p is not None:
            self.ui.ctFindingPlaceWidget.setCurrentNode(p.ctFindings)
            self.ui.unfoldedFindingPlaceWidget.setCurrentNode(p.unfoldedFindings)
        self.ui.findingsCollapsibleButton.enabled = bool(self._findingNodes)

    def _ensureFindingNodes(self):
        """Point lists for findings in the CT and on the unfolded view (made after the first run)."""
        p = self._parameterNode
        if p.ctFindings is None:
            node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "FindingsCT")
            node.CreateDefaultDisplayNodes()
            p.ctFindings = node
        if p.unfoldedFindings is None:
            node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "FindingsUnfolded")
            node.CreateDefaultDisplayNodes()
            p.unfoldedFindings = node
        self._observeFindings([p.ctFindings, p.unfoldedFindings])
        self.ui.findingsLabel.text = _("Mark a finding in either view; it is shown in the other.")

    def _onFindingPlaced(self, caller, event):
        """A finding placed in one view is copied, mapped, into the other; on the unfolded view also jump the slices."""
        if self._linking:
            self._rememberPoints(caller)
            return
        p = self._parameterNode
        if p is None or p.outputVolume is None:
            return
        toOriginal = caller is p.unfoldedFindings
        target = p.ctFindings if toOriginal else p.unfoldedFindings
        for index in self._newlyDefinedPoints(caller):
            if (caller.GetNthControlPointDescription(index) or "").startswith("linked:"):
                continue
            self._linking = True
            try:
                q = self.logic.linkPoint(p.outputVolume, caller, index, target,
                                         "to_original" if toOriginal else "to_unfolded")
            finally:
                self._linking = False
            self._rememberPoints(target)
            if q is None:
                self.ui.findingsLabel.text = _("That point is not on the stomach wall.")
                continue
            if toOriginal:
                self.logic.jumpSlicesTo(q)
            self.ui.findingsLabel.text = _("{label}: R {r:.1f}, A {a:.1f}, S {s:.1f} in the {where}.").format(
                label=caller.GetNthControlPointLabel(index), r=q[0], a=q[1], s=q[2],
                where=_("CT") if toOriginal else _("unfolded view"))

    # ------------------------------------------------------------------ the run
    def _cameraNode(self):
        """The first 3D view's camera node; ValueError when the layout has no 3D view."""
        lm = slicer.app.layoutManager()
        w = lm.threeDWidget(0) if lm is not None else None
        viewNode = w.mrmlViewNode() if w is not None else None
        cameraNode = slicer.modules.cameras.logic().GetViewActiveCameraNode(viewNode) if viewNode else None
        if cameraNode is None:
            raise ValueError(_("The layout has no 3D view: choose a layout with a 3D view, then press Unfold."))
        return cameraNode

    def _ensureDependencies(self):
        """Offer to install what the library needs (after a confirmation); returns True when all is there."""
        missing = missingPackages()
        if not libraryAvailable():
            root = librarySourceTree()
            if root is None:
                raise ValueError(_("StomachUnfoldLib is not installed; install the StomachUnfold extension"))
            missing.append(f'--no-deps "{root}"')
        if not missing:
            return True
        if not slicer.util.confirmOkCancelDisplay(
                _("Stomach Unfold needs these Python packages: {packages}. Install them now?").format(
                    packages=", ".join(missing))):
            return False
        hadLibrary = libraryAvailable()
        for req in missing:
            slicer.util.pip_install(req)
        import importlib

        importlib.invalidate_caches()
        if not hadLibrary and libraryAvailable():
            slicer.util.infoDisplay(_("StomachUnfoldLib is installed. Restart Slicer to use Stomach Unfold."))
            return False
        return libraryAvailable() and not missingPackages()

    def _onProgress(self, stage, fraction):
        """Progress callback of the run: update the dialog, let the Cancel click in; False cancels."""
        d = self._progressDialog
        d.labelText = _("Unfolding: {stage}").format(stage=stage)
        d.value = min(99, max(0, int(round(100 * fraction))))
        slicer.app.processEvents()
        return not d.wasCanceled

    def onAutoPointsButton(self) -> None:
        """Fill the cardia and pylorus automatically (the user can still move them); ask to check them when unsure."""
        p = self._parameterNode
        with slicer.util.tryWithErrorDisplay(_("Finding the cardia and pylorus failed."), waitCursor=True):
            if not self._ensureDependencies():
                return
            if p.inputVolume is None:
                raise ValueError(_("choose the CT volume first"))
            if p.pointsNode is None:
                p.pointsNode = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "StomachPoints")
            found = self.logic.autoPoints(p.inputVolume, p.pointsNode, p.maskNode)
            self._rememberPoints(p.pointsNode)
            self._checkCanApply()
            text = _("Cardia and pylorus found from the {source} (confidence {c:.2f} and {q:.2f}).").format(
                source=found.source, c=found.cardia_confidence, q=found.pylorus_confidence)
            self.ui.resultsLabel.text = text
            if not found.confident:
                slicer.util.warningDisplay(
                    _("The automatic cardia and pylorus are unsure (confidence {c:.2f} and {q:.2f}). Best guesses "
                      "were placed: check them and move them to the oesophageal and duodenal ends of the stomach "
                      "before Unfold.").format(c=found.cardia_confidence, q=found.pylorus_confidence),
                    windowTitle=_("Stomach Unfold"))
            self.lastAutoPoints = found

    def onApplyButton(self) -> None:
        """Unfold with a progress dialog; its Cancel stops the run and leaves the scene as it was."""
        if self._running:
            return
        with slicer.util.tryWithErrorDisplay(_("Unfolding failed."), waitCursor=True):
            if not self._ensureDependencies():
                return
            from StomachUnfoldLib.errors import Cancelled

            cameraNode = self._cameraNode()  # before any output node is made
            self._running = True
            self._checkCanApply()
            self._progressDialog = slicer.util.createProgressDialog(
                windowTitle=_("Stomach Unfold"), labelText=_("Starting"), maximum=100, value=0)
            try:
                out = self.logic.unfoldFromParameterNode(self._parameterNode, progress=self._onProgress)
            except Cancelled:
                logging.info("StomachUnfold: cancelled by the user")
                self.ui.resultsLabel.text = _("Cancelled; nothing was added to the scene.")
                return
            finally:
                self._progressDialog.close()
                self._progressDialog = None
                self._running = False
                self._checkCanApply()
            r = out["report"]
            q = r.get("quality", {}) or {}
            self.ui.resultsLabel.text = _(
                "{seconds:.1f} s; grade {grade}, {visible:.0f}% of the mucosa visible.").format(
                seconds=r["seconds"]["total"], grade=q.get("grade", "?"),
                visible=100 * q.get("visible_fraction", 0))
            StomachUnfoldLogic.applyCamera(cameraNode, out["camera"])
            self._showDistortion(out)
            self._showWarnings(r.get("warnings") or [])
            self._ensureFindingNodes()

    def _showWarnings(self, warnings):
        """List the run's warnings (report.json's: swapped points, a point deep in the lumen, folds, holes, the scan's
        edge) under the results, and log them, so that what the view leaves out is not silent in the panel."""
        for w in warnings:
            logging.warning("StomachUnfold: %s", w)
        if warnings:
            self.ui.resultsLabel.text += "\n" + _("Warnings:") + "".join("\n- " + w for w in warnings)

    def _showDistortion(self, out):
        """Put the unfolded volume with its distortion map over it in the Yellow slice view (the CT stays in Red
        and Green for the linked reading); says in the results how much of the view has lengths within 10 %."""
        lm = slicer.app.layoutManager()
        widget = lm.sliceWidget("Yellow") if lm is not None else None
        if widget is None or out.get("distortion") is None:
            return
        self.logic.showDistortionLayer(widget.mrmlSliceNode(), out["volume"], out["distortion"])
        trusted = float(out["distortion"].GetAttribute("StomachUnfold.trustedFraction") or 0.0)
        self.ui.resultsLabel.text += " " + _(
            "Lengths within 10 % over {trusted:.0f}% of the view (distortion map in the yellow view).").format(
            trusted=100 * trusted)


#
# Test (runs inside Slicer: Slicer --no-main-window --testing --python-code "slicer.selfTests['StomachUnfold']()")
#
class StomachUnfoldTest(ScriptedLoadableModuleTest):
    """Loads the sample phantom through Sample Data, runs the Logic, cancels a run, checks the outputs."""

    def setUp(self):
        """Start from an empty scene."""
        slicer.mrmlScene.Clear()

    def runTest(self):
        """Run every test of the module."""
        self.setUp()
        self.test_unfold_phantom()
        self.setUp()
        self.test_cancel_leaves_scene()

    def _loadSample(self):
        import SampleData

        registerSampleData()
        nodes = SampleData.downloadSamples("StomachPhantom")
        volumeNode = next(n for n in nodes if n.IsA("vtkMRMLScalarVolumeNode"))
        pointsNode = next(n for n in nodes if n.IsA("vtkMRMLMarkupsFiducialNode"))
        return volumeNode, pointsNode

    def test_unfold_phantom(self):
        """The phantom from Sample Data unfolds with a good grade; outputs exist."""
        self.delayDisplay("Loading the stomach phantom")
        volumeNode, pointsNode = self._loadSample()
        logic = StomachUnfoldLogic()
        cardia, pylorus = logic.pointsFromMarkups(pointsNode)
        out = logic.unfold(volumeNode, cardia, pylorus, gridSize=3, wallThicknessMm=4.0)
        self.assertIsNotNone(out["volume"].GetImageData())
        self.assertIn(out["report"]["quality"]["grade"], ("excellent", "good"))
        self.assertGreater(out["incision"].GetNumberOfControlPoints(), 10)
        self.delayDisplay("StomachUnfold test passed")

    def test_cancel_leaves_scene(self):
        """A run cancelled from the progress callback raises Cancelled and adds no node."""
        from StomachUnfoldLib.errors import Cancelled

        volumeNode, pointsNode = self._loadSample()
        logic = StomachUnfoldLogic()
        ids = sorted(slicer.mrmlScene.GetNthNode(i).GetID() for i in range(slicer.mrmlScene.GetNumberOfNodes()))
        calls = []
        with self.assertRaises(Cancelled):
            logic.unfold(volumeNode, *logic.pointsFromMarkups(pointsNode), gridSize=3,
                         progress=lambda stage, f: calls.append(stage) or len(calls) < 3)
        self.assertEqual(ids, sorted(slicer.mrmlScene.GetNthNode(i).GetID()
                                     for i in range(slicer.mrmlScene.GetNumberOfNodes())))
        self.delayDisplay("Cancel test passed")
