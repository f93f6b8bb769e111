"""Automatic quality grade of an unfolded view, by casting rays down -k as the viewer sees it; the same for every method.

``layer_runs`` counts separate tissue layers along each viewing ray (more than one: a wall layer lies over
another); ``visible_points`` says which mucosa points are the first tissue their ray meets;
``quality_metrics`` adds holes, bending, inverted and stretched cells, area and angle distortion and the grade.
(Marker metrics for phantoms with known truth are evaluation: ``StomachUnfoldEval.markers``.)
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .geometry import Volume
from .preprocessing import lumen_edge
from .view import first_hit

__all__ = ["layer_runs", "overlap_fraction", "visible_points", "mucosa_points", "judge_mucosa_points", "onto_wall",
           "on_level", "surface_distortion", "inverted_fraction", "stretched_fraction", "quality_metrics",
           "GRADE_THRESHOLDS"]


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


# ------------------------------------------------------------------------------------------------ metrics
GRADE_THRESHOLDS = {
    # fraction of the mucosa NOT visible from the viewer, and number of failure parts (overlap, broken, bent)
    "excellent": {"max_hidden": 0.02, "max_failure_parts": 0},
    "good": {"max_hidden": 0.30, "max_failure_parts": 1},
    "fair": {"max_hidden": 0.50},
    # bad: more than 50 % hidden
}


def surface_distortion(rest: np.ndarray, deformed: np.ndarray, tris: np.ndarray) -> dict:
    """Area and angle distortion of surface triangles (per-triangle 2D Jacobian singular values s1 >= s2)."""
    from .distortion import triangle_stretch

    s1, s2, a0, ok = triangle_stretch(rest, deformed, tris)
    s1, s2 = s1[ok], s2[ok]
    if not ok.any():
        return {"area_distortion": 0.0, "angle_distortion": 0.0, "area_ratio_p5_p95": [1.0, 1.0], "triangles": 0}
    area_ratio = s1 * s2
    conformal = s1 / np.maximum(s2, 1e-12)
    w = a0[ok] / a0[ok].sum()
    return {"area_distortion": float(np.sum(w * np.abs(np.log(np.maximum(area_ratio, 1e-6))))),
            "angle_distortion": float(np.sum(w * (conformal - 1.0))),
            "area_ratio_p5_p95": [float(np.percentile(area_ratio, 5)), float(np.percentile(area_ratio, 95))],
            "max_stretch": float(np.max(s1)), "triangles": int(ok.sum())}


#: How the judge picks its ``max_points`` mucosa points when the lumen's edge has more (:func:`mucosa_points`):
#: ``"draw"``, a random draw from the edge's list (seed 0): a lumen that differs by one voxel draws another sample, and
#: on CT 03's hybrids (12 000-16 000 edge voxels) two draws differ by a standard deviation of 0.06-0.12 point of
#: visible mucosa; ``"hash"``, the points whose LPS position hashes lowest: two lumens that differ locally keep the
#: same points elsewhere, so a change to the lumen is judged on the same points (a judge change: every row moves by
#: its sampling; not the default until the whole bench is rerun with it)
JUDGE_SAMPLE = "draw"


def _lowest_hash(points_lps: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` points (LPS mm, voxel centres) whose position, in hundredths of a mm, hashes lowest."""
    q = np.rint(np.asarray(points_lps, float) * 100.0).astype(np.int64).astype(np.uint64)
    h = (q[:, 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (q[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)) \
        ^ (q[:, 2] * np.uint64(0x165667B19E3779F9))
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    return np.sort(np.argpartition(h, n - 1)[:n])


def mucosa_points(lumen_crop: Volume, centerline_lps: np.ndarray | None = None, max_points: int = 8000,
                  seed: int = 0, sample: str = "draw") -> np.ndarray:
    """LPS points (mm) on the original inner wall between the cardia and pylorus: lumen voxels touching non-lumen,
    moved onto the lumen's boundary (:func:`onto_wall`).

    With the centreline, points in the cardia and pylorus openings (``centerline.in_openings``, the rule the
    isometric method trims by) are left out, and so is what they cut off: a gas-filled oesophagus or duodenum beyond them
    (pieces of the wall with no point nearest to an inner centreline point). Of more than ``max_points``, ``sample``
    ``"draw"`` keeps a random draw (``seed``), ``"hash"`` those whose position hashes lowest (JUDGE_SAMPLE).
    """
    lum = lumen_crop.array.astype(bool)
    edge = lumen_edge(lum)
    pts = lumen_crop.voxel_lps(edge)
    if centerline_lps is not None and len(centerline_lps) > 2:
        from scipy.spatial import cKDTree

        from .centerline import in_openings

        cl = np.asarray(centerline_lps, float)
        kk, jj, ii = np.nonzero(edge)
        _, near = cKDTree(cl).query(pts)
        keep = ~in_openings(pts, cl, nearest=near)
        edge[kk[~keep], jj[~keep], ii[~keep]] = False
        lab, _ = ndimage.label(edge, structure=np.ones((3, 3, 3), bool))
        pts, kk, jj, ii, near = pts[keep], kk[keep], jj[keep], ii[keep], near[keep]
        comp = lab[kk, jj, ii]
        inner = (near > 0) & (near < len(cl) - 1)
        if inner.any():
            pts = pts[np.isin(comp, np.unique(comp[inner]))]
    if len(pts) > max_points:
        if sample == "hash":
            pts = pts[_lowest_hash(pts, max_points)]
        elif sample == "draw":
            pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
        else:
            raise ValueError(f"sample must be 'draw' or 'hash', not {sample!r}")
    return onto_wall(pts, lumen_crop)


def judge_mucosa_points(lumen_crop: Volume, centerline_lps: np.ndarray | None = None) -> np.ndarray:
    """The judge's mucosa points (LPS mm): :func:`mucosa_points` with its sample JUDGE_SAMPLE."""
    return mucosa_points(lumen_crop, centerline_lps, sample=JUDGE_SAMPLE)


def onto_wall(points_lps: np.ndarray, lumen_crop: Volume, sigma_vox: float = 1.0) -> np.ndarray:
    """Move lumen-edge points (LPS mm) outward along the lumen's normal onto its boundary (the mucosa surface).

    A lumen voxel centre next to the wall lies up to half a voxel inside the lumen: on 2.5 mm slices more than
    a millimetre in front of the mucosa. The boundary is where the lumen mask, smoothed by ``sigma_vox`` voxels,
    falls to 0.5; points with no crossing within 1.5 voxels stay where they are. The smoothed mask is made in
    slabs of slices (with the kernel's halo, so the values are those of the whole mask smoothed at once).
    """
    pts = np.asarray(points_lps, float).reshape(-1, 3)
    out = pts.copy()
    if len(pts) == 0:
        return out
    lum = lumen_crop.array.view(np.uint8) if lumen_crop.array.dtype == bool else lumen_crop.array.astype(np.uint8)
    sp = np.asarray(lumen_crop.spacing, float)
    reach = int(np.ceil(1.5 * float(sp.max()) / sp[2])) + 2      # slices a point's samples may reach along k
    halo = reach + int(4.0 * sigma_vox + 0.5)                     # plus the Gaussian kernel's radius
    k_of = np.floor(lumen_crop.lps_to_index(pts)[:, 2]).astype(int)
    n_k, depth = lum.shape[0], 32
    for k0 in range(min(0, int(k_of.min())), max(n_k, int(k_of.max()) + 1), depth):
        sel = np.flatnonzero((k_of >= k0) & (k_of < k0 + depth))
        if len(sel) == 0:
            continue
        a, b = max(k0 - halo, 0), min(k0 + depth + halo, n_k)
        if b <= a:
            continue
        g = ndimage.gaussian_filter(lum[a:b], sigma_vox, output=np.float32)
        lo, hi = max(k0 - reach, 0) - a, min(k0 + depth + reach, n_k) - a  # the exact part of g
        block = Volume(g[lo:hi], sp, lumen_crop.index_to_lps(np.array([0.0, 0.0, a + lo])), lumen_crop.direction)
        out[sel] = _onto_boundary(pts[sel], block, lumen_crop.direction, sp)
    return out


def _onto_boundary(pts: np.ndarray, g: Volume, direction: np.ndarray, sp: np.ndarray) -> np.ndarray:
    """Points (LPS mm) moved along -grad g onto g = 0.5 (g: the smoothed lumen mask, 0 outside its grid)."""
    grad = np.zeros_like(pts)
    for a in range(3):  # central differences along the grid axes, converted to LPS
        step = direction[:, a] * sp[a]
        d = (g.sample(pts + step, order=1, cval=0.0) - g.sample(pts - step, order=1, cval=0.0)) / (2.0 * sp[a])
        grad += d[:, None] * direction[:, a][None, :]
    norm = np.linalg.norm(grad, axis=1)
    n = -grad / np.maximum(norm, 1e-12)[:, None]
    ts = np.linspace(0.0, 1.5 * float(sp.max()), 25)
    vals = np.stack([g.sample(pts + t * n, order=1, cval=0.0) for t in ts], 1)   # (N, T)
    below = vals < 0.5
    first = np.argmax(below, axis=1)
    ok = below.any(axis=1) & (first > 0) & (norm > 1e-6)
    f = np.clip(first, 1, len(ts) - 1)
    r = np.arange(len(pts))
    v0, v1 = vals[r, f - 1], vals[r, f]
    t = ts[f - 1] + (v0 - 0.5) / np.maximum(v0 - v1, 1e-6) * (ts[1] - ts[0])
    out = pts.copy()
    out[ok] = pts[ok] + t[ok, None] * n[ok]
    return out


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


def inverted_fraction(mesh) -> float:
    """Fraction of a Mesh's cells turned inside out by the unfolding (tetrahedra of hexahedra; flat triangles)."""
    if mesh.kind == "hexahedron":
        from .unfolded_volume import hex_to_tets, tet_inverse

        tets, _ = hex_to_tets(mesh.cells)
        _, _, v0 = tet_inverse(mesh.rest_lps, tets)
        _, _, v1 = tet_inverse(mesh.unfolded_lps, tets)
        return float((np.sign(v0) != np.sign(v1)).mean()) if len(tets) else 0.0
    uv = mesh.unfolded_lps[:, :2]
    a, b, c = (uv[mesh.cells[:, i]] for i in range(3))
    sa = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    if not len(sa):
        return 0.0
    major = np.sign(np.sum(np.sign(sa))) or 1.0
    return float(np.mean(np.sign(sa) != major))


def stretched_fraction(mesh, limit: float = 1.5) -> float:
    """Fraction of a Mesh's edges (springs) longer than ``limit`` times their rest length after unfolding."""
    e = mesh.edges()
    if not len(e):
        return 0.0
    l0 = np.linalg.norm(mesh.rest_lps[e[:, 0]] - mesh.rest_lps[e[:, 1]], axis=1)
    l1 = np.linalg.norm(mesh.unfolded_lps[e[:, 0]] - mesh.unfolded_lps[e[:, 1]], axis=1)
    return float(np.mean(l1 > limit * l0))


def on_level(points_lps: np.ndarray, level: dict | None, lumen_crop: Volume) -> np.ndarray:
    """Which points (LPS mm) lie on the face of a level of contents that read like the wall (``level``: the front end's
    ``fluid_soft_level``, its unit ``gravity_lps`` and ``level_mm`` along it, LPS mm): within one voxel of that plane
    along gravity. That face is no mucosa: the wall under the contents is hidden behind it."""
    pts = np.asarray(points_lps, float).reshape(-1, 3)
    if not level:
        return np.zeros(len(pts), bool)
    g = np.asarray(level["gravity_lps"], float)
    reach = float(np.abs(np.asarray(lumen_crop.direction, float).T @ g) @ np.asarray(lumen_crop.spacing, float))
    return np.abs(pts @ g - float(level["level_mm"])) <= reach


def quality_metrics(vol: Volume, correspondence, mesh, lumen_crop: Volume, centerline_lps,
                    threshold_hu: float = -400.0, progress=None, folded=None, points_lps=None,
                    soft_level: dict | None = None) -> dict:
    """All automatic quality metrics and the grade of an unfolded Volume (HU), from any method's outputs.

    ``correspondence.to_unfolded`` maps CT LPS mm into the view; ``mesh`` is the method's Mesh; ``lumen_crop``
    the lumen on the CT crop and ``centerline_lps`` the centreline, from which the mucosa points are drawn.
    ``progress`` (callable(fraction)) is called several times a second of work. ``folded`` (bool (j, i), e.g. a
    DistortionMap's ``multiple``) marks pixels where more than one piece of the mucosa's surface maps: a fold-over
    of a surface map that the volume, resampled from one piece per pixel, cannot show as a second layer (for a
    surface method's triangle sheet; a volumetric model's folds show as layers). ``points_lps``: the mucosa points
    (LPS mm) when already drawn, :func:`judge_mucosa_points` (else drawn here). ``soft_level``: the front end's
    ``fluid_soft_level`` (a level of contents that read like the wall): the points on its face (:func:`on_level`) are
    no mucosa, and are counted as hidden whatever the view shows there (``known_hidden_fraction``): the wall under the
    contents is hidden behind them.
    """
    report = progress or (lambda fraction: None)
    k_hit, _ = first_hit(vol, threshold_hu)
    seen = k_hit >= 0
    # visible fraction: mucosa points mapped into the view whose column's first hit is at their depth
    pts = judge_mucosa_points(lumen_crop, centerline_lps) if points_lps is None else np.asarray(points_lps, float)
    report(0.05)
    mapped = np.zeros((len(pts), 3))
    for a in range(0, len(pts), 1000):
        mapped[a:a + 1000] = correspondence.to_unfolded(pts[a:a + 1000])
        report(0.05 + 0.55 * min(1.0, (a + 1000) / max(len(pts), 1)))
    ok = np.all(np.isfinite(mapped), axis=1)
    shown = visible_points(vol, mapped, k_hit)
    known_hidden = on_level(pts, soft_level, lumen_crop)
    visible_fraction = float((shown & ~known_hidden).sum() / max(len(pts), 1))
    # overlapping: two layers on a ray; inverted cells of the model
    runs = layer_runs(vol, threshold_hu)
    two = runs > 1
    if folded is not None:
        two = two | np.asarray(folded, bool)
    over = ndimage.binary_opening(two, structure=np.ones((2, 2), bool))
    report(0.7)
    # broken: over-stretched springs (edges longer than 1.5x) and holes inside the view's outline
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
    report(0.85)
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
        "known_hidden_fraction": float(known_hidden.mean()) if len(pts) else 0.0,
        "overlap_area_fraction": float(over[seen].mean()) if seen.any() else 0.0,
        "inverted_fraction": inverted_fraction(mesh),
        "broken_springs_fraction": stretched_fraction(mesh),
        "hole_area_fraction": float(holes.sum() / area_seen),
        "bending_plane_rms_mm": plane_rms,
        "bending_normal_deviation_deg": float(np.mean(tilt)),
        "bent_area_fraction": float(bent.sum() / area_seen),
        **surface_distortion(mesh.rest_lps, mesh.unfolded_lps, mesh.surface),
        "failure_parts": parts,
        "grade": grade,
    }
    return out
