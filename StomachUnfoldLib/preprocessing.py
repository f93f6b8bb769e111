"""Preprocessing (Oda et al., Sec. 2.1): the stomach air region and the stomach wall region.

The air region is the set of voxels below an HU threshold 6-connected to the air next to the cardia and
pylorus points; air outside the body (connected to the side faces of the volume) and air not reached from
the points (lungs, colon) is left out. Retained fluid lying under a flat horizontal air-fluid level on the
dependent (posterior, LPS +y) wall joins the lumen (:func:`fluid_below_level`). With a stomach label (``--mask``) the label replaces the threshold.
The wall region is the shell of tissue within a given thickness (mm) outside the lumen.

All points are LPS mm; masks are bool arrays indexed ``[k, j, i]`` on the CT grid.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import AnatomyError, InputError, PointError
from .geometry import Volume, lps_to_ras
from .volume_file import FileArray, PackedMask

__all__ = ["distance_mm", "snap_to_region", "air_region", "fluid_below_level", "water_beside", "lumen_from_mask",
           "wall_region", "bounding_box",
           "lumen_edge", "BelowThreshold", "MAX_STOMACH_ML"]

#: Air regions larger than this (mL) are not a stomach (lungs, bowel, outside air).
MAX_STOMACH_ML = 4000.0


# ---------------------------------------------------------------------------------------------- helpers
def distance_mm(mask: np.ndarray, spacing) -> np.ndarray:
    """Euclidean distance (mm, float32) from each True voxel to the nearest False voxel centre; 0 on False voxels.

    The same numbers as ``scipy.ndimage.distance_transform_edt(mask, sampling=spacing[::-1])`` (``spacing``
    in i, j, k order, mm), computed with SimpleITK's multi-threaded Maurer transform (3-4x faster here).
    """
    import SimpleITK as sitk

    mask = np.asarray(mask, bool)
    spacing = np.asarray(spacing, float).reshape(3)
    if mask.all() or not mask.any():  # no False voxel (or no True one): leave it to scipy's conventions
        return ndimage.distance_transform_edt(mask, sampling=spacing[::-1]).astype(np.float32)
    img = sitk.GetImageFromArray((~mask).view(np.uint8))
    img.SetSpacing(tuple(float(v) for v in spacing))
    d = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(img, insideIsPositive=True, squaredDistance=False,
                                                                useImageSpacing=True))
    return np.where(mask, -d, 0.0).astype(np.float32)


def bounding_box(mask: np.ndarray, margin_vox=(0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """Index box ``(lo, hi)`` in (i, j, k) voxels, hi exclusive, of the True voxels of ``mask[k, j, i]``.

    Parameters
    ----------
    mask : (K, J, I) bool array
    margin_vox : int or 3 ints
        Margin in voxels along i, j, k added on each side; the box is clipped to the grid.

    Returns
    -------
    lo, hi : (3,) int arrays
        Ready for :meth:`Volume.crop` (``mask[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]`` is the crop).

    Raises
    ------
    AnatomyError
        If the mask is empty.
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise AnatomyError("the stomach region is empty: no voxel is set; check the points, threshold or mask")
    lo, hi = [], []
    for ax in range(3):
        other = tuple(a for a in range(3) if a != ax)
        idx = np.flatnonzero(mask.any(axis=other))
        lo.append(int(idx[0]))
        hi.append(int(idx[-1]) + 1)
    margin = np.broadcast_to(np.asarray(margin_vox, int), (3,))
    size = np.array(mask.shape[::-1])
    lo_ijk = np.clip(np.array(lo[::-1]) - margin, 0, size)
    hi_ijk = np.clip(np.array(hi[::-1]) + margin, 0, size)
    return lo_ijk, hi_ijk


def ras_text(p_lps) -> str:
    """Point as RAS text (mm, 1 decimal) for messages shown to Slicer/command-line users."""
    return str(np.round(lps_to_ras(np.asarray(p_lps, float).reshape(3)), 1).tolist())


def _nearest_in_box(mask: np.ndarray, volume: Volume, p: np.ndarray, radius_mm: float):
    """Nearest True voxel of ``mask`` to LPS point ``p`` within an index box covering radius_mm; (lps, dist) or None."""
    ijk = volume.lps_to_index(p[None])[0]
    # the box must hold the ball of radius_mm for any (orthonormal, maybe flipped) direction
    r = np.ceil(radius_mm / volume.spacing).astype(int) + 1
    size = np.array(volume.size)
    lo = np.clip(np.floor(ijk).astype(int) - r, 0, size)
    hi = np.clip(np.ceil(ijk).astype(int) + r + 1, 0, size)
    if np.any(hi <= lo):
        return None
    sub = mask[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    kk, jj, ii = np.nonzero(sub)
    if len(ii) == 0:
        return None
    cand = np.stack([ii + lo[0], jj + lo[1], kk + lo[2]], axis=1).astype(float)
    pts = volume.index_to_lps(cand)
    d = np.linalg.norm(pts - p, axis=1)
    best = int(np.argmin(d))
    return pts[best], float(d[best])


def nearest_true(mask: np.ndarray, volume: Volume, p: np.ndarray, max_distance_mm: float):
    """Nearest True voxel centre (LPS mm) within max_distance_mm, else None; the point may lie off the grid.

    The voxel containing the point is tried first (its centre is the nearest voxel centre), then boxes
    of growing size, so a point in or next to the region costs almost nothing.
    """
    i, j, k = np.rint(volume.lps_to_index(p[None])[0]).astype(int)
    size = volume.size
    if 0 <= i < size[0] and 0 <= j < size[1] and 0 <= k < size[2] and mask[k, j, i]:
        q = volume.index_to_lps(np.array([[i, j, k]], float))[0]
        if np.linalg.norm(q - p) <= max_distance_mm:
            return q
    r = min(4.0 * float(volume.spacing.max()), max_distance_mm)
    while True:
        hit = _nearest_in_box(mask, volume, p, r)
        # the box holds every voxel within r mm, so a hit closer than r is the nearest one
        if hit is not None and hit[1] <= r:
            return hit[0] if hit[1] <= max_distance_mm else None
        if r >= max_distance_mm:
            return None
        r = min(3.0 * r, max_distance_mm)


def _nearest_distance_text(mask: np.ndarray, volume: Volume, p: np.ndarray, start_mm: float) -> str:
    """How far (mm) the nearest True voxel is, searched in growing boxes; text for error messages."""
    extent = float(np.max(np.array(volume.size) * volume.spacing))
    r = max(start_mm, 1.0) * 3.0
    while True:
        hit = _nearest_in_box(mask, volume, p, r)
        if hit is not None and hit[1] <= r:
            return f"the nearest is {hit[1]:.1f} mm away"
        if r > 2.0 * extent:
            return "there is none in the volume"
        r *= 3.0


def _voxel(volume: Volume, p_lps: np.ndarray) -> tuple[int, int, int]:
    """Array index (k, j, i) of the voxel whose centre is nearest to LPS point p (mm)."""
    i, j, k = np.rint(volume.lps_to_index(np.asarray(p_lps, float)[None])[0]).astype(int)
    return int(k), int(j), int(i)


def _check_inside(volume: Volume, p: np.ndarray, name: str) -> None:
    """Raise PointError naming the point and the volume bounds (LPS mm) if p lies outside the grid."""
    if not volume.contains_lps(p[None])[0]:
        lo, hi = volume.bounds_lps()
        raise PointError(f"the {name} point (LPS {np.round(p, 1).tolist()} mm, RAS {ras_text(p)} mm) lies "
                         f"outside the volume, whose LPS bounds are {np.round(lo, 1).tolist()} to "
                         f"{np.round(hi, 1).tolist()} mm; place the point inside the CT")


# ---------------------------------------------------------------------------------------------- snapping
def lumen_edge(lumen: np.ndarray) -> np.ndarray:
    """Lumen voxels (bool (k, j, i)) with a face neighbour outside the lumen: its boundary, the mucosa's voxels. The
    array's own border does not count as outside (a lumen cut by the crop or the scan has no wall there)."""
    lum = np.asarray(lumen, bool)
    inner = lum.copy()          # a binary erosion by the 6-neighbour cross, the border counted as lumen: by slices
    for a in range(lum.ndim):
        lo, hi = [slice(None)] * lum.ndim, [slice(None)] * lum.ndim
        lo[a], hi[a] = slice(None, -1), slice(1, None)
        inner[tuple(lo)] &= lum[tuple(hi)]
        inner[tuple(hi)] &= lum[tuple(lo)]
    return lum & ~inner


def snap_to_region(mask: np.ndarray, volume: Volume, point_lps, max_distance_mm: float = 20.0,
                   name: str = "point") -> np.ndarray:
    """LPS centre (mm) of the True voxel of ``mask`` nearest to ``point_lps`` (LPS mm), within max_distance_mm.

    Only a box around the point is searched, so this is cheap on a full CT. Anisotropic spacing and any
    direction matrix are handled (distances are Euclidean in mm).

    Parameters
    ----------
    mask : (K, J, I) bool array on ``volume``'s grid
    volume : Volume
        Gives the geometry of ``mask``.
    point_lps : (3,) array-like
        The point, LPS mm. It may lie in the region or near it (e.g. on the wall around the lumen).
    max_distance_mm : float
        Largest distance (mm) to search.
    name : str
        Name of the point used in error messages ("cardia", "pylorus").

    Returns
    -------
    (3,) float array
        LPS position (mm) of the nearest True voxel centre.

    Raises
    ------
    PointError
        If the point lies outside the volume, or no True voxel lies within ``max_distance_mm``.
    """
    p = np.asarray(point_lps, float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise PointError(f"the {name} point has non-finite coordinates {p.tolist()}; give it in mm")
    _check_inside(volume, p, name)
    hit = nearest_true(mask, volume, p, max_distance_mm)
    if hit is None:
        raise PointError(f"no region voxel lies within {max_distance_mm:g} mm of the {name} point (RAS "
                         f"{ras_text(p)} mm); {_nearest_distance_text(mask, volume, p, max_distance_mm)}; "
                         "move the point into the stomach lumen")
    return hit


# ---------------------------------------------------------------------------------------------- air region
def _side_axes(volume: Volume) -> list[int]:
    """Array axes (0=k, 1=j, 2=i) whose faces are the body's sides: all but the one closest to superior-inferior."""
    si_ijk = int(np.argmax(np.abs(volume.direction[2, :])))  # grid axis with the largest S component
    si_arr = 2 - si_ijk
    return [a for a in range(3) if a != si_arr]


def _air_problem(comp: np.ndarray, sides, voxel_ml: float) -> str:
    """Why an air component cannot be a stomach ('' if it can): touching the body's sides, or too large (mL)."""
    if _touches_faces(comp, sides):
        return "is connected to the side of the volume"
    vol_ml = float(np.count_nonzero(comp)) * voxel_ml
    if vol_ml > MAX_STOMACH_ML:
        return f"is {vol_ml:.0f} mL: too large for a stomach (> {MAX_STOMACH_ML:.0f} mL)"
    return ""


def _cut_leaks(comp: np.ndarray, ct: Volume, seeds_kji, sides, voxel_ml: float,
               necks_mm=(3.0, 5.0, 7.0, 10.0)):
    """Cut gas that leaks from the stomach into bowel through a narrow neck; (mask, neck radius mm) or (None, None).

    For each neck radius r: the core of the air (voxels at least r mm from its edge) is split into
    components, the ones nearest the seeds are kept and grown back by r mm inside the air (a morphological
    opening by reconstruction), so channels narrower than 2 r are cut. The first r whose result is a
    plausible stomach (not touching the sides, not too large) wins.
    """
    lo, hi = bounding_box(comp)
    sl = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    sub = comp[sl]
    sampling = ct.spacing[::-1]
    dist = distance_mm(sub, ct.spacing)
    seeds = np.array([[k - lo[2], j - lo[1], i - lo[0]] for k, j, i in seeds_kji], float)
    for r in necks_mm:
        core = dist >= r
        if not core.any():
            break
        lab, _ = ndimage.label(core)
        cidx = np.argwhere(core)
        keep = set()
        for sd in seeds:
            near = cidx[np.argmin(np.linalg.norm((cidx - sd) * sampling, axis=1))]
            keep.add(int(lab[tuple(near)]))
        kept = np.isin(lab, list(keep))
        grown = sub & (distance_mm(~kept, ct.spacing) <= r + float(max(sampling)))
        out = np.zeros_like(comp)
        out[sl] = grown
        if not _air_problem(out, sides, voxel_ml):
            return out, r
    return None, None


def _touches_faces(mask: np.ndarray, axes) -> bool:
    """True if ``mask`` has a True voxel on either face of one of the given array axes."""
    for a in axes:
        if np.take(mask, 0, axis=a).any() or np.take(mask, mask.shape[a] - 1, axis=a).any():
            return True
    return False


class BelowThreshold:
    """The CT's air, ``array < threshold``, computed only for the part indexed (``view[box]`` is a bool array).

    Whole-CT masks cost half the CT's own memory each (int16 -> bool); the air region needs the air near the
    points and in the stomach's box alone, so it indexes this view instead of thresholding the whole grid.
    """

    def __init__(self, array: np.ndarray, threshold: float):
        self.array, self.threshold = array, threshold
        self.shape, self.ndim = array.shape, array.ndim

    def __getitem__(self, index) -> np.ndarray:
        """``array[index] < threshold`` as a bool array (or a bool for one voxel)."""
        return np.asarray(self.array[index] < self.threshold)


def flood_fill(image: np.ndarray, seed) -> np.ndarray:
    """Bool mask of the voxels 6-connected to ``seed`` (k, j, i) holding its value (skimage's flood, connectivity=1).

    SimpleITK's ConnectedThreshold runs on a box only: first the box of the seed's component on a 4x
    subsample (plus a margin), grown on each side the region touches until it touches no inner face, so the
    result is exact whatever the guess (a full-size CT costs a whole-image flood 2-3x more).
    """
    import SimpleITK as sitk

    if not isinstance(image, (BelowThreshold, PackedMask)):  # lazy masks are indexed as they are
        image = np.asarray(image, bool)
    s = tuple(int(x) for x in seed)
    if image.ndim != 3 or len(s) != 3 or any(not 0 <= x < n for x, n in zip(s, image.shape)):
        raise InputError(f"flood seed {list(s)} lies outside the 3-D array of shape {image.shape}")
    value = bool(image[s])
    shape, sv, b = np.array(image.shape), np.array(s), 4
    lab, _ = ndimage.label(image[::b, ::b, ::b] == value)
    cs = tuple(sv // b)
    if lab[cs]:
        box = ndimage.find_objects(lab, max_label=int(lab[cs]))[int(lab[cs]) - 1]
        lo = np.minimum(np.maximum(np.array([x.start for x in box]) * b - b, 0), sv)
        hi = np.maximum(np.minimum(np.array([x.stop for x in box]) * b + b, shape), sv + 1)
    else:
        lo, hi = np.maximum(sv - 16, 0), np.minimum(sv + 17, shape)
    while True:
        sub = np.ascontiguousarray(image[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]).view(np.uint8)
        out = sitk.ConnectedThreshold(sitk.GetImageFromArray(sub), seedList=[tuple(int(x) for x in (sv - lo)[::-1])],
                                      lower=int(value), upper=int(value), replaceValue=1,
                                      connectivity=sitk.ConnectedThresholdImageFilter.FaceConnectivity)
        reg = sitk.GetArrayFromImage(out).view(bool)
        grown = False
        for a in range(3):
            n = int(hi[a] - lo[a])
            if lo[a] > 0 and np.take(reg, 0, axis=a).any():
                lo[a], grown = max(0, lo[a] - n), True
            if hi[a] < shape[a] and np.take(reg, n - 1, axis=a).any():
                hi[a], grown = min(int(shape[a]), hi[a] + n), True
        if not grown:
            break
    if np.array_equal(lo, 0) and np.array_equal(hi, shape):
        return reg
    full = np.zeros(image.shape, bool)
    full[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = reg
    return full


# ---------------------------------------------------------------------------------------------- retained fluid
#: Lower end (HU, after the light smoothing) of retained water under an air-fluid level; fat is about -90 HU.
FLUID_MIN_HU = -20.0
#: Fraction of the level's rays with two or more water voxels behind its partial-volume voxels above which the water is
#: kept: an air boundary lying flat on tissue has about none (its rays stop at once above 25 HU or below -20 HU), a
#: pool in the bowl of the posterior wall has water under its deep middle, less under its shallow rim. At one half
#: the shallow pool of tuning seed 393 (0.44: water up to 12 mm deep) was refused whole, and the view showed the
#: water's surface as mucosa; over the 66 tuning volumes with fluid the others have 0.54-0.98
FLUID_MIN_WATER_FRACTION = 0.25


def _posterior_axis(volume: Volume) -> tuple[int, int]:
    """(array axis 0=k 1=j 2=i, index step +1 or -1) of the grid axis closest to LPS +y, stepping posteriorly."""
    a_ijk = int(np.argmax(np.abs(volume.direction[1, :])))
    return 2 - a_ijk, (1 if volume.direction[1, a_ijk] > 0 else -1)


def _level_patch(air: np.ndarray, ct: Volume, min_level_mm2: float):
    """The flat bottom of the air (a horizontal air-fluid level, LPS y = const): (N, 3) k, j, i of its voxels, or None.

    The air's posterior-most voxel of each column along the grid axis closest to +y is binned by its LPS y (mm, bins of one voxel step); a level is two adjacent bins holding
    at least ``min_level_mm2`` (mm^2) and three times the boundary area of the two bins on either side (a
    curved bottom spreads over many bins).
    """
    ax, st = _posterior_axis(ct)
    a_ijk = 2 - ax
    w = float(abs(ct.direction[1, a_ijk]) * ct.spacing[a_ijk])  # mm of y per posterior step
    face_mm2 = float(np.prod(ct.spacing)) / w
    has = air.any(axis=ax)
    last = air.shape[ax] - 1 - np.argmax(np.flip(air, ax), axis=ax) if st > 0 else np.argmax(air, axis=ax)
    cols = np.argwhere(has)
    if len(cols) == 0:
        return None
    kji = np.insert(cols, ax, last[has], axis=1)
    yb = (kji[:, ::-1] * ct.spacing) @ ct.direction[1, :]
    rows = np.round((yb - yb.min()) / w).astype(np.int64)
    hist = np.bincount(rows, minlength=int(rows.max()) + 4).astype(float) * face_mm2
    win = hist[:-1] + hist[1:]
    p = int(np.argmax(win))
    around = max(win[p - 2] if p >= 2 else 0.0, win[p + 2] if p + 2 < len(win) else 0.0)
    if win[p] < min_level_mm2 or win[p] < 3.0 * around:
        return None
    return kji[(rows == p) | (rows == p + 1)]


def _level_median(values: np.ndarray, rel2: np.ndarray, grid: tuple, mode: str) -> np.ndarray:
    """The 5 x 5 median of a per-ray value over the level's rays (``rel2``: their cells on a 2D ``grid``; cells
    with no ray hold 0; ``mode``: scipy.ndimage's edge mode), one value per ray."""
    vmap = np.zeros(grid, values.dtype)
    vmap[rel2[:, 0], rel2[:, 1]] = values
    return ndimage.median_filter(vmap, size=5, mode=mode)[rel2[:, 0], rel2[:, 1]]


def _falling_floor(depth: np.ndarray, prof: np.ndarray, n_partial: int, rel2: np.ndarray, grid: tuple) -> np.ndarray:
    """1 where a ray's water (``depth`` voxels of its HU profile ``prof``) ends in a fall to fat: drop its last voxel.

    Water never borders fat in a stomach: the wall (2 mm or more) lies between. A wall too thin to be resolved
    between water and fat is blurred away (its voxels average to water), so the ray runs on to the fat (below
    ``FLUID_MIN_HU``) and takes the wall in: its last voxel is that wall, not water. The flag is the majority of the
    5 x 5 window round each ray (:func:`_level_median`; a cell with no ray counts as not falling), so one noisy ray
    leaves no pit in the floor. Rays ending on a rise above the water range (a resolved wall) or in the air-water
    partial zone (``n_partial`` voxels) are 0. (Two voxels on grids finer than 1.3 mm hid a bead under the fluid on
    a tuning stomach.)
    """
    rows = np.arange(len(depth))
    after = prof[rows, np.minimum(depth, prof.shape[1] - 1)]
    fall = ((depth > n_partial) & (depth < prof.shape[1]) & (after < FLUID_MIN_HU)).astype(np.uint8)
    major = _level_median(fall, rel2, grid, "nearest").astype(bool)
    return (major & (depth > n_partial)).astype(depth.dtype)


#: How far back (voxels) from a ray's end the wall's peak is looked for (:func:`thin_wall_edge`), and the least rise
#: (HU) above the water that counts as a wall there
WALL_BACK_VOX = 6
WALL_MIN_RISE_HU = 8.0
#: Smoothed HU above which an object in the water is dense (oral contrast, a calcification, a clip, the phantoms'
#: marker beads; no wall or soft tissue reaches it), and how far (voxels) round it the tail of its blur is looked for
#: (:func:`dense_object_edges`)
DENSE_HU = 200.0
DENSE_REACH_VOX = 3
#: How each ray's water ends (:func:`fluid_below_level`). ``"threshold"``: at its first voxel above the water range
#: (a noise voxel stops it: with 15-40 HU of noise on water at 5-15 HU, 13 % of the water of the drawn stomachs in CT
#: 03's 4.25 mm slices was left out, up to 38 %, most where it is deep; 23 % on CT 01's 3 mm grid, 1.3 % on 1-2.5 mm).
#: ``"evidence"`` (rule 39, ``docs/RULE39_water_by_evidence.md``): where the evidence for water summed along the ray is
#: largest (:func:`water_runs`), and a one-voxel gap of the water across the rays is closed (:func:`close_water_gaps`).
#: ``"thick"`` (rule 40, ``docs/RULE40_water_by_evidence_on_thick_slices.md``): ``"evidence"`` on a CT whose largest
#: spacing exceeds THICK_SLICE_MM (the smoothing, at most 1.5 mm, then weighs the next slice under 13.5 % and averages
#: almost no noise away across slices), ``"threshold"`` on finer grids (where ``"evidence"`` took in about as much
#: wall as the water it added).
WATER_RUNS = "threshold"
THICK_SLICE_MM = 3.0
#: :func:`water_runs`: how far (HU x voxels) the summed evidence must fall below its best for the ray to end there,
#: and each voxel's evidence clipped to +- this (HU)
WATER_RUN_DROP = 20.0
WATER_EVIDENCE_CLIP_HU = 40.0
#: A rise above the water range followed within WALL_FALL_VOX voxels by a fall below WALL_FALL_HU is a thin wall with
#: fat behind it (water never borders fat): the ray ends there, however much water-like fat follows
WALL_FALL_HU = 0.0
WALL_FALL_VOX = 3
#: :func:`close_water_gaps`: a gap voxel joins the water only up to this many HU above the water range (a wall is
#: about 40 HU)
WATER_GAP_MARGIN_HU = 10.0


def _by_evidence(ct: Volume) -> bool:
    """Whether the water of ``ct`` ends by its summed evidence (WATER_RUNS, THICK_SLICE_MM)."""
    return WATER_RUNS == "evidence" or (WATER_RUNS == "thick" and float(np.max(ct.spacing)) > THICK_SLICE_MM)


def _this_and_next(mask: np.ndarray) -> np.ndarray:
    """Where a ray's voxel and the next one along it (the end of the ray counts as one) are both set in ``mask``."""
    return mask & np.concatenate([mask[:, 1:], np.ones((len(mask), 1), bool)], 1)


def _first_runs(ok: np.ndarray, prof: np.ndarray, inside: np.ndarray, n_partial: int, max_hu: float,
                evidence: bool) -> np.ndarray:
    """Voxels of water behind each level voxel: up to the first voxel above ``max_hu``, two in a row not ``ok`` or
    the end of the ray; with ``evidence``, :func:`water_runs`."""
    if evidence:
        return water_runs(prof, inside, n_partial, max_hu)
    stop = _this_and_next(~ok) | (prof > max_hu) | ~inside
    stop[:, -1] = True
    return np.argmax(stop, axis=1)


def water_runs(prof: np.ndarray, inside: np.ndarray, n_partial: int, max_hu: float) -> np.ndarray:
    """Voxels of water behind each level voxel: the prefix of its HU profile with the most evidence for water.

    Each voxel past the ``n_partial`` air-water voxels gives ``max_hu - HU`` (clipped to +-WATER_EVIDENCE_CLIP_HU):
    water at 10 HU gives about +15 per voxel, a wall at 40 HU -15, so a noise voxel above the range costs a little and
    the next water voxels win it back, while a wall two voxels deep ends the ray at its inner edge (the half-way point
    of a blurred step, as the threshold finds it without noise). The sum is followed until it has fallen
    WATER_RUN_DROP below its best, or to a hard stop: two voxels in a row below ``FLUID_MIN_HU`` (fat, air), a rise
    above the range then a fall below WALL_FALL_HU within WALL_FALL_VOX voxels (a thin wall with fat behind), a rise
    within the air-water voxels (tissue right under the level), or the end of the ray; the run is the best prefix.
    """
    n, m = prof.shape
    col = np.arange(m)[None, :]
    low = inside & (prof < FLUID_MIN_HU)
    low[:, :n_partial] = False
    hard = _this_and_next(low) | ~inside
    hard[:, :n_partial] |= prof[:, :n_partial] > max_hu
    fall = inside & (prof < WALL_FALL_HU)
    after = np.zeros_like(fall)
    for d in range(1, WALL_FALL_VOX + 1):
        after[:, :-d] |= fall[:, d:]
    wall = (prof > max_hu) & after
    wall[:, :n_partial] = False
    hard |= wall
    hard[:, -1] = True
    h_end = np.argmax(hard, axis=1)
    c = np.clip(max_hu - prof, -WATER_EVIDENCE_CLIP_HU, WATER_EVIDENCE_CLIP_HU)
    c[:, :n_partial] = 0.0
    c = np.where(col < h_end[:, None], c, -1e6)
    total = np.cumsum(c, axis=1)
    best = np.maximum.accumulate(np.maximum(total, 0.0), axis=1)
    end = np.argmax(((best - total) > WATER_RUN_DROP) | (col >= h_end[:, None]), axis=1)
    run = np.argmax(np.concatenate([np.zeros((n, 1)), np.where(col <= end[:, None], total, -np.inf)], 1), axis=1)
    return np.maximum(run, np.minimum(n_partial, h_end))


def close_water_gaps(fluid: np.ndarray, air: np.ndarray, sm: np.ndarray, ax: int, beyond: np.ndarray,
                      max_hu: float) -> np.ndarray:
    """The water (bool, on the rays' box) with its one-voxel gaps across the rays closed.

    A ray whose level voxel is missing (the air's ragged edge on a noisy slice) or that stopped early leaves a slice
    of "wall" through the water, whose faces the judge and the surface take as mucosa. A voxel beyond the level
    (``beyond``, broadcast along ``ax``) with lumen on both sides along an axis across the rays joins the water when
    its smoothed HU ``sm`` is in [FLUID_MIN_HU, max_hu + WATER_GAP_MARGIN_HU].
    """
    lum = fluid | air
    gap = np.zeros_like(lum)
    for a in range(3):
        if a == ax:
            continue
        lo, mid, hi = [slice(None)] * 3, [slice(None)] * 3, [slice(None)] * 3
        lo[a], mid[a], hi[a] = slice(0, -2), slice(1, -1), slice(2, None)
        gap[tuple(mid)] |= lum[tuple(lo)] & lum[tuple(hi)]
    gap &= ~lum & beyond & (sm >= FLUID_MIN_HU) & (sm <= max_hu + WATER_GAP_MARGIN_HU)
    return fluid | gap


def thin_wall_edge(prof: np.ndarray, run: np.ndarray, n_partial: int, max_hu: float) -> np.ndarray:
    """Each ray's water (voxels of its HU profile ``prof`` behind the level) ending before a thin wall it ran through.

    A ray stops where its profile leaves the water range (``run`` voxels of water). A ray that stopped on a rise
    above ``max_hu`` met a resolved wall and keeps its end (on a wall it crosses obliquely the wall's peak lies
    beyond the window below, and half-way to it would end the ray early). A wall too thin to be resolved is blurred
    to 15-25 HU between the water and the fat, so the ray ran on through it: its water now ends where the profile
    has risen half-way from the water's HU (the median of the rays' middles) to the largest value from
    WALL_BACK_VOX voxels before its end to two after it, that wall's middle (tuning seeds: the floor was one voxel
    too deep in the median column). A peak less than WALL_MIN_RISE_HU above the water changes nothing; no ray gets
    longer. Returns the runs.
    """
    n, m = prof.shape
    rows = np.arange(n)
    deep = run > 2 * n_partial + 4
    f0 = float(np.median(prof[rows[deep], (run[deep] + n_partial) // 2])) if deep.any() else 10.0
    idx = run[:, None] + np.arange(-WALL_BACK_VOX, 3)[None, :]
    valid = (idx >= n_partial) & (idx < m)
    win = np.where(valid, prof[rows[:, None], np.clip(idx, 0, m - 1)], -np.inf)
    pk = np.argmax(win, axis=1)
    peak = win[rows, pk]
    half = 0.5 * (f0 + peak)
    below = valid & (win <= half[:, None]) & (np.arange(win.shape[1])[None, :] < pk[:, None])
    rose = prof[rows, np.minimum(run, m - 1)] > max_hu
    has = below.any(axis=1) & (peak - f0 >= WALL_MIN_RISE_HU) & ~rose
    last = win.shape[1] - 1 - np.argmax(below[:, ::-1], axis=1)
    return np.where(has, np.minimum(run, idx[rows, last] + 1), run)


def dense_object_edges(fluid: np.ndarray, air: np.ndarray, sm: np.ndarray, max_hu: float) -> np.ndarray:
    """The water (bool, on the rays' box) joined by the tail of a dense object's blur beside it, up to the
    object's half-contrast edge (``sm``: the box's lightly smoothed HU).

    Under water the lumen's edge is the water range's top, and a dense object's blur (a marker bead, 2500 HU) stays
    above it over one to two voxels round the object, so the object sat on a mound of "wall" it does not have in air
    (where -500 HU is 14 % of its contrast above the air, not under 1 %). Voxels within DENSE_REACH_VOX of an object
    over DENSE_HU that a closing of the water by a ball of that radius fills (a notch of the water round the object,
    not the wall below a flat floor) join the water where their HU is at most half-way from the water's to the
    object's local peak.
    """
    core = sm > DENSE_HU
    if not core.any() or not fluid.any():
        return fluid
    r = DENSE_REACH_VOX
    at = np.argwhere(core)
    lo = np.maximum(at.min(0) - 2 * r - 1, 0)
    hi = np.minimum(at.max(0) + 2 * r + 2, fluid.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    fb, smb = fluid[box], sm[box]
    zz, yy, xx = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
    ball = zz ** 2 + yy ** 2 + xx ** 2 <= r * r
    pad = r + 1
    closed = ndimage.binary_closing(np.pad(fb, pad), structure=ball)[(slice(pad, -pad),) * 3]
    near = ndimage.binary_dilation(core[box], structure=ball)
    f0 = float(np.median(sm[fluid]))
    half = 0.5 * (f0 + ndimage.maximum_filter(smb, size=2 * r + 1))
    add = closed & near & ~fb & ~air[box] & (smb <= half) & (half > max_hu + 50.0)
    out = fluid.copy()
    out[box] |= add
    return out


#: Under a flat level whose contents read over this (HU: each ray's largest in DENSE_POOL_DEPTH_MM mm under the
#: partial-volume band, over it on half the level or more; the pool's HU is the median of those) lies a dense pool
#: (fluid with positive oral contrast), not water and not the wall: it joins the lumen as the water does, each ray
#: ending at the pool's edge against the wall (:func:`_dense_pool_depths`), and is said (before, its surface was drawn
#: as mucosa and the wall under it hidden, with a warning that asked for a stomach label).
DENSE_POOL_HU = 200.0
DENSE_POOL_DEPTH_MM = 5.0
#: The HU of the wall under a dense pool (soft tissue, unenhanced to arterial), for the pool's edge.
DENSE_WALL_HU = 40.0
#: A dense pool's rays end where the HU has fallen half-way from the pool's median to DENSE_WALL_HU (the blurred
#: step's edge, where the wall begins), or to this (HU) if lower: the contrast's blur beyond the edge would otherwise
#: lie on the mucosa as a coat of 150-250 HU speckled over the view's dense colour (200 HU), the markers under it merged
#: into it (tuning seeds, 350 HU pools: 0 of 5 seen at the half-way edge). A wall enhanced to 100-120 HU still stops
#: the rays.
DENSE_EDGE_MAX_HU = 140.0


@dataclass
class _DensePool:
    """The dense contents under a flat level: their median HU, and their rays' edge (HU: the pool ends where the HU
    falls below it)."""

    hu: float
    edge_hu: float


def _dense_pool_depths(prof: np.ndarray, inside: np.ndarray, n_partial: int, pool: _DensePool, rel2: np.ndarray,
                       grid: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Voxels of a dense pool under each level voxel (rays' HU profiles ``prof``) and the voxels in its range.

    The range runs from ``pool.edge_hu`` (DENSE_EDGE_MAX_HU or the half-way edge of the pool's blurred step down to
    the wall) to as far above the pool's median HU as that half-way edge is below it (a marker bead, clip or
    calcification on the floor stays). Each ray crosses the ``n_partial`` air-pool voxels, then runs to two voxels in
    a row outside the range (one is noise); the depths are the 5 x 5 median of the runs across the level, never past a
    ray's own end. Returns (depths, in range: rays x samples)."""
    top = 2.0 * pool.hu - 0.5 * (pool.hu + DENSE_WALL_HU)
    ok = inside & (((prof >= pool.edge_hu) & (prof <= top)) | (np.arange(prof.shape[1])[None, :] < n_partial))
    run = np.argmax(np.concatenate([_this_and_next(~ok), np.ones((len(ok), 1), bool)], axis=1), axis=1)
    med = _level_median(run.astype(np.int64), rel2, grid, "constant")
    return np.minimum(med, np.count_nonzero(inside, axis=1)), ok


#: Contents under a flat level that read over the water range but under DENSE_POOL_HU (HU: food, mucus, blood) are
#: told from the wall under an air boundary lying flat on it by their depth: on half the level or more, each ray's
#: median HU over this many mm under the partial-volume band is over the water range, and none of its HU there falls
#: below FLUID_MIN_HU (the fat behind a wall of 2-7 mm: the window reaches 9 mm under the level). They look like the
#: wall, so the wall under them cannot be found: they are said (:func:`fluid_below_level`), not added to the lumen.
#: Tuning stomachs (small 0-29, tiny 34000-34019) with their fluid drawn at 40 and 100 HU: said on 29/30 small and
#: 15/20, 19/20 tiny at 6 mm (25/30 small at 10 mm: the shallow pools); said on none of the 836 cached drawn volumes.
SOFT_CONTENTS_DEPTH_MM = 6.0


def _soft_contents(prof: np.ndarray, inside: np.ndarray, n_partial: int, w: float, max_hu: float) -> float | None:
    """The median HU of contents that read like the wall under a level (rays' HU profiles ``prof``, ``w`` mm a
    sample), or None where there are none (see SOFT_CONTENTS_DEPTH_MM)."""
    n = max(2, int(np.ceil(SOFT_CONTENTS_DEPTH_MM / w)))
    if prof.shape[1] < n_partial + n:
        return None
    win = prof[:, n_partial:n_partial + n]
    med = np.median(win, axis=1)
    soft = inside[:, n_partial:n_partial + n].all(axis=1) & (med > max_hu) & (med <= DENSE_POOL_HU)
    soft &= win.min(axis=1) >= FLUID_MIN_HU
    if float(np.mean(soft)) < 0.5:
        return None
    return float(np.median(med[soft]))


def _lightly_smoothed(hu: np.ndarray, spacing) -> np.ndarray:
    """A box of HU (k, j, i; ``spacing`` i, j, k mm) smoothed as the water's rays read it: Gaussian, one voxel or 1.5 mm
    if less, float32."""
    return ndimage.gaussian_filter(np.asarray(hu, np.float32), np.minimum(1.0, 1.5 / np.asarray(spacing, float)[::-1]),
                                   mode="nearest")


def _fluid_on_grid(ct: Volume, air: np.ndarray, max_hu: float, threshold_hu: float, min_level_mm2: float,
                   max_depth_mm: float):
    """The water under the air's flat level, its rays run down the grid axis closest to LPS +y (see
    :func:`fluid_below_level`): (fluid mask, level's LPS y mm, a _DensePool where the level has dense contents under
    it, else None); (None, level's LPS y mm, the median HU of contents that read like the wall under it); or None (no
    level, or none of these under it)."""
    shape = air.shape
    ji = air.any(axis=0)  # the air's box, from one projection (the whole-volume reductions cost 3x more)
    j_, i_ = np.flatnonzero(ji.any(axis=1)), np.flatnonzero(ji.any(axis=0))
    k_ = np.flatnonzero(air[:, j_[0]:j_[-1] + 1, i_[0]:i_[-1] + 1].any(axis=(1, 2)))
    box = (slice(k_[0], k_[-1] + 1), slice(j_[0], j_[-1] + 1), slice(i_[0], i_[-1] + 1))
    level_b = _level_patch(air[box], ct, min_level_mm2)
    if level_b is None:
        return None
    ax, st = _posterior_axis(ct)
    a_ijk = 2 - ax
    w = float(abs(ct.direction[1, a_ijk]) * ct.spacing[a_ijk])
    n_d, n_partial, pad = int(np.ceil(max_depth_mm / w)), max(1, int(round(3.0 / w))), 3
    lev = level_b + np.array([b.start for b in box])  # (k, j, i) on the CT grid
    # the box the rays run through: the level's columns, from the level to max_depth_mm behind it
    r_lo, r_hi = lev.min(0) - pad, lev.max(0) + 1 + pad
    if st > 0:
        r_hi[ax] = lev[:, ax].max() + 1 + n_d + pad
    else:
        r_lo[ax] = lev[:, ax].min() - n_d - pad
    r_lo, r_hi = np.maximum(r_lo, 0), np.minimum(r_hi, shape)
    rbox = tuple(slice(int(a), int(b)) for a, b in zip(r_lo, r_hi))
    hu = ct.array[rbox]
    # sub-voxel level: where the HU crosses threshold_hu between the last air voxel and the one behind it
    rel = lev - r_lo
    nxt = rel.copy()
    nxt[:, ax] = np.clip(nxt[:, ax] + st, 0, hu.shape[ax] - 1)
    h0 = hu[tuple(rel.T)].astype(float)
    h1 = hu[tuple(nxt.T)].astype(float)
    t = np.clip((threshold_hu - h0) / np.maximum(h1 - h0, 1e-3), 0.0, 1.0)
    yl = ((lev[:, ::-1] * ct.spacing) @ ct.direction[1, :] + ct.origin[1]) + t * w
    level_y = float(np.median(yl))
    sm = _lightly_smoothed(hu, ct.spacing)
    fwd = np.moveaxis(sm, ax, -1)
    if st < 0:
        fwd = fwd[..., ::-1]
    rel2 = np.delete(rel, ax, axis=1)
    start = rel[:, ax] if st > 0 else (hu.shape[ax] - 1 - rel[:, ax])
    offs = np.arange(1, n_d + 1)
    pos = start[:, None] + offs[None, :]
    inside = pos < fwd.shape[-1]
    prof = fwd[rel2[:, 0:1], rel2[:, 1:2], np.minimum(pos, fwd.shape[-1] - 1)]
    del fwd
    ok = inside & (prof <= max_hu) & ((prof >= FLUID_MIN_HU) | (offs[None, :] <= n_partial))
    evidence = _by_evidence(ct)
    run = thin_wall_edge(prof, _first_runs(ok, prof, inside, n_partial, max_hu, evidence), n_partial, max_hu)
    grid = tuple(hu.shape[a] for a in range(3) if a != ax)
    med = _level_median(run.astype(np.int64), rel2, grid, "constant")
    take = offs[None, :] <= np.minimum(run, med + 2)[:, None]
    water = np.count_nonzero(take & ok & (offs[None, :] > n_partial), axis=1) >= 2
    pool = None
    if float(np.mean(water)) < FLUID_MIN_WATER_FRACTION:
        # a flat air boundary on tissue, not on water; or on a dense pool (positive oral contrast)
        under = (offs > n_partial) & (offs <= n_partial + max(2, int(np.ceil(DENSE_POOL_DEPTH_MM / w))))
        # each ray's largest HU in the window: a shallow pool's median would take in the wall under it
        hu_under = np.nanmax(np.where(inside[:, under], prof[:, under], np.nan), axis=1)
        if float(np.mean(np.nan_to_num(hu_under, nan=-1000.0) > DENSE_POOL_HU)) < 0.5:
            soft_hu = _soft_contents(prof, inside, n_partial, w, max_hu)
            return None if soft_hu is None else (None, level_y, soft_hu)
        pool_hu = float(np.nanmedian(hu_under))
        pool = _DensePool(pool_hu, min(0.5 * (pool_hu + DENSE_WALL_HU), DENSE_EDGE_MAX_HU))
        depth, ok_pool = _dense_pool_depths(prof, inside, n_partial, pool, rel2, grid)
        take = (offs[None, :] <= depth[:, None]) & ok_pool
    else:
        # the fluid's floor: the 5 x 5 median of the rays' depths (no pillar left by a ray a noise voxel stopped,
        # no spike where a ray went through a thin wall)
        depth = np.minimum(med, np.count_nonzero(inside, axis=1))
        depth -= _falling_floor(depth, prof, n_partial, rel2, grid)
        take = offs[None, :] <= depth[:, None]
        take &= prof <= max_hu + 50.0  # never over a marker, calcification or contrast the median reached
    r, c = np.nonzero(take)
    along = pos[r, c] if st > 0 else (hu.shape[ax] - 1 - pos[r, c])
    vox = np.insert(rel2[r], ax, along, axis=1) + r_lo
    fluid = np.zeros(shape, bool)
    fluid[tuple(vox.T)] = True
    fluid &= ~air
    if pool is not None:
        return fluid, level_y, pool
    if evidence:
        along = np.arange(hu.shape[ax]).reshape([-1 if a == ax else 1 for a in range(3)])
        fluid[rbox] = close_water_gaps(fluid[rbox], air[rbox], sm, ax, along > rel[:, ax].min() if st > 0
                                       else along < rel[:, ax].max(), max_hu)
    fluid[rbox] = dense_object_edges(fluid[rbox], air[rbox], sm, max_hu)
    del sm
    return fluid, level_y, None


#: A grid whose axis closest to LPS +y is tilted from it by more than this (degrees: an oblique reformat, a volume
#: resampled into a turned box) has its water found on a grid turned upright, one axis along +y, and mapped back: the
#: rays that follow the water down run along a grid axis, and on the tilted one they would leave slivers of water
#: untouched between them (cracks of "wall" in the lumen).
UPRIGHT_TILT_DEG = 1.0


def _tilt_deg(ct: Volume) -> float:
    """Angle (degrees) between LPS +y and the CT's grid axis closest to it."""
    return float(np.degrees(np.arccos(np.clip(np.max(np.abs(np.asarray(ct.direction, float)[1, :])), -1.0, 1.0))))


def _upright_direction(direction: np.ndarray) -> np.ndarray:
    """The direction matrix turned by the least rotation that lays its axis closest to LPS +y exactly along +-y."""
    D = np.asarray(direction, float)
    a = int(np.argmax(np.abs(D[1, :])))
    return _onto_y(np.sign(D[1, a]) * D[:, a]) @ D


def _resampled(arr: np.ndarray, src: Volume, ref: Volume, linear: bool, background: float) -> np.ndarray:
    """``arr`` (on ``src``'s grid) resampled onto ``ref``'s grid (trilinear or nearest; ``background`` outside)."""
    import SimpleITK as sitk

    img = Volume(np.ascontiguousarray(arr, np.float32), src.spacing, src.origin, src.direction).to_sitk()
    out = sitk.Resample(img, [int(x) for x in ref.array.shape[::-1]], sitk.Transform(),
                        sitk.sitkLinear if linear else sitk.sitkNearestNeighbor, [float(x) for x in ref.origin],
                        [float(x) for x in ref.spacing], [float(x) for x in np.asarray(ref.direction, float).ravel()],
                        float(background), sitk.sitkFloat32)
    return sitk.GetArrayFromImage(out)


def _fluid_upright(ct: Volume, air: np.ndarray, max_hu: float, threshold_hu: float, min_level_mm2: float,
                   max_depth_mm: float):
    """:func:`_fluid_on_grid` on the air's part of an oblique CT copied (nearest voxel) onto a grid of the same voxel
    size turned upright (:func:`_upright_direction`), its water mapped back to the CT's voxels (nearest) and closed
    where it meets the air (voxels touching both, at most ``max_hu`` HU) and in single voxels the round trip left
    between its own: as :func:`_fluid_on_grid`."""
    sp = np.asarray(ct.spacing, float)
    lo, hi = bounding_box(air, (3, 3, 3))                        # (i, j, k), hi exclusive
    corners = np.array([[i, j, k] for i in (lo[0], hi[0] - 1) for j in (lo[1], hi[1] - 1) for k in (lo[2], hi[2] - 1)],
                       float)
    lps = ct.index_to_lps(corners)
    lps = np.vstack([lps, lps + [0.0, float(max_depth_mm), 0.0]])  # the rays run up to max_depth_mm posteriorly
    D2 = _upright_direction(ct.direction)
    along = lps @ D2
    a_lo, a_hi = along.min(0), along.max(0)
    up_shape = tuple(int(x) for x in (np.ceil((a_hi - a_lo) / sp).astype(int) + 1)[::-1])
    up = Volume(np.zeros(up_shape, np.int16), sp, D2 @ a_lo, D2)
    # the CT's voxels that grid covers
    n = np.array(up_shape[::-1], float) - 1.0
    box_lps = up.index_to_lps(np.array([[i, j, k] for i in (0.0, n[0]) for j in (0.0, n[1]) for k in (0.0, n[2])]))
    ijk = ct.lps_to_index(box_lps)
    b_lo = np.maximum(np.floor(ijk.min(0)).astype(int) - 1, 0)[::-1]
    b_hi = np.minimum(np.ceil(ijk.max(0)).astype(int) + 2, np.array(air.shape[::-1]))[::-1]
    box = tuple(slice(int(a), int(b)) for a, b in zip(b_lo, b_hi))
    hu_sub = np.asarray(ct.array[box])
    sub = Volume(hu_sub, sp, ct.index_to_lps(b_lo[::-1][None].astype(float))[0], ct.direction)
    # the rays read the CT's own voxel values (nearest: no blur beyond the core's own smoothing, which on a trilinear
    # copy let the water run on into the wall); the air is the region's copy cut at the threshold on the trilinear
    # copy, so that its bottom is the flat level, not the staircase of the tilted grid's voxels (which left columns
    # out of the level and their water out of the lumen)
    up = up.with_array(np.rint(_resampled(hu_sub, sub, up, False, -1024.0)).astype(np.int16))
    air_up = ((_resampled(hu_sub, sub, up, True, -1024.0) < threshold_hu)
              & ndimage.binary_dilation(_resampled(air[box], sub, up, False, 0.0) > 0.5, np.ones((3, 3, 3), bool)))
    found = _fluid_on_grid(up, air_up, max_hu, threshold_hu, min_level_mm2, max_depth_mm)
    if found is None or found[0] is None:          # nothing, or soft contents said but not taken
        return found
    fluid_up, level_y, pool = found
    f_sub = (_resampled(fluid_up, up, sub, False, 0.0) > 0.5) & ~air[box]
    touching = ndimage.binary_dilation(f_sub) & ndimage.binary_dilation(air[box])
    f_sub |= touching & ~air[box] & ((hu_sub <= max_hu) if pool is None else (hu_sub >= pool.edge_hu))
    # single voxels the nearest-voxel round trip left between the water's voxels (enclosed, at most 3 together)
    holes, n_holes = ndimage.label(ndimage.binary_fill_holes(f_sub | air[box]) & ~f_sub & ~air[box])
    if n_holes:
        small = np.flatnonzero(np.bincount(holes.ravel())[1:] <= 3) + 1
        f_sub |= np.isin(holes, small)
    fluid = np.zeros(air.shape, bool)
    fluid[box] = f_sub
    return fluid, level_y, pool


#: Water found under a level more than this many times the air's volume is taken for a leak into the body (not added,
#: said). A deep pool under a thin cap of gas is legitimately several times the gas: at 2 (until 2026-12-07) pools
#: filling 65 % of the stomach's height were refused at 2.1-2.2 times (stress seeds 36903 and 36907), and a cardia under
#: them with them; none of the 881 cached drawn volumes (the bench's, hybrids in the real CTs included) had its water
#: refused so at 2, and none changes at 4.
MAX_WATER_TO_AIR = 4.0


def fluid_below_level(ct: Volume, air: np.ndarray, max_hu: float = 25.0, threshold_hu: float = -500.0,
                      min_level_mm2: float = 300.0, max_depth_mm: float = 120.0,
                      max_air_ratio: float = MAX_WATER_TO_AIR) -> tuple[np.ndarray, dict]:
    """Retained fluid (bool mask on ct's grid) under a flat air-fluid level of ``air`` on its dependent side (LPS mm).

    A supine stomach's water lies on the posterior (LPS +y) wall under a flat level; a prone one's on the anterior
    wall, and a patient lying on a side has it on that side: the sides of DEPENDENT_SIDES are tried in turn (the
    CT's frame turned about the S axis so that the side lies along +y; below, "posterior" is that side) and the first
    with a level that has water under it is taken (another side's whose water would leak is passed over); if none
    has, the largest flat parts of the air's boundary tilted up to ROLL_MAX_DEG from a side with water beyond them (a
    patient rolled in the scanner, :func:`_tilted_levels`; at most MAX_TILTED_LEVELS) are tried the same way, each
    plane's normal as the side. The level is the air region's flat
    posterior boundary (:func:`_level_patch`; none: no fluid, nothing changes). From each of its voxels a ray is cast
    posteriorly along the grid axis closest to +y through the CT lightly smoothed
    (Gaussian, one voxel or 1.5 mm if less): it crosses the partial-volume voxels of the first 3 mm (air and
    water) and goes on while the HU stays in the water range [``FLUID_MIN_HU``, ``max_hu``] (HU; the wall is
    about 40 HU, fat about -90 HU), stopping at the first voxel above ``max_hu``, at two in a row below the
    range or after ``max_depth_mm``; a ray that ran on through a wall too thin to resolve then ends half-way up to
    that wall's peak (:func:`thin_wall_edge`). The fluid's depth below each level voxel is the 5 x 5 median of the
    rays' depths (a ray stopped by a noise voxel would leave a pillar of "wall" inside the lumen, one through a thin
    wall a spike), less voxels over ``max_hu`` + 50 HU (a bead or calcification on the floor stays), less the last
    voxel where the water still ends in a fall to fat (a wall too thin to show a peak, :func:`_falling_floor`),
    plus the tail of a dense object's blur beside the water up to half-way to its peak (:func:`dense_object_edges`: a
    marker bead, a clip, contrast), so the mound it sits on under water is smaller. With ``WATER_RUNS = "evidence"``
    (rule 39; ``"thick"``, rule 40: on slices over THICK_SLICE_MM) a ray ends where its summed evidence for water is
    largest rather than at its first voxel above the range (:func:`water_runs`), and one-voxel gaps of the water
    across the rays are closed (:func:`close_water_gaps`).
    On an oblique grid (its axis closest to +y tilted over UPRIGHT_TILT_DEG) the rays run down a grid of the same
    voxel size turned upright about the air, and the water found there is mapped back (:func:`_fluid_upright`).
    Fluid is kept only if at least ``FLUID_MIN_WATER_FRACTION`` of the level has two or more water voxels under it
    (each ray clipped to two voxels beyond that median; an air boundary lying flat on tissue has none), and refused
    with a warning if it leaks: more than ``max_air_ratio`` times the air volume, or touching the side of the volume.
    A level with dense contents under it instead (over DENSE_POOL_HU: fluid with positive oral contrast) has them
    taken the same way, each ray through the pool to its edge against the wall (:func:`_dense_pool_depths`), if no
    side or tilted level has water. A level with contents under it that read like the wall (over ``max_hu`` and up to
    DENSE_POOL_HU, :func:`_soft_contents`) adds nothing (the wall under them cannot be told from them) but is said in
    a warning, if no side has water or a dense pool.

    Returns ``(fluid, info)`` with ``info``: ``fluid_voxels``, ``fluid_ml`` (mL), ``fluid_level_lps_y`` (LPS y
    of the level, mm, sub-voxel from where the HU crosses ``threshold_hu``; None when no level or a level on the left or
    right or tilted), ``fluid_dependent_side`` (a key of DEPENDENT_SIDES or None), ``fluid_gravity_lps`` (the unit
    normal of the level it was found under, LPS), ``fluid_level_text`` (the level's place, for messages),
    ``fluid_dense_hu`` (the median HU of a dense pool taken), ``fluid_soft_hu`` (the median HU of contents that read
    like the wall, said and not taken) with ``fluid_soft_level`` (their level: ``gravity_lps``, unit, and ``level_mm``,
    the level's coordinate along it, LPS mm) and ``warnings`` (list of str).
    """
    air = np.asarray(air, bool)
    info = {"fluid_voxels": 0, "fluid_ml": 0.0, "fluid_level_lps_y": None, "fluid_dependent_side": None,
            "fluid_level_text": None, "warnings": []}
    none = np.zeros(air.shape, bool)
    if not air.any() or max_hu <= FLUID_MIN_HU:
        return none, info
    dense = soft = None
    for side, gravity, Q in _gravity_frames(ct, air, min_level_mm2, max_hu):
        # the CT's frame turned so that gravity lies along +y (the same voxels, LPS relabelled)
        ct_g = ct if Q is None else Volume(ct.array, ct.spacing, Q @ np.asarray(ct.origin, float),
                                           Q @ np.asarray(ct.direction, float))
        found = (_fluid_upright if _tilt_deg(ct_g) > UPRIGHT_TILT_DEG else _fluid_on_grid)(
            ct_g, air, max_hu, threshold_hu, min_level_mm2, max_depth_mm)
        if found is None:
            continue
        if found[0] is None:                           # soft contents: said if no side has water or a dense pool
            soft = soft or (side, gravity, found[1], found[2])
            continue
        if found[2] is not None:                       # a dense pool: taken only if no side has water
            dense = dense or (side, gravity, Q, found)
            continue
        taken = _take_fluid(info, found, side, gravity, Q, air, ct, max_air_ratio)
        if taken is not None:
            return _with_water_beside(taken, info, ct, air, gravity, found[1], max_hu), info
    if dense is not None:
        side, gravity, Q, found = dense
        taken = _take_fluid(info, found, side, gravity, Q, air, ct, max_air_ratio)
        if taken is not None:
            return taken, info
    if soft is not None:
        side, gravity, level, soft_hu = soft
        ras, _ = _level_place(gravity, level, side)
        info["fluid_soft_hu"] = soft_hu
        # the level's plane (LPS mm along gravity): its face is no mucosa, and the grade counts it as wall not shown
        info["fluid_soft_level"] = {"gravity_lps": [float(x) for x in gravity], "level_mm": float(level)}
        info["warnings"].append(f"a flat air-fluid level at {ras} has contents of about {soft_hu:.0f} HU under it "
                                "(food, mucus or blood: they read like the wall), which were not added to the lumen: "
                                "the level is shown as mucosa and the wall under them is hidden; pass a stomach label "
                                "with --mask to unfold that wall")
    return none, info


def _take_fluid(info: dict, found: tuple, side: str, gravity, Q, air: np.ndarray, ct: Volume,
                max_air_ratio: float) -> np.ndarray | None:
    """The fluid mask ``found`` under a level (see :func:`_fluid_on_grid`) checked for a leak and written into
    ``info`` (see :func:`fluid_below_level`): the mask, an empty mask where it leaks (said in ``info["warnings"]``), or
    None where another side's (``Q`` not None) leaks: not a level at all, passed over without a word."""
    fluid, level, pool = found
    n = int(np.count_nonzero(fluid))
    ras, lps_y = _level_place(gravity, level, side)
    n_air = int(np.count_nonzero(air))
    problem = ""
    if n > max_air_ratio * n_air:
        problem = f"is {n / max(n_air, 1):.1f} times the air volume (over {max_air_ratio:g})"
    elif _touches_faces(fluid, (0, 1, 2)):
        problem = "reaches the side of the volume"
    if problem and Q is not None:
        return None
    info.update(fluid_level_lps_y=lps_y, fluid_dependent_side=side,
                fluid_level_text=ras, fluid_gravity_lps=[float(x) for x in gravity])
    what = "fluid-like" if pool is None else f"dense (median {pool.hu:.0f} HU)"
    if pool is not None:
        info["fluid_dense_hu"] = pool.hu
    if problem:
        info["warnings"].append(f"a flat air-fluid level was found at {ras} but the {what} voxels below it "
                                f"{problem}: they leak into the body and were not added to the lumen (check "
                                "the CT, or pass a stomach label with --mask)")
        return np.zeros(air.shape, bool)
    info["fluid_voxels"] = n
    info["fluid_ml"] = n * float(np.prod(ct.spacing)) / 1000.0
    return fluid


#: Water beside the water the rays found (:func:`water_beside`): ``"add"`` joins it to the lumen, ``"say"`` (default:
#: adding it failed protocol P2 twice, docs/RULE52_water_beside.md and RULE53_water_beside_smoothed.md) measures it and
#: says it when it is over WATER_BESIDE_SAY_ML, ``"off"`` does neither. Under an overhang of the wall (a pool wider
#: below its level than at it: a round fundus under a deep pool) or past a noisy voxel that stopped the rays, the rays
#: run down from the level leave water out, and the view draws the wall at its face (tuning draws small 0-29 with a
#: pool filling 40-55 % of the height: 13-33 mL left out on 7 of 29).
WATER_BESIDE = "say"
#: How far (mm) beside the found water it is looked for; how far (mm) below the level it starts (the level's own
#: partial-volume voxels are the rays'); the radius (mm) of the ball of water-range voxels its core must hold (a
#: partial-volume band between the wall and fat, 1-2 voxels thick, reads in the water range too); the largest HU
#: gradient (HU/mm) of its core (water is flat, a band between the wall and fat is not); over how many mL it is said.
WATER_BESIDE_REACH_MM = 40.0
WATER_BESIDE_BELOW_MM = 3.0
WATER_BESIDE_CORE_MM = 1.5
WATER_BESIDE_MAX_GRADIENT = 8.0
WATER_BESIDE_SAY_ML = 10.0
#: The added water's face smoothed with a Gaussian of this sigma (mm; 0: not smoothed; rule 53's 1.5 failed P2)
WATER_BESIDE_SMOOTH_MM = 0.0


def _ball(radius_vox: np.ndarray) -> np.ndarray:
    """A bool ellipsoid structuring element with these radii (voxels, per array axis k, j, i; at least one voxel)."""
    r = np.maximum(np.asarray(radius_vox, float), 1.0)
    n = np.floor(r).astype(int)
    g = np.ogrid[-n[0]:n[0] + 1, -n[1]:n[1] + 1, -n[2]:n[2] + 1]
    return sum((g[a] / r[a]) ** 2 for a in range(3)) <= 1.0


def water_beside(ct: Volume, lumen: np.ndarray, fluid: np.ndarray, gravity_lps, level_mm: float,
                 max_hu: float = 25.0) -> tuple[np.ndarray, tuple]:
    """Water beside the retained fluid under a level that its rays did not reach (bool mask in a box, and the box).

    Voxels more than WATER_BESIDE_BELOW_MM below the level (``level_mm``, the level's coordinate along the unit LPS
    ``gravity_lps``, mm) and within WATER_BESIDE_REACH_MM of ``fluid``'s box whose lightly smoothed HU is in the
    water range [``FLUID_MIN_HU``, ``max_hu``] and not in ``lumen`` (bool on ct's grid; ``fluid``'s voxels count as
    lumen too, so the air alone may be passed: no whole-grid union is made); of those, the core (a ball of
    WATER_BESIDE_CORE_MM of such voxels or ``fluid`` round it, HU gradient under WATER_BESIDE_MAX_GRADIENT HU/mm: a
    partial-volume band between the wall and fat is thinner and steeper) connected to ``fluid``, grown back by the
    ball within the range, with the voxels it and ``lumen`` enclose below the level (a noisy voxel over the range:
    an island of "wall" in the water, whose faces the judge and the view would take for mucosa); with
    WATER_BESIDE_SMOOTH_MM > 0, its face then smoothed (the lumen's indicator blurred by a Gaussian of that sigma,
    mm, and cut at a half, near it only). Returns ``(mask, box)``: the mask on ``box`` (a tuple of three slices of
    ct's ``[k, j, i]`` grid).
    """
    sp = np.asarray(ct.spacing, float)
    lo, hi = bounding_box(fluid, np.ceil(WATER_BESIDE_REACH_MM / sp).astype(int))
    # each voxel's coordinate along gravity (mm): separable over the grid's axes
    step = (np.asarray(ct.direction, float).T @ np.asarray(gravity_lps, float)) * sp          # per i, j, k
    s0 = float(np.asarray(ct.origin, float) @ np.asarray(gravity_lps, float))
    ax_s = [step[2 - a] * np.arange(lo[2 - a], hi[2 - a]).reshape([-1 if b == a else 1 for b in range(3)])
            for a in range(3)]
    below = (s0 + ax_s[0] + ax_s[1] + ax_s[2]) > level_mm + WATER_BESIDE_BELOW_MM
    # the box from the level down: crop to where any voxel lies below it
    nz = [np.flatnonzero(below.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    if any(len(x) == 0 for x in nz):
        return np.zeros((0, 0, 0), bool), (slice(0, 0),) * 3
    sub = tuple(slice(int(x[0]), int(x[-1]) + 1) for x in nz)
    box = tuple(slice(lo[2 - a] + sub[a].start, lo[2 - a] + sub[a].stop) for a in range(3))
    below = below[sub]
    sm = _lightly_smoothed(ct.array[box], sp)
    fluid_box = np.asarray(fluid[box], bool)
    lumen_box = np.asarray(lumen[box], bool) | fluid_box
    found = fluid_box & below
    water = (sm >= FLUID_MIN_HU) & (sm <= max_hu) & below & ~lumen_box
    flat = water & (np.sqrt(sum(g * g for g in np.gradient(sm, *sp[::-1]))) < WATER_BESIDE_MAX_GRADIENT)
    del sm
    ball = _ball(WATER_BESIDE_CORE_MM / sp[::-1])
    core = ndimage.binary_erosion(flat | found, ball) & flat
    labels, _ = ndimage.label(core)
    touching = np.unique(labels[ndimage.binary_dilation(found) & core])
    grown = ndimage.binary_dilation(np.isin(labels, touching[touching > 0]), ball) & water
    # the voxels a noisy HU left out inside it, enclosed by the lumen: islands of "wall" floating in the water
    grown |= ndimage.binary_fill_holes(grown | lumen_box) & ~lumen_box & below
    if WATER_BESIDE_SMOOTH_MM > 0 and grown.any():
        # its face against the wall smoothed: the water range read voxel by voxel under noise leaves it ragged by a
        # voxel, pits on the view
        u = ndimage.gaussian_filter((grown | lumen_box).astype(np.float32), WATER_BESIDE_SMOOTH_MM / sp[::-1])
        grown = (u > 0.5) & ndimage.binary_dilation(grown, ball) & below & ~lumen_box
        grown |= ndimage.binary_fill_holes(grown | lumen_box) & ~lumen_box & below   # none the smoothing opened
    return grown, box


def _with_water_beside(fluid: np.ndarray, info: dict, ct: Volume, air: np.ndarray, gravity, level_mm: float,
                       max_hu: float) -> np.ndarray:
    """The fluid taken under a level with the water beside it (:func:`water_beside`) added or said, as WATER_BESIDE
    asks (``info["fluid_beside_ml"]``, mL; a warning over WATER_BESIDE_SAY_ML); fluid itself when it leaks (more than
    the fluid itself, or to the side of the volume) or with nothing beside."""
    if WATER_BESIDE == "off" or not fluid.any():
        return fluid
    beside, box = water_beside(ct, air, fluid, gravity, level_mm, max_hu)
    n = int(np.count_nonzero(beside))
    if n == 0:
        info["fluid_beside_ml"] = 0.0
        return fluid
    at_face = any((b.start == 0 and np.take(beside, 0, axis=a).any())
                  or (b.stop == fluid.shape[a] and np.take(beside, -1, axis=a).any()) for a, b in enumerate(box))
    if n > info["fluid_voxels"] or at_face:
        return fluid
    ml = n * float(np.prod(ct.spacing)) / 1000.0
    info["fluid_beside_ml"] = ml
    if WATER_BESIDE == "add":
        info["fluid_voxels"] += n
        info["fluid_ml"] += ml
        fluid[box] |= beside
        return fluid
    if ml > WATER_BESIDE_SAY_ML:
        info["warnings"].append(f"about {ml:.0f} mL of water-like voxels lie beside the retained fluid where its rays "
                                "down from the level did not reach (under an overhang of the wall, or past a noisy "
                                "voxel), and were not added to the lumen: the wall there is drawn at the water's face "
                                "and what lies under it is hidden; pass a stomach label with --mask to unfold it")
    return fluid


def _level_place(gravity, level: float, side: str = "posterior") -> tuple[str, float | None]:
    """A level's place: (text for messages, its LPS y in mm or None), from ``level``, its coordinate (mm) along the unit
    ``gravity`` (LPS). On a side's axis (+-x or +-y) the text gives its LPS and RAS coordinate along that axis (the
    LPS y only on +-y); off the axes (a patient rolled) its offset along ``gravity`` and its tilt from the ``side``'s
    wall, and no LPS y."""
    g = np.asarray(gravity, float)
    if np.max(np.abs(g)) < 1.0 - 1e-9:
        tilt = float(np.degrees(np.arccos(np.clip(g @ np.asarray(DEPENDENT_SIDES[side]), -1.0, 1.0))))
        return (f"{level:.1f} mm along LPS ({g[0]:.2f}, {g[1]:.2f}, {g[2]:.2f}), tilted {tilt:.0f} degrees from "
                "the horizontal (a patient rolled in the scanner)", None)
    axis = "y" if g[1] else "x"
    at = level if g[0] + g[1] > 0 else -level                    # the level's LPS coordinate along its axis (mm)
    return f"LPS {axis} = {at:.1f} mm (RAS {'A' if axis == 'y' else 'R'} = {-at:.1f} mm)", (at if g[1] else None)


def _gravity_frames(ct: Volume, air: np.ndarray, min_level_mm2: float, max_hu: float):
    """(side, gravity (unit LPS), rotation taking gravity onto +y, or None for +y itself) to look for the water in:
    each of DEPENDENT_SIDES; then, if none of them holds it, the flat parts of the air's boundary whose normal lies
    within ROLL_MAX_DEG of a side's and that have water or a dense pool beyond them (:func:`_tilted_levels`: a patient
    rolled in the scanner)."""
    for side, gravity in DEPENDENT_SIDES.items():
        yield side, np.asarray(gravity, float), (None if side == "posterior" else _turn_to_posterior(gravity))
    for side, g in _tilted_levels(ct, air, min_level_mm2, max_hu):
        yield side, g, _onto_y(g)


#: A flat air boundary whose normal lies within this (degrees) of a side's direction is tried as a tilted level.
ROLL_MAX_DEG = 35.0
#: The plane fits of :func:`_tilted_levels` start from each side turned about S by each of these (degrees): a fit
#: started from the side itself settles on the flat part of the wall nearest the side's direction, which for a level
#: rolled about 20 degrees is another one.
ROLL_STARTS_DEG = (0.0, -10.0, 10.0, -20.0, 20.0, -30.0, 30.0)
#: At most this many tilted planes are tried as the level (the largest with water beyond them first): each try runs
#: the water's rays on a grid turned upright (0.7-2 s on a full-size CT).
MAX_TILTED_LEVELS = 2
#: Depths (mm) beyond a tilted plane at which :func:`_water_beyond` samples the CT: past the 3 mm of partial volume
#: the rays also cross (:func:`fluid_below_level`), to about 9 mm.
WATER_TEST_DEPTHS_MM = (3.5, 4.5, 5.5, 6.5, 7.5, 8.5)
#: A tilted plane is tried also where a dense pool lies beyond it (positive oral contrast in a rolled patient): its
#: rays then take the pool as under a side's level (:func:`_dense_pool_depths`).
TILTED_DENSE_POOLS = True


def _onto_y(g: np.ndarray) -> np.ndarray:
    """The least rotation (3x3) that takes the unit vector g (LPS) onto +y (Rodrigues' formula)."""
    g = np.asarray(g, float)
    axis = np.cross(g, [0.0, 1.0, 0.0])
    sin, cos = float(np.linalg.norm(axis)), float(g[1])
    if sin < 1e-12:
        return np.eye(3) if cos > 0 else np.diag([-1.0, -1.0, 1.0])
    k = axis / sin
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + sin * K + (1.0 - cos) * K @ K


def _water_beyond(ct: Volume, pts: np.ndarray, m: np.ndarray, max_hu: float) -> float:
    """Fraction of the boundary points ``pts`` (LPS mm) with water or a dense pool beyond them along ``m`` (unit, LPS):
    at least two thirds of the CT's values at WATER_TEST_DEPTHS_MM in the water range [FLUID_MIN_HU, ``max_hu``], or
    (TILTED_DENSE_POOLS) over DENSE_POOL_HU (HU; each the mean of five trilinear samples, one voxel apart across ``m``,
    against the noise). A cheap test before the rays: a wall with fat or an organ behind it crosses the water range in
    a sample or two and stays under the dense one."""
    if len(pts) > 1500:                         # a fraction to about +-0.03: enough for a test
        pts = pts[np.linspace(0, len(pts) - 1, 1500).astype(np.int64)]
    e1 = np.cross(m, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)                    # m lies within ROLL_MAX_DEG of a horizontal side: never along z
    e2 = np.cross(m, e1)
    w = float(np.min(ct.spacing))
    at = pts[:, None, :] + np.asarray(WATER_TEST_DEPTHS_MM, float)[None, :, None] * m[None, None, :]
    offs = (0.0 * e1, w * e1, -w * e1, w * e2, -w * e2)
    # the samples' box only (a CT left on file is read there, never whole)
    ijk = ct.lps_to_index(np.concatenate([(at + off).reshape(-1, 3) for off in offs]))
    size = np.array(ct.size)
    lo = np.clip(np.floor(ijk.min(0)).astype(int) - 2, 0, size)
    hi = np.clip(np.ceil(ijk.max(0)).astype(int) + 3, lo, size)
    if np.any(hi <= lo):
        return 0.0
    box = ct.crop(lo, hi)
    hu = sum(box.sample(at + off) for off in offs) / 5.0
    wet = 3 * np.count_nonzero((hu >= FLUID_MIN_HU) & (hu <= max_hu), axis=1) >= 2 * len(WATER_TEST_DEPTHS_MM)
    if TILTED_DENSE_POOLS:
        wet |= 3 * np.count_nonzero(hu > DENSE_POOL_HU, axis=1) >= 2 * len(WATER_TEST_DEPTHS_MM)
    return float(np.mean(wet))


def _tilted_levels(ct: Volume, air: np.ndarray, min_level_mm2: float, max_hu: float) -> list:
    """(side, unit normal LPS) of up to MAX_TILTED_LEVELS flat parts of the air's boundary tilted 1 to ROLL_MAX_DEG
    degrees from a side's direction with water (or a dense pool) beyond them, the largest first.

    From each side turned about S by each of ROLL_STARTS_DEG, the boundary points whose outward normal (the smoothed
    mask's gradient, on every second voxel of a large box) lies within ROLL_MAX_DEG of it; the plane fitted (least
    squares) to those within 1.5 voxels of the densest slab across it, four times; kept where the densest two-voxel
    slab of that plane holds at least ``min_level_mm2`` (mm^2) of boundary and at least FLUID_MIN_WATER_FRACTION of
    that slab's points have water or a dense pool beyond them (:func:`_water_beyond`); planes within 3 degrees of a
    larger one are dropped."""
    lo, hi = bounding_box(air, (2, 2, 2))
    box = air[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    step = 2 if box.size > 2_000_000 else 1
    box = box[::step, ::step, ::step]
    sp = np.asarray(ct.spacing, float) * step
    sm = ndimage.gaussian_filter(box.astype(np.float32), 1.0)
    shell = (sm > 0.3) & (sm < 0.7)
    if not shell.any():
        return []
    gk, gj, gi = (g[shell] for g in np.gradient(sm))
    D = np.asarray(ct.direction, float)
    grad = np.stack([gi / sp[0], gj / sp[1], gk / sp[2]], 1) @ D.T        # LPS, per mm
    norm = np.linalg.norm(grad, axis=1)
    ok = norm > 1e-6
    n = -grad[ok] / norm[ok, None]                                         # outward: from the air into the wall
    kk, jj, ii = np.nonzero(shell)
    p = ct.index_to_lps(np.stack([ii[ok] * step + lo[0], jj[ok] * step + lo[1], kk[ok] * step + lo[2]], 1)
                        .astype(float))
    face = float(np.prod(sp)) / float(sp.min())                            # mm^2 of boundary per shell voxel, about
    found = []
    w = float(sp.min())
    for side, g0 in DEPENDENT_SIDES.items():
        g0 = np.asarray(g0, float)
        for roll in ROLL_STARTS_DEG:
            t = np.radians(roll)
            m = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]]) @ g0
            sel = n @ m > np.cos(np.radians(ROLL_MAX_DEG))
            if sel.sum() * face < min_level_mm2:
                continue
            # the plane through the most of those points: the densest slab along m, then least squares (its normal
            # the covariance's least axis), again on the points within 1.5 voxels of that plane (a staircase's own
            # normals lean toward the grid's axes; its points do not)
            q = p[sel]
            for _ in range(4):
                d = q @ m
                hist = np.bincount(np.floor((d - d.min()) / w).astype(np.int64))
                b = int(np.argmax(hist[:-1] + hist[1:])) if len(hist) > 1 else 0
                on = np.abs(d - (d.min() + (b + 1.0) * w)) <= 1.5 * w
                if on.sum() < 10:
                    break
                c = q[on] - q[on].mean(0)
                m_new = np.linalg.eigh(c.T @ c)[1][:, 0]
                m = m_new * (1.0 if m_new @ m >= 0 else -1.0)
            tilt = float(np.degrees(np.arccos(np.clip(m @ g0, -1.0, 1.0))))
            if tilt < UPRIGHT_TILT_DEG or tilt > ROLL_MAX_DEG:
                continue
            d = q @ m
            b0 = np.floor((d - d.min()) / w).astype(np.int64)
            hist = np.bincount(b0)
            b = int(np.argmax(hist[:-1] + hist[1:])) if len(hist) > 1 else 0
            slab = (b0 == b) | (b0 == b + 1)
            if slab.sum() * face >= min_level_mm2:
                found.append((float(slab.sum()) * face, side, m, q[slab]))
    out = []
    for _, side, m, pts in sorted(found, key=lambda x: -x[0]):             # the largest first, each plane once
        if len(out) >= MAX_TILTED_LEVELS:
            break
        if any(np.degrees(np.arccos(np.clip(m @ m2, -1.0, 1.0))) <= 3.0 for _, m2 in out):
            continue
        if _water_beyond(ct, pts, m, max_hu) >= FLUID_MIN_WATER_FRACTION:
            out.append((side, m))
    return out


#: The sides of the stomach its water may lie on, in the order they are tried, each with its direction in LPS: the
#: posterior wall of a supine patient first, then the anterior of a prone one and the left and right of a patient on
#: that side (decubitus); the first whose air has a flat level with water under it is taken. A level on another side
#: whose water would leak is not one (no warning; the posterior side's leak is said, as before).
DEPENDENT_SIDES = {"posterior": (0.0, 1.0, 0.0), "anterior": (0.0, -1.0, 0.0), "left": (1.0, 0.0, 0.0),
                   "right": (-1.0, 0.0, 0.0)}


def _turn_to_posterior(gravity) -> np.ndarray:
    """Rotation (3x3) about LPS z that takes the unit vector ``gravity`` (along +-x or +-y) onto +y."""
    g = np.asarray(gravity, float)
    c, s = g[1], g[0]                                  # the angle from +y to g, about z: g = (sin, cos)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: A point with no gas within the snapping distance may lie under retained water: a supine stomach's cardia, on the
#: posterior wall of the fundus, goes under a deep pool. A ray from the point up through water alone (against a side's
#: gravity, DEPENDENT_SIDES in turn) that leaves the water within SUBMERGED_MAX_MM with gas beside its exit joins the
#: point to that gas; the water found under the gas's level must then hold the point (:func:`air_region`). (Water
#: grown from the point instead, through voxels in the water range, ran into tissue of 30 HU under noise.)
SUBMERGED_MAX_MM = 80.0
#: The point may be clicked on the wall under the water: water this near (mm) is its water.
SUBMERGED_LEAD_MM = 5.0
#: Longest run (mm) of the ray's samples above the water range on its way up (noise left by the light smoothing; a
#: wall is thicker).
SUBMERGED_GAP_MM = 2.0
#: How far (mm) beyond the ray's exit from the water (its first sample below the range) gas is looked for: the level's
#: partial-volume band, and a thin cap of gas that the smoothing lifts above the gas threshold.
SUBMERGED_EXIT_MM = 5.0
#: A point's nearest gas in a pocket smaller than this (mL) is a bubble (in the oesophagus, the duodenum or a fold)
#: when the point lies under water that a ray crosses to other gas: that gas is taken (held-out seed 1011 with a pool
#: up to half the stomach's height: both points had snapped to bubbles of 0.1-0.2 mL in the tubes).
BUBBLE_ML = 1.0


def _smoothed_box(ct: Volume, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The CT's HU in the index box [lo, hi) (i, j, k), lightly smoothed (:func:`_lightly_smoothed`)."""
    return _lightly_smoothed(ct.array[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]], ct.spacing)


def _gas_above_water(ct: Volume, air, p: np.ndarray, max_hu: float) -> tuple | None:
    """(gas voxel LPS mm, its distance from p mm) a ray from LPS point p (mm) up through water alone reaches, else None.

    The rays run against each side's gravity (DEPENDENT_SIDES, in turn) in steps of half the smallest spacing, through
    the CT lightly smoothed (:func:`_smoothed_box`) round each ray. A ray is taken when it reaches water
    ([FLUID_MIN_HU, ``max_hu``] HU) within SUBMERGED_LEAD_MM, no run of its samples above the range is longer than
    SUBMERGED_GAP_MM (a wall) until it leaves the water below the range within SUBMERGED_MAX_MM, and an ``air`` voxel
    (bool mask on ct's grid) lies within SUBMERGED_EXIT_MM of that exit (fat or bowel has none)."""
    p = np.asarray(p, float).reshape(3)
    step = 0.5 * float(np.min(ct.spacing))
    t = np.arange(0.0, SUBMERGED_MAX_MM + step, step)
    size = np.asarray(ct.size)
    for gravity in DEPENDENT_SIDES.values():
        pts = p[None] + t[:, None] * -np.asarray(gravity, float)[None]
        ijk = ct.lps_to_index(pts)
        inside = np.all((ijk > -0.5) & (ijk < size - 0.5), axis=1)
        n = int(np.argmin(inside)) if not inside.all() else len(t)
        if n < 2:
            continue
        ijk = ijk[:n]
        lo = np.maximum(np.floor(ijk.min(0)).astype(int) - 3, 0)
        hi = np.minimum(np.ceil(ijk.max(0)).astype(int) + 4, size)
        vals = ndimage.map_coordinates(_smoothed_box(ct, lo, hi), (ijk - lo)[:, ::-1].T, order=1, mode="nearest")
        water = np.flatnonzero((vals >= FLUID_MIN_HU) & (vals <= max_hu))
        if not len(water) or t[water[0]] > SUBMERGED_LEAD_MM:
            continue
        w0 = int(water[0])
        low = np.flatnonzero(vals[w0:] < FLUID_MIN_HU)
        if not len(low):
            continue
        exit_ = w0 + int(low[0])
        high = np.r_[0, (vals[w0:exit_] > max_hu).view(np.int8), 0]
        runs = np.diff(np.flatnonzero(np.diff(high)).reshape(-1, 2), axis=1)
        if len(runs) and float(runs.max()) * step > SUBMERGED_GAP_MM:
            continue
        gas = nearest_true(air, ct, pts[exit_], SUBMERGED_EXIT_MM)
        if gas is not None:
            return gas, float(np.linalg.norm(gas - p))
    return None


def _seeds(ct: Volume, air, pts: dict, threshold_hu: float, max_snap_mm: float, max_hu: float, voxel_ml: float):
    """Each point's air seed (LPS mm), its pocket (bool on ct's grid, flooded once per pocket) and the points joined to
    their gas through water: (seeds, pockets, {name: (depth mm, None or the bubble passed over: (mL, mm away))}).

    A point's seed is its nearest air voxel within ``max_snap_mm``; with none, or with one in a pocket under BUBBLE_ML,
    the gas a ray from it up through water alone meets (:func:`_gas_above_water`, water up to ``max_hu`` HU) when there
    is such a ray (to other gas than the bubble). ``voxel_ml``: a voxel's volume (mL). Raises AnatomyError naming the
    point when it has no seed."""
    seeds, pockets, joined = {}, {}, {}
    for name, p in pts.items():
        s = nearest_true(air, ct, p, max_snap_mm)
        if s is not None:  # its pocket (flooded once: the other point's, when it lies in it)
            kji = _voxel(ct, s)
            pockets[name] = next((c for c in pockets.values() if c[kji]), None)
            if pockets[name] is None:
                pockets[name] = flood_fill(air, kji)
        bubble = s is not None and np.count_nonzero(pockets[name]) * voxel_ml < BUBBLE_ML
        if (s is None or bubble) and max_hu > FLUID_MIN_HU:  # under water? the gas above it, through the water
            up = _gas_above_water(ct, air, p, max_hu)
            if up is not None and (s is None or not pockets[name][_voxel(ct, up[0])]):
                passed = None if s is None else (np.count_nonzero(pockets.pop(name)) * voxel_ml,
                                                 float(np.linalg.norm(s - p)))
                s, joined[name] = up[0], (up[1], passed)
        if s is None:
            raise AnatomyError(f"the stomach has no gas near the {name} point (RAS {ras_text(p)} mm): no voxel "
                               f"below {threshold_hu:g} HU within {max_snap_mm:g} mm "
                               f"({_nearest_distance_text(air, ct, p, max_snap_mm)}) nor above it through water; "
                               "pass a stomach label with --mask, or place the point in the gas-filled lumen")
        seeds[name] = s
    return seeds, pockets, joined


def air_region(ct: Volume, cardia_lps, pylorus_lps, threshold_hu: float = -500.0, max_snap_mm: float = 20.0,
               progress=None, fluid_max_hu: float = 25.0) -> tuple[np.ndarray, dict]:
    """Stomach lumen (bool mask on ct's grid): air below threshold_hu (HU) 6-connected to the points' air, plus fluid.

    Each point (LPS mm) is snapped to the nearest air voxel within ``max_snap_mm``; the air component(s)
    reached are flood-filled with 6-connectivity. Lungs and colon gas are left out because they are not
    connected to the seeds. Retained fluid under a flat air-fluid level of that air (up to ``fluid_max_hu``
    HU, :func:`fluid_below_level`) is added; without a level the mask is the air alone. A point with no air that near
    but under water (a cardia under a deep pool) is joined to the gas a ray from it up through the water alone meets
    (:func:`_gas_above_water`), and the water found must then hold it (within SUBMERGED_LEAD_MM); it is said.

    Parameters
    ----------
    ct : Volume
        CT in HU.
    cardia_lps, pylorus_lps : (3,) array-like
        The two points, LPS mm, in the gas-filled lumen or on the wall near it.
    threshold_hu : float
        Air threshold (HU); voxels strictly below it are air.
    max_snap_mm : float
        How far (mm) from each point air is looked for.
    progress : Progress or callable(fraction), optional
    fluid_max_hu : float
        Upper HU of retained water under an air-fluid level (at most ``FLUID_MIN_HU``: no fluid is added).

    Returns
    -------
    mask : (K, J, I) bool array
    info : dict
        ``volume_ml`` (mL), ``n_components`` (1 or 2), ``seeds_lps`` (snapped points, LPS mm),
        ``warnings`` (list of str), ``fluid_voxels``, ``fluid_ml`` (mL) and ``fluid_level_lps_y`` (LPS y of
        the air-fluid level, mm, or None); ``volume_ml`` is the air's.

    Raises
    ------
    PointError
        If a point lies outside the volume.
    AnatomyError
        If no air lies near a point nor above it through water (pass a stomach mask), or a point joined through water
        lies in no water found, or the air reached touches the side faces of the volume (outside air) or is larger than
        ``MAX_STOMACH_ML`` (lung, bowel).
    """
    pts = {"cardia": np.asarray(cardia_lps, float).reshape(3), "pylorus": np.asarray(pylorus_lps, float).reshape(3)}
    for name, p in pts.items():
        _check_inside(ct, p, name)
    # thresholded where looked at (no whole-CT mask); a CT on file gives its air from one scan, packed in bits
    air = ct.array.below(threshold_hu) if isinstance(ct.array, FileArray) else BelowThreshold(ct.array, threshold_hu)
    if progress is not None:
        progress(0.1)
    voxel_ml = float(np.prod(ct.spacing)) / 1000.0
    seeds, pockets, joined = _seeds(ct, air, pts, threshold_hu, max_snap_mm, fluid_max_hu, voxel_ml)
    sides = _side_axes(ct)
    region = None
    n_comp = 0
    leak_warnings: list[str] = []
    for n_done, (name, s) in enumerate(seeds.items()):
        kji = _voxel(ct, s)
        if region is not None and region[kji]:
            continue
        comp = pockets[name] if name in pockets else flood_fill(air, kji)
        problem = _air_problem(comp, sides, voxel_ml)
        if problem:
            inside = [_voxel(ct, q) for q in seeds.values() if comp[_voxel(ct, q)]]
            cut, neck = _cut_leaks(comp, ct, inside, sides, voxel_ml)
            if cut is None:
                raise AnatomyError(f"the air reached from the {name} point (RAS {ras_text(pts[name])} mm) {problem}: "
                                   "the point is probably in the air outside the body or in lung, or the stomach "
                                   "gas leaks into the bowel through an opening too wide to cut; move the point "
                                   "into the stomach, or pass a stomach label with --mask")
            removed = (np.count_nonzero(comp) - np.count_nonzero(cut)) * voxel_ml
            leak_warnings.append(f"the stomach gas leaked into neighbouring air ({problem.split(':')[0]}); "
                                 f"{removed:.0f} mL beyond necks narrower than {2 * neck:g} mm was cut away "
                                 "(check the air region, or pass a stomach label with --mask)")
            comp = cut
        if region is None:
            region = comp
        else:  # the union in comp's box alone, so that no whole-CT page is written
            lo, hi = bounding_box(comp)
            box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
            region[box] |= comp[box]
        n_comp += 1
        if progress is not None:
            progress(0.2 + 0.4 * (n_done + 1))
    warnings = list(dict.fromkeys(leak_warnings))
    if n_comp == 2:
        warnings.append("the cardia and pylorus points reach two separate air pockets; their union is used as "
                        "the stomach lumen (check the points, or pass a stomach label with --mask)")
    info = {"volume_ml": float(np.count_nonzero(region)) * voxel_ml, "n_components": n_comp,
            "seeds_lps": [seeds["cardia"].tolist(), seeds["pylorus"].tolist()], "warnings": warnings}
    fluid, info_fluid = fluid_below_level(ct, region, max_hu=fluid_max_hu, threshold_hu=threshold_hu)
    warnings += info_fluid.pop("warnings")
    info.update(info_fluid)
    if info["fluid_voxels"]:
        lo, hi = bounding_box(fluid)
        box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
        region[box] |= fluid[box]  # in the fluid's box only: the rest of region stays untouched zero pages
        side = info["fluid_dependent_side"]
        dense = (f" (dense, median {info['fluid_dense_hu']:.0f} HU: positive oral contrast?)"
                 if info.get("fluid_dense_hu") is not None else "")
        warnings.append(f"retained fluid{dense} below an air-fluid level at {info['fluid_level_text']}"
                        + ("" if side == "posterior" else f", on the {side} wall ("
                           + ("a prone scan" if side == "anterior" else f"the patient on the {side} side") + ")")
                        + f", {info['fluid_ml']:.0f} mL, was added to the lumen; its contents are shown as air "
                        "and the wall is bounded by the lumen")
    for name, (depth, bubble) in joined.items():
        if nearest_true(region, ct, pts[name], SUBMERGED_LEAD_MM) is None:
            raise AnatomyError(f"the {name} point (RAS {ras_text(pts[name])} mm) lies {depth:.0f} mm from gas with "
                               "only water between, but no retained fluid under a flat level of that gas holds it; "
                               "pass a stomach label with --mask, or place the point in the gas-filled lumen")
        warnings.append(f"the {name} point lies under the retained fluid, {depth:.0f} mm from the gas it was joined "
                        "to through the water above it" + ("" if bubble is None else
                                                           ", not to the bubble of {:.2f} mL {:.0f} mm away".format(
                                                               *bubble)))
    if progress is not None:
        progress(1.0)
    return region, info


def lumen_from_mask(mask: np.ndarray, ct: Volume, cardia_lps, pylorus_lps,
                    max_snap_mm: float = 20.0, gas_hu: float | None = None) -> tuple[np.ndarray, dict]:
    """Lumen from a stomach label (bool on ct's grid): its 6-connected component(s) reached by the two LPS points (mm).

    Used in place of :func:`air_region` when the stomach holds no gas. Returns ``(mask, info)`` with the
    same info keys as :func:`air_region` (volume in mL, seeds in LPS mm). With ``gas_hu`` (HU), the label's voxels
    of a gas body lying mostly outside it are left out first (:func:`drop_neighbour_gas`; ``info["neighbour_gas_ml"]``).

    Raises
    ------
    InputError
        If the mask is not on the CT grid.
    AnatomyError
        If the mask is empty.
    PointError
        If a point lies outside the volume or more than ``max_snap_mm`` (mm) from the mask.
    """
    mask = np.asarray(mask, bool)
    if mask.shape != ct.array.shape:
        raise InputError(f"the stomach mask has shape {mask.shape} but the CT {ct.array.shape}; resample the "
                           "mask onto the CT grid")
    if not mask.any():
        raise AnatomyError("the stomach mask is empty on the CT grid; check the label value and that the label "
                           "volume overlaps the CT")
    dropped = 0
    if gas_hu is not None:
        mask, dropped = drop_neighbour_gas(mask, ct, gas_hu)
    seeds = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        seeds.append(snap_to_region(mask, ct, p, max_snap_mm, name))
    # flood on the mask's bounding box only
    lo, hi = bounding_box(mask)
    sub = mask[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    reg = np.zeros_like(sub)
    n_comp = 0
    for s in seeds:
        k, j, i = _voxel(ct, s)
        kji = (k - lo[2], j - lo[1], i - lo[0])
        if reg[kji]:
            continue
        reg |= flood_fill(sub, kji)
        n_comp += 1
    region = np.zeros_like(mask)
    region[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]] = reg
    warnings = []
    if n_comp > 1:
        warnings.append("the cardia and pylorus lie in separate parts of the stomach mask; their union is used")
    ml = float(np.prod(ct.spacing)) / 1000.0
    return region, {"volume_ml": float(np.count_nonzero(reg)) * ml, "neighbour_gas_ml": dropped * ml,
                    "n_components": n_comp, "seeds_lps": [s.tolist() for s in seeds], "warnings": warnings}


#: How far (mm) around a stomach label :func:`drop_neighbour_gas` follows the gas bodies it touches.
NEIGHBOUR_GAS_MARGIN_MM = 15.0


def drop_neighbour_gas(mask: np.ndarray, ct: Volume, gas_hu: float,
                       margin_mm: float = NEIGHBOUR_GAS_MARGIN_MM) -> tuple[np.ndarray, int]:
    """A stomach label (bool on ct's grid) without its voxels of gas bodies (below ``gas_hu`` HU, 6-connected) that
    lie mostly outside it: where an automatic label's edge runs into a bowel loop or lung base beside the stomach.

    The gas is followed within ``margin_mm`` (mm) of the label's bounding box. The stomach's own gas, even where the
    label clips it, lies mostly inside and is kept. Returns (the label, a new array if any voxel was dropped; the
    number of voxels dropped). An empty result keeps the label as given.
    """
    lo, hi = bounding_box(mask, tuple(int(np.ceil(margin_mm / sp)) for sp in ct.spacing))
    box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    sub = np.asarray(mask[box], bool)
    gas = np.asarray(ct.array[box]) < gas_hu
    touched = gas & sub
    if not touched.any():
        return mask, 0
    lab, n = ndimage.label(gas)
    inside = np.bincount(lab[touched], minlength=n + 1)
    total = np.bincount(lab.ravel(), minlength=n + 1)
    drop = inside < 0.5 * total
    drop[0] = False
    cut = sub & drop[lab]
    count = int(np.count_nonzero(cut))
    if count == 0 or count == int(np.count_nonzero(sub)):
        return mask, 0
    out = np.array(mask, bool, copy=True)
    out[box] = sub & ~cut
    return out, count


# ---------------------------------------------------------------------------------------------- wall region
def wall_region(lumen: np.ndarray, spacing, thickness_mm: float = 5.0) -> np.ndarray:
    """Wall shell (bool, lumen's grid): voxels outside the lumen within thickness_mm (mm, Euclidean) of it.

    Distances are between voxel centres with the anisotropic ``spacing`` (i, j, k order, mm); the
    distance transform runs on the lumen's bounding box grown by the thickness only.
    """
    spacing = np.asarray(spacing, float).reshape(3)
    if not thickness_mm > 0:
        raise InputError(f"the wall thickness must be positive, got {thickness_mm} mm")
    lumen = np.asarray(lumen, bool)
    margin = tuple(int(np.ceil(thickness_mm / s)) + 1 for s in spacing)
    lo, hi = bounding_box(lumen, margin)
    sub = lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    dist = distance_mm(~sub, spacing)
    out = np.zeros_like(lumen)
    out[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]] = (~sub) & (dist <= thickness_mm)
    return out
