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

__all__ = ["layer_runs", "overlap_fraction", "visible_points", "visible_markers", "marker_report"]


def layer_runs(unfolded: Volume, threshold_hu: float = -400.0, min_gap_mm: float = 1.5) -> np.ndarray:
    """Number of separate tissue runs (HU > threshold) along -k per (j, i) column; gaps under min_gap_mm merge."""
    a = unfolded.array > threshold_hu
    n = int(np.ceil(min_gap_mm / float(unfolded.spacing[2]) - 1e-9)) - 1  # gaps of up to n voxels are under min_gap_mm
    if n >= 1:
        a = ndimage.binary_closing(a, structure=np.ones((n + 1, 1, 1), bool), border_value=0) | a
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


# ------------------------------------------------------------------------------------------------ metrics
GRADE_THRESHOLDS = {
    # fraction of the mucosa NOT visible from the viewer, and number of failure parts (overlap, broken, bent)
    "excellent": {"max_hidden": 0.02, "max_failure_parts": 0},
    "good": {"max_hidden": 0.30, "max_failure_parts": 1},
    "fair": {"max_hidden": 0.50},
    # bad: more than 50 % hidden
}


def inner_surface_triangles(model) -> np.ndarray:
    """Triangles (T,3 vertex ids) of the model's inner surface: cell faces whose four vertices are all in S_vi."""
    from .wall_model import _FACES

    tris = []
    for _, local in _FACES:
        q = model.hexes[:, list(local)]
        ok = model.inner[q].all(axis=1)
        q = q[ok]
        tris.append(q[:, [0, 1, 2]])
        tris.append(q[:, [0, 2, 3]])
    t = np.vstack(tris)
    return np.unique(np.sort(t, axis=1), axis=0)


def surface_distortion(rest: np.ndarray, deformed: np.ndarray, tris: np.ndarray) -> dict:
    """Area and angle distortion of surface triangles (per-triangle 2D Jacobian singular values s1 >= s2)."""
    def frame(p):
        e1 = p[:, 1] - p[:, 0]
        e2 = p[:, 2] - p[:, 0]
        n = np.cross(e1, e2)
        area = 0.5 * np.linalg.norm(n, axis=1)
        u = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
        w = np.cross(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12), u)
        return np.stack([np.einsum("ij,ij->i", e1, u), np.einsum("ij,ij->i", e1, w),
                         np.einsum("ij,ij->i", e2, u), np.einsum("ij,ij->i", e2, w)], 1).reshape(-1, 2, 2), area

    A, a0 = frame(rest[tris])
    B, a1 = frame(deformed[tris])
    ok = (a0 > 1e-9) & (a1 > 1e-9)
    J = np.einsum("nij,njk->nik", np.transpose(B[ok], (0, 2, 1)), np.linalg.inv(np.transpose(A[ok], (0, 2, 1))))
    s = np.linalg.svd(J, compute_uv=False)
    area_ratio = s[:, 0] * s[:, 1]
    conformal = s[:, 0] / np.maximum(s[:, 1], 1e-12)
    w = a0[ok] / a0[ok].sum()
    return {"area_distortion": float(np.sum(w * np.abs(np.log(np.maximum(area_ratio, 1e-6))))),
            "angle_distortion": float(np.sum(w * (conformal - 1.0))),
            "area_ratio_p5_p95": [float(np.percentile(area_ratio, 5)), float(np.percentile(area_ratio, 95))],
            "triangles": int(ok.sum())}


def mucosa_points(lumen_crop: Volume, centerline_lps: np.ndarray | None = None, max_points: int = 8000,
                  seed: int = 0) -> np.ndarray:
    """LPS points (mm) on the original inner wall (lumen voxels touching non-lumen) between the cardia and pylorus.

    With the centreline, points beyond the planes through its end points (the openings the method trims)
    are left out.
    """
    lum = lumen_crop.array.astype(bool)
    edge = lum & ~ndimage.binary_erosion(lum, border_value=1)
    pts = lumen_crop.voxel_lps(edge)
    if centerline_lps is not None and len(centerline_lps) > 2:
        from scipy.spatial import cKDTree

        cl = np.asarray(centerline_lps, float)
        _, k = cKDTree(cl).query(pts)
        t0, t1 = cl[1] - cl[0], cl[-1] - cl[-2]
        beyond = ((k == 0) & ((pts - cl[0]) @ t0 < 0)) | ((k == len(cl) - 1) & ((pts - cl[-1]) @ t1 > 0))
        pts = pts[~beyond]
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    return pts


def visible_points(vol: Volume, mapped_lps: np.ndarray, k_hit: np.ndarray) -> np.ndarray:
    """Which points mapped into the unfolded volume (LPS mm) are the first tissue their ray down -k meets (k_hit from first_hit)."""
    mapped_lps = np.asarray(mapped_lps, float).reshape(-1, 3)
    vis = np.zeros(len(mapped_lps), bool)
    ok = np.all(np.isfinite(mapped_lps), axis=1)
    ijk = vol.lps_to_index(mapped_lps[ok])
    ii = np.rint(ijk[:, 0]).astype(int)
    jj = np.rint(ijk[:, 1]).astype(int)
    inside = (ii >= 0) & (ii < vol.array.shape[2]) & (jj >= 0) & (jj < vol.array.shape[1])
    tol = max(2.0, 2.5 / float(vol.spacing[2]))  # voxels along k: 2 voxels or 2.5 mm
    seen = np.zeros(len(ijk), bool)
    seen[inside] = np.abs(k_hit[jj[inside], ii[inside]] - ijk[inside, 2]) <= tol
    vis[ok] = seen
    return vis


def quality_metrics(result, marker_lps: dict | None = None, threshold_hu: float = -400.0) -> dict:
    """All automatic quality metrics of an UnfoldResult (needs its lumen_crop), plus marker metrics if given."""
    vol = result.unfolded
    k_hit, _ = first_hit(vol, threshold_hu)
    seen = k_hit >= 0
    # visible fraction: mucosa points mapped into the view whose column's first hit is at their depth
    pts = mucosa_points(result.lumen_crop, result.centerline_lps)
    mapped = result.correspondence.to_unfolded(pts) if len(pts) else np.zeros((0, 3))
    ok = np.all(np.isfinite(mapped), axis=1)
    visible_fraction = float(visible_points(vol, mapped, k_hit).sum() / max(len(pts), 1))
    # overlapping: two layers on a ray; inverted cells of the model
    runs = layer_runs(vol, threshold_hu)
    over = ndimage.binary_opening(runs > 1, structure=np.ones((2, 2), bool))
    from .unfolded_volume import hex_to_tets, tet_inverse

    tets, hid = hex_to_tets(result.hexes)
    _, _, v0 = tet_inverse(result.rest_vertices, tets)
    _, _, v1 = tet_inverse(result.deformed_vertices, tets)
    inverted = np.sign(v0) != np.sign(v1)
    # broken: over-stretched springs (edges longer than 1.5x) and holes inside the view's outline
    edges = np.unique(np.sort(result.hexes[:, [0, 1, 1, 2, 2, 3, 3, 0, 4, 5, 5, 6, 6, 7, 7, 4, 0, 4, 1, 5, 2, 6, 3, 7]]
                              .reshape(-1, 2), axis=1), axis=0)
    l0 = np.linalg.norm(result.rest_vertices[edges[:, 0]] - result.rest_vertices[edges[:, 1]], axis=1)
    l1 = np.linalg.norm(result.deformed_vertices[edges[:, 0]] - result.deformed_vertices[edges[:, 1]], axis=1)
    stretched = l1 > 1.5 * l0
    holes = ndimage.binary_fill_holes(seen) & ~seen
    # bending: distance of the mucosa from its best plane, normal deviation from +k
    h = np.where(seen, k_hit * vol.spacing[2], np.nan)
    jj_s, ii_s = np.nonzero(seen)
    if len(ii_s) > 3:
        X = np.stack([ii_s * vol.spacing[0], jj_s * vol.spacing[1], np.ones(len(ii_s))], 1)
        coef, *_ = np.linalg.lstsq(X, h[seen], rcond=None)
        resid = h[seen] - X @ coef
        plane_rms = float(np.sqrt(np.mean(resid ** 2)))
        hs = ndimage.gaussian_filter(np.where(seen, h, np.nanmean(h)), 2.0)
        gy, gx = np.gradient(hs, vol.spacing[1], vol.spacing[0])
        tilt = np.degrees(np.arctan(np.hypot(gx, gy)))[seen]
        bent = ndimage.binary_opening(np.abs(np.where(seen, h - (np.stack(
            [np.arange(h.shape[1])[None, :].repeat(h.shape[0], 0) * vol.spacing[0],
             np.arange(h.shape[0])[:, None].repeat(h.shape[1], 1) * vol.spacing[1],
             np.ones_like(h)], -1) @ coef), 0)) > 10.0, structure=np.ones((3, 3), bool))
    else:
        plane_rms, tilt, bent = float("nan"), np.zeros(1), np.zeros_like(seen)
    # failure parts: connected regions of overlap, holes and strongly bent mucosa (each > 25 mm^2)
    px = float(vol.spacing[0] * vol.spacing[1])
    fail = over | holes | bent
    lab, n = ndimage.label(fail)
    sizes = np.bincount(lab.ravel())[1:] * px
    parts = int((sizes > 25.0).sum())
    hidden = 1.0 - visible_fraction
    grade = "bad"
    if hidden <= GRADE_THRESHOLDS["excellent"]["max_hidden"] and parts <= 0:
        grade = "excellent"
    elif hidden <= GRADE_THRESHOLDS["good"]["max_hidden"] and parts <= 1:
        grade = "good"
    elif hidden <= GRADE_THRESHOLDS["fair"]["max_hidden"]:
        grade = "fair"
    area_seen = max(int(seen.sum()), 1)
    out = {
        "visible_fraction": visible_fraction,
        "mucosa_points": int(len(pts)), "mucosa_points_mapped": int(ok.sum()),
        "overlap_area_fraction": float(over[seen].mean()) if seen.any() else 0.0,
        "inverted_fraction": float(inverted.mean()),
        "broken_springs_fraction": float(stretched.mean()),
        "hole_area_fraction": float(holes.sum() / area_seen),
        "bending_plane_rms_mm": plane_rms,
        "bending_normal_deviation_deg": float(np.mean(tilt)),
        "bent_area_fraction": float(bent.sum() / area_seen),
        **surface_distortion(result.rest_vertices, result.deformed_vertices, inner_surface_triangles_from(result)),
        "failure_parts": parts,
        "grade": grade,
    }
    if marker_lps:
        out["markers"] = marker_metrics(result, marker_lps)
    return out


def _densify(polyline: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` mm along a polyline."""
    p = np.asarray(polyline, float)
    out = [p[:1]]
    for a, b in zip(p[:-1], p[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(out)


def inner_surface_triangles_from(result) -> np.ndarray:
    """Inner-surface triangles of a result's model (rebuilt from its hexes and inner-vertex flags)."""
    from types import SimpleNamespace

    inner = getattr(result, "inner_vertices", None)
    if inner is None:
        return np.zeros((0, 3), int)
    return inner_surface_triangles(SimpleNamespace(hexes=result.hexes, inner=inner))


def marker_metrics(result, marker_lps: dict) -> dict:
    """Marker visibility, position error (mm) and pairwise distance distortion (view 2D vs geodesic on the mucosa)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    vol = result.unfolded
    mapped = result.map_landmarks(marker_lps)
    rep = marker_report(vol, mapped)
    ids = [k for k in marker_lps if np.all(np.isfinite(mapped[k]))]
    out = {"seen": rep["n_seen"], "total": rep["n_total"],
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
