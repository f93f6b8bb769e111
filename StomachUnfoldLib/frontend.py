"""The shared front end of every method: checked input, lumen, crop, centreline and incision line (and the wall region,
made when a method asks for it).

``prepare(ct, cardia_lps, pylorus_lps, params, mask)`` returns a :class:`Prepared`; every method
(``StomachUnfoldLib.methods``) starts from it. Coordinates are LPS mm throughout; messages name points in RAS.
"""
from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, PointError
from .geometry import Volume, lps_to_ras
from .params import AUTO_PIXEL_MAX_MM, UnfoldParameters
from .progress import Progress
from .volume_file import FileArray

__all__ = ["Prepared", "prepare", "check_volume", "check_points", "outside_message", "crop_margin_mm", "timed_stage",
           "available_memory_bytes", "estimate_memory_bytes", "check_incision_curve", "check_mask_region",
           "estimate_model_bytes", "check_model_memory", "MODEL_BYTES_PER_VERTEX", "SWAP_LIMIT_MM", "FRONT_STAGES",
           "return_freed_memory", "LEAN_MALLOC_BYTES"]

#: The cardia lies superior to the pylorus on supine CT; a "cardia" this far (mm) below the "pylorus" is a swap.
SWAP_LIMIT_MM = 20.0
#: The front end's stages and their share of the front end's progress.
FRONT_STAGES = [("air region", 0.0, 0.4), ("centerline", 0.4, 0.83), ("incision line", 0.83, 1.0)]


@dataclass
class Prepared:
    """What every method starts from: the CT crop (HU), lumen and wall masks on it, centreline and incision (LPS mm).

    The wall mask (``wall``) is made on first use: only the wall model's methods need it.
    """

    ct: Volume                      # the whole input CT (HU), never modified
    crop: Volume                    # the CT cropped to the stomach plus a margin (HU)
    lumen: np.ndarray               # bool (k, j, i) on the crop: the stomach lumen
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
    _wall: np.ndarray | None = field(default=None, repr=False)

    @property
    def wall(self) -> np.ndarray:
        """Bool (k, j, i) on the crop: the wall region, voxels within the wall thickness (mm) outside the lumen; made
        on first use (its seconds under "wall region")."""
        if self._wall is None:
            from .preprocessing import wall_region

            t = time.perf_counter()
            self._wall = wall_region(self.lumen, self.crop.spacing, self.params.wall_thickness_mm)
            self.seconds["wall region"] = time.perf_counter() - t
        return self._wall

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
        """The unfolded view's voxel size (mm, the same along i, j and the depth): ``output_spacing_mm`` when set,
        else the input CT's in-plane voxel size, at most ``params.AUTO_PIXEL_MAX_MM``."""
        if self.params.output_spacing_mm:
            return float(self.params.output_spacing_mm)
        in_plane = float(np.sqrt(self.ct.spacing[0] * self.ct.spacing[1]))
        return min(in_plane, AUTO_PIXEL_MAX_MM)

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


#: Blocks at least this large (bytes) are mapped and unmapped on their own under :func:`return_freed_memory`: the
#: crop-sized arrays, not the flat map's per-iteration temporaries (about 1 MB each on 25,000 triangles), which
#: would then be mapped, zero-filled and unmapped every iteration (128 KiB: the full-size CT 9.3-9.8 s against
#: 7.1-7.6 s at 4 MiB, random stomachs 1.3-1.6x as slow; the peak 390 MiB against 406-421 MiB)
LEAN_MALLOC_BYTES = 4 << 20


def return_freed_memory() -> bool:
    """On glibc, give freed blocks of LEAN_MALLOC_BYTES or more back to the system at once; True if set.

    glibc raises its mmap threshold after large frees (up to 32 MB), so later arrays come from the heap and a
    freed crop's pages stay resident; fixing the mmap and trim thresholds (``mallopt``) keeps the process's
    resident memory close to its live arrays (about 90 MB less at the peak of a full-size run). For processes
    the library owns (the command line, batch workers); Slicer's own process is left alone.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
    return bool(mallopt(M_MMAP_THRESHOLD, LEAN_MALLOC_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, LEAN_MALLOC_BYTES))


def estimate_memory_bytes(ct: Volume) -> int:
    """Rough peak extra memory (bytes) of a run on this CT: masks and labels over the whole grid, before cropping
    (a CT left on file, read box by box, needs only its packed air mask: an eighth of a byte per voxel)."""
    return int(ct.array.size * (0.125 if isinstance(ct.array, FileArray) else 6))


#: Rough working memory (bytes) per vertex of the hexahedral wall model: springs, the sparse system and its factor.
MODEL_BYTES_PER_VERTEX = 4096


def estimate_model_bytes(prep: "Prepared") -> int:
    """Rough peak memory (bytes) of the hexahedral wall model of ``prep``: about 3.4 vertices per cell of the wall."""
    steps = np.array(prep.cell_mm) / np.asarray(prep.ct.spacing, float)
    cells = float(np.count_nonzero(prep.wall)) / max(float(np.prod(np.maximum(np.rint(steps), 1))), 1.0)
    return int(3.4 * cells * MODEL_BYTES_PER_VERTEX)


def check_model_memory(prep: "Prepared") -> None:
    """InputError before the model is built when the wall model of this cell size cannot fit in the free memory."""
    need, avail = estimate_model_bytes(prep), available_memory_bytes()
    if need > 0.8 * avail:
        raise InputError(f"a wall model of {np.round(prep.cell_mm, 1).tolist()} mm cells needs about "
                         f"{need / 2**30:.1f} GiB and only {avail / 2**30:.1f} GiB is free; use larger cells "
                         "(--grid-mm or --grid-size) or crop the CT")


def check_volume(ct: Volume) -> list[str]:
    """Refuse volumes that cannot be a CT in HU (InputError saying why); return warnings for odd but usable ones."""
    if not isinstance(ct, Volume):
        raise InputError(f"the CT must be a geometry.Volume (HU, LPS), got {type(ct).__name__}")
    a = ct.array
    warnings = []
    if a.dtype.kind not in "iuf":
        raise InputError(f"the CT must hold numbers (HU), got dtype {a.dtype}")
    D = np.asarray(ct.direction, float)
    if not np.allclose(D.T @ D, np.eye(3), atol=1e-4):
        raise InputError("the volume's axes are sheared (its direction matrix is not orthonormal); resample it onto "
                         "an orthogonal grid first (Slicer: Resample Scalar/Vector/DWI Volume)")
    if not (np.all(np.isfinite(ct.spacing)) and np.all(np.asarray(ct.spacing) > 0)):
        raise InputError(f"the voxel spacing {np.asarray(ct.spacing).tolist()} mm is not positive; fix the header")
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
    lo, hi, bad = _value_range(a)
    if bad:
        raise InputError(f"{bad} voxels ({100.0 * bad / a.size:.2g} %) are NaN or infinite; give a CT with "
                         "finite HU values")
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


def _value_range(a) -> tuple[float, float, int]:
    """(lowest, highest finite value, count of NaN or infinite values) of an ndarray or a FileArray (one scan)."""
    if isinstance(a, FileArray):
        return a.value_range()
    bad = 0
    if a.dtype.kind == "f":
        finite = np.isfinite(a)
        bad = int(finite.size - np.count_nonzero(finite))
        if bad:
            return float(np.min(a[finite], initial=np.inf)), float(np.max(a[finite], initial=-np.inf)), bad
    return float(a.min()), float(a.max()), 0


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
    lumen, info = lumen_from_mask(mask, ct, cardia, pylorus, max_snap_mm=params.max_snap_mm,
                                  gas_hu=params.air_threshold_hu)
    check_mask_region(lumen, info["volume_ml"])
    return lumen, info


#: No stomach holds more (mL); a larger mask region is a body or whole-volume label.
MAX_STOMACH_ML = 5000.0


def check_mask_region(region: np.ndarray, volume_ml: float) -> None:
    """AnatomyError when the stomach mask's region reached from the points is no stomach: the whole volume (it
    touches all six sides of the volume) or over MAX_STOMACH_ML."""
    from .errors import AnatomyError

    faces = sum(bool(np.take(region, 0, axis=a).any()) + bool(np.take(region, -1, axis=a).any()) for a in range(3))
    if faces == 6 or volume_ml > MAX_STOMACH_ML:
        raise AnatomyError(f"the mask given with --mask is no stomach label: the part the points reach holds "
                           f"{volume_ml:.0f} mL{' and fills the volume to all six sides' if faces == 6 else ''}; "
                           "give the stomach's label (check --mask and --mask-label)")


def _check_centerline(cl, cell_mm) -> list[str]:
    """PointError when the points lie in one part of the stomach; the front end's warnings about the centreline."""
    if cl.length_mm < 1.5 * float(np.median(cl.radius_mm)):
        raise PointError(f"the cardia and pylorus are only {cl.length_mm:.0f} mm apart along the lumen, less than the "
                         f"stomach's width ({2 * np.median(cl.radius_mm):.0f} mm): both lie in the same part of the "
                         "stomach; place the cardia at the oesophageal end and the pylorus at the duodenal end")
    return []


def check_incision_curve(curve_lps, lumen: np.ndarray, crop: Volume, max_mm: float) -> None:
    """PointError when a user incision curve (LPS mm) has a point farther than ``max_mm`` from the lumen's surface."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    curve = np.asarray(curve_lps, float)
    if curve.ndim != 2 or curve.shape[1] != 3 or len(curve) < 2 or not np.all(np.isfinite(curve)):
        raise InputError(f"a user incision curve needs at least two finite 3D points (mm), got shape {curve.shape}")
    surface = lumen & ~ndimage.binary_erosion(lumen)
    d, _ = cKDTree(crop.voxel_lps(surface)).query(curve)
    worst = int(np.argmax(d))
    if d[worst] > max_mm:
        raise PointError(f"the incision curve's point {worst + 1} of {len(curve)} (RAS "
                         f"{np.round(lps_to_ras(curve[worst]), 1).tolist()} mm) lies {d[worst]:.0f} mm from the "
                         f"stomach wall (at most {max_mm:.0f} mm allowed): draw the curve on this CT's stomach wall")


class _AsGiven:
    """After the swap check exchanged the points, errors name each point as the user gave it (cardia <-> pylorus)."""

    def __init__(self, swapped: bool):
        self.swapped = swapped

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        from .errors import AnatomyError

        if not self.swapped or not isinstance(value, (PointError, AnatomyError)) or not value.args:
            return False
        text = re.sub(r"cardia|pylorus", lambda m: "pylorus" if m.group(0) == "cardia" else "cardia", str(value))
        raise type(value)(f"{text} (points named as given; the swap check had exchanged them, --swap-check false "
                          "keeps them as given)") from None


def prepare(ct: Volume, cardia_lps, pylorus_lps, params: UnfoldParameters | None = None,
            mask: np.ndarray | None = None, incision_curve_lps=None, progress=None) -> Prepared:
    """Run the shared front end on CT ``ct`` (HU) between cardia and pylorus (LPS mm); returns Prepared.

    ``mask``: optional bool stomach label on ct's grid replacing the air threshold; ``incision_curve_lps``: an
    optional user incision curve (LPS mm); ``progress``: a Progress or callable ``(stage, fraction)``.
    """
    from .centerline import compute_centerline
    from .incision_line import compute_incision_line, incision_from_curve
    from .preprocessing import bounding_box
    from .wall_model import grid_steps

    params = params or UnfoldParameters()
    params.validate()
    prog = progress if isinstance(progress, Progress) else Progress(progress)
    seconds: dict[str, float] = {}
    on_file = isinstance(getattr(ct, "array", None), FileArray)
    if on_file and mask is None:  # a CT on file: one pass for the value range and the air (unless made before)
        seconds["reading"] = ct.array.scan(params.air_threshold_hu)  # and the crop's read below
    warnings = check_volume(ct)
    cardia, pylorus, w = check_points(ct, cardia_lps, pylorus_lps, params.swap_check)
    warnings += w
    with _AsGiven(bool(w)), timed_stage(prog, "air region", seconds, *FRONT_STAGES[0][1:]) as report:
        lumen, info_air = _lumen(ct, cardia, pylorus, params, mask, report)
    warnings += list(info_air.get("warnings", []))
    cell_mm = np.array(grid_steps(ct.spacing, params.grid_voxels(ct.spacing))) * ct.spacing
    margin = crop_margin_mm(params, cell_mm)
    lo, hi = bounding_box(lumen, tuple(int(np.ceil(margin / s)) for s in ct.spacing))
    t_crop = time.perf_counter()
    crop = ct.crop(lo, hi)
    if on_file:  # the crop is read now
        seconds["reading"] = seconds.get("reading", 0.0) + time.perf_counter() - t_crop
    lumen_c = np.ascontiguousarray(lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]])
    del lumen
    if on_file:
        ct.array.release()
    if incision_curve_lps is not None:
        check_incision_curve(incision_curve_lps, lumen_c, crop, params.wall_thickness_mm + params.max_snap_mm)
    with _AsGiven(bool(w)), timed_stage(prog, "centerline", seconds, *FRONT_STAGES[1][1:]) as report:
        cl = compute_centerline(lumen_c, crop, cardia, pylorus, step_mm=params.centerline_step_mm,
                                max_snap_mm=params.max_snap_mm, progress=report)
    with _AsGiven(bool(w)):
        warnings += _check_centerline(cl, cell_mm)
    with timed_stage(prog, "incision line", seconds, *FRONT_STAGES[2][1:]):
        if incision_curve_lps is not None:
            inc = incision_from_curve(incision_curve_lps, cl)
        else:
            inc = compute_incision_line(lumen_c, crop, cl, side=params.incision)
    return Prepared(ct=ct, crop=crop, lumen=lumen_c, centerline=cl, incision=inc, cardia_lps=cardia,
                    pylorus_lps=pylorus, crop_lo_ijk=lo, crop_hi_ijk=hi, params=params, mask_given=mask is not None,
                    air_info={k: v for k, v in info_air.items() if k != "warnings"}, warnings=warnings,
                    fluid_voxels=int(info_air.get("fluid_voxels", 0)),
                    seconds=seconds)
