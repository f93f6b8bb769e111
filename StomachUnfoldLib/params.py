"""Every parameter of a run, defined once: grouped by stage, one default each, with its unit, range and help.

``UnfoldParameters`` holds one group per stage (``front``: air region, crop, centreline and incision line;
``model``: the wall model's cells; ``solver``: the mass-spring simulation; ``output``: the unfolded volume and
report) and the ``method``. The command line's flags, the Python keywords and the Slicer parameter node are made
from, or checked against, :func:`parameter_specs`; a test fails when they drift.

Flat keywords are accepted and read back: ``UnfoldParameters(kappa=0.2).kappa == 0.2 ==
UnfoldParameters(kappa=0.2).solver.kappa``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from .errors import InputError

__all__ = ["INCISION_SIDES", "INTEGRATORS", "DEFAULT_CELL_MM", "DEFAULT_METHOD", "FrontEndParameters",
           "ModelParameters", "SolverParameters", "SurfaceParameters", "OutputParameters", "LSCM_BOUNDARIES", "UnfoldParameters", "ParameterSpec",
           "parameter_specs"]

#: Incision sides a user can choose (a user-drawn curve is given as a curve, not as a side).
INCISION_SIDES = ("greater", "lesser", "anterior", "posterior")
#: Integrators of the mass-spring solver: implicit Newmark-beta, or semi-implicit Euler for comparison.
INTEGRATORS = ("newmark", "explicit")
#: Boundary forms of the LSCM method's conformal map.
LSCM_BOUNDARIES = ("tube", "two_pins", "spectral")
#: The method a run uses unless told otherwise.
DEFAULT_METHOD = "isometric"

# The default cell: the paper's d = 8 voxels on its CTs of about 0.7 mm, kept in mm so that a coarser CT does not
# get a coarser model (d = 8 at 1.2 mm makes 9.6 mm cells, one per wall thickness, and grades fair where 5.6 mm
# grades good on the benchmark's resolution chart, docs/benchmark/README.md).
DEFAULT_CELL_MM = 5.6


def _p(default, help: str, lo=None, hi=None, choices=None, lo_open: bool = False):
    """A dataclass field with its help text, valid range [lo, hi] (lo excluded if lo_open) or choices."""
    meta = {"help": help, "lo": lo, "hi": hi, "choices": choices, "lo_open": lo_open}
    return field(default=default, metadata=meta)


class _Group:
    """A stage's parameter group: ``validate()`` checks its fields against their ranges and choices."""

    def validate(self) -> None:
        """Raise InputError naming the first field of this group out of its range or choices."""
        for spec in parameter_specs():
            if spec.group and spec.group == _GROUP_NAME.get(type(self)):
                spec.check(getattr(self, spec.name))


@dataclass
class FrontEndParameters(_Group):
    """The shared front end: air region or mask, crop, wall region, centreline, incision line (mm, HU)."""

    air_threshold_hu: float = _p(-500.0, "air threshold in HU", -1000.0, 0.0)
    fluid_max_hu: float = _p(25.0, "retained water under a flat air-fluid level joins the lumen up to this HU "
                             "(the wall is about 40 HU; -20 or less: never)", -1000.0, 100.0)
    wall_thickness_mm: float = _p(5.0, "stomach wall thickness in mm", 0.0, 30.0, lo_open=True)
    max_snap_mm: float = _p(20.0, "how far (mm) a point may lie from the lumen", 0.0, 200.0)
    centerline_step_mm: float = _p(2.0, "centreline point spacing in mm", 0.0, 20.0, lo_open=True)
    crop_margin_mm: float = _p(0.0, "extra margin (mm) around the stomach crop", 0.0, 1000.0)
    incision: str = _p("greater", "incision side", choices=INCISION_SIDES)
    swap_check: bool = _p(True, "exchange the points when the cardia lies 20 mm or more below the pylorus")


@dataclass
class ModelParameters(_Group):
    """The hexahedral wall model's cell size: d in voxels (the paper's) or in mm."""

    grid_size: int | None = _p(None, "in-plane cell size d in voxels (default: from --grid-mm)", 1, 256)
    grid_mm: float | None = _p(None, f"cell size in mm (default {DEFAULT_CELL_MM} mm; overrides --grid-size)",
                               0.0, 100.0, lo_open=True)


@dataclass
class SolverParameters(_Group):
    """The mass-spring-damper simulation: Newmark-beta constants, forces and termination (unit-free, kappa in mm)."""

    kappa: float = _p(0.5, "termination threshold on |D(a-1) - D(a)| in mm", 0.0, 100.0, lo_open=True)
    beta: float = _p(0.25, "Newmark beta (unit-free)", 0.0, 0.5, lo_open=True)
    gamma: float = _p(0.5, "Newmark gamma (unit-free)", 0.0, 1.0, lo_open=True)
    time_step: float = _p(1.0, "time step h (simulation time units: the model's unit mass and stiffness)", 0.0, 100.0, lo_open=True)
    spring_stiffness: float = _p(1.0, "spring stiffness (unit-free: the model's force per unit strain)", 0.0, 1e4, lo_open=True)
    damping: float = _p(0.5, "dashpot coefficient per spring on the relative velocity (unit-free)", 0.0, 1e4)
    mass_damping: float = _p(0.2, "viscous damping per unit mass on the absolute velocity (unit-free)", 0.0, 1e4)
    unfolding_stiffness: float = _p(10.0, "pull of the cut edges toward their destination points (unit-free, per spring stiffness)", 0.0, 1e4,
                                    lo_open=True)
    flattening_stiffness: float = _p(0.3, "pull toward the unfolded plane (unit-free, per spring stiffness; 0: the paper's forces only)", 0.0, 1e4)
    ramp_iterations: int = _p(30, "iterations of guided destinations and flattening ramp (0: the paper's fixed g)",
                              0, 10000)
    max_iterations: int = _p(300, "iteration cap (iterations)", 1, 100000)
    min_iterations: int = _p(5, "iterations before the kappa test may stop (iterations)", 0, 100000)
    inner_iterations: int = _p(2, "local/global sweeps per step for the spring directions (sweeps)", 1, 100)
    integrator: str = _p("newmark", "time integrator", choices=INTEGRATORS)
    max_retries: int = _p(4, "time-step halvings after a divergence (count)", 0, 20)


@dataclass
class SurfaceParameters(_Group):
    """The surface-based methods (cylindrical unrolling, LSCM): sampling and boundary form."""

    angular_samples: int | None = _p(None, "cylindrical: rays around the centreline (default: one per pixel of "
                                     "the mean circumference)", 8, 100000)
    lscm_boundary: str = _p("tube", "lscm: openings on two lines with the seam glued (tube), Levy's two pins "
                            "(two_pins) or the pin-free spectral form (spectral)", choices=LSCM_BOUNDARIES)
    isometric_surface: str = _p("opened", "isometric: the whole lumen surface opened where the graded mucosa ends "
                                "(opened) or trimmed at the centreline's end planes (trimmed)",
                                choices=("opened", "trimmed"))
    isometric_vertices: int = _p(20000, "isometric: the most vertices of the surface mesh it flattens; fewer is "
                                 "faster and coarser (12000 was 2.6x faster on the benchmark's random stomachs and "
                                 "lost a little accuracy: docs/benchmark/README.md)", 1000, 200000)


#: The view's voxel (mm) when ``output_spacing_mm`` is not set is the CT's in-plane voxel size, but at most this, so
#: that a 5 mm lesion spans at least three pixels (rule 37, docs/RULE37_view_pixel_cap.md).
AUTO_PIXEL_MAX_MM = 1.5


@dataclass
class OutputParameters(_Group):
    """The unfolded volume and the report."""

    output_spacing_mm: float | None = _p(None, "unfolded volume spacing in mm (default: input in-plane spacing, at most "
                                         f"{AUTO_PIXEL_MAX_MM:g}; "
                                         "over 5 mm a stomach's view is a few dozen pixels)", 0.0, 5.0, lo_open=True)
    clear_lumen: bool = _p(True, "with a mask: show the lumen contents as air in the unfolded volume")
    quality: bool = _p(True, "compute the automatic quality metrics and grade into the report")


#: The stage groups of UnfoldParameters, in pipeline order.
GROUPS = {"front": FrontEndParameters, "model": ModelParameters, "solver": SolverParameters,
          "surface": SurfaceParameters, "output": OutputParameters}
_GROUP_NAME = {cls: name for name, cls in GROUPS.items()}


@dataclass(frozen=True)
class ParameterSpec:
    """One parameter: flat name, group, type (float/int/str/bool), default, help, range or choices, optional."""

    name: str
    group: str
    kind: type
    default: Any
    help: str
    lo: Any = None
    hi: Any = None
    choices: tuple | None = None
    lo_open: bool = False
    optional: bool = False

    @property
    def flag(self) -> str:
        """The command-line flag of this parameter (``--wall-thickness-mm``)."""
        return "--" + self.name.replace("_", "-")

    def check(self, value) -> None:
        """Raise InputError naming this parameter when ``value`` is out of its range or choices."""
        if value is None:
            if not self.optional:
                raise InputError(f"{self.name} must be given")
            return
        if self.choices is not None:
            if value not in self.choices:
                raise InputError(f"{self.name} must be one of {', '.join(self.choices)}, got {value!r}")
            return
        if self.kind is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise InputError(f"{self.name} must be true or false, got {value!r}")
            return
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{self.name} must be a number, got {value!r}") from None
        if self.kind is int and v != int(v):
            raise InputError(f"{self.name} must be a whole number, got {value!r}")
        low_bad = (v <= self.lo) if self.lo_open else (v < self.lo)
        if not np.isfinite(v) or (self.lo is not None and low_bad) or (self.hi is not None and v > self.hi):
            lo_txt = f"above {self.lo:g}" if self.lo_open else f"at least {self.lo:g}"
            raise InputError(f"{self.name} must be {lo_txt} and at most {self.hi:g}, got {value!r}")


def _kind(f) -> tuple[type, bool]:
    t = str(f.type)
    optional = "None" in t
    for name, kind in (("bool", bool), ("int", int), ("float", float), ("str", str)):
        if t.startswith(name):
            return kind, optional
    raise TypeError(f"parameter {f.name} has an unsupported type {t}")


def parameter_specs() -> list[ParameterSpec]:
    """Every parameter of a run as a ParameterSpec, in group order (the method first)."""
    from .methods import method_names

    out = [ParameterSpec("method", "", str, DEFAULT_METHOD, "unfolding method", choices=method_names())]
    for group, cls in GROUPS.items():
        for f in fields(cls):
            kind, optional = _kind(f)
            m = f.metadata
            out.append(ParameterSpec(f.name, group, kind, f.default, m["help"], m["lo"], m["hi"],
                                     tuple(m["choices"]) if m["choices"] else None, m["lo_open"], optional))
    return out


def _group_of() -> dict[str, str]:
    return _GROUP_OF


_GROUP_OF = {f.name: g for g, cls in GROUPS.items() for f in fields(cls)}


class UnfoldParameters:
    """Parameters of a run: ``method`` and one group per stage; flat keywords (``kappa=0.2``) route to their group.

    Units are in the names (mm, HU); grid sizes in voxels; simulation constants unit-free.
    """

    __slots__ = ("method", "front", "model", "solver", "surface", "output")

    def __init__(self, method: str = DEFAULT_METHOD, *, front: FrontEndParameters | None = None,
                 model: ModelParameters | None = None, solver: SolverParameters | None = None,
                 surface: SurfaceParameters | None = None, output: OutputParameters | None = None, **flat):
        object.__setattr__(self, "method", method)
        groups = {"front": front or FrontEndParameters(), "model": model or ModelParameters(),
                  "solver": solver or SolverParameters(), "surface": surface or SurfaceParameters(),
                  "output": output or OutputParameters()}
        for g, obj in groups.items():
            object.__setattr__(self, g, obj)
        where = _group_of()
        for name, value in flat.items():
            if name not in where:
                raise InputError(f"unknown parameter {name!r}; known: {', '.join(sorted(where))}")
            setattr(groups[where[name]], name, value)

    def __getattr__(self, name):
        where = _group_of()
        if name in where:
            return getattr(object.__getattribute__(self, where[name]), name)
        raise AttributeError(f"UnfoldParameters has no parameter {name!r}")

    def __setattr__(self, name, value):
        if name in self.__slots__:
            object.__setattr__(self, name, value)
            return
        where = _group_of()
        if name not in where:
            raise AttributeError(f"UnfoldParameters has no parameter {name!r}")
        setattr(getattr(self, where[name]), name, value)

    def __eq__(self, other):
        return isinstance(other, UnfoldParameters) and self.to_dict() == other.to_dict()

    def __repr__(self):
        defaults = {s.name: s.default for s in parameter_specs()}
        changed = {k: v for k, v in self.flat().items() if v != defaults.get(k)}
        return "UnfoldParameters(" + ", ".join(f"{k}={v!r}" for k, v in changed.items()) + ")"

    def replace(self, **flat) -> "UnfoldParameters":
        """A copy with some parameters changed (flat names)."""
        return UnfoldParameters(**{**self.flat(), **flat})

    def flat(self) -> dict:
        """All parameters as one flat dict {name: value}."""
        out = {"method": self.method}
        for g in GROUPS:
            out.update(asdict(getattr(self, g)))
        return out

    def to_dict(self) -> dict:
        """All parameters grouped by stage: {"method": ..., "front": {...}, "model": {...}, ...} (for reports)."""
        return {"method": self.method, **{g: asdict(getattr(self, g)) for g in GROUPS}}

    @classmethod
    def from_dict(cls, d: dict) -> "UnfoldParameters":
        """Parameters from a flat or grouped dict (as written by to_dict or flat)."""
        flat = {}
        for k, v in dict(d).items():
            if k in GROUPS and isinstance(v, dict):
                flat.update(v)
            else:
                flat[k] = v
        return cls(**flat)

    def validate(self) -> None:
        """Raise InputError naming the first parameter out of its range or choices."""
        values = self.flat()
        for spec in parameter_specs():
            spec.check(values[spec.name])

    def grid_voxels(self, spacing) -> int:
        """The in-plane cell size d in voxels for a CT of this spacing (mm): grid_mm, else grid_size, else DEFAULT_CELL_MM."""
        m = self.model
        if m.grid_mm is None and m.grid_size is not None:
            return int(m.grid_size)
        cell = m.grid_mm if m.grid_mm is not None else DEFAULT_CELL_MM
        pixel = float(np.sqrt(spacing[0] * spacing[1]))
        return max(1, int(round(cell / pixel)))

