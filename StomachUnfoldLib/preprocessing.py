"""Preprocessing (Oda et al., Sec. 2.1): the stomach air region and the stomach wall region.

The air region is the set of voxels below an HU threshold connected to where the cardia and pylorus
points are; air outside the body (touching the side faces of the volume) and air not reached from the
points (lungs, colon) is left out. With a stomach label volume (``--mask``) the label replaces the
threshold. The wall region is the shell of tissue within a given thickness (mm) outside the lumen.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .errors import AnatomyError, PointError
from .geometry import Volume, lps_to_ras

__all__ = ["snap_to_region", "air_region", "lumen_from_mask", "wall_region", "bounding_box"]


def bounding_box(mask: np.ndarray, margin_vox=(0, 0, 0)):
    """Index box (lo, hi) in (i, j, k) order, hi exclusive, of the True voxels of ``mask[k, j, i]`` grown by a margin."""
    if not mask.any():
        raise AnatomyError("the stomach region is empty")
    lo, hi = [], []
    for axis_arr in range(3):
        other = tuple(a for a in range(3) if a != axis_arr)
        idx = np.flatnonzero(mask.any(axis=other))
        lo.append(int(idx[0]))
        hi.append(int(idx[-1]) + 1)
    lo_ijk = np.array(lo[::-1]) - np.asarray(margin_vox, int)
    hi_ijk = np.array(hi[::-1]) + np.asarray(margin_vox, int)
    size = np.array(mask.shape[::-1])
    return np.clip(lo_ijk, 0, size), np.clip(hi_ijk, 0, size)


def _ras_text(p_lps) -> str:
    return str(np.round(lps_to_ras(np.asarray(p_lps, float)), 1).tolist())


def snap_to_region(mask: np.ndarray, volume: Volume, point_lps, max_distance_mm: float = 20.0,
                   name: str = "point") -> np.ndarray:
    """LPS centre (mm) of the True voxel of ``mask`` nearest to ``point_lps``, searched within max_distance_mm."""
    p = np.asarray(point_lps, float).reshape(3)
    if not volume.contains_lps(p[None])[0]:
        lo, hi = volume.bounds_lps()
        raise PointError(f"the {name} point (RAS {_ras_text(p)} mm) lies outside the volume (LPS bounds "
                         f"{np.round(lo, 1).tolist()} to {np.round(hi, 1).tolist()})")
    ijk = volume.lps_to_index(p[None])[0]
    r = np.ceil(max_distance_mm / volume.spacing).astype(int) + 1
    size = np.array(volume.size)
    lo = np.clip(np.floor(ijk).astype(int) - r, 0, size)
    hi = np.clip(np.ceil(ijk).astype(int) + r + 1, 0, size)
    sub = mask[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    kk, jj, ii = np.nonzero(sub)
    if len(ii) == 0:
        return None
    cand = np.stack([ii + lo[0], jj + lo[1], kk + lo[2]], axis=1).astype(float)
    pts = volume.index_to_lps(cand)
    d = np.linalg.norm(pts - p, axis=1)
    best = int(np.argmin(d))
    if d[best] > max_distance_mm:
        return None
    return pts[best]


def _side_faces(volume: Volume):
    """Array axes (of k, j, i) whose faces are the body's sides: all but the one closest to superior-inferior."""
    si_axis_ijk = int(np.argmax(np.abs(volume.direction[2, :])))  # column with the largest S component
    si_axis_arr = 2 - si_axis_ijk
    return [a for a in range(3) if a != si_axis_arr]


def _touches_faces(mask: np.ndarray, axes) -> bool:
    for a in axes:
        if np.take(mask, 0, axis=a).any() or np.take(mask, mask.shape[a] - 1, axis=a).any():
            return True
    return False


def air_region(ct: Volume, cardia_lps, pylorus_lps, threshold_hu: float = -500.0, max_snap_mm: float = 20.0,
               progress=None):
    """Stomach air region (bool mask on ct's grid): air below threshold_hu (HU) 6-connected to the two points.

    Returns ``(mask, info)`` with info "volume_ml", "n_components", "seeds_lps", "warnings".
    """
    from skimage.morphology import flood

    air = ct.array < threshold_hu
    if progress is not None:
        progress(0.2)
    seeds = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        s = snap_to_region(air, ct, p, max_snap_mm, name)
        if s is None:
            raise AnatomyError(f"no air (below {threshold_hu:g} HU) within {max_snap_mm:g} mm of the {name} point "
                               f"(RAS {_ras_text(p)} mm): the stomach holds no gas there; pass a stomach label "
                               "with --mask, or place the point in the gas-filled lumen")
        seeds.append(s)
    faces = _side_faces(ct)
    region = np.zeros_like(air)
    n_comp = 0
    warnings = []
    for name, s in zip(("cardia", "pylorus"), seeds):
        ijk = np.rint(ct.lps_to_index(s[None])[0]).astype(int)
        if region[ijk[2], ijk[1], ijk[0]]:
            continue
        comp = flood(air, (ijk[2], ijk[1], ijk[0]), connectivity=1)
        if _touches_faces(comp, faces):
            raise AnatomyError(f"the air reached from the {name} point touches the side of the volume: the point is "
                               "probably in the air outside the body; place it inside the stomach")
        vol_ml = comp.sum() * float(np.prod(ct.spacing)) / 1000.0
        if vol_ml > 4000.0:
            raise AnatomyError(f"the air reached from the {name} point is {vol_ml:.0f} mL, too large for a stomach: "
                               "the point is probably in a lung or the air leaks into the bowel; move the point "
                               "or pass a stomach label with --mask")
        region |= comp
        n_comp += 1
        if progress is not None:
            progress(0.5 + 0.5 * n_comp / 2)
    if n_comp == 2:
        warnings.append("the cardia and pylorus reach separate air pockets; both are used as the stomach lumen")
    info = {"volume_ml": float(region.sum() * np.prod(ct.spacing) / 1000.0), "n_components": n_comp,
            "seeds_lps": [s.tolist() for s in seeds], "warnings": warnings}
    return region, info


def lumen_from_mask(mask: np.ndarray, ct: Volume, cardia_lps, pylorus_lps, max_snap_mm: float = 20.0):
    """Lumen from a stomach label: the mask's connected component(s) reached by the two points; returns (mask, info)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise AnatomyError("the stomach mask is empty on the CT grid; check the label value and that the label "
                           "volume overlaps the CT")
    lab, n = ndimage.label(mask)
    keep = np.zeros(n + 1, bool)
    seeds = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        s = snap_to_region(mask, ct, p, max_snap_mm, name)
        if s is None:
            raise PointError(f"the {name} point (RAS {_ras_text(p)} mm) is more than {max_snap_mm:g} mm from the "
                             "stomach mask; place it in or on the stomach")
        ijk = np.rint(ct.lps_to_index(s[None])[0]).astype(int)
        keep[lab[ijk[2], ijk[1], ijk[0]]] = True
        seeds.append(s)
    keep[0] = False
    region = keep[lab]
    warnings = []
    if keep.sum() > 1:
        warnings.append("the cardia and pylorus lie in separate parts of the stomach mask; both are used")
    return region, {"volume_ml": float(region.sum() * np.prod(ct.spacing) / 1000.0),
                    "n_components": int(keep.sum()), "seeds_lps": [s.tolist() for s in seeds],
                    "warnings": warnings}


def wall_region(lumen: np.ndarray, spacing, thickness_mm: float = 5.0) -> np.ndarray:
    """Wall shell: voxels outside the lumen within thickness_mm (Euclidean, anisotropic spacing) of it."""
    spacing = np.asarray(spacing, float)
    margin = tuple(int(np.ceil(thickness_mm / s)) + 1 for s in spacing)
    lo, hi = bounding_box(lumen, margin)
    sub = lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    dist = ndimage.distance_transform_edt(~sub, sampling=spacing[::-1])
    out = np.zeros_like(lumen)
    out[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]] = (dist > 0) & (dist <= thickness_mm)
    return out
