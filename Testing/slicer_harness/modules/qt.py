"""``qt`` for the test harness: real Qt (PySide6, offscreen) with PythonQt's calling conventions.

Slicer's ``qt`` module is PythonQt. What Slicer's own Python (ScriptedLoadableModule, parameterNodeWrapper,
SampleData, slicer.util) and a module's code rely on, and what is emulated here over PySide6:

- Qt properties read and written as attributes (``button.text = "Cancel"``, ``spinBox.value``); a Qt
  property shadows a getter method of the same name, as in PythonQt; ``obj.name`` is ``objectName``;
- ``obj.connect("signal(args)", callable)`` and ``obj.disconnect("signal(args)", callable)``;
- ``QUiLoader`` that creates the CTK/qMRML stand-ins registered with it and makes the ``<connections>`` of
  the .ui in Python (Qt's loader makes them by C++ signature, which Python-declared signals do not have).

Nothing else is changed: widgets, layouts, events, dialogs and painting are Qt's own.
"""
import os
import re
import types as _types
import xml.etree.ElementTree as ET

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from PySide6 import QtCore, QtGui, QtWidgets
from PySide6.QtCore import *
from PySide6.QtGui import *
from PySide6.QtUiTools import QUiLoader as _QUiLoader
from PySide6.QtWidgets import *

_getattribute = QtCore.QObject.__getattribute__
_setattr = QtCore.QObject.__mro__[-2].__setattr__  # Shiboken.Object: the C slot below the patched ones
_PROPERTY_CACHE = {}


def _qtPropertyNames(obj):
    """Names of the C++ (not Python-declared) Qt properties of obj's class."""
    cls = type(obj)
    names = _PROPERTY_CACHE.get(cls)
    if names is None:
        mo = QtCore.QObject.metaObject(obj)
        names = {mo.property(i).name(): i for i in range(mo.propertyCount())}
        _PROPERTY_CACHE[cls] = names
    return names


def _readProperty(obj, name):
    """Read a C++ Qt property through its QMetaProperty (not through Python attribute lookup)."""
    mo = QtCore.QObject.metaObject(obj)
    return mo.property(_qtPropertyNames(obj)[name]).read(obj)


#: Qt properties named like a C++ virtual method: Shiboken looks these up by attribute to find Python overrides,
#: so they must stay methods here (PythonQt has no such lookup).
_VIRTUAL_NAMES = {"sizeHint", "minimumSizeHint"}


def _definedInPython(cls, name):
    for k in cls.__mro__:
        if name in k.__dict__:
            return not (k.__module__ or "").startswith(("PySide6", "Shiboken"))
    return False


_ORIGINAL_GETATTRIBUTE = {}  # PySide class -> its own (C) __getattribute__, before the patch


def _nativeGetattribute(self, name):
    for k in type(self).__mro__:
        f = _ORIGINAL_GETATTRIBUTE.get(k)
        if f is not None:
            return f(self, name)
    return object.__getattribute__(self, name)


def _pqGetattribute(self, name):
    if name[:1] != "_":
        if name == "name":
            return QtCore.QObject.objectName(self)
        if name == "connect":
            return _types.MethodType(_pqConnect, self)
        if name == "disconnect":
            return _types.MethodType(_pqDisconnect, self)
        if name in _qtPropertyNames(self) and name not in _VIRTUAL_NAMES and not _definedInPython(type(self), name):
            return _readProperty(self, name)
    return _nativeGetattribute(self, name)


def _pqSetattr(self, name, value):
    if name[:1] != "_":
        if name == "name":
            QtCore.QObject.setObjectName(self, value)
            return
        if name in _qtPropertyNames(self) and not _definedInPython(type(self), name):
            setter = "set" + name[0].upper() + name[1:]
            fn = getattr(type(self), setter, None)
            if fn is not None:
                fn(self, value)
            elif not QtCore.QObject.setProperty(self, name, value):
                raise AttributeError(f"cannot set Qt property {name!r} of {type(self).__name__}")
            return
    _setattr(self, name, value)


_SIGNATURE = re.compile(r"^\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$")
_ARG_TYPES = {"bool": bool, "int": int, "double": float, "float": float, "QString": str, "const QString&": str}


def _signalInstance(obj, signature):
    """The bound signal for a PythonQt-style signature such as "clicked(bool)" or "currentNodeChanged(vtkMRMLNode*)"."""
    m = _SIGNATURE.match(signature)
    if not m:
        raise ValueError(f"not a signal signature: {signature!r}")
    name, args = m.group(1), [a.strip() for a in m.group(2).split(",") if a.strip()]
    try:
        sig = _getattribute(obj, name)
    except AttributeError:
        raise AttributeError(f"{type(obj).__name__} has no signal {signature}") from None
    if not isinstance(sig, QtCore.SignalInstance):
        raise AttributeError(f"{type(obj).__name__}.{name} is not a signal")
    if len(args) == 1:
        t = _ARG_TYPES.get(args[0], object)
        try:
            return sig[t]
        except (KeyError, IndexError, TypeError):
            return sig
    return sig


def _pqConnect(self, signature, slot, *rest):
    """PythonQt's obj.connect("signal(args)", callable)."""
    if not isinstance(signature, str):  # QObject.connect(sender, SIGNAL, ...) static form
        return QtCore.QObject._pyside_connect(self, signature, slot, *rest)
    _signalInstance(self, signature).connect(slot)
    return True


def _pqDisconnect(self, signature=None, slot=None, *rest):
    """PythonQt's obj.disconnect("signal(args)", callable)."""
    if not isinstance(signature, str):
        return QtCore.QObject._pyside_disconnect(self, signature, slot, *rest)
    try:
        _signalInstance(self, signature).disconnect(slot)
    except (RuntimeError, TypeError):
        return False
    return True


QtCore.QObject._pyside_connect = QtCore.QObject.connect
QtCore.QObject._pyside_disconnect = QtCore.QObject.disconnect


_delattr = QtCore.QObject.__mro__[-2].__delattr__


def _pqDelattr(self, name):
    _delattr(self, name)


def _patch(cls):
    cls.__delattr__ = _pqDelattr
    cls.__getattribute__ = _pqGetattribute
    cls.__setattr__ = _pqSetattr
    cls.connect = _pqConnect
    cls.disconnect = _pqDisconnect


_QOBJECT_CLASSES = [c for m in (QtCore, QtGui, QtWidgets) for c in vars(m).values()
                    if isinstance(c, type) and issubclass(c, QtCore.QObject)]
for _c in _QOBJECT_CLASSES:  # first keep each class's own C __getattribute__ (QFile, QMenu... have one)
    if "__getattribute__" in vars(_c):
        _ORIGINAL_GETATTRIBUTE[_c] = vars(_c)["__getattribute__"]
for _c in _QOBJECT_CLASSES:
    _patch(_c)


def application():
    """The QApplication (created on first use, offscreen)."""
    app = QtWidgets.QApplication.instance()
    return app if app is not None else QtWidgets.QApplication(["slicer-harness"])


class QUiLoader(_QUiLoader):
    """QUiLoader that knows the harness's CTK/qMRML stand-ins and makes the .ui's <connections> in Python."""

    customWidgets = {}  # class name -> Python class, filled by the harness

    def __init__(self, parent=None):
        application()
        super().__init__(parent)
        for cls in self.customWidgets.values():
            self.registerCustomWidget(cls)

    def load(self, device, parentWidget=None):
        """Load a .ui from a QFile (or a path) into widgets; returns the top-level widget."""
        if isinstance(device, str):
            f = QtCore.QFile(device)
            f.open(QtCore.QIODevice.ReadOnly)
            device = f
        data = bytes(device.readAll())
        buffer = QtCore.QBuffer()
        buffer.setData(QtCore.QByteArray(data.replace(b"<connections>", b"<!--c").replace(b"</connections>", b"c-->")))
        buffer.open(QtCore.QIODevice.ReadOnly)
        widget = super().load(buffer, parentWidget)
        if widget is not None:
            _makeConnections(widget, data)
        return widget


def _makeConnections(top, data):
    root = ET.fromstring(data)
    conns = root.find("connections")
    if conns is None:
        return

    def find(name):
        if top.objectName == name:
            return top
        w = top.findChild(QtCore.QObject, name)
        if w is None:
            raise RuntimeError(f".ui connection names {name!r}, which is not in the form")
        return w

    for c in conns.findall("connection"):
        sender, receiver = find(c.findtext("sender")), find(c.findtext("receiver"))
        slotName = _SIGNATURE.match(c.findtext("slot")).group(1)
        slot = _getattribute(receiver, slotName)
        _signalInstance(sender, c.findtext("signal")).connect(slot)
