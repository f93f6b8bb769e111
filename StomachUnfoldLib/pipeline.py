"""The whole method, CT volume to unfolded volume: chains the stages and writes the output contract.

``unfold(ct, cardia_lps, pylorus_lps, params)`` runs: air region (or stomach mask) -> crop to the stomach
-> wall region -> centreline and radius -> incision line -> hexahedral wall model -> unfolded plane, base
line and destination points -> Newmark-beta unfolding -> unfolded volume -> correspondence.
``UnfoldResult.write(out_dir)`` writes ``unfolded.nrrd``, ``report.json``, ``view.png``,
``model_rest.vtu``, ``model_unfolded.vtu``, ``incision.mrk.json`` and ``centerline.mrk.json``.
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from . import __version__
from .errors import InputError, PointError
from .geometry import Volume, lps_to_ras
from .progress import Progress

__all__ = ["UnfoldParameters", "UnfoldResult", "unfold", "STAGES", "DEFAULT_CELL_MM"]

#: Stage names and their share of the progress bar.
STAGES = [("air region", 0.0, 0.08), ("wall region", 0.08, 0.12), ("centreline", 0.12, 0.2),
          ("incision line", 0.2, 0.24), ("wall model", 0.24, 0.3), ("unfolding forces", 0.3, 0.32),
          ("simulation", 0.32, 0.78), ("unfolded volume", 0.78, 0.92), ("correspondence", 0.92, 0.93),
          ("quality", 0.93, 1.0)]


# The default cell: the paper's d = 8 voxels on its CTs of about 0.7 mm, kept in mm so that a coarser CT does not
# get a coarser model (d = 8 at 1.2 mm makes 9.6 mm cells, one per wall thickness, and grades fair where 5.6 mm
# grades good on the benchmark's resolution chart, docs/benchmark/README.md).
DEFAULT_CELL_MM = 5.6


@dataclass
class UnfoldParameters:
    """Parameters of a run; units in the names (mm, HU), grid sizes in voxels, simulation constants unit-free."""

    grid_size: int | None = None        # d, in-plane cell size in voxels (the paper's d); None: from grid_mm
    grid_mm: float | None = None        # if set, d = round(grid_mm / in-plane spacing); overrides grid_size
    kappa: float = 0.5                  # termination threshold on |D(a-1) - D(a)|, mm
    incision: str = "greater"           # greater | lesser | anterior | posterior
    wall_thickness_mm: float = 5.0
    air_threshold_hu: float = -500.0
    beta: float = 0.25
    gamma: float = 0.5
    time_step: float = 1.0
    spring_stiffness: float = 1.0
    damping: float = 0.5
    mass_damping: float = 0.2
    unfolding_stiffness: float = 10.0
    flattening_stiffness: float = 0.3   # pull toward the unfolded plane (0: the paper's forces only)
    ramp_iterations: int = 30           # guided destinations and flattening ramp (0: the paper's fixed g)
    max_iterations: int = 300
    min_iterations: int = 5
    integrator: str = "newmark"         # newmark (implicit) | explicit (semi-implicit Euler, for comparison)
    max_retries: int = 4                # time-step halvings after a divergence
    output_spacing_mm: float | None = None  # unfolded volume spacing; default the input's in-plane spacing
    max_snap_mm: float = 20.0           # how far a point may lie from the lumen
    centerline_step_mm: float = 2.0
    clear_lumen: bool = True            # with a mask: show the lumen contents as air in the unfolded volume
    swap_check: bool = True             # exchange the points when the "cardia" lies well below the "pylorus"
    quality: bool = True                # compute the automatic quality metrics and grade into the report
    crop_margin_mm: float = 0.0         # extra margin (mm) around the stomach crop (benchmark of crop size)

    def validate(self) -> None:
        """Raise InputError naming the first parameter out of range."""
        if self.incision not in ("greater", "lesser", "anterior", "posterior", "user"):
            raise InputError(f"incision must be greater, lesser, anterior or posterior, got {self.incision!r}")
        if self.grid_size is not None and (int(self.grid_size) != self.grid_size or int(self.grid_size) < 1):
            raise InputError(f"grid_size must be a whole number of voxels >= 1, got {self.grid_size}")
        if self.grid_mm is not None and not self.grid_mm > 0:
            raise InputError(f"grid_mm must be positive, got {self.grid_mm}")
        if not self.wall_thickness_mm > 0:
            raise InputError(f"wall_thickness_mm must be positive, got {self.wall_thickness_mm}")
        if self.output_spacing_mm is not None and not self.output_spacing_mm > 0:
            raise InputError(f"output_spacing_mm must be positive, got {self.output_spacing_mm}")
        if self.crop_margin_mm < 0:
            raise InputError(f"crop_margin_mm must not be negative, got {self.crop_margin_mm}")
        if self.flattening_stiffness < 0 or self.ramp_iterations < 0:
            raise InputError("flattening_stiffness and ramp_iterations must not be negative")

    def newmark(self):
        """The Newmark-beta constants of these parameters."""
        from .newmark import NewmarkParameters

        return NewmarkParameters(beta=self.beta, gamma=self.gamma, time_step=self.time_step,
                                 spring_stiffness=self.spring_stiffness, damping=self.damping,
                                 mass_damping=self.mass_damping, unfolding_stiffness=self.unfolding_stiffness,
                                 kappa=self.kappa, max_iterations=int(self.max_iterations),
                                 min_iterations=int(self.min_iterations), integrator=self.integrator,
                                 max_retries=int(self.max_retries))

    def grid_voxels(self, spacing) -> int:
        """The in-plane cell size d in voxels for a CT of this spacing (mm): grid_mm, else grid_size, else DEFAULT_CELL_MM."""
        if self.grid_mm is None and self.grid_size is not None:
            return int(self.grid_size)
        cell = self.grid_mm if self.grid_mm is not None else DEFAULT_CELL_MM
        pixel = float(np.sqrt(spacing[0] * spacing[1]))
        return max(1, int(round(cell / pixel)))


@dataclass
class UnfoldResult:
    """Everything a run produces: the unfolded volume, the model before/after, curves, report, correspondence."""

    unfolded: Volume
    report: dict
    centerline_lps: np.ndarray
    incision_lps: np.ndarray
    rest_vertices: np.ndarray
    deformed_vertices: np.ndarray
    hexes: np.ndarray
    correspondence: object
    lumen_crop: Volume | None = field(default=None, repr=False)
    inner_vertices: np.ndarray | None = field(default=None, repr=False)

    def write(self, out_dir, landmarks_lps: dict | None = None) -> dict:
        """Write the output files into ``out_dir`` all together or not at all; returns {name: path}."""
        from . import io as suio
        from .view import render_view
        from .wall_model import write_vtu

        os.makedirs(out_dir, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=".unfold-", dir=out_dir)
        try:
            names = {}
            def path(name):
                names[name] = os.path.join(out_dir, name)
                return os.path.join(tmp, name)
            suio.write_volume(self.unfolded, path("unfolded.nrrd"))
            render_view(self.unfolded, path("view.png"))
            write_vtu(self.rest_vertices, self.hexes, path("model_rest.vtu"))
            write_vtu(self.deformed_vertices, self.hexes, path("model_unfolded.vtu"))
            suio.write_markups_curve(path("incision.mrk.json"), self.incision_lps, "incision", color=(1.0, 0.3, 0.2))
            suio.write_markups_curve(path("centerline.mrk.json"), self.centerline_lps, "centerline",
                                     color=(0.2, 0.8, 1.0))
            if landmarks_lps:
                mapped = self.map_landmarks(landmarks_lps)
                ok = {k: v for k, v in mapped.items() if np.all(np.isfinite(v))}
                self.report["landmarks"] = {k: {"original_lps": np.asarray(landmarks_lps[k]).tolist(),
                                                "unfolded_lps": (np.asarray(v).tolist() if k in ok else None)}
                                            for k, v in mapped.items()}
                suio.write_markups_fiducials(path("landmarks_unfolded.mrk.json"), ok, "landmarks_unfolded")
            suio.atomic_write_text(path("report.json"), json.dumps(self.report, indent=2, default=_json_default))
            for name, final in names.items():
                os.replace(os.path.join(tmp, name), final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return names

    def map_landmarks(self, points_lps: dict) -> dict:
        """Map named LPS points (mm) of the original CT into the unfolded volume's LPS frame (NaN if not on the wall)."""
        keys = list(points_lps)
        if not keys:
            return {}
        pts = np.array([points_lps[k] for k in keys], float)
        mapped = self.correspondence.to_unfolded(pts)
        return {k: mapped[i] for i, k in enumerate(keys)}


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def available_memory_bytes() -> int:
    """Memory this process may still use (bytes): MemAvailable from /proc/meminfo, else physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def estimate_memory_bytes(ct: Volume) -> int:
    """Rough peak extra memory (bytes) of a run on this CT: masks and labels over the whole grid, before cropping."""
    return int(ct.array.size * 6)


def check_volume(ct: Volume) -> list[str]:
    """Refuse volumes that cannot be a CT in HU (InputError saying why); return warnings for odd but usable ones."""
    a = ct.array
    warnings = []
    if a.dtype.kind not in "iuf":
        raise InputError(f"the CT must hold numbers (HU), got dtype {a.dtype}")
    if min(a.shape) < 8:
        raise InputError(f"the volume is only {ct.size} voxels (i, j, k); an abdominal CT with at least 8 voxels "
                         "along each axis is needed")
    extent = np.array(ct.size) * ct.spacing
    if extent.min() < 20.0:
        raise InputError(f"the volume covers only {np.round(extent, 1).tolist()} mm; it cannot hold a stomach")
    need = estimate_memory_bytes(ct)
    avail = available_memory_bytes()
    if need > 0.8 * avail:
        raise InputError(f"this volume ({ct.size} voxels) needs about {need / 2**30:.1f} GiB of working memory and "
                         f"only {avail / 2**30:.1f} GiB is free; crop the CT to the upper abdomen first")
    if a.dtype.kind == "f":
        finite = np.isfinite(a)
        if not finite.all():
            frac = 1.0 - finite.mean()
            raise InputError(f"{100 * frac:.1f}% of the voxels are NaN or infinite; give a CT with finite HU values")
    lo, hi = float(a.min()), float(a.max())
    if hi - lo < 1e-6:
        raise InputError(f"the volume is constant ({lo:g}); give a CT volume")
    if lo > -300.0 or hi - lo < 500.0:
        raise InputError(f"the values range from {lo:g} to {hi:g}, which is not a CT in Hounsfield units (air is "
                         "about -1000 HU, soft tissue 0 to 100 HU); give a CT, or rescale it to HU")
    ratio = float(ct.spacing.max() / ct.spacing.min())
    if ratio > 5.0:
        warnings.append(f"the voxels are {ratio:.1f} times longer along one axis ({np.round(ct.spacing, 2).tolist()} "
                        "mm); the wall model follows the coarse axis and the view will be coarse along it")
    return warnings


def _check_points(ct: Volume, cardia_lps, pylorus_lps):
    pts = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        p = np.asarray(p, float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PointError(f"the {name} point must be three finite numbers (mm), got {p}")
        if not ct.contains_lps(p[None], margin=0.5)[0]:
            lo, hi = ct.bounds_lps()
            ras = lps_to_ras(p)
            raise PointError(f"the {name} point RAS {np.round(ras, 1).tolist()} mm lies outside the volume "
                             f"(LPS bounds {np.round(lo, 1).tolist()} to {np.round(hi, 1).tolist()}); "
                             "place it inside the stomach")
        pts.append(p)
    if np.linalg.norm(pts[0] - pts[1]) < 10.0:
        raise PointError(f"the cardia and pylorus are only {np.linalg.norm(pts[0] - pts[1]):.1f} mm apart; "
                         "place them at the two ends of the stomach")
    return pts


def unfold(ct: Volume, cardia_lps, pylorus_lps, params: UnfoldParameters | None = None,
           mask: np.ndarray | None = None, incision_curve_lps=None, progress=None) -> UnfoldResult:
    """Unfold the stomach of CT ``ct`` (HU) between the cardia and pylorus points (LPS mm); returns UnfoldResult.

    ``mask`` is an optional bool stomach label on ct's grid that replaces the air threshold (for a stomach
    without gas); ``incision_curve_lps`` an optional user incision curve (LPS mm); ``progress`` a callable
    ``(stage, fraction)`` that may return False to cancel (raises Cancelled). The input is never modified.
    """
    from .centerline import compute_centerline
    from .correspondence import Correspondence
    from .incision_line import compute_incision_line, incision_from_curve, incision_surface_points
    from .newmark import simulate
    from .preprocessing import air_region, bounding_box, lumen_from_mask, wall_region
    from .unfolded_volume import build_unfolded_volume, make_grid
    from .unfolding_force import unfolding_targets, wall_depth
    from .wall_model import build_wall_model, grid_steps

    params = params or UnfoldParameters()
    params.validate()
    nm_params = params.newmark()
    nm_params.validate()
    prog = progress if isinstance(progress, Progress) else Progress(progress)
    stage = {name: prog.sub(name, lo, hi) for name, lo, hi in STAGES}
    seconds: dict[str, float] = {}
    warnings: list[str] = []
    t_all = time.perf_counter()
    warnings += check_volume(ct)
    cardia_lps, pylorus_lps = _check_points(ct, cardia_lps, pylorus_lps)
    if params.swap_check and pylorus_lps[2] > cardia_lps[2] + 20.0:
        # the cardia lies superior to the pylorus in every stomach orientation seen on supine CT
        cardia_lps, pylorus_lps = pylorus_lps, cardia_lps
        warnings.append("the cardia point lay 20 mm or more below the pylorus point: the two points were probably "
                        "swapped and have been exchanged (set swap_check=False to keep them as given)")

    # --- air region / lumen -------------------------------------------------------------------
    t = time.perf_counter()
    stage["air region"](0.0)
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != ct.array.shape:
            raise InputError(f"the stomach mask has shape {mask.shape}, the CT {ct.array.shape}: resample the "
                             "mask onto the CT grid (io.read_label_volume does)")
        lumen, info_air = lumen_from_mask(mask, ct, cardia_lps, pylorus_lps, max_snap_mm=params.max_snap_mm)
    else:
        lumen, info_air = air_region(ct, cardia_lps, pylorus_lps, threshold_hu=params.air_threshold_hu,
                                     max_snap_mm=params.max_snap_mm, progress=stage["air region"])
    warnings += list(info_air.get("warnings", []))
    seconds["air region"] = time.perf_counter() - t

    # --- crop to the stomach -------------------------------------------------------------------
    d = params.grid_voxels(ct.spacing)
    steps = grid_steps(ct.spacing, d)
    cell_mm = np.array(steps) * ct.spacing
    margin_mm = params.wall_thickness_mm + 2.0 * cell_mm.max() + 4.0 + float(params.crop_margin_mm)
    lo, hi = bounding_box(lumen, tuple(int(np.ceil(margin_mm / s)) for s in ct.spacing))
    crop = ct.crop(lo, hi)
    lumen_c = lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    del lumen

    # --- wall region -----------------------------------------------------------------------------
    t = time.perf_counter()
    stage["wall region"](0.0)
    wall = wall_region(lumen_c, crop.spacing, params.wall_thickness_mm)
    wall_voxels = int(np.count_nonzero(wall))
    seconds["wall region"] = time.perf_counter() - t

    # --- centreline ------------------------------------------------------------------------------
    t = time.perf_counter()
    cl = compute_centerline(lumen_c, crop, cardia_lps, pylorus_lps, step_mm=params.centerline_step_mm,
                            max_snap_mm=params.max_snap_mm, progress=stage["centreline"])
    seconds["centreline"] = time.perf_counter() - t
    if cl.length_mm < 1.5 * float(np.median(cl.radius_mm)):
        raise PointError(f"the cardia and pylorus are only {cl.length_mm:.0f} mm apart along the lumen, less than the "
                         f"stomach's width ({2 * np.median(cl.radius_mm):.0f} mm): both lie in the same part of the "
                         "stomach; place the cardia at the oesophageal end and the pylorus at the duodenal end")
    if float(np.min(cl.radius_mm)) < 1.5 * float(cell_mm[:2].max()) / 2:
        warnings.append(f"the lumen is as narrow as {np.min(cl.radius_mm):.1f} mm radius, close to the cell size "
                        f"{cell_mm.max():.1f} mm; a smaller --grid-size gives a finer model")

    # --- incision line ---------------------------------------------------------------------------
    t = time.perf_counter()
    stage["incision line"](0.0)
    if incision_curve_lps is not None:
        inc = incision_from_curve(incision_curve_lps, cl)
    else:
        inc = compute_incision_line(lumen_c, crop, cl, side=params.incision)
    seconds["incision line"] = time.perf_counter() - t

    # --- wall model ------------------------------------------------------------------------------
    t = time.perf_counter()
    stage["wall model"](0.0)
    cut = incision_surface_points(inc, cl, depth_mm=params.wall_thickness_mm + 2.0 * cell_mm.max(),
                                  inside_mm=cell_mm.max(), sample_mm=0.3 * cell_mm.min(),
                                  extend_mm=cell_mm.max())
    openings = [(cl.points_lps[0], -cl.tangents[0]), (cl.points_lps[-1], cl.tangents[-1])]
    model = build_wall_model(crop, wall, lumen_c, d=d, cut_points_lps=cut, openings=openings,
                             centerline_lps=cl.points_lps)
    del wall
    seconds["wall model"] = time.perf_counter() - t

    # --- unfolding forces ------------------------------------------------------------------------
    t = time.perf_counter()
    stage["unfolding forces"](0.0)
    depth = wall_depth(model.vertices, lumen_c, crop)
    targets = unfolding_targets(model, inc, cl, depth=depth)
    seconds["unfolding forces"] = time.perf_counter() - t

    # --- simulation --------------------------------------------------------------------------------
    sim = simulate(model.vertices, model.springs, model.rest_length, model.mass, targets.vertex_ids,
                   targets.destinations, nm_params, progress=stage["simulation"], frame=targets.frame,
                   origin=targets.b, heights=targets.heights, flatten_stiffness=params.flattening_stiffness,
                   ramp_iterations=int(params.ramp_iterations), pulled_side=targets.side)
    warnings += sim.warnings
    seconds["simulation"] = sim.seconds

    # --- unfolded volume ---------------------------------------------------------------------------
    t = time.perf_counter()
    pixel = float(np.sqrt(ct.spacing[0] * ct.spacing[1]))
    out_sp = float(params.output_spacing_mm or pixel)
    grid = make_grid(sim.positions, targets.frame, np.full(3, out_sp), margin_mm=2.0)
    clear = lumen_c if (mask is not None and params.clear_lumen) else None
    unfolded, info_vol = build_unfolded_volume(crop, model.vertices, sim.positions, model.hexes, grid,
                                               background=-1024.0, clear_mask=clear,
                                               progress=stage["unfolded volume"])
    seconds["unfolded volume"] = time.perf_counter() - t
    if info_vol.get("outside_ct_voxels", 0) > 0:
        warnings.append(f"{info_vol['outside_ct_voxels']} voxels of the unfolded volume map outside the CT crop; "
                        "they show the background")

    t = time.perf_counter()
    stage["correspondence"](0.0)
    corr = Correspondence(model.vertices, sim.positions, model.hexes, view_axis=grid.axes[:, 2])
    seconds["correspondence"] = time.perf_counter() - t
    stage["correspondence"](1.0)

    report = {
        "software": {"name": "StomachUnfoldLib", "version": __version__},
        "parameters": asdict(params),
        "input": {"size_ijk": list(ct.size), "spacing_mm": ct.spacing.tolist(), "origin_lps": ct.origin.tolist(),
                  "direction": ct.direction.tolist(), "mask_given": mask is not None,
                  "crop_lo_ijk": [int(v) for v in lo], "crop_hi_ijk": [int(v) for v in hi],
                  "crop_voxels": int(np.prod(np.asarray(hi) - np.asarray(lo)))},
        "points": {"cardia_lps": cardia_lps.tolist(), "pylorus_lps": pylorus_lps.tolist(),
                   "cardia_ras": lps_to_ras(cardia_lps).tolist(), "pylorus_ras": lps_to_ras(pylorus_lps).tolist()},
        "air_region": {k: v for k, v in info_air.items() if k != "warnings"},
        "centerline": {"points": int(len(cl.points_lps)), "length_mm": float(cl.length_mm),
                       "radius_mm": {"min": float(np.min(cl.radius_mm)), "median": float(np.median(cl.radius_mm)),
                                     "max": float(np.max(cl.radius_mm))}},
        "incision": {"side": inc.side, "points": int(len(inc.points_lps)), "length_mm": inc.length_mm},
        "model": {**model.summary(), "grid_size_d": d, "cell_mm": cell_mm.tolist(), "wall_voxels": wall_voxels},
        "unfolding": {"plane_normal_lps": targets.n.tolist(), "plane_point_lps": targets.b.tolist(),
                      "base_line_direction_lps": targets.v1.tolist(), "pulled_vertices": int(len(targets.vertex_ids)),
                      "epsilon_mm": {"min": float(targets.epsilon.min()), "max": float(targets.epsilon.max())}},
        "simulation": {"iterations": int(sim.iterations), "converged": bool(sim.converged), "reason": sim.reason,
                       "time_step": sim.time_step, "retries": sim.retries, "D_final_mm": sim.d_trace[-1]},
        "iterations": int(sim.iterations),
        "D_trace": sim.d_trace,
        "unfolded_volume": {"size_ijk": list(unfolded.size), "spacing_mm": unfolded.spacing.tolist(),
                            "origin_lps": unfolded.origin.tolist(), "direction": unfolded.direction.tolist(),
                            **{k: v for k, v in info_vol.items() if np.isscalar(v)}},
        "seconds": seconds,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "warnings": warnings,
    }
    result = UnfoldResult(unfolded=unfolded, report=report, centerline_lps=np.asarray(cl.points_lps),
                          incision_lps=np.asarray(inc.points_lps), rest_vertices=model.vertices,
                          deformed_vertices=sim.positions, hexes=model.hexes, correspondence=corr,
                          lumen_crop=crop.with_array(lumen_c), inner_vertices=model.inner)
    if params.quality:
        from .quality import quality_metrics

        t = time.perf_counter()
        stage["quality"](0.0)
        report["quality"] = quality_metrics(result)
        seconds["quality"] = time.perf_counter() - t
        stage["quality"](1.0)
    seconds["total"] = time.perf_counter() - t_all
    return result


def parameter_names() -> list[str]:
    """Names of the UnfoldParameters fields (for command lines and GUIs)."""
    return [f.name for f in fields(UnfoldParameters)]
