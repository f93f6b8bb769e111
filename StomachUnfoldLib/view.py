"""The unfolded view as a picture: shaded first-hit rendering of the unfolded volume seen from the viewer.

The viewer looks down -k: for every (i, j) column the first voxel from the top (largest k) above the
tissue threshold is the visible mucosa. Its depth gives a height map shaded with a head-light, its HU a
colour (soft tissue pink, dense markers or contrast yellow-white). i runs left to right (cardia to
pylorus) and j bottom to top, as the viewer sees it.
"""
from __future__ import annotations

import errno
import os

import numpy as np

from .geometry import Volume

__all__ = ["first_hit", "clean_outline", "edge_sharpness", "staircase_smoothing_vox", "surface_height", "ripple_mm",
           "smooth_mucosa_mask", "display_volume", "shade_first_hit", "render_view", "save_png", "write_png",
           "STAIRCASE_SMOOTH_VOX", "SHARPNESS_RAMP", "HEIGHT_SIGMA_MM", "SPIKE_WIDTH_PX"]

#: Gaussian blur (voxels) of the unfolded volume before the surface is located, for data whose air/wall edge
#: is a voxel staircase (a binary lumen: the terraced "wood-grain"); a CT with a scanner's blur gets none.
STAIRCASE_SMOOTH_VOX = 1.25
#: Edge sharpness (:func:`edge_sharpness`) from which the staircase smoothing starts, and where it is full:
#: about 0.4-0.5 for a CT blurred by 0.7-1 voxel, 0.6-0.75 for a binary lumen resampled trilinearly, 1 on its grid.
SHARPNESS_RAMP = (0.5, 0.7)
#: Gaussian blur (mm) of the height map before shading (normalised within the view's outline).
HEIGHT_SIGMA_MM = 0.85
#: Parts of the view narrower than this (pixels) are spikes, not mucosa (:func:`clean_outline`).
SPIKE_WIDTH_PX = 5


def first_hit(unfolded: Volume, threshold_hu: float = -400.0, depth_mm: float = 2.5):
    """First voxel above ``threshold_hu`` (HU) along -k per (j, i) column: returns (k index or -1, surface HU).

    The surface HU is the maximum over ``depth_mm`` below the hit, as a renderer's surface colour
    integrates a little depth; a single sample at the rim of a small dense bead would miss it.
    """
    a = unfolded.array  # (k, j, i)
    above = a > threshold_hu
    rev = above[::-1]
    hit_rev = np.argmax(rev, axis=0)
    any_hit = rev.any(axis=0)
    k = a.shape[0] - 1 - hit_rev
    k = np.where(any_hit, k, -1)
    n = max(1, int(round(depth_mm / float(unfolded.spacing[2]))) + 1)
    hu = np.full(k.shape, -np.inf)
    for dk in range(n):
        kk = np.clip(k - dk, 0, None)
        hu = np.maximum(hu, np.take_along_axis(a, kk[None], axis=0)[0].astype(float))
    hu[k < 0] = np.nan
    return k, hu


def _column_crossing(a: np.ndarray, threshold_hu: float, k: np.ndarray) -> np.ndarray:
    """Sub-voxel height (k index units) where each (j, i) column of ``a`` (k, j, i) first crosses ``threshold_hu`` going down.

    The crossing is searched from the top as in :func:`first_hit`; ``k`` (-1 where none) is that first voxel
    above the threshold, and the height is linearly interpolated between it and the voxel above it.
    """
    kc = np.clip(k, 0, a.shape[0] - 1)
    up = np.clip(kc + 1, 0, a.shape[0] - 1)
    v0 = np.take_along_axis(a, kc[None], 0)[0].astype(float)
    v1 = np.take_along_axis(a, up[None], 0)[0].astype(float)
    frac = np.where((kc + 1 < a.shape[0]) & (v0 > v1), (v0 - threshold_hu) / np.maximum(v0 - v1, 1e-6), 0.0)
    return np.where(k >= 0, k + np.clip(frac, 0.0, 1.0), np.nan)


def _first_above(a: np.ndarray, threshold_hu: float) -> np.ndarray:
    """Index (k) of the first voxel above ``threshold_hu`` from the top of each (j, i) column of ``a`` (k, j, i); -1 if none."""
    rev = (a > threshold_hu)[::-1]
    k = a.shape[0] - 1 - np.argmax(rev, axis=0)
    return np.where(rev.any(axis=0), k, -1)


def clean_outline(hit: np.ndarray, width_px: int = SPIKE_WIDTH_PX) -> np.ndarray:
    """Hit mask (j, i) without the spikes: protrusions narrower than ``width_px`` pixels are dropped.

    A morphological opening by a ``width_px`` x ``width_px`` square removes what no such square fits into
    (lines and specks up to ``width_px - 1`` pixels wide: a sliver of the cut face seen edge-on); the pixels
    of ``hit`` within one pixel of what remains then come back, so the outline keeps its own detail.
    """
    from scipy import ndimage

    if width_px <= 1 or not hit.any():
        return hit.copy()
    opened = ndimage.binary_opening(hit, structure=np.ones((width_px, width_px), bool))
    return hit & ndimage.binary_dilation(opened, structure=np.ones((3, 3), bool))


def edge_sharpness(unfolded: Volume, threshold_hu: float = -400.0, k_hit: np.ndarray | None = None) -> float:
    """Median share (0-1) of the air/wall step taken by the steepest one-voxel rise at the first hit of each column.

    1 for a binary staircase on the output grid, about 0.75 for one resampled trilinearly, 0.5 for an edge
    blurred by 0.7 voxel (a CT), 0.4 at 1 voxel. NaN when too few columns cross a clear step (over 600 HU).
    Every 3rd column in i and j is read; ``k_hit`` is :func:`first_hit`'s k when already known.
    """
    k0 = first_hit(unfolded, threshold_hu)[0] if k_hit is None else k_hit
    a = unfolded.array[:, ::3, ::3]
    k0 = k0[::3, ::3]
    nk = a.shape[0]

    def at(d):
        return np.take_along_axis(a, np.clip(k0 + d, 0, nk - 1)[None], 0)[0].astype(np.float32)

    step = at(-2) - at(2)
    rise = np.max(np.stack([at(d) - at(d + 1) for d in (-1, 0, 1)]), axis=0)
    ok = (k0 >= 2) & (k0 < nk - 2) & (step > 600.0)
    return float(np.median(rise[ok] / step[ok])) if ok.sum() >= 20 else float("nan")


def staircase_smoothing_vox(unfolded: Volume, threshold_hu: float = -400.0, k_hit: np.ndarray | None = None) -> float:
    """Gaussian blur (voxels) :func:`surface_height` applies by default: none for blurred data, up to STAIRCASE_SMOOTH_VOX."""
    r = edge_sharpness(unfolded, threshold_hu, k_hit)
    if not np.isfinite(r):
        return 0.0
    lo, hi = SHARPNESS_RAMP
    return float(STAIRCASE_SMOOTH_VOX * np.clip((r - lo) / (hi - lo), 0.0, 1.0))


def surface_height(unfolded: Volume, threshold_hu: float = -400.0, smooth_mm: float | None = None,
                   height_sigma_mm: float = HEIGHT_SIGMA_MM, clean: bool = True, k_hit: np.ndarray | None = None):
    """Height map (mm along k, NaN off the view) of the visible mucosa and its (j, i) hit mask.

    The columns hit are :func:`first_hit`'s (less the spikes when ``clean``). The height is where the volume,
    smoothed by a Gaussian of ``smooth_mm`` (mm; None: :func:`staircase_smoothing_vox` voxels, i.e. only
    where the data's edge is a voxel staircase, whose iso-surface lies on the voxel faces), crosses
    ``threshold_hu``, linearly interpolated along k; then smoothed by ``height_sigma_mm`` (mm) within the mask.
    ``k_hit``: :func:`first_hit`'s k when already known.
    """
    from scipy import ndimage

    a = unfolded.array
    sp = np.asarray(unfolded.spacing, float)
    k0 = first_hit(unfolded, threshold_hu)[0] if k_hit is None else k_hit
    hit = k0 >= 0
    if clean:
        hit = clean_outline(hit)
    h = _column_crossing(a, threshold_hu, k0)
    sig_vox = (np.full(3, staircase_smoothing_vox(unfolded, threshold_hu, k0)) if smooth_mm is None
               else float(smooth_mm) / sp)[::-1]  # (k, j, i)
    if np.any(sig_vox > 0.05) and hit.any():
        # only the slab of k around the hits matters (a box margin of 3 sigma + 2 voxels)
        r = int(np.ceil(3.0 * sig_vox.max())) + 2
        kk = k0[hit]
        lo, hi = max(int(kk.min()) - r, 0), min(int(kk.max()) + r + 1, a.shape[0])
        s = ndimage.gaussian_filter(a[lo:hi].astype(np.float32), sig_vox, mode="nearest", truncate=3.0)
        ks = _first_above(s, threshold_hu)
        hs = _column_crossing(s, threshold_hu, ks) + lo
        ks = np.where(ks >= 0, ks + lo, -1)
        # the smoothed crossing where it is the same surface (within 2 voxels of the raw one), else the raw one
        same = (ks >= 0) & (np.abs(hs - h) <= 2.0)
        h = np.where(same, hs, h)
    h = h * sp[2]
    if height_sigma_mm > 0 and hit.any():
        w = hit.astype(float)
        f = np.where(hit, h, 0.0)
        sig = height_sigma_mm / sp[1::-1]
        h = ndimage.gaussian_filter(f, sig) / np.maximum(ndimage.gaussian_filter(w, sig), 1e-6)
    return np.where(hit, h, np.nan), hit


def ripple_mm(height: np.ndarray, mask: np.ndarray, spacing_ji=(1.0, 1.0), sigma_mm: float = 2.0) -> float:
    """Ripple of a height map (mm): RMS over ``mask`` of the height minus its Gaussian (``sigma_mm``) low-pass.

    The low-pass is a normalised convolution over the finite heights, so the view's outline adds nothing;
    the high-pass keeps wavelengths up to about 2 pi ``sigma_mm`` (the 1-10 mm band of terraces).
    """
    from scipy import ndimage

    ok = np.isfinite(height)
    f = np.where(ok, height, 0.0)
    sig = sigma_mm / np.asarray(spacing_ji, float)
    low = ndimage.gaussian_filter(f, sig) / np.maximum(ndimage.gaussian_filter(ok.astype(float), sig), 1e-6)
    sel = mask & ok
    return float(np.sqrt(np.mean((height - low)[sel] ** 2))) if sel.any() else float("nan")


def smooth_mucosa_mask(hit: np.ndarray, hu: np.ndarray, spacing_mm: float, edge_mm: float = 5.0,
                       marker_hu: float = 150.0, marker_mm: float = 5.0) -> np.ndarray:
    """(j, i) mask of view pixels at least ``edge_mm`` (mm) inside the outline and ``marker_mm`` from dense (> ``marker_hu`` HU) surface."""
    from scipy import ndimage

    inner = ndimage.distance_transform_edt(np.pad(hit, 1))[1:-1, 1:-1] * spacing_mm > edge_mm
    dense = np.nan_to_num(hu, nan=-1024.0) > marker_hu
    if dense.any():
        inner &= ndimage.distance_transform_edt(~dense) * spacing_mm > marker_mm
    return inner


def display_volume(unfolded: Volume, threshold_hu: float = -400.0) -> Volume:
    """Copy of the unfolded volume (int16 HU) for volume rendering: staircase-smoothed and without the spikes.

    The same two fixes as the shaded view: a Gaussian of :func:`staircase_smoothing_vox` voxels (none on a
    CT's blurred edges, so real detail is kept as it is) and background (-1024 HU) in the columns that
    :func:`clean_outline` drops. Slicer's renderer shades from the volume's own gradient, so its terraces
    are those of the data and no transfer function removes them; ``unfolded.nrrd`` itself stays as sampled.
    """
    from scipy import ndimage

    k0, _ = first_hit(unfolded, threshold_hu)
    hit = k0 >= 0
    drop = hit & ~clean_outline(hit)
    sv = staircase_smoothing_vox(unfolded, threshold_hu, k0)
    a = unfolded.array
    out = (ndimage.gaussian_filter(a.astype(np.float32), sv, mode="nearest", truncate=3.0) if sv > 0.05
           else a.astype(np.float32))
    out[:, drop] = -1024.0
    return unfolded.with_array(np.clip(np.rint(out), -1024, 3071).astype(np.int16))


def shade_first_hit(unfolded: Volume, threshold_hu: float = -400.0, marker_hu: float = 200.0,
                    smooth_mm: float | None = None, height_sigma_mm: float = HEIGHT_SIGMA_MM,
                    clean: bool = True) -> np.ndarray:
    """RGB uint8 image (rows = j from top to bottom reversed, columns = i) of the shaded first-hit view.

    Shading: a head-light on the normals of :func:`surface_height`'s height map (mm); colour: the surface HU
    of :func:`first_hit` (pink soft tissue, yellow above ``marker_hu`` HU). Off the view (and on the spikes
    :func:`clean_outline` removes) the image is black.
    """
    k0, hu = first_hit(unfolded, threshold_hu)
    hgt, hit = surface_height(unfolded, threshold_hu, smooth_mm, height_sigma_mm, clean, k0)
    fill = np.nanmin(hgt) if hit.any() else 0.0
    hgt = np.where(hit, hgt, fill)
    gy, gx = np.gradient(hgt, unfolded.spacing[1], unfolded.spacing[0])
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    light = np.array([-0.35, 0.35, 0.87])
    light /= np.linalg.norm(light)
    lam = np.clip(normal @ light, 0, 1)
    shade = 0.25 + 0.75 * lam
    tissue = np.array([0.93, 0.62, 0.58])
    marker = np.array([1.0, 0.95, 0.45])
    w = np.clip((np.nan_to_num(hu, nan=0.0) - marker_hu + 100.0) / 200.0, 0, 1)[..., None]
    rgb = (tissue * (1 - w) + marker * w) * shade[..., None]
    rgb[~hit] = 0.0
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)[::-1]


def save_png(img: np.ndarray, path: str, spacing=(1.0, 1.0), min_pixels: int = 512) -> str:
    """Write an RGB image (rows top to bottom) of a view with pixel ``spacing`` (mm, i then j) to PNG.

    The image is resampled bilinearly to square pixels, at least ``min_pixels`` wide (small views are enlarged
    for legibility by interpolation, not by repeating pixels).
    """
    from .figure import resize_rgb

    ratio = float(spacing[1]) / float(spacing[0])
    w = max(int(img.shape[1]), int(min_pixels))
    h = max(1, int(round(img.shape[0] * ratio * w / max(img.shape[1], 1))))
    if (h, w) != img.shape[:2]:
        img = np.clip(np.rint(resize_rgb(img, (h, w))), 0, 255).astype(np.uint8)
    return write_png(img, path)


def write_png(img: np.ndarray, path: str) -> str:
    """Write an RGB uint8 image (rows top to bottom) to a PNG file as it is; OSError when it cannot."""
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkIOImage import vtkPNGWriter  # the submodules alone: `import vtk` costs 0.7 s

    h, w = img.shape[:2]
    vimg = vtkImageData()
    vimg.SetDimensions(w, h, 1)
    arr = ns.numpy_to_vtk(np.ascontiguousarray(img[::-1]).reshape(-1, 3), deep=True)
    arr.SetNumberOfComponents(3)
    vimg.GetPointData().SetScalars(arr)
    writer = vtkPNGWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(vimg)
    writer.Write()
    if writer.GetErrorCode() or not os.path.exists(str(path)):
        if _disk_full(writer.GetErrorCode(), str(path), img.nbytes):  # libpng says only "Write Error"
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        raise OSError(f"could not write the PNG {path}: check that its folder exists and is writable")
    return str(path)


def _disk_full(code: int, path: str, nbytes: int) -> bool:
    """Whether a failed write of about ``nbytes`` to ``path`` failed for want of space (VTK's error code, or the
    folder's free space)."""
    import shutil

    from vtkmodules.vtkCommonMisc import vtkErrorCode

    if code == vtkErrorCode.OutOfDiskSpaceError:
        return True
    try:
        return shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free < nbytes + (1 << 16)
    except OSError:
        return False


def render_view(unfolded: Volume, path: str, threshold_hu: float = -400.0, min_pixels: int = 512) -> str:
    """Write the shaded first-hit view of the unfolded volume to a PNG (upscaled to at least ``min_pixels`` wide)."""
    return save_png(shade_first_hit(unfolded, threshold_hu), path, unfolded.spacing, min_pixels)
