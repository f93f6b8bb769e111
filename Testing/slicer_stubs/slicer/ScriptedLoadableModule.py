"""Test-only stand-in for Slicer's ScriptedLoadableModule (absent from the slicer-core wheel).

Only what the module's Logic needs to import and run headless; the Widget is not exercised here.
"""


class ScriptedLoadableModule:
    def __init__(self, parent=None):
        self.parent = parent


class ScriptedLoadableModuleWidget:
    def __init__(self, parent=None):
        self.parent = parent


class ScriptedLoadableModuleLogic:
    def __init__(self, parent=None):
        self._parameterNode = None

    def getParameterNode(self):
        import slicer

        if self._parameterNode is None:
            self._parameterNode = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", "StomachUnfold")
        return self._parameterNode


class ScriptedLoadableModuleTest:
    def delayDisplay(self, message, msec=0):
        print(message)

    def assertIsNotNone(self, v):
        assert v is not None

    def assertGreater(self, a, b):
        assert a > b

    def assertIn(self, a, b):
        assert a in b
