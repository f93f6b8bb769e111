"""The unfolded view as a picture: shaded first-hit rendering of the unfolded volume seen from the viewer.

The viewer looks down -k: for every (i, j) column the first voxel from the top (largest k) above the
tissue threshold is the visible mucosa. Its depth gives a height map shaded with a head-light, its HU a
colour (soft tissue pink, dense markers or contrast yellow-white). i runs left to right (cardia to
pylorus) and j bottom to top, as the viewer sees it.
"""
from __future__ import annotations

import os

import numpy as np

from .geometry import Volume

__all__ = ["first_hit", "shade_first_hit", "render_view", "save_png"]


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


def shade_first_hit(unfolded: Volume, threshold_hu: float = -400.0, marker_hu: float = 200.0) -> np.ndarray:
    """RGB uint8 image (rows = j from top to bottom reversed, columns = i) of the shaded first-hit view."""
    k, hu = first_hit(unfolded, threshold_hu)
    hit = k >= 0
    # sub-voxel depth: where the profile crosses the threshold between the hit voxel and the one above
    a = unfolded.array
    kc = np.clip(k, 0, a.shape[0] - 1)
    above = np.clip(kc + 1, 0, a.shape[0] - 1)
    v0 = np.take_along_axis(a, kc[None], 0)[0].astype(float)
    v1 = np.take_along_axis(a, above[None], 0)[0].astype(float)
    frac = np.where((kc + 1 < a.shape[0]) & (v0 > v1), (v0 - threshold_hu) / np.maximum(v0 - v1, 1e-6), 0.0)
    height = np.where(hit, (k + np.clip(frac, 0, 1)) * unfolded.spacing[2], np.nan)
    fill = np.nanmin(height) if hit.any() else 0.0
    hgt = np.where(hit, height, fill)
    from scipy import ndimage

    hgt = ndimage.gaussian_filter(hgt, 0.7)
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
    """Write an RGB image (rows top to bottom) of a view with pixel ``spacing`` (mm, i then j) to PNG, upscaled."""
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkIOImage import vtkPNGWriter  # the submodules alone: `import vtk` costs 0.7 s

    # resample to square pixels, then upscale small views for legibility
    ratio = float(spacing[1]) / float(spacing[0])
    rows = max(1, int(round(img.shape[0] * ratio)))
    ri = np.clip((np.arange(rows) / ratio).astype(int), 0, img.shape[0] - 1)
    img = img[ri]
    f = max(1, int(np.ceil(min_pixels / max(img.shape[1], 1))))
    img = np.repeat(np.repeat(img, f, axis=0), f, axis=1)
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
        raise OSError(f"could not write the PNG {path}: check that its folder exists and is writable")
    return str(path)


def render_view(unfolded: Volume, path: str, threshold_hu: float = -400.0, min_pixels: int = 512) -> str:
    """Write the shaded first-hit view of the unfolded volume to a PNG (upscaled to at least ``min_pixels`` wide)."""
    return save_png(shade_first_hit(unfolded, threshold_hu), path, unfolded.spacing, min_pixels)
