"""Cylindrical unrolling around the centreline: the colon "virtual dissection" of the 1990s-2000s.

Every centreline point (arc length -> i) casts rays in its cross-section plane at angles theta around the
tangent (rotation-minimising frame, theta = 0 on the incision line -> j); each ray is sampled radially around
where it leaves the lumen (depth -> k). Expected failures: in a curved stomach adjacent cross-section planes
converge on the lesser-curvature side (the wall there is compressed and, where the planes cross inside the
lumen, sampled twice: ``fold_back_fraction``) and fan out on the greater curvature (wall stretched or skipped:
``unsampled_fraction``); rays from an off-centre centreline graze folds and miss what lies behind them; the
fundus and antrum ends, beyond the centreline's end planes, are not seen.
"""
from __future__ import annotations

import time

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..correspondence import MapCorrespondence
from ..errors import AnatomyError
from ..geometry import Volume
from ..quality import mucosa_points
from ..surface import (depth_axis, perpendicular, ray_exits, rotation_minimising_frame, sample_profiles,
                       smooth_free_ends, smooth_tangents, surface_field, to_int16, unit)
from . import Mesh, Method, Unfolding, register

__all__ = ["CylindricalUnrolling", "PHI_SMOOTH_MM"]

PHI_SMOOTH_MM = 20.0    # smoothing of the cut angle along the centreline (mm)


@register
class CylindricalUnrolling(Method):
    """Cylindrical unrolling (LPS mm in, unfolded Volume in mm): arc length -> i, angle -> j, depth -> k."""

    name = "cylindrical"
    description = "cylindrical unrolling around the centreline (a peer: colon virtual dissection)"

    def unfold(self, prep, progress) -> Unfolding:
        """Cast rays around the smoothed centreline and sample the wall where they leave the lumen."""
        warnings, seconds = [], {}
        vol, fwd, inv, mesh, report = _unroll(prep, progress, warnings, seconds)
        return Unfolding(vol, MapCorrespondence(fwd, inv), mesh, report, warnings, seconds)


def _unroll(prep, prog, warnings, seconds):
    """The unrolling proper: (unfolded Volume, to_unfolded, to_original, Mesh, report section)."""
    crop, lumen, cl, inc, s = prep.crop, prep.lumen, prep.centerline, prep.incision, prep.pixel_mm
    w = prep.params.wall_thickness_mm
    angular_samples = prep.params.angular_samples

    # --- frames along the centreline, resampled every s mm of arc length ---------------------------------
    t = time.perf_counter()
    prog.report("frames", 0.0)
    # a lightly smoothed centreline (sigma 4 mm, ends free): ray origins jittering by a fraction of a voxel between
    # neighbouring cross-sections, or a snapped end point off the axis, would shear the unrolled image
    P, arc = np.asarray(cl.points_lps, float), cl.arclength_mm
    step = float(arc[-1] / max(len(arc) - 1, 1))
    P = smooth_free_ends(P, 4.0 / max(step, 1e-6))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    T = smooth_tangents(P, arc)
    rmf = rotation_minimising_frame(P, T, inc.directions[0])
    ni = int(np.floor(arc[-1] / s + 1e-9)) + 1
    a_out = np.arange(ni) * s

    def interp(x):
        return np.stack([np.interp(a_out, arc, x[:, c]) for c in range(3)], 1)

    if ni < 4:
        raise AnatomyError(f"the centreline is only {arc[-1]:.0f} mm long; place the cardia and pylorus further apart")

    C = interp(P)
    Tn = unit(interp(T))
    E1 = unit(perpendicular(interp(rmf), Tn))
    E2 = np.cross(Tn, E1)
    dinc = perpendicular(interp(np.asarray(inc.directions, float)), Tn)
    phi = np.unwrap(np.arctan2(np.sum(dinc * E2, 1), np.sum(dinc * E1, 1)))
    # follow the incision line only on a large scale (sigma 20 mm): its end wiggles would shear the image
    phi = ndimage.gaussian_filter1d(phi, max(0.5, PHI_SMOOTH_MM / s), mode="nearest")
    F1 = np.cos(phi)[:, None] * E1 + np.sin(phi)[:, None] * E2   # theta = 0: toward the incision line
    F2 = np.cross(Tn, F1)
    radius = np.asarray(cl.radius_mm, float)
    r_mean = float(np.mean(radius[radius > 0])) if np.any(radius > 0) else 10.0
    nj = int(angular_samples) if angular_samples is not None else max(16, int(round(2 * np.pi * r_mean / s)))
    dtheta = 2 * np.pi / nj
    theta = np.arange(nj) * dtheta
    D = (np.cos(theta)[None, :, None] * F1[:, None, :] + np.sin(theta)[None, :, None] * F2[:, None, :])  # (ni,nj,3)
    seconds["frames"] = time.perf_counter() - t

    # --- rays: where they leave the lumen -----------------------------------------------------------------
    t = time.perf_counter()
    r_max = 2.5 * float(radius.max()) + 10.0
    field, level = surface_field(crop, lumen, prep.lumen_is_mask)
    origins = np.repeat(C, nj, axis=0)
    r_exit = ray_exits(field, level, crop, origins, D.reshape(-1, 3), r_max, 0.5 * float(crop.spacing.min()),
                        prog.sub("rays", 0.083, 0.417)).reshape(ni, nj)
    seconds["rays"] = time.perf_counter() - t
    missing = ~np.isfinite(r_exit)
    if missing.mean() > 0.5:
        raise AnatomyError(f"{100 * missing.mean():.0f}% of the rays from the centreline never leave the lumen within "
                           f"{r_max:.0f} mm; check the points and the lumen")
    if missing.any():
        warnings.append(f"{int(missing.sum())} rays never left the lumen within {r_max:.0f} mm; their columns are empty")

    # --- sample the CT along the rays ---------------------------------------------------------------------
    t = time.perf_counter()
    prog.report("volume", 0.417)
    depths, k0, nk = depth_axis(s, w)
    X = C[:, None, :] + np.nan_to_num(r_exit)[..., None] * D        # wall exit points (ni, nj, 3)
    prof = sample_profiles(crop, X.reshape(-1, 3), D.reshape(-1, 3), depths,
                            lumen if prep.lumen_is_mask else None)
    prof[missing.reshape(-1)] = -1024.0
    arr = to_int16(prof.reshape(ni, nj, nk).transpose(2, 1, 0))     # (k, j, i)
    vol = Volume(arr, np.full(3, s), np.zeros(3), np.eye(3))
    seconds["volume"] = time.perf_counter() - t
    prog.report("volume", 0.667)

    to_unfolded, to_original = _maps(C, Tn, F1, F2, r_exit, s, k0, r_max, dtheta)

    # --- the model: wall exit points before (rest) and after (flat grid) unrolling; failure diagnostics ----------
    valid = np.isfinite(r_exit)
    ii, jj = np.meshgrid(np.arange(ni - 1), np.arange(nj - 1), indexing="ij")
    q_ok = valid[:-1, :-1] & valid[1:, :-1] & valid[1:, 1:] & valid[:-1, 1:]
    ids = (ii * nj + jj)[q_ok]
    tris = np.concatenate([np.stack([ids, ids + nj, ids + nj + 1], 1), np.stack([ids, ids + nj + 1, ids + 1], 1)])
    flat = np.stack(list(np.meshgrid(np.arange(ni) * s, np.arange(nj) * s, indexing="ij"))
                    + [np.full((ni, nj), k0 * s)], -1)
    # cross-sections folding back (wall sampled twice) and wall left unsampled
    step_vec = np.sum((X[1:] - X[:-1]) * Tn[:-1, None, :], axis=2)
    both = valid[1:] & valid[:-1]
    diag = {"fold_back_fraction": float((step_vec[both] < 0).mean()) if both.any() else 0.0,
            "missing_rays_fraction": float(missing.mean())}
    mp = mucosa_points(prep.lumen_crop, cl.points_lps)
    if len(mp) and valid.any():
        dd, _ = cKDTree(X[valid]).query(mp)
        diag["unsampled_fraction"] = float(np.mean(dd > 2.0 * s))
    prog.report("volume", 1.0)
    report = {"columns_i": ni, "angular_samples_j": nj, "depth_samples_k": nk, "spacing_mm": s,
              "mean_radius_mm": r_mean, "centreline_points": int(len(P)), "ray_max_mm": r_max, **diag}
    mesh = Mesh(X.reshape(-1, 3), flat.reshape(-1, 3), tris, "triangle", tris)
    return vol, to_unfolded, to_original, mesh, report


def _maps(C, Tn, F1, F2, r_exit, s, k0, r_max, dtheta):
    """The unrolling's two maps, CT LPS mm -> unfolded LPS mm and back, for frames C, Tn, F1, F2 and exit radii."""
    ni, nj = r_exit.shape
    r_ext = np.concatenate([r_exit, r_exit[:, :1]], axis=1)  # periodic in j for interpolation

    def to_unfolded(points_lps) -> np.ndarray:
        """(N,3) LPS mm of the CT -> (N,3) LPS mm of the unfolded volume (NaN where unmapped)."""
        p = np.asarray(points_lps, float).reshape(-1, 3)
        out = np.full((len(p), 3), np.nan)
        if len(p) == 0 or ni < 2:
            return out
        best_i = np.full(len(p), np.nan)
        rows = max(1, 2_000_000 // ni)
        for a in range(0, len(p), rows):
            q = p[a:a + rows]
            rel = q[:, None, :] - C[None]                      # (n, ni, 3)
            dist = np.einsum("nkc,kc->nk", rel, Tn)            # signed distance to each cross-section plane
            rho = np.linalg.norm(rel - dist[..., None] * Tn[None], axis=2)
            # between planes n and n+1: d_n >= 0 > d_{n+1}; several brackets where planes cross -> nearest in-plane
            br = (dist[:, :-1] >= 0) & (dist[:, 1:] < 0) & (rho[:, :-1] < r_max) & (rho[:, 1:] < r_max)
            rr = np.where(br, 0.5 * (rho[:, :-1] + rho[:, 1:]), np.inf)
            n = np.argmin(rr, axis=1)
            ok = np.isfinite(rr[np.arange(len(q)), n])
            d0 = dist[np.arange(len(q)), n]
            d1 = dist[np.arange(len(q)), n + 1]
            fi = n + d0 / np.where(ok, d0 - d1, 1.0)
            # just before the first or after the last plane (within half a step): clamp to the end column
            for end, sign in ((0, -1), (ni - 1, 1)):
                e = ~ok & (sign * dist[:, end] >= 0) & (sign * dist[:, end] <= 0.5 * s) & (rho[:, end] < r_max)
                fi = np.where(e, end, fi)
                ok |= e
            best_i[a:a + rows] = np.where(ok, fi, np.nan)
        good = np.isfinite(best_i)
        if not good.any():
            return out
        fi = np.clip(best_i[good], 0, ni - 1)
        i0 = np.clip(np.floor(fi).astype(int), 0, ni - 2)
        u = (fi - i0)[:, None]
        c = (1 - u) * C[i0] + u * C[i0 + 1]
        tn = unit((1 - u) * Tn[i0] + u * Tn[i0 + 1])
        f1 = unit(perpendicular((1 - u) * F1[i0] + u * F1[i0 + 1], tn))
        f2 = np.cross(tn, f1)
        v = perpendicular(p[good] - c, tn)
        rho = np.linalg.norm(v, axis=1)
        th = np.mod(np.arctan2(np.sum(v * f2, 1), np.sum(v * f1, 1)), 2 * np.pi)
        fj = th / dtheta
        # exit radius at (fi, fj), bilinear and periodic in j
        j0 = np.clip(np.floor(fj).astype(int), 0, nj - 1)
        vj = fj - j0
        uu = u[:, 0]
        re = ((1 - uu) * (1 - vj) * r_ext[i0, j0] + uu * (1 - vj) * r_ext[i0 + 1, j0]
              + (1 - uu) * vj * r_ext[i0, j0 + 1] + uu * vj * r_ext[i0 + 1, j0 + 1])
        fk = k0 - (rho - re) / s
        res = np.stack([fi, fj, fk], 1) * s
        res[~np.isfinite(re)] = np.nan
        out[good] = res
        return out

    def to_original(points_lps) -> np.ndarray:
        """(N,3) LPS mm of the unfolded volume -> (N,3) LPS mm of the CT (NaN outside the unrolled columns)."""
        q = np.asarray(points_lps, float).reshape(-1, 3) / s
        out = np.full((len(q), 3), np.nan)
        ok = (q[:, 0] >= 0) & (q[:, 0] <= ni - 1)
        if not ok.any():
            return out
        fi, fj, fk = q[ok, 0], np.mod(q[ok, 1], nj), q[ok, 2]
        i0 = np.clip(np.floor(fi).astype(int), 0, ni - 2)
        u = (fi - i0)[:, None]
        j0 = np.clip(np.floor(fj).astype(int), 0, nj - 1)
        vj = fj - j0
        uu = u[:, 0]
        re = ((1 - uu) * (1 - vj) * r_ext[i0, j0] + uu * (1 - vj) * r_ext[i0 + 1, j0]
              + (1 - uu) * vj * r_ext[i0, j0 + 1] + uu * vj * r_ext[i0 + 1, j0 + 1])
        c = (1 - u) * C[i0] + u * C[i0 + 1]
        tn = unit((1 - u) * Tn[i0] + u * Tn[i0 + 1])
        f1 = unit(perpendicular((1 - u) * F1[i0] + u * F1[i0 + 1], tn))
        f2 = np.cross(tn, f1)
        th = (fj * dtheta)[:, None]
        d = np.cos(th) * f1 + np.sin(th) * f2
        rho = re + (k0 - fk) * s
        out[ok] = c + rho[:, None] * d
        return out
    return to_unfolded, to_original
