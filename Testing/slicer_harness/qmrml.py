"""Stand-ins for the qMRML/qSlicer C++ widgets the module's .ui uses, put into the ``slicer`` namespace.

Properties, signals and slots follow Slicer's headers (Libs/MRML/Widgets/qMRMLNodeComboBox.h, qMRMLWidget.h,
Base/QTGUI/qSlicerWidget.h, Modules/Loadable/Markups/Widgets/qSlicerMarkupsPlaceWidget.h); the node list,
selection rules and place mode work on the real MRML scene, interaction node and selection node.
"""
import qt
import vtk
from PySide6.QtCore import Property, Signal, Slot


class qMRMLWidget(qt.QWidget):
    """qMRMLWidget: a QWidget that holds a scene and emits mrmlSceneChanged(vtkMRMLScene*)."""

    mrmlSceneChanged = Signal(object)

    def __init__(self, parent=None):
        super().__init__(parent)
        self._scene = None

    @Slot(object)
    def setMRMLScene(self, scene):
        """Set the scene and pass it on (the .ui connects this signal to the children's setMRMLScene)."""
        if scene is self._scene:
            return
        self._scene = scene
        self.mrmlSceneChanged.emit(scene)

    def mrmlScene(self):
        return self._scene


class qSlicerWidget(qMRMLWidget):
    """qSlicerWidget: qMRMLWidget with the Slicer application's MRML logic (not needed here)."""


class qSlicerScriptedLoadableModuleWidget(qSlicerWidget):
    """The module panel that Slicer gives a scripted module's Widget as ``parent`` (isEntered, a VBox layout)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setLayout(qt.QVBoxLayout())
        self._entered = False

    isEntered = Property(bool, lambda s: s._entered)


class qMRMLNodeComboBox(qt.QWidget):
    """qMRMLNodeComboBox: selects a node of the scene among nodeTypes (qMRMLNodeComboBox.h)."""

    currentNodeChanged = Signal((object,), (bool,))
    currentNodeIDChanged = Signal(str)
    nodeActivated = Signal(object)
    nodeAdded = Signal(object)
    nodeAddedByUser = Signal(object)
    nodeAddedByUserAction = Signal(object)
    nodeAboutToBeRemoved = Signal(object)
    nodeAboutToBeEdited = Signal(object)
    currentNodeRenamed = Signal(str)

    def __init__(self, parent=None):
        super().__init__(parent)
        self._combo = qt.QComboBox(self)
        lay = qt.QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self._combo)
        self._scene = None
        self._tags = []
        self._nodeTypes = []
        self._hideChildNodeTypes = []
        self._current = None
        self._nodes = []
        self._flags = {"showHidden": False, "showChildNodeTypes": True, "noneEnabled": False, "addEnabled": True,
                       "removeEnabled": True, "editEnabled": False, "renameEnabled": False,
                       "selectNodeUponCreation": True}
        self._baseName = ""
        self._attributes = []
        self._typeLabels = {}
        self._noneDisplay = "None"
        self._interactionNodeSingletonTag = ""
        self.setEnabled(False)

    # ---- properties (Q_PROPERTY in the header)
    def _flag(name):
        return Property(bool, lambda s: s._flags[name], lambda s, v: s._setFlag(name, v))

    showHidden = _flag("showHidden")
    showChildNodeTypes = _flag("showChildNodeTypes")
    noneEnabled = _flag("noneEnabled")
    addEnabled = _flag("addEnabled")
    removeEnabled = _flag("removeEnabled")
    editEnabled = _flag("editEnabled")
    renameEnabled = _flag("renameEnabled")
    selectNodeUponCreation = _flag("selectNodeUponCreation")
    del _flag

    def _setFlag(self, name, value):
        self._flags[name] = bool(value)
        self._refresh()

    def _setNodeTypes(self, types):
        self._nodeTypes = [str(t) for t in types]
        self._refresh()

    nodeTypes = Property("QStringList", lambda s: list(s._nodeTypes), _setNodeTypes)
    hideChildNodeTypes = Property("QStringList", lambda s: list(s._hideChildNodeTypes),
                                  lambda s, v: (setattr(s, "_hideChildNodeTypes", list(v)), s._refresh()))
    baseName = Property(str, lambda s: s._baseName, lambda s, v: setattr(s, "_baseName", v))
    noneDisplay = Property(str, lambda s: s._noneDisplay, lambda s, v: setattr(s, "_noneDisplay", v))
    interactionNodeSingletonTag = Property(str, lambda s: s._interactionNodeSingletonTag,
                                           lambda s, v: setattr(s, "_interactionNodeSingletonTag", v))
    currentNodeID = Property(str, lambda s: s._current.GetID() if s._current is not None else "",
                             lambda s, v: s.setCurrentNodeID(v), notify=currentNodeIDChanged)
    currentNodeId = Property(str, lambda s: s._current.GetID() if s._current is not None else "",
                             lambda s, v: s.setCurrentNodeID(v))  # deprecated in the header
    sizeAdjustPolicy = Property(int, lambda s: int(s._combo.sizeAdjustPolicy().value),
                                lambda s, v: s._combo.setSizeAdjustPolicy(qt.QComboBox.SizeAdjustPolicy(v)))

    def setNodeTypes(self, types):
        self._setNodeTypes(types)

    def setHideChildNodeTypes(self, types):
        self._hideChildNodeTypes = list(types)
        self._refresh()

    def setBaseName(self, name, nodeType=""):
        self._baseName = name

    def setNoneDisplay(self, text):
        self._noneDisplay = text
        self._refresh()

    def setSelectNodeUponCreation(self, v):
        self._setFlag("selectNodeUponCreation", v)

    def setEditEnabled(self, v):
        self._setFlag("editEnabled", v)

    def setInteractionNodeSingletonTag(self, tag):
        self._interactionNodeSingletonTag = tag

    def addAttribute(self, nodeType, attributeName, attributeValue=None):
        """Show only nodes of nodeType whose attribute matches (any value when attributeValue is None)."""
        self._attributes.append((nodeType, attributeName, attributeValue))
        self._refresh()

    def removeAttribute(self, nodeType, attributeName):
        self._attributes = [a for a in self._attributes if a[:2] != (nodeType, attributeName)]
        self._refresh()

    def setNodeTypeLabel(self, label, nodeType):
        self._typeLabels[nodeType] = label

    def nodeTypeLabel(self, nodeType):
        return self._typeLabels.get(nodeType, "")

    def nodes(self):
        return list(self._nodes)

    def setNoneEnabled(self, v):
        self._setFlag("noneEnabled", v)

    def setAddEnabled(self, v):
        self._setFlag("addEnabled", v)

    def setRemoveEnabled(self, v):
        self._setFlag("removeEnabled", v)

    def setRenameEnabled(self, v):
        self._setFlag("renameEnabled", v)

    def setShowHidden(self, v):
        self._setFlag("showHidden", v)

    def setShowChildNodeTypes(self, v):
        self._setFlag("showChildNodeTypes", v)

    # ---- scene
    @Slot(object)
    def setMRMLScene(self, scene):
        """Observe a scene and list its nodes of nodeTypes."""
        if self._scene is not None:
            for tag in self._tags:
                self._scene.RemoveObserver(tag)
        self._tags = []
        self._scene = scene
        if scene is not None:
            for ev in (vtk.vtkCommand.ModifiedEvent, scene.NodeAddedEvent, scene.NodeRemovedEvent,
                       scene.EndCloseEvent, scene.EndImportEvent, scene.EndBatchProcessEvent):
                self._tags.append(scene.AddObserver(ev, lambda c, e: self._refresh()))
        self.setEnabled(scene is not None)
        self._refresh()

    def mrmlScene(self):
        return self._scene

    def _matches(self, node):
        if not self._flags["showHidden"] and node.GetHideFromEditors():
            return False
        if any(node.IsA(t) for t in self._hideChildNodeTypes):
            return False
        for nodeType, name, value in self._attributes:
            if node.IsA(nodeType) and (node.GetAttribute(name) is None
                                       or (value is not None and node.GetAttribute(name) != str(value))):
                return False
        for t in self._nodeTypes:
            if node.IsA(t) and (self._flags["showChildNodeTypes"] or node.GetClassName() == t):
                return True
        return False

    def _refresh(self):
        scene = self._scene
        nodes = []
        if scene is not None and not scene.IsBatchProcessing():
            nodes = [scene.GetNthNode(i) for i in range(scene.GetNumberOfNodes())]
            nodes = [n for n in nodes if self._matches(n)]
        elif scene is not None:
            return
        added = [n for n in nodes if not any(n is m for m in self._nodes)]
        self._nodes = nodes
        for n in added:  # emitted for every node that enters the list (the header's nodeAdded/nodeAddedByUser)
            self.nodeAdded.emit(n)
            self.nodeAddedByUser.emit(n)
        self._combo.blockSignals(True)
        self._combo.clear()
        if self._flags["noneEnabled"]:
            self._combo.addItem(self._noneDisplay)
        for n in nodes:
            self._combo.addItem(n.GetName())
        self._combo.blockSignals(False)
        current = self._current if self._current is not None and any(n is self._current for n in nodes) else None
        if current is None and not self._flags["noneEnabled"] and nodes:
            current = nodes[0]
        self._select(current)

    def _select(self, node):
        changed = node is not self._current
        self._current = node
        idx = -1
        if node is not None:
            idx = next(i for i, n in enumerate(self._nodes) if n is node) + (1 if self._flags["noneEnabled"] else 0)
        elif self._flags["noneEnabled"]:
            idx = 0
        self._combo.blockSignals(True)
        self._combo.setCurrentIndex(idx)
        self._combo.blockSignals(False)
        if changed:
            self.currentNodeChanged[object].emit(node)
            self.currentNodeChanged[bool].emit(node is not None)
            self.currentNodeIDChanged.emit(node.GetID() if node is not None else "")

    # ---- selection (Q_INVOKABLE / slots)
    def currentNode(self):
        """The selected node, or None."""
        return self._current

    @Slot(object)
    def setCurrentNode(self, node):
        """Select a node (must be listed; None only when noneEnabled)."""
        if node is not None and not any(n is node for n in self._nodes):
            self._refresh()
            if not any(n is node for n in self._nodes):
                return
        if node is None and not self._flags["noneEnabled"] and self._nodes:
            return
        self._select(node)

    @Slot(str)
    def setCurrentNodeID(self, nodeID):
        self.setCurrentNode(self._scene.GetNodeByID(nodeID) if (self._scene and nodeID) else None)

    @Slot(int)
    def setCurrentNodeIndex(self, index):
        self.setCurrentNode(self._nodes[index] if 0 <= index < len(self._nodes) else None)

    def nodeCount(self):
        return len(self._nodes)

    def nodeFromIndex(self, index):
        return self._nodes[index] if 0 <= index < len(self._nodes) else None

    @Slot()
    def addNode(self, nodeType=None):
        """Create a node of nodeType (one of nodeTypes; default the first), as the "Create new" item does."""
        if self._scene is None or not self._nodeTypes or (nodeType and nodeType not in self._nodeTypes):
            return None
        nodeType = nodeType or self._nodeTypes[0]
        node = self._scene.AddNewNodeByClass(nodeType, self._scene.GenerateUniqueName(self._baseName or
                                                                                      nodeType[len("vtkMRML"):]))
        for t, name, value in self._attributes:
            if node.IsA(t):
                node.SetAttribute(name, "" if value is None else str(value))
        self.nodeAddedByUserAction.emit(node)
        if self._flags["selectNodeUponCreation"]:
            self.setCurrentNode(node)
        return node

    @Slot()
    def editCurrentNode(self):
        if self._current is not None:
            self.nodeAboutToBeEdited.emit(self._current)

    @Slot()
    def renameCurrentNode(self):
        """Slicer asks for the name in a dialog; here the node keeps its name (no dialog offscreen)."""
        if self._current is not None:
            self.currentNodeRenamed.emit(self._current.GetName())

    @Slot()
    def removeCurrentNode(self):
        if self._current is not None and self._scene is not None:
            self.nodeAboutToBeRemoved.emit(self._current)
            self._scene.RemoveNode(self._current)


class qSlicerMarkupsPlaceWidget(qSlicerWidget):
    """qSlicerMarkupsPlaceWidget: place button for a markups node (qSlicerMarkupsPlaceWidget.h).

    Place mode goes through the scene's real interaction and selection nodes, as in Slicer.
    """

    ShowPlaceMultipleMarkupsOption, HidePlaceMultipleMarkupsOption, ForcePlaceSingleMarkup, ForcePlaceMultipleMarkups = range(4)

    activeMarkupsPlaceModeChanged = Signal(bool)
    activeMarkupsFiducialPlaceModeChanged = Signal(bool)

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = qt.QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self._placeButton = qt.QToolButton(self)
        self._placeButton.setCheckable(True)
        self._placeButton.setText("Place")
        self._placeButton.setToolButtonStyle(qt.Qt.ToolButtonTextBesideIcon)
        self._deleteButton = qt.QToolButton(self)
        self._deleteButton.setText("Delete")
        lay.addWidget(self._placeButton)
        lay.addWidget(self._deleteButton)
        lay.addStretch(1)
        self._node = None
        self._interactionNode = None
        self._selectionNode = None
        self._tags = []
        self._placeMultiple = self.ShowPlaceMultipleMarkupsOption
        self._persistency = False
        self._visible = {"buttons": True, "deleteAll": True, "unsetLast": False, "unsetAll": False}
        self._nodeColor = qt.QColor()
        self._defaultNodeColor = qt.QColor()
        self._lastActive = False
        self._placeButton.clicked.connect(self.setPlaceModeEnabled)
        self._deleteButton.clicked.connect(self.deleteLastPoint)
        self.setEnabled(False)

    def _vis(key):
        return Property(bool, lambda s: s._visible[key], lambda s, v: s._setVisible(key, v))

    buttonsVisible = _vis("buttons")
    deleteAllControlPointsOptionVisible = _vis("deleteAll")
    unsetLastControlPointOptionVisible = _vis("unsetLast")
    unsetAllControlPointsOptionVisible = _vis("unsetAll")
    deleteAllMarkupsOptionVisible = _vis("deleteAll")
    del _vis

    def _setVisible(self, key, v):
        self._visible[key] = bool(v)
        if key == "buttons":
            self._deleteButton.setVisible(bool(v))

    def setButtonsVisible(self, v):
        self._setVisible("buttons", v)

    def setDeleteAllControlPointsOptionVisible(self, v):
        self._setVisible("deleteAll", v)

    def setUnsetLastControlPointOptionVisible(self, v):
        self._setVisible("unsetLast", v)

    def setUnsetAllControlPointsOptionVisible(self, v):
        self._setVisible("unsetAll", v)

    placeMultipleMarkups = Property(int, lambda s: s._placeMultiple, lambda s, v: s.setPlaceMultipleMarkups(v))
    nodeColor = Property(qt.QColor, lambda s: s._nodeColor, lambda s, v: s.setNodeColor(v))
    defaultNodeColor = Property(qt.QColor, lambda s: s._defaultNodeColor, lambda s, v: s.setDefaultNodeColor(v))
    currentNodeActive = Property(bool, lambda s: s._isActive(), lambda s, v: s.setCurrentNodeActive(v))
    placeModeEnabled = Property(bool, lambda s: s._placeModeOn(), lambda s, v: s.setPlaceModeEnabled(v))
    placeModePersistency = Property(bool, lambda s: s._persistencyNow(), lambda s, v: s.setPlaceModePersistency(v))

    @Slot(int)
    def setPlaceMultipleMarkups(self, option):
        self._placeMultiple = int(option)

    @Slot(qt.QColor)
    def setNodeColor(self, color):
        self._nodeColor = qt.QColor(color)

    @Slot(qt.QColor)
    def setDefaultNodeColor(self, color):
        self._defaultNodeColor = qt.QColor(color)

    # ---- Q_INVOKABLE
    def currentNode(self):
        return self._node

    def currentMarkupsNode(self):
        return self._node

    def currentMarkupsFiducialNode(self):
        return self._node if self._node is not None and self._node.IsA("vtkMRMLMarkupsFiducialNode") else None

    def interactionNode(self):
        return self._interactionNode

    def selectionNode(self):
        return self._selectionNode

    def placeButton(self):
        return self._placeButton

    def deleteButton(self):
        return self._deleteButton

    # ---- scene and nodes
    @Slot(object)
    def setMRMLScene(self, scene):
        for obj, tag in self._tags:
            obj.RemoveObserver(tag)
        self._tags = []
        super().setMRMLScene(scene)
        self._interactionNode = scene.GetNodeByID("vtkMRMLInteractionNodeSingleton") if scene else None
        self._selectionNode = scene.GetNodeByID("vtkMRMLSelectionNodeSingleton") if scene else None
        for n in (self._interactionNode, self._selectionNode):
            if n is not None:
                self._tags.append((n, n.AddObserver(vtk.vtkCommand.ModifiedEvent, lambda c, e: self.updateWidget())))
        self.updateWidget()

    @Slot(object)
    def setInteractionNode(self, node):
        self._interactionNode = node
        self.updateWidget()

    @Slot(object)
    def setSelectionNode(self, node):
        self._selectionNode = node
        self.updateWidget()

    @Slot(object)
    def setCurrentNode(self, node):
        self._node = node
        self.updateWidget()

    def _isActive(self):
        return (self._node is not None and self._selectionNode is not None
                and self._selectionNode.GetActivePlaceNodeID() == self._node.GetID())

    def _placeModeOn(self):
        i = self._interactionNode
        return bool(self._isActive() and i is not None and i.GetCurrentInteractionMode() == i.Place)

    def _persistencyNow(self):
        i = self._interactionNode
        return bool(i.GetPlaceModePersistence()) if i is not None else self._persistency

    @Slot(bool)
    def setCurrentNodeActive(self, active):
        if self._selectionNode is None or self._node is None:
            return
        if active:
            self._selectionNode.SetReferenceActivePlaceNodeClassName(self._node.GetClassName())
            self._selectionNode.SetActivePlaceNodeID(self._node.GetID())
        elif self._isActive():
            self._selectionNode.SetActivePlaceNodeID(None)

    @Slot(bool)
    def setPlaceModeEnabled(self, enable):
        """Enter or leave place mode for the current node (persistency from placeMultipleMarkups)."""
        i = self._interactionNode
        if i is None or self._node is None:
            self._placeButton.setChecked(False)
            return
        if enable:
            self.setCurrentNodeActive(True)
            if self._placeMultiple == self.ForcePlaceSingleMarkup:
                i.SetPlaceModePersistence(0)
            elif self._placeMultiple == self.ForcePlaceMultipleMarkups:
                i.SetPlaceModePersistence(1)
            i.SetCurrentInteractionMode(i.Place)
        elif self._placeModeOn():
            i.SetCurrentInteractionMode(i.ViewTransform)
        self.updateWidget()

    @Slot(bool)
    def setPlaceModePersistency(self, persistent):
        self._persistency = bool(persistent)
        if self._interactionNode is not None:
            self._interactionNode.SetPlaceModePersistence(1 if persistent else 0)

    @Slot(bool)
    def onPlacePersistentPoint(self, enable):
        self.setPlaceModePersistency(enable)
        self.setPlaceModeEnabled(True)

    @Slot()
    def modifyLastPoint(self):
        self.deleteLastPoint()

    @Slot()
    def deleteLastPoint(self):
        if self._node is not None and self._node.GetNumberOfControlPoints():
            self._node.RemoveNthControlPoint(self._node.GetNumberOfControlPoints() - 1)

    @Slot()
    def deleteAllPoints(self):
        if self._node is not None:
            self._node.RemoveAllControlPoints()

    @Slot()
    def unsetLastDefinedPoint(self):
        n = self._node
        if n is not None:
            for k in reversed(range(n.GetNumberOfControlPoints())):
                if n.GetNthControlPointPositionStatus(k) == n.PositionDefined:
                    n.UnsetNthControlPointPosition(k)
                    return

    @Slot()
    def unsetAllPoints(self):
        if self._node is not None:
            self._node.UnsetAllControlPoints()

    @Slot()
    def updateWidget(self):
        self.setEnabled(self._node is not None and self._interactionNode is not None)
        on = self._placeModeOn()
        self._placeButton.blockSignals(True)
        self._placeButton.setChecked(on)
        self._placeButton.blockSignals(False)
        if on != self._lastActive:
            self._lastActive = on
            self.activeMarkupsPlaceModeChanged.emit(on)
            self.activeMarkupsFiducialPlaceModeChanged.emit(on)


class _NotStoodIn(qt.QWidget):
    def __init__(self, *args, **kwargs):
        raise NotImplementedError(f"{type(self).__name__} is not stood in by the harness")


STANDINS = {c.__name__: c for c in (qMRMLWidget, qSlicerWidget, qMRMLNodeComboBox, qSlicerMarkupsPlaceWidget)}
PLACEHOLDERS = {n: type(n, (_NotStoodIn,), {}) for n in ("qMRMLSliderWidget", "qMRMLSpinBox", "qMRMLRangeWidget",
                                                         "qMRMLSubjectHierarchyTreeView",
                                                         "qMRMLSubjectHierarchyComboBox")}
