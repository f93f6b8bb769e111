"""Stand-in for ``slicer.app`` (qSlicerApplication) and the module panel, over a real MRML scene.

What stands in for C++ in Slicer: the module manager (its moduleAboutToBeUnloaded(QString) signal), the
layout manager (3D views and slice views backed by the scene's real view, camera and slice nodes; how many
3D views the layout has is settable), the core IO manager (reads volumes and markups through MRML storage
nodes), and a click in a view in place mode (what the markups displayable manager does: fill the first
unplaced control point or add one, then fire PointPositionDefinedEvent).
"""
import importlib
import os
import sys

import numpy as np
import qt
import slicer
import vtk
from PySide6.QtCore import Property, Signal


class _ModuleManager(qt.QObject):
    moduleAboutToBeUnloaded = Signal(str)


class _ThreeDWidget:
    def __init__(self, viewNode):
        self._viewNode = viewNode

    def mrmlViewNode(self):
        return self._viewNode


class _SliceWidget:
    def __init__(self, sliceNode):
        self._sliceNode = sliceNode

    def mrmlSliceNode(self):
        return self._sliceNode


class _LayoutManager(qt.QObject):
    """qSlicerLayoutManager: 3D and slice widgets for the scene's view nodes."""

    def __init__(self):
        super().__init__()
        self.numberOfThreeDViews = 1  # a layout without a 3D view: 0

    threeDViewCount = Property(int, lambda s: s.numberOfThreeDViews)

    def threeDWidget(self, index):
        if index >= self.numberOfThreeDViews:
            return None
        node = slicer.mrmlScene.GetSingletonNode(str(index + 1), "vtkMRMLViewNode")
        return _ThreeDWidget(node) if node is not None else None

    def sliceViewNames(self):
        return ["Red", "Yellow", "Green"]

    def sliceWidget(self, name):
        node = slicer.mrmlScene.GetSingletonNode(name, "vtkMRMLSliceNode")
        return _SliceWidget(node) if node is not None else None


class _CoreIOManager:
    """qSlicerCoreIOManager: fileType() and loadNodes() for volumes and markups, through MRML storage nodes."""

    def fileType(self, fileName):
        f = fileName.lower()
        if f.endswith((".mrk.json", ".fcsv")):
            return "MarkupsFile"
        if f.endswith((".nrrd", ".nhdr", ".nii", ".nii.gz", ".mha", ".mhd")):
            return "VolumeFile"
        return "NoFile"

    def loadNodes(self, fileType, properties, loadedNodes=None):
        scene = slicer.mrmlScene
        fileName = properties["fileName"]
        name = properties.get("name") or os.path.basename(fileName).split(".")[0]
        if fileType == "VolumeFile":
            node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", scene.GenerateUniqueName(name))
            storage = scene.AddNewNodeByClass("vtkMRMLVolumeArchetypeStorageNode")
        elif fileType == "MarkupsFile":
            node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", scene.GenerateUniqueName(name))
            storage = scene.AddNewNodeByClass("vtkMRMLMarkupsJsonStorageNode")
        else:
            return False
        storage.SetFileName(fileName)
        node.SetAndObserveStorageNodeID(storage.GetID())
        if not storage.ReadData(node):
            scene.RemoveNode(storage)
            scene.RemoveNode(node)
            return False
        if properties.get("name"):
            node.SetName(properties["name"])
        node.CreateDefaultDisplayNodes()
        if loadedNodes is not None:
            loadedNodes.AddItem(node)
        return True


class SlicerApplication(qt.QObject):
    """qSlicerApplication as seen from Python: testing mode on, as under ``Slicer --testing``."""

    startupCompleted = Signal()

    def __init__(self):
        super().__init__()
        self._moduleManager = _ModuleManager()
        self._layoutManager = _LayoutManager()
        self._io = _CoreIOManager()
        self._queuedUserInput = []
        self.processEventsFlags = []
        self.applicationName = "Slicer"
        self.documentationBaseUrl = "https://slicer.readthedocs.io/en/latest"

    def moduleManager(self):
        return self._moduleManager

    def layoutManager(self):
        return self._layoutManager

    def coreIOManager(self):
        return self._io

    def testingEnabled(self):
        return True

    def moduleDocumentationUrl(self, moduleName):
        return f"{self.documentationBaseUrl}/user_guide/modules/{moduleName.lower()}.html"

    def translate(self, context, text):
        return qt.QCoreApplication.translate(context, text)

    def userSettings(self):
        return qt.QSettings()

    def settings(self):
        return qt.QSettings()

    def topLevelWidgets(self):
        return qt.QApplication.topLevelWidgets()

    def setOverrideCursor(self, cursor):
        qt.QApplication.setOverrideCursor(cursor)

    def restoreOverrideCursor(self):
        qt.QApplication.restoreOverrideCursor()

    def queueUserInput(self, action):
        """Queue a user action (a click): delivered by the next processEvents that does not exclude user input."""
        self._queuedUserInput.append(action)

    def processEvents(self, flags=None):
        """QApplication.processEvents; queued user input waits while ExcludeUserInputEvents is set, as in Qt."""
        flags = qt.QEventLoop.AllEvents if flags is None else flags
        self.processEventsFlags.append(flags)
        qt.QApplication.processEvents(flags)
        if not (flags & qt.QEventLoop.ExcludeUserInputEvents):
            queued, self._queuedUserInput = self._queuedUserInput, []
            for action in queued:
                action()
            qt.QApplication.processEvents(flags)


def _cacheDirectory():
    """Sample Data's download cache for this process (a temporary folder, as Slicer's is per user)."""
    global _CACHE
    if _CACHE is None:
        import tempfile
        _CACHE = tempfile.mkdtemp(prefix="slicer-harness-cache-")
    return _CACHE


_CACHE = None


def newScene():
    """A scene wired like Slicer's: application logic, colours, markups, volumes, volume rendering, cameras,
    a 3D view "1" with its camera, and the Red/Yellow/Green slice nodes; also sets slicer.mrmlScene/modules."""
    scene = slicer.vtkMRMLScene()
    slicer.mrmlScene = scene
    cache = slicer.vtkCacheManager()
    cache.SetRemoteCacheDirectory(_cacheDirectory())
    scene.SetCacheManager(cache)
    appLogic = slicer.vtkSlicerApplicationLogic()
    appLogic.SetMRMLScene(scene)
    appLogic.GetColorLogic().SetMRMLScene(scene)
    appLogic.GetColorLogic().AddDefaultColorNodes()
    appLogic.SetSliceLogics(vtk.vtkCollection())
    appLogic.SetViewLogics(vtk.vtkCollection())
    logics = {}
    for name, logic in (("Colors", slicer.vtkMRMLColorLogic()), ("Markups", slicer.vtkSlicerMarkupsLogic()),
                        ("Volumes", slicer.vtkSlicerVolumesLogic()),
                        ("VolumeRendering", slicer.vtkSlicerVolumeRenderingLogic()),
                        ("Cameras", slicer.vtkSlicerCamerasModuleLogic())):
        logic.SetMRMLScene(scene)
        logic.SetMRMLApplicationLogic(appLogic)
        appLogic.SetModuleLogic(name, logic)
        logics[name] = logic
    view = scene.AddNewNodeByClass("vtkMRMLViewNode")
    view.SetSingletonTag("1")
    view.SetLayoutName("1")
    camera = scene.AddNewNodeByClass("vtkMRMLCameraNode")
    camera.SetLayoutName("1")
    if hasattr(slicer.vtkMRMLSliceNode, "AddDefaultSliceOrientationPresets"):
        slicer.vtkMRMLSliceNode.AddDefaultSliceOrientationPresets(scene)
    for name, orient in (("Red", "Axial"), ("Yellow", "Sagittal"), ("Green", "Coronal")):
        s = scene.CreateNodeByClass("vtkMRMLSliceNode")
        s.UnRegister(None)
        getattr(s, f"SetOrientationTo{orient}")()
        s.SetName(name)
        s.SetLayoutName(name)
        s.SetSingletonTag(name)
        scene.AddNode(s)
        # each slice view has its composite node (background/foreground layers), as Slicer's layout makes them
        c = scene.CreateNodeByClass("vtkMRMLSliceCompositeNode")
        c.UnRegister(None)
        c.SetLayoutName(name)
        c.SetSingletonTag(name)
        scene.AddNode(c)
    for key, logicName in (("volumerendering", "VolumeRendering"), ("cameras", "Cameras"), ("markups", "Markups"),
                           ("volumes", "Volumes"), ("colors", "Colors")):
        setattr(slicer.modules, key, _ModuleStub(logics[logicName]))
    _KEEP.append((scene, appLogic, logics))  # logics hold the application logic by a raw pointer
    return scene, appLogic, logics


_KEEP = []


class _ModuleStub:
    def __init__(self, logic, path=""):
        self._logic = logic
        self.path = path

    def logic(self):
        return self._logic


class _ModuleParent(qt.QObject):
    """qSlicerScriptedLoadableModule as the module class's ``parent``: the module's metadata."""

    def __init__(self, path):
        super().__init__()
        self.path = path
        self.title = ""
        self.categories = []
        self.dependencies = []
        self.contributors = []
        self.helpText = ""
        self.acknowledgementText = ""
        self.icon = None
        self.hidden = False
        self.widgetRepresentationCreationEnabled = True

    def logic(self):
        return None


class ModulePanel:
    """A scripted module as Slicer loads it: module object, then (on first open) the widget in its panel."""

    def __init__(self, moduleDir, moduleName):
        self.moduleName = moduleName
        path = os.path.join(moduleDir, moduleName + ".py")
        if moduleDir not in sys.path:
            sys.path.insert(0, moduleDir)
        self.pythonModule = importlib.import_module(moduleName)
        self.parent = _ModuleParent(path)
        setattr(slicer.modules, moduleName.lower(), self.parent)
        self.module = getattr(self.pythonModule, moduleName)(self.parent)
        slicer.app.startupCompleted.emit()
        self.panel = None
        self.widget = None

    def open(self):
        """Create the panel and the Widget (setup) if needed, then enter the module; returns the Widget."""
        if self.widget is None:
            self.panel = slicer.qSlicerScriptedLoadableModuleWidget()
            self.panel.setMRMLScene(slicer.mrmlScene)
            self.widget = getattr(self.pythonModule, self.moduleName + "Widget")(self.panel)
            self.widget.setup()
        self.panel._entered = True
        self.widget.enter()
        return self.widget

    def close(self):
        """Leave the module (another module is selected)."""
        self.widget.exit()
        self.panel._entered = False

    def unload(self):
        """Application exit: moduleAboutToBeUnloaded -> cleanup()."""
        slicer.app.moduleManager().moduleAboutToBeUnloaded.emit(self.moduleName)




def clickInView(positionRAS):
    """A left click in a view in place mode: what the markups displayable manager does with the active node.

    Fills the first control point without a position, or adds one; fires PointPositionDefinedEvent
    (through SetNthControlPointPositionWorld); in single-place mode leaves place mode. Checks afterwards
    that the control point it placed is still where it put it (observers must not remove points during the
    event: the displayable manager keeps using the index). Returns the index, or None if not in place mode.
    """
    scene = slicer.mrmlScene
    interaction = scene.GetNodeByID("vtkMRMLInteractionNodeSingleton")
    selection = scene.GetNodeByID("vtkMRMLSelectionNodeSingleton")
    if interaction.GetCurrentInteractionMode() != interaction.Place:
        return None
    node = scene.GetNodeByID(selection.GetActivePlaceNodeID() or "")
    if node is None:
        return None
    index = None
    for i in range(node.GetNumberOfControlPoints()):
        if node.GetNthControlPointPositionStatus(i) != node.PositionDefined:
            index = i
            break
    position = [float(v) for v in positionRAS]
    if index is None:  # a new point, added with its position (PointAdded + PointPositionDefined)
        index = node.GetNumberOfControlPoints()
        node.AddControlPointWorld(vtk.vtkVector3d(*position), "")
    else:  # the first unplaced point gets the position (PointPositionDefined)
        node.SetNthControlPointPositionWorld(index, *position)
    pointID = node.GetNthControlPointID(index) if index < node.GetNumberOfControlPoints() else None
    p = [0.0, 0.0, 0.0]
    if pointID is not None:
        node.GetNthControlPointPositionWorld(index, p)
    if pointID is None or not np.allclose(p, position):
        raise AssertionError("a control point was removed while PointPositionDefinedEvent was being handled")
    if not interaction.GetPlaceModePersistence():
        interaction.SetCurrentInteractionMode(interaction.ViewTransform)
    return index
