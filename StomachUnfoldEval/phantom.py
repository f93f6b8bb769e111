"""Synthetic abdominal CT of a gas-distended stomach with numbered markers on the mucosa, and its truth.

Patient frame LPS mm (x toward the patient's left, y posterior, z superior). The stomach is a tube of
gas (-1000 HU) with a tissue wall (40 HU) around a smooth centreline from the cardia (top) to the pylorus,
capped at both ends, with a collapsed oesophagus and duodenum attached. Around it: a body of soft tissue
(30 HU) with a fat ring (-100 HU) and outside air, liver (60 HU), spleen (50 HU), lungs (-850 HU) above
and a gas-filled colon segment below, each kept at least 6 mm of tissue away from the stomach lumen.
Markers are dense beads (400 HU) on the inner wall, none within 25 degrees of the greater curvature
(the default incision line) nor within 20 mm of either end. Shapes: straight, bent, j, twisted, thin_wall.
"""
from __future__ import annotations

import json
import os

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.geometry import Volume, lps_to_ras

__all__ = ["SHAPES", "SIZES", "stomach_centerline", "make_phantom", "write_phantom", "write_case"]

SHAPES = ("straight", "bent", "j", "twisted", "thin_wall", "hook")
SIZES = {"tiny": 1.8, "small": 1.2, "medium": 0.9, "full": 0.7}
HU = {"air": -1000, "wall": 40, "tissue": 30, "fat": -100, "liver": 60, "spleen": 50, "lung": -850, "marker": 400}


def stomach_centerline(shape: str = "j", n: int = 2000):
    """Dense centreline (n,3 LPS mm, cardia first) and lumen radius (n, mm) of a phantom stomach shape."""
    s = np.linspace(0.0, 1.0, n)
    if shape == "straight":
        pts = np.stack([0 * s, 0 * s, 75 - 150 * s], 1)
        radius = np.full(n, 25.0)
    elif shape == "bent":
        th = np.radians(110) * s
        pts = np.stack([70 * np.cos(th) - 35, 0 * s, 70 * np.sin(th) - 30], 1)[::-1]
        # cardia at the top: reversed so the curve starts high
        pts = pts[np.argsort(-pts[:, 2])] if pts[0, 2] < pts[-1, 2] else pts
        radius = np.full(n, 22.0)
    elif shape in ("j", "thin_wall", "twisted"):
        ctrl = np.array([[30, 0, 75], [45, 0, 40], [42, 0, 5], [28, 0, -30], [0, 0, -52], [-35, 0, -50],
                         [-58, 0, -28]], float)
        t = np.linspace(0, 1, len(ctrl))
        cs = CubicSpline(t, ctrl, axis=0)
        pts = cs(s)
        if shape == "twisted":
            pts[:, 1] += 28.0 * np.sin(np.pi * s) * np.sin(2.2 * np.pi * s + 0.4)
        radius = 30.0 - 13.0 * np.clip((s - 0.55) / 0.45, 0, 1) + 3.0 * np.clip(0.25 - s, 0, 1) / 0.25
    elif shape == "hook":
        # a sharp angular incisure: the body descends and the antrum turns to the horizontal around a bend whose
        # radius (under 20 mm) is smaller than the lumen's, so cross-sections of the bend cross inside it
        ctrl = np.array([[20, 0, 80], [22, 0, 40], [20, 0, 8], [14, 0, -8], [2, 0, -15], [-15, 0, -18],
                         [-40, 0, -19], [-65, 0, -18]], float)
        cs = CubicSpline(np.linspace(0, 1, len(ctrl)), ctrl, axis=0)
        pts = cs(s)
        radius = 28.0 - 10.0 * np.clip((s - 0.5) / 0.5, 0, 1)
    else:
        raise InputError(f"unknown phantom shape {shape!r}; choose one of {', '.join(SHAPES)}")
    return pts, radius


def _tangents(pts):
    t = np.gradient(pts, axis=0)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def _greater_curvature_dirs(pts, tangents):
    """Unit directions from each centreline point to the greater curvature: away from the centroid of the curve."""
    d = pts - pts.mean(axis=0)
    d -= np.sum(d * tangents, axis=1, keepdims=True) * tangents
    fallback = np.array([1.0, 0.0, 0.0]) - tangents[:, :1] * tangents
    w = np.clip(np.linalg.norm(d, axis=1) / 50.0, 0, 1)[:, None]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9) * w + \
        fallback / np.maximum(np.linalg.norm(fallback, axis=1, keepdims=True), 1e-9) * (1 - w)
    d -= np.sum(d * tangents, axis=1, keepdims=True) * tangents
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def make_phantom(shape: str = "j", size: str = "small", spacing=None, wall_thickness_mm: float = 4.0,
                 rugae: bool = False, noise_hu: float = 15.0, n_markers: int = 12, seed: int = 0,
                 flip_direction: bool = False, radius_scale: float = 1.0, full_slices: int = 400):
    """Synthetic CT (int16 HU Volume, LPS) of a gas-distended stomach with markers, and its truth dict (LPS/RAS mm).

    ``radius_scale`` scales the lumen radius profile; ``full_slices`` sets the slice count of the "full" size
    (512 x 512 x full_slices at 0.7 mm).
    """
    if size not in SIZES:
        raise InputError(f"unknown phantom size {size!r}; choose one of {', '.join(SIZES)}")
    if shape == "thin_wall":
        wall_thickness_mm = min(wall_thickness_mm, 2.0)
    sp = np.broadcast_to(np.asarray(SIZES[size] if spacing is None else spacing, float), (3,)).astype(float)
    rng = np.random.default_rng(seed)
    cl, radius = stomach_centerline(shape)
    radius = radius * float(radius_scale)
    tan = _tangents(cl)
    gdir = _greater_curvature_dirs(cl, tan)
    seg = np.linalg.norm(np.diff(cl, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    L = arc[-1]
    w = float(wall_thickness_mm)
    rmax = float(radius.max())
    lo = cl.min(0) - rmax - w
    hi = cl.max(0) + rmax + w
    if size == "full":
        # the clinical field of view: 358.4 x 358.4 x 280 mm (512 x 512 x 400 voxels at 0.7 mm)
        centre_z = 0.5 * (lo[2] + hi[2])
        fov_lo = np.array([-179.2, -179.2, centre_z - 0.35 * full_slices])
        fov_hi = fov_lo + np.array([511 * 0.7, 511 * 0.7, (int(full_slices) - 1) * 0.7])
    else:
        fov_lo = lo - np.array([20.0, 20.0, 34.0])
        fov_hi = hi + np.array([20.0, 20.0, 34.0])
    D = np.eye(3)
    if flip_direction:
        D = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # i and j swapped: det = -1
    # origin and size so that the grid spans the field of view in LPS whatever the direction
    corners = np.array([[a, b, c] for a in (fov_lo[0], fov_hi[0]) for b in (fov_lo[1], fov_hi[1])
                        for c in (fov_lo[2], fov_hi[2])])
    local = corners @ D
    n_vox = np.rint((local.max(0) - local.min(0)) / sp).astype(int) + 1
    origin = D @ local.min(0)
    vol = Volume(np.zeros(tuple(n_vox[::-1]), np.int16), sp, origin, D)

    # anatomy outside the stomach, evaluated slab by slab to bound memory
    top_wall = float(cl[:, 2].max() + rmax + w)
    bot_wall = float(cl[:, 2].min() - rmax - w)
    lung_bottom = top_wall + 8.0
    colon_z = bot_wall - 8.0 - 9.0
    colon_x = float(cl[np.argmin(cl[:, 2]), 0])
    tree = cKDTree(cl)
    arr = vol.array
    nk = arr.shape[0]
    slab = max(1, int(4_000_000 // (arr.shape[1] * arr.shape[2])))
    jj, ii = np.mgrid[0:arr.shape[1], 0:arr.shape[2]]
    lum_total = 0
    for k0 in range(0, nk, slab):
        k1 = min(nk, k0 + slab)
        kk = np.arange(k0, k1)[:, None, None] * np.ones_like(ii)[None]
        ijk = np.stack([np.broadcast_to(ii, kk.shape), np.broadcast_to(jj, kk.shape), kk], -1).reshape(-1, 3)
        P = vol.index_to_lps(ijk.astype(np.float64))
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        val = np.full(len(P), HU["tissue"], np.float32)
        body = (x / 165.0) ** 2 + (y / 125.0) ** 2
        val[body > (1 - 15 / 150) ** 2] = HU["fat"]
        val[body > 1] = HU["air"]
        liver = ((x + 95) / 60) ** 2 + ((y - 5) / 70) ** 2 + ((z - 40) / 70) ** 2 < 1
        val[liver & (body <= 1)] = HU["liver"]
        spleen = ((x - 105) / 25) ** 2 + ((y - 70) / 30) ** 2 + ((z - 30) / 45) ** 2 < 1
        val[spleen] = HU["spleen"]
        lung = (z > lung_bottom) & ((np.abs(x) - 75) ** 2 / 60 ** 2 + (y / 80) ** 2 < 1)
        val[lung] = HU["lung"]
        colon = ((x - colon_x) / 200) ** 2 < 1
        colon &= (y - 10) ** 2 + (z - colon_z) ** 2 < 9.0 ** 2
        val[colon] = HU["air"]
        # stomach: distance to the centreline
        near = np.all((P > lo - 1) & (P < hi + 1), axis=1)
        if near.any():
            q = P[near]
            dist, idx = tree.query(q, distance_upper_bound=rmax + w + 2, workers=-1)
            found = np.isfinite(dist)
            idx = np.minimum(idx, len(cl) - 1)
            r = radius[idx]
            if rugae:
                v = q - cl[idx]
                e1 = gdir[idx]
                e2 = np.cross(tan[idx], e1)
                phi = np.arctan2(np.sum(v * e2, 1), np.sum(v * e1, 1))
                r = r - 1.0 - 1.0 * np.sin(10 * phi)
            vq = val[near]
            wall_m = found & (dist < r + w)
            vq[wall_m] = HU["wall"]
            lum = found & (dist < r)
            vq[lum] = HU["air"]
            lum_total += int(lum.sum())
            val[near] = vq
        arr[k0:k1] = val.reshape(k1 - k0, arr.shape[1], arr.shape[2]).astype(np.int16)

    # oesophagus and duodenum: collapsed tissue tubes leaving the two ends
    for end, direction in ((0, -tan[0]), (-1, tan[-1])):
        start = cl[end] + direction * (radius[end] + w * 0.5)
        seg_pts = start[None] + np.linspace(0, 30, 40)[:, None] * direction[None]
        _paint_spheres(vol, seg_pts, 5.0, HU["wall"], only_above=-500)

    # markers on the inner wall, away from the greater curvature and the ends
    markers = []
    s_vals = np.linspace(20.0, L - 20.0, max(n_markers, 1))[:n_markers]
    for m in range(n_markers):
        a = int(np.searchsorted(arc, s_vals[m]))
        a = min(a, len(cl) - 1)
        phi = np.radians(60.0 + (m * 137.5) % 240.0)  # 60..300 degrees from the greater curvature
        e1 = gdir[a]
        e2 = np.cross(tan[a], e1)
        d = np.cos(phi) * e1 + np.sin(phi) * e2
        r_here = radius[a] - (1.0 if rugae else 0.0)
        pos = cl[a] + r_here * d
        markers.append({"id": m + 1, "lps": pos.tolist(), "ras": lps_to_ras(pos).tolist(), "normal_lps": (-d).tolist(),
                        "angle_from_greater_curvature_deg": float(np.degrees(phi)), "arclength_mm": float(arc[a])})
    bead = max(2.5, 1.2 * float(sp.max()))
    _paint_spheres(vol, np.array([m["lps"] for m in markers]).reshape(-1, 3), bead, HU["marker"])

    if noise_hu > 0:
        noise = rng.normal(0.0, noise_hu, size=arr.shape).astype(np.float32)
        arr[:] = np.clip(arr + noise, -1024, 3071).astype(np.int16)

    c_pt = cl[0] + 2.0 * tan[0]
    p_pt = cl[-1] - 2.0 * tan[-1]
    step = max(1, int(round(2.0 / seg.mean())))
    truth = {"shape": shape, "size": size, "spacing": sp.tolist(), "seed": int(seed),
             "size_ijk": [int(v) for v in vol.size], "direction": D.tolist(),
             "cardia_lps": c_pt.tolist(), "pylorus_lps": p_pt.tolist(),
             "cardia_ras": lps_to_ras(c_pt).tolist(), "pylorus_ras": lps_to_ras(p_pt).tolist(),
             "centerline_lps": cl[::step].tolist(), "radius_mm": radius[::step].tolist(),
             "wall_thickness_mm": w, "rugae": bool(rugae),
             "greater_curvature_lps": (cl + radius[:, None] * gdir)[::step].tolist(),
             "lumen_volume_ml": float(lum_total * np.prod(sp) / 1000.0),
             "markers": markers, "marker_radius_mm": bead, "hu": dict(HU)}
    return vol, truth


def _paint_spheres(vol: Volume, centres, radius_mm: float, value: int, only_above=None) -> None:
    """Set voxels within radius_mm of each LPS centre to ``value`` (optionally only where HU > only_above)."""
    arr = vol.array
    r_vox = np.ceil(radius_mm / vol.spacing).astype(int) + 1
    for c in np.asarray(centres, float).reshape(-1, 3):
        ijk = np.rint(vol.lps_to_index(c[None])[0]).astype(int)
        lo = np.maximum(ijk - r_vox, 0)
        hi = np.minimum(ijk + r_vox + 1, np.array(vol.size))
        if np.any(hi <= lo):
            continue
        k, j, i = np.mgrid[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        P = vol.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1)).reshape(k.shape + (3,))
        inside = np.linalg.norm(P - c, axis=-1) <= radius_mm
        sub = arr[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        if only_above is not None:
            inside &= sub > only_above
        sub[inside] = value


def write_phantom(path, **kwargs):
    """Write a phantom volume, its truth JSON (same stem + .json) and a cardia/pylorus .mrk.json; returns (path, json)."""
    vol, truth = make_phantom(**kwargs)
    return write_case(path, vol, truth)


def write_case(path, vol: Volume, truth: dict):
    """Write a synthetic CT (HU), its truth JSON (stem + .json) and a cardia/pylorus stem.mrk.json (LPS); (path, json)."""
    from StomachUnfoldLib.io import atomic_write_text, write_markups_fiducials, write_volume

    path = os.fspath(path)
    stem = path
    for ext in (".nii.gz", ".nrrd", ".nii", ".mha", ".mhd"):
        if path.endswith(ext):
            stem = path[: -len(ext)]
            break
    write_volume(vol, path)
    json_path = stem + ".json"
    atomic_write_text(json_path, json.dumps(truth, indent=1))
    write_markups_fiducials(stem + ".mrk.json", {"cardia": np.array(truth["cardia_lps"]),
                                                  "pylorus": np.array(truth["pylorus_lps"])}, "stomach points")
    return path, json_path
