"""Marker metrics for phantoms with known truth: which markers a view shows, where, and pairwise distortion.

Markers are dense beads (HU above ``marker_hu``) on the phantom's mucosa; ``visible_markers`` finds them in
the view's first-hit image, ``marker_report`` matches them to the true markers mapped into the view (LPS mm of
the unfolded volume), ``marker_metrics`` adds the position error and the pairwise distance distortion (2D
distance in the view against the geodesic distance on the original mucosa).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.quality import mucosa_points
from StomachUnfoldLib.view import first_hit

__all__ = ["visible_markers", "marker_report", "marker_metrics", "family_marker_metrics"]


def visible_markers(unfolded: Volume, marker_hu: float = 200.0, threshold_hu: float = -400.0,
                    min_area_mm2: float = 2.0, merge_mm: float = 2.0):
    """Markers seen from the viewer: connected regions of the first-hit image with HU above marker_hu.

    Pieces of one marker split by a crease narrower than ``merge_mm`` count as one region.

    Returns a list of dicts with the region's centre in the unfolded volume's LPS frame (mm, at the hit
    depth), its (i, j) index centre and area in mm^2.
    """
    return _marker_regions(unfolded, marker_hu, threshold_hu, min_area_mm2, merge_mm)[1]


def _marker_regions(unfolded: Volume, marker_hu: float = 200.0, threshold_hu: float = -400.0,
                    min_area_mm2: float = 2.0, merge_mm: float = 2.0):
    """(label image (j, i): each kept region's dense pixels numbered from 1 in the order of the list, 0 elsewhere;
    the list of :func:`visible_markers`)."""
    k, hu = first_hit(unfolded, threshold_hu)
    dense = np.nan_to_num(hu, nan=-2000.0) > marker_hu
    r = max(1, int(round(0.5 * merge_mm / float(min(unfolded.spacing[:2])))))
    joined = ndimage.binary_dilation(dense, structure=np.ones((2 * r + 1, 2 * r + 1), bool))
    lab, n = ndimage.label(joined, structure=np.ones((3, 3), bool))
    lab = np.where(dense, lab, 0)
    out = []
    kept = np.zeros(lab.shape, np.int32)
    px = float(unfolded.spacing[0] * unfolded.spacing[1])
    for idx, sl in enumerate(ndimage.find_objects(lab), start=1):
        m = lab[sl] == idx
        area = m.sum() * px
        if area < min_area_mm2:
            continue
        kept[sl][m] = len(out) + 1
        jj, ii = np.nonzero(m)
        jj = jj + sl[0].start
        ii = ii + sl[1].start
        kk = k[jj, ii]
        centre = np.array([ii.mean(), jj.mean(), kk.mean()])
        out.append({"index_ijk": centre.tolist(), "lps": unfolded.index_to_lps(centre[None])[0].tolist(),
                    "area_mm2": float(area)})
    return kept, out


def marker_report(unfolded: Volume, markers_unfolded_lps: dict, marker_hu: float = 200.0,
                  tolerance_mm: float = 4.0) -> dict:
    """Which true markers (id -> LPS in the unfolded frame, NaN if unmapped) are seen, and the in-plane error (mm).

    A marker is seen when a visible marker region lies within ``tolerance_mm`` of its mapped position in the
    (i, j) plane of the view. A marker not seen gets ``missed``, by what the view shows within ``tolerance_mm`` of
    its mapped position: "merged" (a pixel of a region that also lies within ``tolerance_mm`` of another marker's
    place, or is over MERGED_AREA_FACTOR times the median region's area: the bead joined to another bead or to dense
    tissue, the region's centre between them), "off" (a pixel of a lone bead-sized region whose centre lies
    farther), "not shown" (no pixel of any region) or "unmapped" (no place on the view).
    ``missed_counts`` sums them.
    """
    lab, seen = _marker_regions(unfolded, marker_hu)
    centres = np.array([s["index_ijk"][:2] for s in seen]) * unfolded.spacing[:2] if seen else np.zeros((0, 2))
    res, near = {}, {}
    for mid, p in markers_unfolded_lps.items():
        p = np.asarray(p, float)
        if not np.all(np.isfinite(p)):
            res[mid] = {"seen": False, "error_mm": None, "mapped": False, "missed": "unmapped"}
            continue
        ij = unfolded.lps_to_index(p[None])[0][:2] * unfolded.spacing[:2]
        if len(centres):
            dist = np.linalg.norm(centres - ij[None], axis=1)
            best = float(dist.min())
        else:
            best = np.inf
        res[mid] = {"seen": bool(best <= tolerance_mm), "error_mm": (best if np.isfinite(best) else None),
                    "mapped": True}
        near[mid] = _regions_near(lab, ij, unfolded.spacing[:2], tolerance_mm)
    big = MERGED_AREA_FACTOR * float(np.median([r["area_mm2"] for r in seen])) if seen else np.inf
    for mid, r in res.items():
        if r["seen"] or not r["mapped"]:
            continue
        shared = any(near[mid] & ids for other, ids in near.items() if other != mid)
        r["missed"] = ("not shown" if not near[mid] else
                       "merged" if shared or any(seen[i - 1]["area_mm2"] > big for i in near[mid]) else "off")
    counts = {r: sum(x.get("missed") == r for x in res.values()) for r in MISS_REASONS}
    return {"markers": res, "n_seen": int(sum(r["seen"] for r in res.values())), "n_total": len(res),
            "n_regions": len(seen), "missed_counts": counts}


#: why a marker was not seen (see :func:`marker_report`)
MISS_REASONS = ("merged", "off", "not shown", "unmapped")
#: a region over this many times the median region's area holds more than one bead (or a bead and dense tissue)
MERGED_AREA_FACTOR = 2.0


def _regions_near(lab: np.ndarray, ij_mm: np.ndarray, spacing_ij, tolerance_mm: float) -> set:
    """Ids of the regions of the label image of :func:`_marker_regions` with a pixel within tolerance_mm of ij_mm
    (mm in the view's (i, j) plane)."""
    si, sj = float(spacing_ij[0]), float(spacing_ij[1])
    ci, cj = ij_mm[0] / si, ij_mm[1] / sj
    ri, rj = int(np.ceil(tolerance_mm / si)), int(np.ceil(tolerance_mm / sj))
    j0, j1 = max(0, int(np.floor(cj)) - rj), min(lab.shape[0], int(np.ceil(cj)) + rj + 1)
    i0, i1 = max(0, int(np.floor(ci)) - ri), min(lab.shape[1], int(np.ceil(ci)) + ri + 1)
    if j0 >= j1 or i0 >= i1:
        return set()
    jj, ii = np.mgrid[j0:j1, i0:i1]
    win = lab[j0:j1, i0:i1]
    inside = (((ii - ci) * si) ** 2 + ((jj - cj) * sj) ** 2 <= tolerance_mm ** 2) & (win > 0)
    return {int(x) for x in np.unique(win[inside])}


def _densify(polyline: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` mm along a polyline."""
    p = np.asarray(polyline, float)
    out = [p[:1]]
    for a, b in zip(p[:-1], p[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(out)


def marker_metrics(result, marker_lps: dict) -> dict:
    """Marker visibility, position error (mm) and pairwise distance distortion (view 2D vs geodesic on the mucosa)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    vol = result.unfolded
    mapped = result.map_landmarks(marker_lps)
    rep = marker_report(vol, mapped)
    ids = [k for k in marker_lps if np.all(np.isfinite(mapped[k]))]
    out = {"seen": rep["n_seen"], "total": rep["n_total"], "missed": rep["missed_counts"],
           "position_error_mm_mean": float(np.mean([r["error_mm"] for r in rep["markers"].values()
                                                    if r["error_mm"] is not None] or [np.nan]))}
    if len(ids) >= 2 and result.lumen_crop is not None:
        # geodesic distances over the original mucosa: a graph of inner-wall voxels (neighbours within 1.8
        # voxels), with the voxels along the incision removed so that no path crosses the cut
        from scipy.spatial import cKDTree

        pts = mucosa_points(result.lumen_crop, result.centerline_lps, max_points=60000)
        cut_r = float(np.max(result.lumen_crop.spacing)) * 2.0
        d_cut, _ = cKDTree(_densify(result.incision_lps, 0.5)).query(pts)
        pts = pts[d_cut > cut_r]
        tree = cKDTree(pts)
        pairs = tree.query_pairs(1.8 * float(np.max(result.lumen_crop.spacing)), output_type="ndarray")
        w = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
        n = len(pts)
        G = coo_matrix((np.r_[w, w], (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                       shape=(n, n)).tocsr()
        src = tree.query(np.array([marker_lps[k] for k in ids]))[1]
        D = dijkstra(G, indices=src)[:, src]
        P = np.array([vol.lps_to_index(np.asarray(mapped[k])[None])[0][:2] * vol.spacing[:2] for k in ids])
        d2 = np.linalg.norm(P[:, None] - P[None], axis=2)
        iu = np.triu_indices(len(ids), 1)
        g = D[iu]
        fin = np.isfinite(g) & (g > 1e-6)
        ratio = d2[iu][fin] / g[fin]
        out["pairwise_distance_ratio_median"] = float(np.median(ratio)) if len(ratio) else None
        out["pairwise_distance_distortion"] = float(np.median(np.abs(np.log(ratio)))) if len(ratio) else None
    return out


def family_marker_metrics(result, truth: dict, pair_min_mm: float = 10.0, pair_max_mm: float = 80.0) -> dict:
    """Markers of a drawn stomach (StomachUnfoldEval.random_stomach truth): seen per region, and the pairwise
    distortion of the view against the true geodesics (cut along the greater curvature) and the flat-layout bound.

    Distances are mm; the distortion is the median over marker pairs with a true geodesic of 10-80 mm of
    |log(view distance / geodesic)|, as ``flat_bound`` defines it. ``length_error_mm`` is view minus true distance
    over pairs 10-30 mm apart (a lesion-sized measurement), mean and standard deviation.
    """
    from .flat_bound import flat_layout_bound, pairwise_distortion

    vol = result.unfolded
    ids = [m["id"] for m in truth["markers"]]
    mapped = result.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]})
    rep = marker_report(vol, mapped)
    G = np.array(truth["geodesic_cut_mm"], float)
    xy = np.array([vol.lps_to_index(np.asarray(mapped[k], float)[None])[0][:2] * vol.spacing[:2] for k in ids])
    view = pairwise_distortion(xy, G, pair_min_mm, pair_max_mm)
    bound = flat_layout_bound(G, pair_min_mm, pair_max_mm)
    by_region: dict = {}
    for m in truth["markers"]:
        key = "under_fluid" if m.get("under_fluid") else m.get("region", "other")
        seen = bool(rep["markers"][m["id"]]["seen"])
        r = by_region.setdefault(key, [0, 0])
        r[0] += seen
        r[1] += 1
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    iu = np.triu_indices(len(ids), 1)
    g, v = G[iu], d[iu]
    lesion = np.isfinite(g) & np.isfinite(v) & (g >= 10.0) & (g <= 30.0)
    err = v[lesion] - g[lesion]
    med = view.get("median_relative_error")
    b = bound.get("median_relative_error")
    return {"seen": rep["n_seen"], "total": rep["n_total"], "missed": rep["missed_counts"], "by_region": by_region,
            "pairwise_distance_distortion": med, "flat_bound": b,
            "ratio_to_bound": (med / b) if (med is not None and b) else None,
            "pairs": view.get("n_pairs"),
            "length_error_mm": {"mean": float(np.mean(err)) if len(err) else None,
                                "sd": float(np.std(err)) if len(err) else None, "pairs": int(len(err))}}
