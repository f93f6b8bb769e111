"""The shared front end of every method: checked input, lumen, crop, wall region, centreline and incision line.

``prepare(ct, cardia_lps, pylorus_lps, params, mask)`` returns a :class:`Prepared`; every method
(``StomachUnfoldLib.methods``) starts from it. Coordinates are LPS mm throughout; messages name points in RAS.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, PointError
from .geometry import Volume, lps_to_ras
from .params import UnfoldParameters
from .progress import Progress

__all__ = ["Prepared", "prepare", "check_volume", "check_points", "outside_message", "crop_margin_mm", "timed_stage",
           "available_memory_bytes", "estimate_memory_bytes", "SWAP_LIMIT_MM", "FRONT_STAGES"]

#: The cardia lies superior to the pylorus on supine CT; a "cardia" this far (mm) below the "pylorus" is a swap.
SWAP_LIMIT_MM = 20.0
#: The front end's stages and their share of the front end's progress.
FRONT_STAGES = [("air region", 0.0, 0.33), ("wall region", 0.33, 0.5), ("centerline", 0.5, 0.83),
                ("incision line", 0.83, 1.0)]


@dataclass
class Prepared:
    """What every method starts from: the CT crop (HU), lumen and wall masks on it, centreline and incision (LPS mm)."""

    ct: Volume                      # the whole input CT (HU), never modified
    crop: Volume                    # the CT cropped to the stomach plus a margin (HU)
    lumen: np.ndarray               # bool (k, j, i) on the crop: the stomach lumen
    wall: np.ndarray                # bool (k, j, i) on the crop: the wall region around the lumen
    centerline: object              # centerline.Centerline (LPS mm), cardia first
    incision: object                # incision_line.Incision (LPS mm)
    cardia_lps: np.ndarray
    pylorus_lps: np.ndarray
    crop_lo_ijk: np.ndarray
    crop_hi_ijk: np.ndarray
    params: UnfoldParameters
    mask_given: bool = False
    fluid_voxels: int = 0           # lumen voxels of retained fluid under an air-fluid level (no gas there)
    air_info: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)

    @property
    def lumen_crop(self) -> Volume:
        """The lumen as a Volume on the crop's grid (geometry kept)."""
        return self.crop.with_array(self.lumen)

    @property
    def lumen_is_mask(self) -> bool:
        """True when the lumen is not all gas (a stomach mask, or fluid under a level): its inner wall is then the
        lumen mask's boundary, not the CT's air threshold, and the lumen's contents are shown as air."""
        return bool(self.mask_given or self.fluid_voxels > 0)

    @property
    def pixel_mm(self) -> float:
        """The input CT's in-plane voxel size (mm): the default spacing of the unfolded view."""
        return float(np.sqrt(self.ct.spacing[0] * self.ct.spacing[1]))

    @property
    def cell_mm(self) -> np.ndarray:
        """The wall model's cell size (mm along i, j, k of the CT) for these parameters."""
        from .wall_model import grid_steps

        return np.array(grid_steps(self.ct.spacing, self.params.grid_voxels(self.ct.spacing))) * self.ct.spacing

    def input_summary(self) -> dict:
        """The report's ``input`` section: the CT's geometry (LPS) and the crop (voxel indices)."""
        ct = self.ct
        lo, hi = self.crop_lo_ijk, self.crop_hi_ijk
        return {"size_ijk": list(ct.size), "spacing_mm": ct.spacing.tolist(), "origin_lps": ct.origin.tolist(),
                "direction": ct.direction.tolist(), "mask_given": self.mask_given,
                "crop_lo_ijk": [int(v) for v in lo], "crop_hi_ijk": [int(v) for v in hi],
                "crop_voxels": int(np.prod(np.asarray(hi) - np.asarray(lo)))}


class timed_stage:
    """Context manager: reports ``stage`` at 0 and 1 on ``progress``, adds its wall time (s) to ``seconds[stage]``.

    ``with timed_stage(progress, "centerline", seconds) as report: ...`` where ``report(fraction)`` reports within
    the stage (a callable for the library's ``progress=`` arguments).
    """

    def __init__(self, progress: Progress, stage: str, seconds: dict, lo: float = 0.0, hi: float = 1.0):
        self.stage, self.seconds = stage, seconds
        self.report = progress.sub(stage, lo, hi)

    def __enter__(self):
        self.t = time.perf_counter()
        self.report(0.0)
        return self.report

    def __exit__(self, kind, value, tb):
        self.seconds[self.stage] = self.seconds.get(self.stage, 0.0) + time.perf_counter() - self.t
        if kind is None:
            self.report(1.0)
        return False


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
    if not isinstance(ct, Volume):
        raise InputError(f"the CT must be a geometry.Volume (HU, LPS), got {type(ct).__name__}")
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


def outside_message(ct: Volume, name: str, p_lps) -> str:
    """The error for a point (LPS mm) outside the CT: the point and the volume's bounds in RAS mm (the frame the
    user gave), and whether the sign-flipped point (LPS values typed as RAS) would lie inside."""
    lo, hi = (np.asarray(b, float) for b in ct.bounds_lps())
    ras_lo = np.array([-hi[0], -hi[1], lo[2]])
    ras_hi = np.array([-lo[0], -lo[1], hi[2]])
    p = np.asarray(p_lps, float)

    def txt(v):
        return ", ".join(f"{x:.1f}" for x in v)
    msg = (f"the {name} point (RAS {txt(lps_to_ras(p))} mm) lies outside the volume (RAS bounds: R {ras_lo[0]:.1f} "
           f"to {ras_hi[0]:.1f}, A {ras_lo[1]:.1f} to {ras_hi[1]:.1f}, S {ras_lo[2]:.1f} to {ras_hi[2]:.1f} mm)")
    flipped = np.array([-p[0], -p[1], p[2]])
    if ct.contains_lps(flipped[None], margin=0.5)[0]:
        msg += (f"; with R and A sign-flipped (RAS {txt(lps_to_ras(flipped))}) it would lie inside: were LPS "
                "coordinates given as RAS? Slicer shows RAS")
    return msg + "; place it inside the stomach"


def check_points(ct: Volume, cardia_lps, pylorus_lps, swap_check: bool = True) -> tuple[np.ndarray, np.ndarray, list]:
    """Checked cardia and pylorus (LPS mm), exchanged if they were swapped; PointError saying why if unusable."""
    pts = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        p = np.asarray(p, float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PointError(f"the {name} point must be three finite numbers (mm), got {p}")
        if not ct.contains_lps(p[None], margin=0.5)[0]:
            raise PointError(outside_message(ct, name, p))
        pts.append(p)
    if np.linalg.norm(pts[0] - pts[1]) < 10.0:
        raise PointError(f"the cardia and pylorus are only {np.linalg.norm(pts[0] - pts[1]):.1f} mm apart; "
                         "place them at the two ends of the stomach")
    warnings = []
    cardia, pylorus = pts
    if swap_check and pylorus[2] > cardia[2] + SWAP_LIMIT_MM:
        cardia, pylorus = pylorus, cardia
        warnings.append(f"the cardia point lay {SWAP_LIMIT_MM:g} mm or more below the pylorus point: the two points "
                        "were probably swapped and have been exchanged (set swap_check=False to keep them as given)")
    return cardia, pylorus, warnings


def crop_margin_mm(params: UnfoldParameters, cell_mm: np.ndarray) -> float:
    """Margin (mm) kept around the lumen's bounding box: the wall, two cells, 4 mm and the user's extra margin."""
    return params.wall_thickness_mm + 2.0 * float(np.max(cell_mm)) + 4.0 + float(params.crop_margin_mm)


def _lumen(ct, cardia, pylorus, params, mask, report):
    from .preprocessing import air_region, lumen_from_mask

    if mask is None:
        return air_region(ct, cardia, pylorus, threshold_hu=params.air_threshold_hu,
                          max_snap_mm=params.max_snap_mm, progress=report, fluid_max_hu=params.fluid_max_hu)
    mask = np.asarray(mask, bool)
    if mask.shape != ct.array.shape:
        raise InputError(f"the stomach mask has shape {mask.shape}, the CT {ct.array.shape}: resample the "
                         "mask onto the CT grid (io.read_label_volume does)")
    return lumen_from_mask(mask, ct, cardia, pylorus, max_snap_mm=params.max_snap_mm)


def _check_centerline(cl, cell_mm) -> list[str]:
    """PointError when the points lie in one part of the stomach; the front end's warnings about the centreline."""
    if cl.length_mm < 1.5 * float(np.median(cl.radius_mm)):
        raise PointError(f"the cardia and pylorus are only {cl.length_mm:.0f} mm apart along the lumen, less than the "
                         f"stomach's width ({2 * np.median(cl.radius_mm):.0f} mm): both lie in the same part of the "
                         "stomach; place the cardia at the oesophageal end and the pylorus at the duodenal end")
    return []


def prepare(ct: Volume, cardia_lps, pylorus_lps, params: UnfoldParameters | None = None,
            mask: np.ndarray | None = None, incision_curve_lps=None, progress=None) -> Prepared:
    """Run the shared front end on CT ``ct`` (HU) between cardia and pylorus (LPS mm); returns Prepared.

    ``mask``: optional bool stomach label on ct's grid replacing the air threshold; ``incision_curve_lps``: an
    optional user incision curve (LPS mm); ``progress``: a Progress or callable ``(stage, fraction)``.
    """
    from .centerline import compute_centerline
    from .incision_line import compute_incision_line, incision_from_curve
    from .preprocessing import bounding_box, wall_region
    from .wall_model import grid_steps

    params = params or UnfoldParameters()
    params.validate()
    prog = progress if isinstance(progress, Progress) else Progress(progress)
    seconds: dict[str, float] = {}
    warnings = check_volume(ct)
    cardia, pylorus, w = check_points(ct, cardia_lps, pylorus_lps, params.swap_check)
    warnings += w
    with timed_stage(prog, "air region", seconds, *FRONT_STAGES[0][1:]) as report:
        lumen, info_air = _lumen(ct, cardia, pylorus, params, mask, report)
    warnings += list(info_air.get("warnings", []))
    cell_mm = np.array(grid_steps(ct.spacing, params.grid_voxels(ct.spacing))) * ct.spacing
    margin = crop_margin_mm(params, cell_mm)
    lo, hi = bounding_box(lumen, tuple(int(np.ceil(margin / s)) for s in ct.spacing))
    crop = ct.crop(lo, hi)
    lumen_c = np.ascontiguousarray(lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]])
    del lumen
    with timed_stage(prog, "wall region", seconds, *FRONT_STAGES[1][1:]):
        wall = wall_region(lumen_c, crop.spacing, params.wall_thickness_mm)
    with timed_stage(prog, "centerline", seconds, *FRONT_STAGES[2][1:]) as report:
        cl = compute_centerline(lumen_c, crop, cardia, pylorus, step_mm=params.centerline_step_mm,
                                max_snap_mm=params.max_snap_mm, progress=report)
    warnings += _check_centerline(cl, cell_mm)
    with timed_stage(prog, "incision line", seconds, *FRONT_STAGES[3][1:]):
        if incision_curve_lps is not None:
            inc = incision_from_curve(incision_curve_lps, cl)
        else:
            inc = compute_incision_line(lumen_c, crop, cl, side=params.incision)
    return Prepared(ct=ct, crop=crop, lumen=lumen_c, wall=wall, centerline=cl, incision=inc, cardia_lps=cardia,
                    pylorus_lps=pylorus, crop_lo_ijk=lo, crop_hi_ijk=hi, params=params, mask_given=mask is not None,
                    air_info={k: v for k, v in info_air.items() if k != "warnings"}, warnings=warnings,
                    fluid_voxels=int(info_air.get("fluid_voxels", 0)),
                    seconds=seconds)
