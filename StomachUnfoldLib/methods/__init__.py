"""Unfolding methods: each takes the shared front end's :class:`~StomachUnfoldLib.frontend.Prepared` and returns an
:class:`Unfolding` with the same contract (unfolded volume, correspondence, model, its own report section).

Adding a method is writing one file in this package with a class like::

    @register
    class MyMethod(Method):
        name = "mine"
        description = "one line for --help and the Slicer panel"

        def unfold(self, prep, progress):
            ...
            return Unfolding(unfolded=volume, correspondence=corr, mesh=mesh, report={...})

and adding its module name to ``BUILTIN`` below. The unfolded volume's axes are the same for every method:
``array[k, j, i]`` in HU, i from the cardia toward the pylorus, j across the opened wall, k along the wall's
normal toward the viewer, who looks down -k at the mucosa (air above it, then the wall).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..geometry import Volume

__all__ = ["Mesh", "Unfolding", "Method", "register", "get_method", "method_names", "methods", "BUILTIN"]

#: The built-in methods' modules, in the order they are listed.
BUILTIN = ("massspring", "cylindrical", "lscm", "isometric")

_REGISTRY: dict[str, type] = {}


@dataclass
class Mesh:
    """A method's model before and after unfolding: vertices (LPS mm), cells, and the mucosa's triangles.

    ``kind`` is the VTK cell type name (``"hexahedron"`` or ``"triangle"``); ``surface`` holds the mucosa's
    triangles (indices into the vertices) on which distortion is measured (for triangles: the cells).
    """

    rest_lps: np.ndarray
    unfolded_lps: np.ndarray
    cells: np.ndarray
    kind: str
    surface: np.ndarray

    def edges(self) -> np.ndarray:
        """Unique vertex pairs (E,2) joined by a cell edge."""
        if self.kind == "hexahedron":
            pairs = self.cells[:, [0, 1, 1, 2, 2, 3, 3, 0, 4, 5, 5, 6, 6, 7, 7, 4, 0, 4, 1, 5, 2, 6, 3, 7]]
        else:
            pairs = self.cells[:, [0, 1, 1, 2, 2, 0]]
        return np.unique(np.sort(pairs.reshape(-1, 2), axis=1), axis=0)


@dataclass
class Unfolding:
    """What a method returns: the unfolded Volume (HU), a correspondence, its Mesh, its report section, warnings.

    ``correspondence`` maps LPS mm of the CT to LPS mm of the unfolded volume and back:
    ``to_unfolded(points)`` and ``to_original(points)`` on (N,3) arrays, NaN where a point is not on the wall.
    """

    unfolded: Volume
    correspondence: object
    mesh: Mesh
    report: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)


class Method:
    """One unfolding method: ``unfold(prep, progress) -> Unfolding`` (progress a Progress spanning the method)."""

    name = ""
    description = ""
    #: report name of the stages this method reports, with their share of its progress, for the progress bar
    stages: tuple = ()

    def unfold(self, prep, progress) -> Unfolding:
        """Unfold the prepared stomach (LPS mm) into an Unfolding."""
        raise NotImplementedError


def register(cls: type) -> type:
    """Class decorator: make a Method subclass available by its ``name`` (``--method NAME``)."""
    if not (isinstance(cls, type) and issubclass(cls, Method) and cls.name):
        raise TypeError("register() takes a Method subclass with a name")
    _REGISTRY[cls.name] = cls
    return cls


def _load_builtin() -> None:
    for mod in BUILTIN:
        importlib.import_module(f"{__name__}.{mod}")


def method_names() -> tuple[str, ...]:
    """Names of the registered methods, built-in ones first."""
    _load_builtin()
    return tuple(_REGISTRY)


def methods() -> dict[str, str]:
    """{name: one-line description} of the registered methods."""
    _load_builtin()
    return {n: c.description for n, c in _REGISTRY.items()}


def get_method(name: str) -> Method:
    """A fresh instance of the method called ``name``; InputError listing the choices if there is none."""
    _load_builtin()
    if name not in _REGISTRY:
        raise InputError(f"unknown method {name!r}; choose one of {', '.join(_REGISTRY)}")
    return _REGISTRY[name]()
