"""Load a Slicer scripted module as the Slicer application does, over Slicer's real pure-Python base classes.

Real: ``slicer.ScriptedLoadableModule``, ``slicer.parameterNodeWrapper``, ``slicer.i18n`` and the ``SampleData``
module (verbatim from Slicer 5.10.0, in ``$STOMACHUNFOLD_SHARED/slicer_python/v5.10.0``, default
``<repo>/../shared``), ``slicer.util`` and MRML with its logics (the ``slicer-core`` wheel), and Qt (PySide6,
offscreen). Stand-ins: PythonQt's calling conventions over PySide6 (``modules/qt.py``), the CTK and qMRML C++
widgets (``modules/ctk.py``, ``qmrml.py``), and ``slicer.app`` (``app.py``: module manager, layout manager
with a configurable number of 3D views, core IO manager reading through MRML storage nodes, processEvents
that holds back queued user input under ``ExcludeUserInputEvents`` as Qt does).
"""
import os
import sys
import types

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
SHARED = os.path.abspath(os.environ.get("STOMACHUNFOLD_SHARED", os.path.join(ROOT, "..", "shared")))
SLICER_PYTHON = os.path.join(SHARED, "slicer_python", "v5.10.0")
MODULE_DIR = os.path.join(ROOT, "StomachUnfold")

_installed = None


def skipReason():
    """Why the harness cannot run here (None when it can)."""
    if not os.path.isfile(os.path.join(SLICER_PYTHON, "slicer", "ScriptedLoadableModule.py")):
        return (f"Slicer's pure-Python base classes are not at {SLICER_PYTHON} (set STOMACHUNFOLD_SHARED to the "
                "folder holding slicer_python/v5.10.0)")
    for name in ("PySide6", "slicer"):
        try:
            __import__(name)
        except ImportError:
            return f"{name} is not installed (PySide6-Essentials and slicer-core are test dependencies)"
    return None


def require():
    """For a test module: skip it (saying why) when the harness cannot run here, else install it; the namespace."""
    import pytest

    reason = skipReason()
    if reason:
        pytest.skip(reason, allow_module_level=True)
    return install()


def install():
    """Put qt/ctk, Slicer's real Python and the module on sys.path and set up slicer.app; returns the namespace."""
    global _installed
    if _installed is not None:
        return _installed
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    for p in (MODULE_DIR, os.path.join(SLICER_PYTHON, "SampleData"), os.path.join(HERE, "modules")):
        if p not in sys.path:
            sys.path.insert(0, p)
    import ctk
    import qt

    qtApp = qt.application()
    import tempfile
    settingsDir = tempfile.mkdtemp(prefix="slicer-harness-settings-")
    qt.QSettings.setDefaultFormat(qt.QSettings.IniFormat)
    qt.QSettings.setPath(qt.QSettings.IniFormat, qt.QSettings.UserScope, settingsDir)
    qtApp.setOrganizationName("slicer-harness")
    qtApp.setApplicationName("Slicer")

    import slicer  # the wheel: MRML, logics, slicer.util

    from . import app as appModule
    from . import qmrml

    # Slicer's Python reads these at import (annotations), so they come first
    for name, cls in {**qmrml.STANDINS, **qmrml.PLACEHOLDERS}.items():
        setattr(slicer, name, cls)
    slicer.qSlicerScriptedLoadableModuleWidget = qmrml.qSlicerScriptedLoadableModuleWidget
    qt.QUiLoader.customWidgets.update(qmrml.STANDINS)
    qt.QUiLoader.customWidgets["ctkCollapsibleButton"] = ctk.ctkCollapsibleButton

    realDir = os.path.join(SLICER_PYTHON, "slicer")
    if realDir not in list(slicer.__path__):
        slicer.__path__.append(realDir)
    import importlib
    for name in ("i18n", "ScriptedLoadableModule", "parameterNodeWrapper"):
        mod = importlib.import_module(f"slicer.{name}")
        if not mod.__file__.startswith(realDir):
            raise RuntimeError(f"slicer.{name} came from {mod.__file__}, not from Slicer's real sources in {realDir}")
        setattr(slicer, name, mod)
    slicer.app = appModule.SlicerApplication()
    slicer.modules = types.SimpleNamespace()
    _installed = types.SimpleNamespace(qt=qt, ctk=ctk, slicer=slicer, app=slicer.app, qmrml=qmrml, appModule=appModule)
    return _installed
