"""Automatic judging of an unfolded volume by casting rays down -k, as the viewer sees it.

Works from the unfolded volume alone (HU array and geometry): ``layer_runs`` counts separate tissue layers
along each viewing ray (more than one: a wall layer lies over another), ``visible_markers`` finds dense
markers (e.g. the phantom's numbered beads, HU above ``marker_hu``) in the first-hit image. Given the
true marker positions mapped into the unfolded frame, ``marker_report`` says which are seen where.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .geometry import Volume
from .view import first_hit

__all__ = ["layer_runs", "overlap_fraction", "visible_markers", "marker_report"]


def layer_runs(unfolded: Volume, threshold_hu: float = -400.0, min_gap_mm: float = 1.5) -> np.ndarray:
    """Number of separate tissue runs (HU > threshold) along -k per (j, i) column; gaps under min_gap_mm merge."""
    a = unfolded.array > threshold_hu
    gap = max(1, int(round(min_gap_mm / unfolded.spacing[2])))
    if gap > 1:
        a = ndimage.binary_closing(a, structure=np.ones((gap + 1, 1, 1), bool), border_value=0) | a
    starts = a[1:] & ~a[:-1]
    return starts.sum(axis=0) + a[0].astype(int)


def overlap_fraction(unfolded: Volume, threshold_hu: float = -400.0, min_gap_mm: float = 1.5,
                     min_patch: int = 2) -> float:
    """Fraction of the seen area (columns with any tissue) where more than one wall layer lies on the ray.

    Isolated columns (patches narrower than ``min_patch`` pixels, e.g. one-voxel rasterisation pinholes)
    are ignored: a real fold covers an area. ``min_patch=1`` counts every column.
    """
    runs = layer_runs(unfolded, threshold_hu, min_gap_mm)
    seen = runs > 0
    over = runs > 1
    if min_patch > 1:
        over = ndimage.binary_opening(over, structure=np.ones((min_patch, min_patch), bool))
    return float(over[seen].mean()) if seen.any() else 0.0


def visible_markers(unfolded: Volume, marker_hu: float = 200.0, threshold_hu: float = -400.0,
                    min_area_mm2: float = 2.0, merge_mm: float = 2.0):
    """Markers seen from the viewer: connected regions of the first-hit image with HU above marker_hu.

    Pieces of one marker split by a crease narrower than ``merge_mm`` count as one region.

    Returns a list of dicts with the region's centre in the unfolded volume's LPS frame (mm, at the hit
    depth), its (i, j) index centre and area in mm^2.
    """
    k, hu = first_hit(unfolded, threshold_hu)
    dense = np.nan_to_num(hu, nan=-2000.0) > marker_hu
    r = max(1, int(round(0.5 * merge_mm / float(min(unfolded.spacing[:2])))))
    joined = ndimage.binary_dilation(dense, structure=np.ones((2 * r + 1, 2 * r + 1), bool))
    lab, n = ndimage.label(joined, structure=np.ones((3, 3), bool))
    lab = np.where(dense, lab, 0)
    out = []
    px = float(unfolded.spacing[0] * unfolded.spacing[1])
    for idx, sl in enumerate(ndimage.find_objects(lab), start=1):
        m = lab[sl] == idx
        area = m.sum() * px
        if area < min_area_mm2:
            continue
        jj, ii = np.nonzero(m)
        jj = jj + sl[0].start
        ii = ii + sl[1].start
        kk = k[jj, ii]
        centre = np.array([ii.mean(), jj.mean(), kk.mean()])
        out.append({"index_ijk": centre.tolist(), "lps": unfolded.index_to_lps(centre[None])[0].tolist(),
                    "area_mm2": float(area)})
    return out


def marker_report(unfolded: Volume, markers_unfolded_lps: dict, marker_hu: float = 200.0,
                  tolerance_mm: float = 4.0) -> dict:
    """Which true markers (id -> LPS in the unfolded frame, NaN if unmapped) are seen, and the in-plane error (mm).

    A marker is seen when a visible marker region lies within ``tolerance_mm`` of its mapped position in the
    (i, j) plane of the view.
    """
    seen = visible_markers(unfolded, marker_hu)
    centres = np.array([s["index_ijk"][:2] for s in seen]) * unfolded.spacing[:2] if seen else np.zeros((0, 2))
    res = {}
    for mid, p in markers_unfolded_lps.items():
        p = np.asarray(p, float)
        if not np.all(np.isfinite(p)):
            res[mid] = {"seen": False, "error_mm": None, "mapped": False}
            continue
        ij = unfolded.lps_to_index(p[None])[0][:2] * unfolded.spacing[:2]
        if len(centres):
            dist = np.linalg.norm(centres - ij[None], axis=1)
            best = float(dist.min())
        else:
            best = np.inf
        res[mid] = {"seen": bool(best <= tolerance_mm), "error_mm": (best if np.isfinite(best) else None),
                    "mapped": True}
    return {"markers": res, "n_seen": int(sum(r["seen"] for r in res.values())), "n_total": len(res),
            "n_regions": len(seen)}
