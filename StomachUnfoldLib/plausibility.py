"""Plausibility warnings of a finished run: a "stomach" too small to be one, a point on the scan's first or last
slice, a point clicked deep in a wide lumen, and for a grade of fair or worse which failure parts the view has and
where."""
from __future__ import annotations

import numpy as np

from .geometry import Volume

__all__ = ["plausibility_warnings", "failure_regions", "hidden_fold_warnings", "where_on_view", "gas_contact_fraction",
           "opening_warnings", "MIN_STOMACH_ML", "GAS_CONTACT_WARN", "DEEP_POINT_WARNING"]

#: A lumen smaller than this (mL) is an air pocket, not a stomach (a gas-distended stomach holds hundreds of mL).
MIN_STOMACH_ML = 50.0
#: Share of the lumen's boundary touching gas outside it from which the view's holes are put down to it.
GAS_CONTACT_WARN = 0.005
#: The words of :func:`opening_warnings`' warning that find it among a run's warnings.
DEEP_POINT_WARNING = "inside a wide part of the lumen"


def gas_contact_fraction(crop: Volume, lumen: np.ndarray, air_hu: float) -> float:
    """Share of the lumen's boundary voxels (bool (k, j, i) on the CT crop) with a face neighbour outside the lumen
    below ``air_hu`` (HU): gas of the colon, the lungs or outside the body against the stomach, with no wall the scan
    resolves between them (a whole-organ label reaching into it, or a wall thinner than the voxels)."""
    from scipy import ndimage

    from .preprocessing import lumen_edge

    lum = np.asarray(lumen, bool)
    edge = lumen_edge(lum)
    n = int(edge.sum())
    if n == 0:
        return 0.0
    gas = (np.asarray(crop.array) < air_hu) & ~lum
    touch = edge & ndimage.binary_dilation(gas)
    return float(touch.sum() / n)


def opening_warnings(lumen_crop: Volume, centerline_lps, max_points: int = 20000) -> list[str]:
    """A warning for each end of the centreline (LPS mm) that lies deep in a wide lumen, where the opening left out
    about it (``centerline.in_openings``: up to twice the end point's distance from the wall) takes more of the
    lumen's wall, beyond OPENING_RADIUS_MM (mm), than the share an excellent grade may hide: neither the view nor the
    grade has that wall. Not at a tube's end (all the wall behind the end plane left out: the whole end opens)."""
    from scipy.spatial import cKDTree

    from .centerline import OPENING_RADIUS_MM, in_openings
    from .preprocessing import lumen_edge
    from .quality import GRADE_THRESHOLDS

    cl = np.asarray(centerline_lps, float)
    pts = lumen_crop.voxel_lps(lumen_edge(lumen_crop.array.astype(bool)))
    if len(cl) < 3 or not len(pts):
        return []
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
    near = cKDTree(cl).query(pts)[1]
    left_out = in_openings(pts, cl, nearest=near)
    behind = in_openings(pts, cl, radius_mm=np.inf, nearest=near)  # all the wall behind each end plane
    out = []
    for end, name in ((0, "cardia"), (len(cl) - 1, "pylorus")):
        mine = near == end
        d = np.linalg.norm(pts - cl[end], axis=1)
        share = float(np.mean(left_out & mine & (d >= OPENING_RADIUS_MM)))
        if share > GRADE_THRESHOLDS["excellent"]["max_hidden"] and (behind & mine & ~left_out).any():
            out.append(f"the {name} point lies {d.min():.0f} mm from the wall, {DEEP_POINT_WARNING}: the opening "
                       f"left out about it takes {100 * share:.0f} % of the stomach's wall, neither shown nor graded; "
                       f"place the {name} point at its opening, a few mm from the wall")
    return out


def failure_regions(unfolded: Volume, orient: dict | None = None, min_area_mm2: float = 25.0) -> list[dict]:
    """The view's overlap and hole regions over ``min_area_mm2`` (mm^2): kind, area (mm^2) and where on the view.

    Where: the third along the view (near the left or right end, or the middle, named by ``orient``'s ends)
    and the half (``orient``'s upper or lower half), from the region's centroid.
    """
    from scipy import ndimage

    from .quality import layer_runs
    from .view import first_hit

    orient = orient or {}
    k, _ = first_hit(unfolded)
    seen = k >= 0
    kinds = {"overlap": ndimage.binary_opening(layer_runs(unfolded) > 1, structure=np.ones((2, 2), bool)),
             "hole": ndimage.binary_fill_holes(seen) & ~seen}
    px = float(unfolded.spacing[0] * unfolded.spacing[1])
    nj, ni = seen.shape
    out = []
    for kind, m in kinds.items():
        lab, n = ndimage.label(m)
        for r in range(1, n + 1):
            jj, ii = np.nonzero(lab == r)
            area = len(jj) * px
            if area <= min_area_mm2:
                continue
            out.append({"kind": kind, "area_mm2": float(area), "where": where_on_view(ii.mean(), jj.mean(), seen.shape,
                                                                                    orient),
                        "centroid_ij": [float(ii.mean()), float(jj.mean())]})
    return out


def where_on_view(i: float, j: float, shape, orient: dict | None = None) -> str:
    """Where view pixel (i, j) lies, in words: the third along the view (named by ``orient``'s ends) and the half."""
    orient = orient or {}
    nj, ni = shape
    fi, fj = i / max(ni - 1, 1), j / max(nj - 1, 1)
    along = (f"near the {orient.get('left') or 'left end'}" if fi < 1 / 3 else
             f"near the {orient.get('right') or 'right end'}" if fi > 2 / 3 else "mid-way")
    half = orient.get("upper_half") if fj > 0.5 else orient.get("lower_half")
    return along + (f", {half} half" if half else (", upper half" if fj > 0.5 else ", lower half"))


def hidden_fold_warnings(folds: list[dict], unfolded: Volume, orient: dict | None = None) -> list[str]:
    """One warning per peeled fold of the flat map (``folds``: area mm^2 and ``view_ij``, its place on the view in
    pixels, from the method): its mucosa is not shown, so say how much and where; each fold gets ``where`` added."""
    out = []
    for n, fold in enumerate(folds, 1):
        if "view_ij" in fold:
            fold["where"] = where_on_view(*fold["view_ij"], unfolded.array.shape[1:], orient)
        where = f" {fold['where']}" if "where" in fold else ""
        out.append(f"a fold of the flat map was peeled off: {fold['area_mm2']:.0f} mm^2 of mucosa{where} (ring F{n} "
                   "in the command line's view.png) is not shown, its place taken by the mucosa around it; read that "
                   "part on the original CT")
    return out


def plausibility_warnings(ct: Volume, cardia_lps, pylorus_lps, lumen_ml: float | None, quality: dict | None,
                          unfolded: Volume | None = None, orient: dict | None = None,
                          gas_contact=None, cut_by_scan: tuple = ()) -> list[str]:
    """Warnings (plain sentences) on a finished run: lumen under MIN_STOMACH_ML (mL), a point (LPS mm) on the CT's
    first or last slice, a lumen cut off by the scan range (``cut_by_scan``: "first" and/or "last", the slices of the
    CT the lumen reaches), a grade of fair or worse with its failure parts and where they lie on the view, and holes
    in the view where the lumen touches gas outside it (``gas_contact``: :func:`gas_contact_fraction`'s share, or a
    callable giving it, called only when the view has a hole part)."""
    out = []
    # the regions behind the grade's failure parts (none to look for when it counted none)
    parts = (failure_regions(unfolded, orient) if unfolded is not None and quality
             and quality.get("failure_parts", 0) > 0 else [])
    if any(p["kind"] == "hole" for p in parts) and callable(gas_contact):
        gas_contact = gas_contact()
    gas_contact = gas_contact if isinstance(gas_contact, float) else None
    if (gas_contact or 0.0) >= GAS_CONTACT_WARN and quality and quality.get("grade") not in ("fair", "bad"):
        holes = [p for p in parts if p["kind"] == "hole"]
        if holes:
            where = "; ".join(f"{p['area_mm2']:.0f} mm^2 {p['where']}" for p in holes)
            out.append(f"the view has holes ({where}): {100 * gas_contact:.1f} % of the stomach's boundary touches gas "
                       "outside it (the colon, a lung base, or gas a stomach label leaves out) with no wall the scan "
                       "resolves in between, so the rays there meet no tissue; read those parts on the original CT")
    if lumen_ml is not None and lumen_ml < MIN_STOMACH_ML:
        out.append(f"the stomach region holds only {lumen_ml:.0f} mL: probably a gas pocket, not the whole stomach; "
                   "pass --mask with a stomach segmentation (e.g. TotalSegmentator's, label 6)")
    nk = int(ct.size[2])
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        k = float(ct.lps_to_index(np.asarray(p, float)[None])[0][2])
        if k < 1.0 or k > nk - 2.0:
            which = "first" if k < 1.0 else "last"
            out.append(f"the {name} point lies on the {which} slice of the scan: the stomach is probably cut off "
                       "by the scan range, so its end is missing from the view")
            cut_by_scan = tuple(c for c in cut_by_scan if c != which)  # said already
    for which in cut_by_scan:
        out.append(f"the stomach reaches the {which} slice of the scan: it is cut off by the scan range there, and "
                   "the view ends where the scan does (the isometric view leaves that part of the wall out, open to its "
                   "border; other methods show a flat cap or a hole there); read the rest on a scan that covers the "
                   "whole stomach")
    if quality and quality.get("grade") in ("fair", "bad"):
        txt = "; ".join(f"{p['kind']} of {p['area_mm2']:.0f} mm^2 {p['where']}" for p in parts)
        bent = quality.get("bent_area_fraction") or 0.0
        if bent > 0:
            txt = (txt + "; " if txt else "") + f"{100 * bent:.1f} % of the view bent over 10 mm off its plane"
        if (gas_contact or 0.0) >= GAS_CONTACT_WARN and any(p["kind"] == "hole" for p in parts):
            txt += (f"; the holes where {100 * gas_contact:.1f} % of the stomach's boundary touches gas outside it "
                    "(the colon, a lung base, or gas a stomach label leaves out) with no wall the scan resolves in "
                    "between")
        out.append(f"grade {quality['grade']}: {100 * (1 - quality.get('visible_fraction', 0)):.0f} % of the mucosa "
                   f"hidden, {quality.get('failure_parts', 0)} failure parts" + (f" ({txt})" if txt else "")
                   + "; read those parts on the original CT")
    return out
