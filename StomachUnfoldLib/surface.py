"""Surfaces and profiles shared by the surface-based methods: the inner wall's iso-surface, cutting, conformal maps,
rasterising a flat map and sampling the CT along the wall's normals. All coordinates are LPS mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from scipy.spatial import cKDTree

from .errors import AnatomyError, SimulationError
from .geometry import Volume, onto_edge_voxels
from .preprocessing import lumen_edge
from .progress import Progress

INSIDE_MM = 2.0         # how far into the lumen (mm) each depth profile starts
CLEARANCE_MM = 2.0      # profile length beyond the wall thickness (mm)
CRACK_PX = 1.0          # pinholes and cracks inside the flat map's outline up to two pixels wide are closed (pixels)
SURFACE_SIGMA_VOX = 1.0  # blur of the inner-wall field (voxels of each axis; of the finest one with SURFACE_BLUR_IN_MM)
#: Rule 34 (docs/RULE34_surface_blur_in_mm.md): the inner wall's blur SURFACE_SIGMA_VOX of the finest spacing, in mm,
#: along every axis, not SURFACE_SIGMA_VOX voxels of each axis (on 4.25 mm slices one voxel is 4.25 mm along them and
#: closes a pyloric canal a few mm wide that the lumen keeps; isotropic voxels are unchanged to the bit). With the map
#: along the rays it saw 50 more markers on 40 new hybrids, but it failed its decision sets (the real CT 03 pocket
#: 98.87 -> 97.74 % with holes: a real scan's wall needs the voxel's blur along its slices). Off.
SURFACE_BLUR_IN_MM = False
CLEAR_RAMP = 0.3        # a lumen mask clears the profiles from 0.5 to 0.8 of its blurred field, in proportion
TISSUE_HU = -400.0      # a view's sample above this is tissue: where the view is seen (view.first_hit's default)


def unit(v, eps=1e-12):
    """Vectors (..., 3) scaled to unit length (zero vectors stay near zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), eps)


def perpendicular(v, t):
    """The part of vectors v perpendicular to unit vectors t (row-wise)."""
    return v - np.sum(v * t, axis=-1, keepdims=True) * t


def surface_sigma_vox(spacing) -> float | tuple:
    """The inner wall's blur (voxels; per array axis k, j, i when SURFACE_BLUR_IN_MM) on a grid of ``spacing`` (mm, i j k)."""
    if not SURFACE_BLUR_IN_MM:
        return SURFACE_SIGMA_VOX
    sp = np.asarray(spacing, float)
    return tuple(float(SURFACE_SIGMA_VOX * sp.min() / x) for x in sp[::-1])


def sample_profiles(crop: Volume, surf: np.ndarray, normal: np.ndarray, depths: np.ndarray,
                     lumen: np.ndarray | None, batch: int = 4_000_000) -> np.ndarray:
    """CT HU (float32, (N, D)) at ``surf + depth * normal`` (LPS mm); lumen samples cleared to -1024 if given.

    A sample is cleared by the mask ``lumen`` (on the crop's grid) blurred as for the inner wall (SURFACE_SIGMA_VOX
    voxels) and interpolated trilinearly: not at all below one half, fully from 0.5 + CLEAR_RAMP, in proportion
    between. The cleared region ends on the same smooth surface the profiles start from, not on the mask's voxel
    staircase (which on thick slices drew terraces, a "wood grain", across the view).

    Where a label's edge borders gas (a neighbouring bowel loop or lung base, or gas the label left out), clearing
    would leave a profile with no tissue at all: a hole in the view. There the label's own outermost tissue on the
    profile (above TISSUE_HU: the stomach's wall between its content and that gas) is kept, so the view shows it.
    """
    n, d = len(surf), len(depths)
    out = np.empty((n, d), np.float32)
    rows = max(1, batch // max(d, 1))
    soft = None
    if lumen is not None:
        soft = ndimage.gaussian_filter(np.asarray(lumen, np.float32), surface_sigma_vox(crop.spacing), output=np.float32)
    for a in range(0, n, rows):
        b = min(n, a + rows)
        p = surf[a:b, None, :] + depths[None, :, None] * normal[a:b, None, :]
        v = crop.sample(p.reshape(-1, 3), order=1, cval=-1024.0)
        if soft is not None:
            # the edge voxels' outer halves read the edge voxel, as crop.sample reads the HU there: where the lumen
            # meets the scan's edge, a lumen sample there is cleared like its HU's voxel, not shown as wall
            coords = onto_edge_voxels(crop.lps_to_index(p.reshape(-1, 3))[:, ::-1].T, soft.shape)
            occ = ndimage.map_coordinates(soft, coords, order=1, mode="constant", cval=0.0, prefilter=False)
            # cleared in proportion across the surface (a ramp over CLEAR_RAMP of the field), so that where the
            # view finds the wall moves smoothly with it, not in steps of the depth samples
            alpha = np.clip((occ - 0.5) / CLEAR_RAMP, 0.0, 1.0)
            v = v.reshape(b - a, d)
            cleared = v + alpha.reshape(b - a, d) * (-1024.0 - v)
            _keep_outer_tissue(cleared, v, depths)
            v = cleared
        out[a:b] = v.reshape(b - a, d)
    return out


def _keep_outer_tissue(cleared: np.ndarray, raw: np.ndarray, depths: np.ndarray) -> None:
    """In profiles (N, D at ``depths`` mm, wall side positive) that clearing left without tissue, restore the raw HU
    of the outermost raw sample above TISSUE_HU and of every sample deeper than it (in place)."""
    lost = (cleared.max(axis=1) <= TISSUE_HU) & (raw.max(axis=1) > TISSUE_HU)
    if not lost.any():
        return
    rows = np.nonzero(lost)[0]
    depths = np.asarray(depths, float)
    outer = np.where(raw[rows] > TISSUE_HU, depths[None, :], -np.inf).max(axis=1)  # its deepest tissue sample (mm)
    deeper = depths[None, :] >= outer[:, None]
    cleared[rows] = np.where(deeper, raw[rows], cleared[rows])


def depth_axis(s: float, wall_thickness_mm: float, extra_inside_mm: float = 0.0):
    """Depth samples (mm along the outward normal, from the lumen side down) and the k index of depth 0; the samples
    reach INSIDE_MM plus ``extra_inside_mm`` (mm) into the lumen."""
    n_in = int(np.ceil((INSIDE_MM + extra_inside_mm) / s))
    n_out = int(np.ceil((wall_thickness_mm + CLEARANCE_MM) / s))
    nk = n_in + n_out + 1
    k = np.arange(nk)
    depths = (n_out - k) * s  # k = 0 deepest, k = nk - 1 inside the lumen
    return depths, n_out, nk


def smooth_free_ends(points: np.ndarray, sigma_pts: float) -> np.ndarray:
    """Gaussian smoothing of a polyline (sigma in points), padded by point reflection at the ends, ends not pinned."""
    n = len(points)
    if n < 4 or sigma_pts <= 0:
        return points.copy()
    pad = min(n - 1, int(np.ceil(3 * sigma_pts)))
    ext = np.concatenate([2 * points[0] - points[pad:0:-1], points, 2 * points[-1] - points[-2:-2 - pad:-1]])
    return ndimage.gaussian_filter1d(ext, sigma_pts, axis=0, mode="nearest")[pad:pad + n]


def smooth_tangents(points: np.ndarray, arc: np.ndarray, sigma_mm: float = 4.0, end_mm: float = 10.0) -> np.ndarray:
    """Unit tangents (K,3) smoothed along the curve; each end tangent is the chord over its last ``end_mm`` mm.

    The centreline's own end tangent is one 2 mm step to a snapped end point and can tilt by 20-30 degrees,
    which would tilt the first and last cross-sections and the trimming planes.
    """
    t = np.gradient(points, axis=0)
    m = int(np.clip(np.searchsorted(arc, end_mm), 1, len(points) - 1))
    t[0] = points[m] - points[0]
    t[-1] = points[-1] - points[-1 - m]
    t = unit(t)
    step = float(arc[-1] / max(len(arc) - 1, 1))
    t = ndimage.gaussian_filter1d(t, max(0.5, sigma_mm / max(step, 1e-6)), axis=0, mode="nearest")
    return unit(t)


def surface_field(crop: Volume, lumen: np.ndarray, mask_given: bool, step: int = 1,
                  start: int = 0) -> tuple[np.ndarray, float]:
    """Float field on the crop grid whose ``level`` iso-surface is the inner wall (below the level = lumen side).

    With gas: the CT's HU in a one-voxel band around the lumen (+200 HU elsewhere, so no other gas counts), blurred
    by SURFACE_SIGMA_VOX voxels, level -500 HU (the lumen's air threshold): a smooth sub-voxel surface. With a stomach
    mask (no gas): the mask blurred the same way and scaled to -1000..0, level -500. With ``step`` > 1, only the
    voxels ``start::step`` along each axis (what a marching cubes of that step reads), the same values as the whole
    field's there.
    """
    if mask_given:
        g = _blur(lumen.astype(np.float32), surface_sigma_vox(crop.spacing), step, start)
        return (-1000.0 * g).astype(np.float32), -500.0
    band = _box_dilate(lumen)
    field = np.full(band.shape, 200.0, np.float32)
    np.copyto(field, crop.array, casting="unsafe", where=band)     # HU (exact in float32) in the band
    # a little blur (1 voxel) as a CT's partial volume gives: voxel staircases would tilt the sampled surface
    return _blur(field, surface_sigma_vox(crop.spacing), step, start), -500.0


def _box_dilate(mask: np.ndarray) -> np.ndarray:
    """A bool 3-D mask dilated by a 3 x 3 x 3 box (voxels), as a maximum filter with zero outside: one voxel's shift
    each way along each axis in turn (the box is separable), eight times faster than the filter."""
    b = np.asarray(mask, bool)
    for axis in range(b.ndim):
        lo = tuple(slice(None, -1) if a == axis else slice(None) for a in range(b.ndim))
        hi = tuple(slice(1, None) if a == axis else slice(None) for a in range(b.ndim))
        grown = b.copy()
        grown[hi] |= b[lo]
        grown[lo] |= b[hi]
        b = grown
    return b


def _blur(a: np.ndarray, sigma_vox, step: int, start: int) -> np.ndarray:
    """``ndimage.gaussian_filter(a, sigma_vox)`` (float32; sigma one number or one per axis) at the voxels
    ``start::step`` of each axis: the axes are filtered in its order, each on the lines the later axes still need, so
    the values are the same to the bit."""
    if step == 1 and start == 0:
        return ndimage.gaussian_filter(a, sigma_vox)
    sig = np.broadcast_to(np.asarray(sigma_vox, float), (a.ndim,))
    for axis in range(a.ndim):
        a = ndimage.gaussian_filter1d(a, float(sig[axis]), axis=axis, output=np.float32)
        a = a[(slice(None),) * axis + (slice(start, None, step),)]
    return a


def to_int16(a: np.ndarray) -> np.ndarray:
    """HU values rounded and clipped to the int16 CT range [-1024, 3071]."""
    return np.clip(np.rint(a), -1024, 3071).astype(np.int16)


def rotation_minimising_frame(points: np.ndarray, tangents: np.ndarray, r0: np.ndarray) -> np.ndarray:
    """Normals (K,3) of the double-reflection rotation-minimising frame (Wang et al. 2008) starting at r0."""
    r = np.empty_like(points)
    r[0] = unit(perpendicular(r0, tangents[0]))
    for n in range(len(points) - 1):
        v1 = points[n + 1] - points[n]
        c1 = float(v1 @ v1)
        if c1 < 1e-12:
            r[n + 1] = r[n]
            continue
        rl = r[n] - (2.0 / c1) * (v1 @ r[n]) * v1
        tl = tangents[n] - (2.0 / c1) * (v1 @ tangents[n]) * v1
        v2 = tangents[n + 1] - tl
        c2 = float(v2 @ v2)
        r[n + 1] = rl - (2.0 / c2) * (v2 @ rl) * v2 if c2 > 1e-12 else rl
        r[n + 1] = unit(perpendicular(r[n + 1], tangents[n + 1]))
    return r


def ray_exits(field: np.ndarray, level: float, crop: Volume, origins: np.ndarray, dirs: np.ndarray, r_max: float,
               step: float, prog: Progress, batch: int = 1_000_000) -> np.ndarray:
    """Distance (mm) along each ray (origins (N,3), dirs (N,3)) to where the field first reaches ``level``; NaN if never."""
    t = np.arange(0.0, r_max + step, step)
    out = np.full(len(origins), np.nan)
    rows = max(1, batch // len(t))
    inv = np.linalg.inv(crop.direction * crop.spacing[None, :])
    for a in range(0, len(origins), rows):
        b = min(len(origins), a + rows)
        o = (origins[a:b] - crop.origin) @ inv.T
        d = dirs[a:b] @ inv.T
        ijk = o[:, None, :] + t[None, :, None] * d[:, None, :]
        v = ndimage.map_coordinates(field, ijk.reshape(-1, 3)[:, ::-1].T, order=1, mode="constant", cval=1e4,
                                    output=np.float32, prefilter=False).reshape(b - a, len(t))
        v[:, 0] = np.minimum(v[:, 0], level - 1.0)
        out_ = v >= level
        first = np.argmax(out_, axis=1)
        has = out_.any(axis=1)
        f = np.clip(first, 1, len(t) - 1)
        v0 = v[np.arange(b - a), f - 1]
        v1 = v[np.arange(b - a), f]
        frac = np.clip((level - v0) / np.maximum(v1 - v0, 1e-6), 0.0, 1.0)
        out[a:b] = np.where(has, t[f - 1] + frac * step, np.nan)
        prog(b / len(origins))
    return out


def inner_surface(lumen: np.ndarray, crop: Volume, max_vertices: int, mask_given: bool = False):
    """Iso-surface (LPS mm vertices, triangles) of the inner wall (see surface_field), <= ~max_vertices."""
    from .isosurface import isosurface

    n_edge = int(np.count_nonzero(lumen_edge(lumen)))
    step = max(1, int(np.ceil(np.sqrt(n_edge / float(max_vertices)))))
    # the field padded by 2 voxels, read every step-th voxel: only the field's voxels -2 (mod step) are needed
    start = (-2) % step
    field, level = surface_field(crop, lumen, mask_given, step, start)
    n_pad = [-(-(n + 4) // step) for n in lumen.shape]              # len(range(0, n + 4, step))
    sm = np.full(n_pad, np.float32(1e4 if not mask_given else 0.0), np.float32)
    m0 = (start + 2) // step
    sm[m0:m0 + field.shape[0], m0:m0 + field.shape[1], m0:m0 + field.shape[2]] = field
    del field
    verts, faces = isosurface(sm, level, step, sampled=True)
    ijk = verts[:, ::-1] - 2.0
    return crop.index_to_lps(ijk), faces.astype(np.int64), step


def vertex_normals(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted vertex normals and face normals (both unit, along the triangles' winding)."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for c in range(3):
        np.add.at(vn, f[:, c], fn)
    return unit(vn), unit(fn)


def largest_component(nv: int, f: np.ndarray) -> np.ndarray:
    """Bool mask of the triangles of the largest edge-connected component."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv))
    _, lab = connected_components(g, directed=False)
    fl = lab[f[:, 0]]
    big = np.bincount(fl).argmax()
    return fl == big


def compact(v: np.ndarray, f: np.ndarray, *extra):
    """Drop vertices no triangle uses: (v, f renumbered, *extra per-vertex arrays) for the used vertices."""
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return (v[used], remap[f]) + tuple(x[used] for x in extra)


def lscm_matrix(v: np.ndarray, f: np.ndarray):
    """Real (2F, 2V) matrix A of the LSCM energy |A [u; v]|^2 (Levy et al. 2002), unknowns u then v."""
    from scipy.sparse import csr_matrix

    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1 = p1 - p0
    n = np.cross(e1, p2 - p0)
    dT = np.linalg.norm(n, axis=1)
    ok = dT > 1e-10
    f, p0, p1, p2, e1, n, dT = f[ok], p0[ok], p1[ok], p2[ok], e1[ok], n[ok], dT[ok]
    x1 = np.linalg.norm(e1, axis=1)
    u = e1 / x1[:, None]
    w = np.cross(n / dT[:, None], u)
    q = np.stack([np.zeros((len(f), 2)), np.stack([x1, np.zeros_like(x1)], 1),
                  np.stack([np.sum((p2 - p0) * u, 1), np.sum((p2 - p0) * w, 1)], 1)], 1)   # (F,3,2)
    W = np.stack([q[:, 2] - q[:, 1], q[:, 0] - q[:, 2], q[:, 1] - q[:, 0]], 1) / np.sqrt(dT)[:, None, None]
    nv, nf = len(v), len(f)
    rows = np.repeat(np.arange(nf), 3)
    cols = f.reshape(-1)
    mr, mi = W[..., 0].reshape(-1), W[..., 1].reshape(-1)
    # real form of |M U|^2 with U = u + i v: [[Mr, -Mi], [Mi, Mr]] @ [u; v]
    A = csr_matrix((np.concatenate([mr, -mi, mi, mr]),
                    (np.concatenate([rows, rows, rows + nf, rows + nf]),
                     np.concatenate([cols, cols + nv, cols, cols + nv]))), shape=(2 * nf, 2 * nv))
    return A


def lscm(v: np.ndarray, f: np.ndarray, pins: np.ndarray, pin_uv: np.ndarray) -> np.ndarray:
    """Least Squares Conformal Map (Levy et al. 2002) of a disc mesh: (V,2) coordinates with pinned vertices."""
    from scipy.sparse.linalg import spsolve

    nv = len(v)
    A = lscm_matrix(v, f)
    pinned = np.zeros(2 * nv, bool)
    pinned[np.concatenate([pins, pins + nv])] = True
    xp = np.concatenate([pin_uv[:, 0], pin_uv[:, 1]])
    Af, Ap = A[:, ~pinned], A[:, pinned]
    rhs = -(Af.T @ (Ap @ xp))
    sol = spsolve((Af.T @ Af).tocsc(), rhs)
    if not np.all(np.isfinite(sol)):
        raise SimulationError("the conformal map of the surface could not be solved (singular system); the surface "
                              "mesh is probably broken")
    x = np.zeros(2 * nv)
    x[~pinned] = sol
    x[pinned] = xp
    return np.stack([x[:nv], x[nv:]], 1)


def spectral_conformal(v: np.ndarray, f: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """Free-boundary spectral conformal map (Mullen et al. 2008): smallest non-trivial LSCM eigenvector, (V,2)."""
    from scipy.sparse import diags, identity
    from scipy.sparse.linalg import LinearOperator, eigsh, splu

    nv = len(v)
    A = lscm_matrix(v, f)
    M = (A.T @ A).tocsc()
    eps = 1e-8 * float(M.diagonal().mean())
    lu = splu((M + eps * identity(2 * nv)).tocsc())
    b = np.zeros(nv)
    b[boundary] = 1.0
    B = diags(np.concatenate([b, b])).tocsc()
    op = LinearOperator(M.shape, matvec=lu.solve, dtype=float)
    x0 = np.random.default_rng(0).normal(size=2 * nv)
    lam, vec = eigsh(M, k=6, M=B, sigma=0.0, which="LM", OPinv=op, v0=x0, tol=1e-8)
    # drop the constant maps (zero energy), keep the smallest non-trivial (a double eigenvalue: U and iU)
    cands = []
    for ix in np.argsort(lam):
        y = vec[:, ix]
        u, w = y[:nv] - (b @ y[:nv]) / b.sum(), y[nv:] - (b @ y[nv:]) / b.sum()
        spread = np.sqrt((b @ u ** 2 + b @ w ** 2) / b.sum())
        if spread > 1e-3 * np.sqrt((b @ y[:nv] ** 2 + b @ y[nv:] ** 2) / b.sum()) and lam[ix] > 1e-9:
            cands.append(ix)
    if not cands:
        raise SimulationError("the spectral conformal map found no non-trivial map; the surface mesh is probably broken")
    x = vec[:, cands[0]]
    if not np.all(np.isfinite(x)):
        raise SimulationError("the spectral conformal map of the surface could not be solved; the mesh is probably broken")
    return np.stack([x[:nv], x[nv:]], 1)


def tube_conformal(v: np.ndarray, f: np.ndarray, partner: np.ndarray, end_flag: np.ndarray, pin: int) -> np.ndarray:
    """LSCM energy minimised with the openings on lines u = 0 (cardia) and u = 1 (pylorus) and the seam glued periodically.

    ``partner[c]`` is the original of seam copy ``c`` (-1 otherwise): u(c) = u(partner), v(c) = v(partner) + P with
    the period P unknown; v is pinned at vertex ``pin``. This is the conformal map of the tube (an annulus) onto a
    rectangle, as conformal colon flattening does (Hong et al. 2006); returns (V,2).
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import spsolve

    nv = len(v)
    A = lscm_matrix(v, f)
    base = np.where(partner >= 0, partner, np.arange(nv))
    pin_b = base[pin]
    fixed_u = end_flag[base] > 0
    x0 = np.zeros(2 * nv)
    x0[:nv] = np.where(end_flag[base] == 2, 1.0, 0.0)
    # columns: u of free originals, v of originals except the pin, then the period P
    free_u_orig = (partner < 0) & ~fixed_u
    col_u = np.full(nv, -1, np.int64)
    col_u[free_u_orig] = np.arange(free_u_orig.sum())
    nu = int(free_u_orig.sum())
    free_v_orig = (partner < 0) & (np.arange(nv) != pin_b)
    col_v = np.full(nv, -1, np.int64)
    col_v[free_v_orig] = nu + np.arange(free_v_orig.sum())
    n_y = nu + int(free_v_orig.sum()) + 1
    rows, cols = [], []
    cu = col_u[base]
    ok = cu >= 0
    rows.append(np.flatnonzero(ok)); cols.append(cu[ok])
    cv = col_v[base]
    ok = cv >= 0
    rows.append(nv + np.flatnonzero(ok)); cols.append(cv[ok])
    cp = np.flatnonzero(partner >= 0)
    rows.append(nv + cp); cols.append(np.full(len(cp), n_y - 1))
    r, c = np.concatenate(rows), np.concatenate(cols)
    S = csr_matrix((np.ones(len(r)), (r, c)), shape=(2 * nv, n_y))
    AS = A @ S
    y = spsolve((AS.T @ AS).tocsc(), -(AS.T @ (A @ x0)))
    if not np.all(np.isfinite(y)):
        raise SimulationError("the conformal map of the tube could not be solved (singular system); the surface mesh "
                              "is probably broken")
    x = S @ y + x0
    return np.stack([x[:nv], x[nv:]], 1)


def sorted_edges(f: np.ndarray) -> np.ndarray:
    """Each triangle's three edges (3F,2 vertex indices, the smaller first): corners (0,1) of every triangle, then
    (1,2), then (2,0) (as np.sort(..., axis=1) of them, without a sort per row)."""
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    return np.stack([np.minimum(a, b), np.maximum(a, b)], 1)


def signed_area_2d(uv: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Signed area (mm^2) of each triangle f of a flat map uv (V,2); positive when counter-clockwise."""
    x, y = uv[:, 0], uv[:, 1]                   # each coordinate gathered apart: contiguous arrays, the same sums
    f0, f1, f2 = f[:, 0], f[:, 1], f[:, 2]
    ax, ay = np.take(x, f0), np.take(y, f0)
    return 0.5 * ((np.take(x, f1) - ax) * (np.take(y, f2) - ay) - (np.take(y, f1) - ay) * (np.take(x, f2) - ax))


def rasterise(uv: np.ndarray, f: np.ndarray, shape_ji: tuple[int, int], s: float, prog: Progress,
               batch: int = 2_000_000):
    """Per pixel (j, i) of a grid with pixel centres at (i*s, j*s) mm: covering triangle id (-1 none), barycentrics,
    and how many triangles hold the pixel centre strictly inside (more than one: the map folds over there)."""
    nj, ni = shape_ji
    tri = np.full(nj * ni, -1, np.int64)
    bary = np.zeros((nj * ni, 3))
    hits = np.zeros(nj * ni, np.int32)
    P = np.take(uv, f, axis=0) / s                            # (F,3,2) in pixel units
    lo = np.ceil(np.minimum(np.minimum(P[:, 0], P[:, 1]), P[:, 2]) - 1e-9).astype(int)
    hi = np.floor(np.maximum(np.maximum(P[:, 0], P[:, 1]), P[:, 2]) + 1e-9).astype(int)
    size = np.maximum(hi - lo + 1, 0)                         # (F,2) pixels per axis in each bbox
    key = np.maximum(size[:, 0], size[:, 1])
    order = np.argsort(key, kind="stable")
    done = 0
    for b in np.unique(key):
        if b <= 0:
            done += int((key == b).sum())
            continue
        ids = order[key[order] == b]
        off = np.stack(np.meshgrid(np.arange(b), np.arange(b), indexing="ij"), -1).reshape(-1, 2)  # (b*b, 2)
        per = max(1, batch // (b * b))
        for a in range(0, len(ids), per):
            t_ids = ids[a:a + per]
            pi = lo[t_ids, 0][:, None] + off[None, :, 0]     # (n, b*b) integer i, then j
            pj = lo[t_ids, 1][:, None] + off[None, :, 1]
            tp = P[t_ids]
            v0 = tp[:, 1] - tp[:, 0]
            v1 = tp[:, 2] - tp[:, 0]
            den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
            good_t = np.abs(den) > 1e-12
            den = np.where(good_t, den, 1.0)[:, None]
            di, dj = pi - tp[:, 0, 0][:, None], pj - tp[:, 0, 1][:, None]
            l1 = (di * v1[:, 1][:, None] - dj * v1[:, 0][:, None]) / den
            l2 = (v0[:, 0][:, None] * dj - v0[:, 1][:, None] * di) / den
            l0 = 1.0 - l1 - l2
            least = np.minimum(np.minimum(l0, l1), l2)
            inside = (least >= -1e-7) & good_t[:, None]
            inside &= (pi >= 0) & (pi < ni) & (pj >= 0) & (pj < nj)
            tt, kk = np.nonzero(inside)
            lin = pj[tt, kk] * ni + pi[tt, kk]
            # hits count triangles holding the pixel centre strictly inside (not on a shared edge or vertex)
            strict = least[tt, kk] > 1e-3
            hits += np.bincount(lin[strict], minlength=len(hits)).astype(np.int32)
            tri[lin] = t_ids[tt]
            bary[lin] = np.stack([l0[tt, kk], l1[tt, kk], l2[tt, kk]], 1)
            prog((done + a + len(t_ids)) / len(f))
        done += len(ids)
        prog(done / len(f))
    return tri.reshape(nj, ni), bary.reshape(nj, ni, 3), hits.reshape(nj, ni)


@dataclass
class CutSurface:
    """The inner wall's surface (LPS mm) trimmed at the openings and cut open along the incision into a disc.

    ``near`` is each vertex's nearest point of the dense centreline ``Pd``; ``end_flag`` 1 on the cardia
    opening, 2 on the pylorus opening; ``is_copy`` marks the seam's duplicated vertices and ``partner`` their
    originals (-1 elsewhere); ``theta`` the angle about the centreline from the incision (radians).
    """

    v: np.ndarray
    f: np.ndarray
    vn: np.ndarray
    near: np.ndarray
    theta: np.ndarray
    is_copy: np.ndarray
    end_flag: np.ndarray
    partner: np.ndarray
    boundary_edges: np.ndarray
    Pd: np.ndarray
    info: dict


def cut_surface(prep, max_vertices: int = 20000, warnings: list | None = None) -> CutSurface:
    """Iso-surface of the prepared lumen's inner wall, trimmed at the centreline's end planes, cut along the incision."""
    warnings = [] if warnings is None else warnings
    crop, lumen, cl, inc = prep.crop, prep.lumen, prep.centerline, prep.incision
    # --- surface mesh, trimmed at the centreline's end planes ---------------------------------------------
    v, f, mc_step = inner_surface(lumen, crop, max_vertices, prep.lumen_is_mask)
    n_mc = len(v)
    P = np.asarray(cl.points_lps, float)
    # dense centreline (0.5 mm) with tangents and incision directions, for the cut angle of each vertex
    arc = cl.arclength_mm
    a_d = np.linspace(0.0, arc[-1], max(3, int(np.ceil(arc[-1] / 0.5)) + 1))
    Pd = np.stack([np.interp(a_d, arc, P[:, c]) for c in range(3)], 1)
    Ts = smooth_tangents(P, arc)
    Td = unit(np.stack([np.interp(a_d, arc, Ts[:, c]) for c in range(3)], 1))
    Id = unit(perpendicular(np.stack([np.interp(a_d, arc, inc.directions[:, c]) for c in range(3)], 1), Td))
    _, near = cKDTree(Pd).query(v)
    t0, t1 = Ts[0], Ts[-1]
    # beyond an end plane, near that end (a nearest-point test alone leaves a slanted rim of the cap)
    r_end = float(np.max(cl.radius_mm)) + 5.0
    beyond = (((a_d[near] < r_end) & ((v - P[0]) @ t0 < 0))
              | ((a_d[near] > arc[-1] - r_end) & ((v - P[-1]) @ t1 > 0)))
    keep = ~beyond[f].any(axis=1)
    f = f[keep]
    if len(f) < 100:
        raise AnatomyError("the lumen surface between the cardia and pylorus has almost no triangles; check the points")
    f = f[largest_component(len(v), f)]
    v, f, near = compact(v, f, near)
    vn, fn = vertex_normals(v, f)
    # outward (lumen -> wall) orientation, decided for the whole mesh: away from the centreline for most vertices
    radial = v - Pd[near]
    if np.mean(np.sum(vn * radial, 1) > 0) < 0.5:
        f = f[:, ::-1]
        vn, fn = -vn, -fn

    # --- cut along the incision line: duplicate the low-angle vertices of triangles straddling theta = 0 ----
    e1 = Id[near]
    e2 = np.cross(Td[near], e1)
    rad = perpendicular(radial, Td[near])
    # the two openings: boundary vertices of the trimmed (uncut) tube, by their position along the centreline
    e_all = sorted_edges(f)
    ue0, cnt0 = np.unique(e_all, axis=0, return_counts=True)
    open_v = np.unique(ue0[cnt0 == 1])
    end_flag = np.zeros(len(v), np.int8)
    end_flag[open_v[near[open_v] < 0.5 * len(Pd)]] = 1   # cardia opening
    end_flag[open_v[near[open_v] >= 0.5 * len(Pd)]] = 2  # pylorus opening
    theta = np.mod(np.arctan2(np.sum(rad * e2, 1), np.sum(rad * e1, 1)), 2 * np.pi)
    th_f = theta[f]
    straddle = (th_f.max(1) - th_f.min(1)) > np.pi
    low = straddle[:, None] & (th_f < np.pi)
    dup_src = np.unique(f[low])
    new_id = np.full(len(v), -1, np.int64)
    new_id[dup_src] = len(v) + np.arange(len(dup_src))
    f = f.copy()
    f[low] = new_id[f[low]]
    v = np.concatenate([v, v[dup_src]])
    vn = np.concatenate([vn, vn[dup_src]])
    near = np.concatenate([near, near[dup_src]])
    theta = np.concatenate([theta, theta[dup_src] + 2 * np.pi])
    end_flag = np.concatenate([end_flag, end_flag[dup_src]])
    is_copy = np.zeros(len(v), bool)
    is_copy[len(v) - len(dup_src):] = True
    partner = np.concatenate([np.arange(len(v) - len(dup_src)), dup_src])
    used = np.zeros(len(v), bool)
    used[np.unique(f)] = True
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(used.sum())
    partner = np.where(used[partner], remap[partner], -1)
    v, f, vn, near, theta, is_copy, end_flag, partner = compact(v, f, vn, near, theta, is_copy, end_flag, partner)
    partner[~is_copy] = -1                               # only copies point to their original
    # topology: a disc has Euler characteristic 1 and a single boundary loop
    edges = sorted_edges(f)
    ue, cnt = np.unique(edges, axis=0, return_counts=True)
    euler = len(v) - len(ue) + len(f)
    bnd = ue[cnt == 1]
    if euler != 1:
        warnings.append(f"the cut surface is not a topological disc (Euler characteristic {euler}); the flat map may "
                        "fold or tear")
    if len(dup_src) == 0:
        raise AnatomyError("the incision line does not cross the lumen surface; the surface cannot be cut open")
    info = {"marching_cubes_vertices": n_mc, "marching_cubes_step": mc_step, "vertices": int(len(v)),
            "triangles": int(len(f)), "seam_vertices": int(len(dup_src)), "euler_characteristic": int(euler),
            "boundary_edges": int(len(bnd))}
    return CutSurface(v, f, vn, near, theta, is_copy, end_flag, partner, bnd, Pd, info)


def orient_and_scale(uv: np.ndarray, cut: CutSurface, s: float, scale: bool = True) -> tuple[np.ndarray, float, float]:
    """Turn a flat map (V,2) so the mucosa faces +k and the cardia->pylorus axis runs along +i; with ``scale`` also
    give it the 3D surface's area (a conformal map's scale is arbitrary; an isometric one's is not).

    Returns (uv in mm with one pixel ``s`` of margin, fraction of flipped triangles, surface area in mm^2).
    """
    v, f, vn, near = cut.v, cut.f, cut.vn, cut.near
    bv = np.unique(cut.boundary_edges)
    uv = np.array(uv, float)
    # orientation: k must point into the lumen (the viewer's side), i.e. (i, j, k) right-handed with k = -outward
    sa = signed_area_2d(uv, f)
    n3 = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inward = -np.sum(n3 * (vn[f[:, 0]] + vn[f[:, 1]] + vn[f[:, 2]]), 1)
    if np.sum(np.sign(sa) == np.sign(inward)) < 0.5 * len(f):
        uv[:, 1] *= -1.0
        sa = -sa
    # rotate: cardia-end boundary -> pylorus-end boundary along +i
    ref = bv if len(bv) else np.arange(len(v))
    end_a = ref[near[ref] <= np.percentile(near[ref], 10)]
    end_b = ref[near[ref] >= np.percentile(near[ref], 90)]
    axis = uv[end_b].mean(0) - uv[end_a].mean(0)
    ang = np.arctan2(axis[1], axis[0])
    R = np.array([[np.cos(ang), np.sin(ang)], [-np.sin(ang), np.cos(ang)]])
    uv = uv @ R.T
    area3 = 0.5 * np.linalg.norm(n3, axis=1).sum()
    if scale:
        uv *= np.sqrt(area3 / max(abs(sa.sum()), 1e-12))
    flipped = float(np.mean(np.sign(signed_area_2d(uv, f)) != np.sign(inward)))
    uv = uv - uv.min(0) + s  # one pixel of margin
    return uv, flipped, float(area3)


#: Where the view's raster lies on the flat map: its pixels' offset (pixels, along i and j) from the map's own corner.
#: 0 in use; the benchmark's ``phase`` part moves it half a pixel to measure how much the judge's figures depend on
#: where the pixel centres fall (StomachUnfoldEval/raster_phase.py).
RASTER_OFFSET_PX = 0.0
#: Where the view's depth samples lie along the rays: their offset (voxels, toward the lumen) from the surface the map
#: was made of. 0 in use (the surface at a sample, slice ``k0``); the ``phase`` part moves it half a voxel to measure
#: how much the judge's figures depend on where the samples fall in depth.
DEPTH_OFFSET_PX = 0.0


def sample_flat_map(prep, cut: CutSurface, uv: np.ndarray, progress=None, hidden_lps: np.ndarray | None = None):
    """Rasterise a flat map (uv mm) of a CutSurface and sample the CT along the normals into the unfolded Volume.

    Returns (Volume (HU, k toward the viewer), to_unfolded, to_original, Mesh, info); the maps take and give
    (N,3) LPS mm (NaN off the wall). ``hidden_lps``: vertices (LPS mm) of surface left out of the map (a peeled
    fold): CT points nearer to them than to the map's surface are not on the view (NaN), not moved onto it.
    """
    from .methods import Mesh

    progress = progress or (lambda fraction: None)
    v, f, vn = cut.v, cut.f, cut.vn
    crop, lumen, s, w = prep.crop, prep.lumen, prep.pixel_mm, prep.params.wall_thickness_mm
    if RASTER_OFFSET_PX:
        uv = uv + float(RASTER_OFFSET_PX) * s   # the pixels laid elsewhere on the same map (the bench's `phase`)
    # --- rasterise and sample the CT along the normals -------------------------------------------------------
    ni = int(np.ceil(uv[:, 0].max() / s)) + 2
    nj = int(np.ceil(uv[:, 1].max() / s)) + 2
    if ni * nj > 25_000_000:
        raise SimulationError(f"the flattened surface spans {ni} x {nj} pixels: the conformal map degenerated")
    tri, bary, hits = view_raster(uv, f, (nj, ni), s, progress, open_mouths=True)
    covered = tri >= 0
    lift = getattr(cut, "lift", None)
    lift = None if lift is None or not np.any(lift > 0) else np.asarray(lift, float)
    depths, k0, nk = depth_axis(s, w, 0.0 if lift is None else float(lift.max()))
    if DEPTH_OFFSET_PX:
        depths = depths - float(DEPTH_OFFSET_PX) * s  # the samples moved toward the lumen (the bench's `phase`)
        k0 = k0 - float(DEPTH_OFFSET_PX)              # depth 0 then lies between samples: a fractional slice
    tt = tri[covered]
    bb = bary[covered]
    surf = np.einsum("nc,ncx->nx", bb, v[f[tt]])
    nrm = unit(np.einsum("nc,ncx->nx", bb, vn[f[tt]]))
    prof = sample_profiles(crop, surf, nrm, depths, lumen if prep.lumen_is_mask else None)
    if lift is not None:
        lifted_rays(prof, depths, INSIDE_MM + np.einsum("nc,nc->n", bb, lift[f[tt]]))
    arr = np.full((nk, nj, ni), -1024.0, np.float32)
    jj, ii = np.nonzero(covered)
    arr[:, jj, ii] = prof.T
    arr = to_int16(arr)
    pinholes = fill_pinholes(arr, tri=tri)                # on the stored HU: the view's reader sees the same
    vol = Volume(arr, np.full(3, s), np.zeros(3), np.eye(3))
    to_unfolded, to_original = flat_maps(v, f, vn, uv, tri, bary, s, k0, w, hidden_lps, view=vol)
    mesh = Mesh(v, np.concatenate([uv, np.full((len(uv), 1), k0 * s)], 1), f, "triangle", f)
    info = {"size_ij": [ni, nj], "depth_samples_k": nk, "spacing_mm": s,
            "param_overlap_pixel_fraction": float((hits > 1).sum() / max(int(covered.sum()), 1)),
            "pinholes_filled": pinholes}
    return vol, to_unfolded, to_original, mesh, info


def lifted_rays(prof: np.ndarray, depths: np.ndarray, reach: np.ndarray) -> None:
    """Clear (to -1024 HU, in place) what profiles (N, D at ``depths`` mm, the wall's side positive) read above
    ``reach`` (N, mm into the lumen) and, beyond INSIDE_MM, above the first air (HU at or under TISSUE_HU) met going
    up from depth 0: where a bridged dome stands above the membrane the map was made of, the ray starts as much higher
    to draw its top, but stops at the lumen's air, so in a narrow canal it does not read the far wall as well."""
    prof[depths[None, :] < -reach[:, None] - 1e-9] = -1024.0
    up = np.flatnonzero(depths <= 0.0)
    up = up[np.argsort(-depths[up], kind="stable")]           # from depth 0 into the lumen
    air = np.logical_or.accumulate(prof[:, up] <= TISSUE_HU, axis=1)
    above = np.zeros_like(air)
    above[:, 1:] = air[:, :-1]                              # strictly above the first air sample
    clear = above & (depths[up] < -INSIDE_MM - 1e-9)[None, :]
    block = prof[:, up]
    block[clear] = -1024.0
    prof[:, up] = block


PINHOLE_PIXELS = 2   # a view's patch without tissue of at most this many pixels, tissue all round it, is a pinhole


def fill_pinholes(arr: np.ndarray, max_pixels: int = PINHOLE_PIXELS, tri: np.ndarray | None = None) -> int:
    """Give pinholes of a view (arr (K,J,I) HU, k the depth) the median profile of their neighbours; in place.

    A pinhole is a patch of at most ``max_pixels`` pixels without tissue (no sample above TISSUE_HU) whose side
    neighbours all have tissue (a corner may touch the outside: the judge counts such a notch as a hole too): a
    crack that :func:`_close_cracks` left uncovered (no triangle within CRACK_PX + 0.5 pixels), or a wall thinner
    than a voxel that partial volume holds under the threshold along one ray (a real CT's 4 mm slices), which its
    neighbours' rays show. Either would be drawn as a black dot in the mucosa. Larger patches and patches on the
    view's border are left as they are (a gap in the wall, the view's edge). With ``tri`` (J,I: the raster's
    triangle per pixel, -1 none; in place) a filled crack pixel takes a neighbour's triangle, so the view-to-CT map
    finds a point there (extrapolated from that triangle, under a pixel away). Returns the number of pixels filled.
    """
    seen = arr.max(axis=0) > TISSUE_HU
    empty = ~seen
    if not empty.any():
        return 0
    lab, n = ndimage.label(empty)  # 4-connected, as the judge's holes (a notch open to the outside by a corner too)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    objects = ndimage.find_objects(lab)
    filled = 0
    for k in np.flatnonzero(sizes[1:] <= max_pixels) + 1:
        sl = objects[k - 1]
        if sl[0].start == 0 or sl[1].start == 0 or sl[0].stop == seen.shape[0] or sl[1].stop == seen.shape[1]:
            continue  # on the view's border: its edge, not a pinhole
        box = tuple(slice(q.start - 1, q.stop + 1) for q in sl)
        patch = lab[box] == k
        # the patch is a whole 4-connected patch without tissue: its side neighbours have tissue; the profile is
        # the median of every neighbour with tissue (corners too)
        ring = ndimage.binary_dilation(patch, structure=np.ones((3, 3), bool)) & ~patch & seen[box]
        sub = arr[:, box[0], box[1]]
        sub[:, patch] = np.round(np.median(sub[:, ring], axis=1))[:, None]
        filled += int(patch.sum())
        if tri is not None:
            t = tri[box]
            crack = patch & (t < 0)
            if crack.any():  # the triangle of a neighbour with one, nearest first (side neighbours before corners)
                _, (nj_, ni_) = ndimage.distance_transform_edt(t < 0, return_indices=True)
                t[crack] = t[nj_[crack], ni_[crack]]
    return filled


def view_raster(uv: np.ndarray, f: np.ndarray, shape_ji: tuple[int, int], s: float, prog: Progress | None = None,
                open_mouths: bool = False):
    """The pixels (j, i; pixel s mm, centres at (i*s, j*s) mm) a flat map (uv mm) covers in the view, as
    :func:`rasterise` gives them and extended by the outline's rim and closed cracks (:func:`_rim`): returns
    (triangle id per pixel, -1 none; barycentrics; triangles holding the pixel centre strictly inside). With
    ``open_mouths`` (the view itself), a notch's mouth the rim closed is opened again (:func:`_open_mouths`)."""
    tri, bary, hits = rasterise(uv, f, shape_ji, s, prog or (lambda fraction: None))
    tri, bary = _rim(uv, f, tri, bary, s)
    if open_mouths:
        _open_mouths(uv, f, tri, s)
    return tri, bary, hits


MOUTH_FINE = 4        # the finer raster that finds where a gap of the view meets the outside: pixels per view pixel
MOUTH_REACH_PX = 16   # how far (view pixels) about an enclosed gap the way out to the outside is looked for


def _open_mouths(uv, f, tri, s):
    """Reopen (in place: ``tri`` -1) the mouth that the raster's rim closed between an enclosed gap of the view and its
    outside, where the flat map (uv mm, pixel s mm) leaves a way between them narrower than a pixel.

    The outline's rim (:func:`_rim`) draws every pixel an outline edge reaches, so a notch of the map whose sides come
    within about a pixel (the cardia's opening, laid out between the fundus on both sides of the incision) is drawn
    closed at its mouth: a gap inside the mucosa, which the judge counts as a hole, though the map has none there. A gap
    of more than PINHOLE_PIXELS pixels is looked at in a raster MOUTH_FINE times finer (within MOUTH_REACH_PX pixels of
    it): when its uncovered points reach the view's outside there, the view pixels on the shortest such way (4-connected)
    are left uncovered, so the notch stays open as the map draws it. A gap the map itself encloses (a peeled fold's) has
    no way out and stays. Returns the number of pixels reopened."""
    covered = tri >= 0
    enclosed = ndimage.binary_fill_holes(covered) & ~covered
    if not enclosed.any():
        return 0
    lab, n = ndimage.label(enclosed)
    sizes = np.bincount(lab.ravel())
    cross = ndimage.generate_binary_structure(2, 1)
    nj, ni = tri.shape
    F, R = MOUTH_FINE, MOUTH_REACH_PX
    corners = np.take(uv, f, axis=0) / s                            # (F,3,2) pixel units
    t_lo, t_hi = corners.min(1), corners.max(1)
    opened = 0
    for r in np.flatnonzero(sizes[1:] > PINHOLE_PIXELS) + 1:
        outside = ~(tri >= 0) & ~ndimage.binary_fill_holes(tri >= 0)
        jj, ii = np.nonzero(lab == r)
        j0, j1 = max(jj.min() - R, 0), min(jj.max() + R, nj - 1)
        i0, i1 = max(ii.min() - R, 0), min(ii.max() + R, ni - 1)
        near = np.flatnonzero((t_hi[:, 0] >= i0 - 1) & (t_lo[:, 0] <= i1 + 1) & (t_hi[:, 1] >= j0 - 1)
                              & (t_lo[:, 1] <= j1 + 1))
        # the finer raster of the box: fine pixel (J, I) centred at view pixel (j0 + J / F, i0 + I / F)
        shape = ((j1 - j0) * F + 1, (i1 - i0) * F + 1)
        origin = np.array([i0, j0], float) * s
        fine, _, _ = rasterise(uv - origin, f[near], shape, s / F, lambda fraction: None)
        free = fine < 0
        J, I = np.mgrid[0:shape[0], 0:shape[1]]
        cj, ci = j0 + np.rint(J / F).astype(int), i0 + np.rint(I / F).astype(int)
        dist = np.where((lab[cj, ci] == r) & free, 0, -1)
        front, step, hit = dist == 0, 0, None
        goal = outside[cj, ci] & free
        while front.any() and hit is None:
            step += 1
            front = ndimage.binary_dilation(front, cross) & free & (dist < 0)
            dist[front] = step
            if (front & goal).any():
                hit = tuple(np.argwhere(front & goal)[0])
        if hit is None:
            continue                                                # no way out within reach: the map's own gap
        way = [hit]
        while dist[way[-1]] > 0:                                    # back along the 4-connected shortest way
            y, x = way[-1]
            for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < shape[0] and 0 <= xx < shape[1] and dist[yy, xx] == dist[y, x] - 1:
                    way.append((yy, xx))
                    break
        yy, xx = np.array(way).T
        pj, pi = cj[yy, xx], ci[yy, xx]
        shut = tri[pj, pi] >= 0
        opened += int(len(set(zip(pj[shut].tolist(), pi[shut].tolist()))))
        tri[pj[shut], pi[shut]] = -1
    return opened


def _rim(uv, f, tri, bary, s):
    """Extend the raster to every pixel whose square the flat map reaches: a pixel whose centre lies outside every
    triangle but whose square holds part of the outline takes the nearest point of that outline (its triangle, with
    barycentrics on the edge), so every point of the map is drawn in the pixel it rounds to and the mucosa reaches the
    view's edge. Inside the outline, pinholes and cracks at most two pixels wide (where a fold was peeled, the two
    sides' edges do not quite meet) are closed from the nearest covered pixel's triangle up to CRACK_PX pixels away;
    wider holes stay holes."""
    covered = tri >= 0
    if not covered.any():
        return tri, bary
    tri, bary = tri.copy(), bary.copy()
    _outline_squares(uv, f, tri, bary, s)
    _close_cracks(uv, f, tri, bary, s, tri >= 0)
    return tri, bary


def _close_cracks(uv, f, tri, bary, s, covered):
    """Fill (in place) enclosed uncovered pixels of cracks at most 2 x CRACK_PX wide from the nearest covered pixel's
    triangle, barycentrics clamped, where that triangle lies within CRACK_PX + 0.5 pixels."""
    enclosed = ndimage.binary_fill_holes(covered) & ~covered
    if not enclosed.any():
        return
    gap, (nj_idx, ni_idx) = ndimage.distance_transform_edt(~covered, return_indices=True)
    lab, n = ndimage.label(enclosed)
    inside = lab[enclosed]
    widest = np.zeros(n + 1)                                    # each enclosed region's largest gap (pixels)
    np.maximum.at(widest, inside, gap[enclosed])
    thin_lab = widest <= CRACK_PX
    thin_lab[0] = False
    jj, ii = np.nonzero(thin_lab[lab])
    if not len(jj):
        return
    t = tri[nj_idx[jj, ii], ni_idx[jj, ii]]
    a, b, c = uv[f[t, 0]], uv[f[t, 1]], uv[f[t, 2]]
    p = np.stack([ii * s, jj * s], 1)
    den = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    den = np.where(np.abs(den) > 1e-12, den, 1.0)
    l1 = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (p[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])) / den
    l2 = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (p[:, 0] - a[:, 0])) / den
    q = np.clip(np.stack([1 - l1 - l2, l1, l2], 1), 0.0, 1.0)
    q /= np.maximum(q.sum(1, keepdims=True), 1e-12)
    near = np.linalg.norm(np.einsum("nc,ncx->nx", q, uv[f[t]]) - p, axis=1) <= (CRACK_PX + 0.5) * s
    tri[jj[near], ii[near]] = t[near]
    bary[jj[near], ii[near]] = q[near]


def _outline_squares(uv, f, tri, bary, s, step_px: float = 0.5):
    """Fill (in place) the uncovered pixels whose square an outline edge of the flat map crosses: each takes the point
    of that edge, inside its square, nearest its centre (the nearest such edge's). A point of the map that rounds to
    an uncovered pixel lies in a square the outline crosses (the segment from it to the pixel's centre leaves the
    map in that square), so every such pixel is drawn. Candidates are the pixels round points ``step_px`` apart along
    each edge and their eight neighbours; each is kept only if the edge meets its square (a clipped segment)."""
    nj, ni = tri.shape
    nf = len(f)
    ends = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])          # (3F, 2): corner c to c+1
    key = sorted_edges(f) @ np.array([len(uv), 1], np.int64)
    _, first, count = np.unique(key, return_index=True, return_counts=True)
    edge = first[count == 1]                                                  # outline edges (one triangle)
    if not len(edge):
        return
    t_of, c_of = edge % nf, edge // nf                                        # triangle; its corners c, (c+1)%3
    a, b = uv[ends[edge, 0]] / s, uv[ends[edge, 1]] / s                       # pixel units
    n = np.ceil(np.linalg.norm(b - a, axis=1) / step_px).astype(np.int64) + 1
    e = np.repeat(np.arange(len(edge)), n)
    tau = (np.arange(len(e)) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(np.maximum(n - 1, 1), n)
    pix = np.rint(a[e] + tau[:, None] * (b[e] - a[e])).astype(np.int64)
    nb = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 2)
    pix = (pix[:, None, :] + nb[None]).reshape(-1, 2)
    e = np.repeat(e, len(nb))
    ok = (pix[:, 0] >= 0) & (pix[:, 0] < ni) & (pix[:, 1] >= 0) & (pix[:, 1] < nj)
    e, pix = e[ok], pix[ok]
    ok = tri[pix[:, 1], pix[:, 0]] < 0
    if not ok.any():
        return
    ne = len(edge)
    pair = np.unique((pix[ok, 1] * ni + pix[ok, 0]) * ne + e[ok])       # (pixel, edge) once each, by pixel then edge
    lin, e = pair // ne, pair % ne
    centre = np.stack([lin % ni, lin // ni], 1).astype(float)
    d = b[e] - a[e]
    # the part [t0, t1] of each edge inside the pixel's square (Liang-Barsky), empty when t0 > t1
    t0, t1 = np.zeros(len(e)), np.ones(len(e))
    for x in range(2):
        flat = np.abs(d[:, x]) < 1e-12
        dd = np.where(flat, 1.0, d[:, x])
        lo, hi = (centre[:, x] - 0.5 - a[e, x]) / dd, (centre[:, x] + 0.5 - a[e, x]) / dd
        t0 = np.where(flat, t0, np.maximum(t0, np.minimum(lo, hi)))
        t1 = np.where(flat, t1, np.minimum(t1, np.maximum(lo, hi)))
        t1 = np.where(flat & (np.abs(a[e, x] - centre[:, x]) > 0.5), -1.0, t1)
    meets = t0 <= t1 + 1e-12
    if not meets.any():
        return
    lin, e, d, centre, t0, t1 = lin[meets], e[meets], d[meets], centre[meets], t0[meets], t1[meets]
    w = np.clip(np.sum((centre - a[e]) * d, 1) / np.maximum(np.sum(d * d, 1), 1e-18), t0, np.maximum(t0, t1))
    dist = np.linalg.norm(a[e] + w[:, None] * d - centre, axis=1)
    order = np.lexsort((dist, lin))                                           # per pixel, its nearest edge first
    lin, e, w = lin[order], e[order], w[order]
    one = np.r_[True, lin[1:] != lin[:-1]]
    lin, e, w = lin[one], e[one], w[one]
    q = np.zeros((len(e), 3))
    r = np.arange(len(e))
    q[r, c_of[e]] = 1.0 - w
    q[r, (c_of[e] + 1) % 3] = w
    tri.reshape(-1)[lin] = t_of[e]
    bary.reshape(-1, 3)[lin] = q


def flat_maps(v, f, vn, uv, tri, bary, s, k0, w, hidden_lps=None, view: Volume | None = None):
    """The two maps of a flattened surface: CT LPS mm -> unfolded LPS mm (by the foot on a triangle round the nearest
    vertex, or along the view's rays with RAY_INVERSE / RAY_SIDE), and back through the raster (tri, bary; pixel ``s``
    mm, the surface at slice ``k0``, wall ``w`` mm). ``view``: the unfolded Volume (HU) drawn from this raster, read by
    RAY_SIDE "shown" to tell where the view shows a point."""
    nj, ni = tri.shape
    first: list = []                     # the view's first-hit k per pixel, read once when first needed

    def shown(uvp, depth) -> np.ndarray:
        """Whether the view's first tissue (view.first_hit) along the pixel of uvp (mm) lies within SHOWN_VOXELS
        voxels or SHOWN_MM mm of the depth (mm), as the judge (quality.visible_points) tells a point seen."""
        if view is None:
            return np.ones(len(uvp), bool)
        if not first:
            from .view import first_hit

            first.append(first_hit(view)[0])
        kh = first[0]
        ii, jj = np.rint(uvp[:, 0] / s).astype(np.int64), np.rint(uvp[:, 1] / s).astype(np.int64)
        ok = (ii >= 0) & (ii < kh.shape[1]) & (jj >= 0) & (jj < kh.shape[0])
        hit = np.full(len(uvp), -1, np.int64)
        hit[ok] = kh[jj[ok], ii[ok]]
        tol = max(SHOWN_VOXELS, SHOWN_MM / s)
        return (hit >= 0) & (np.abs(hit - (k0 - depth / s)) <= tol)

    # --- map from the CT ------------------------------------------------------------------------------------
    tree = cKDTree(v)
    hidden = cKDTree(np.asarray(hidden_lps, float)) if hidden_lps is not None and len(hidden_lps) else None
    order = np.argsort(np.concatenate([f[:, 0], f[:, 1], f[:, 2]]), kind="stable")
    vt_face = np.tile(np.arange(len(f)), 3)[order]
    vt_start = np.searchsorted(np.concatenate([f[:, 0], f[:, 1], f[:, 2]])[order], np.arange(len(v) + 1))
    deg = np.diff(vt_start)
    maxdeg = int(deg.max())
    inc_tris = np.full((len(v), maxdeg), -1, np.int64)
    for c in range(maxdeg):
        has = deg > c
        inc_tris[has, c] = vt_face[vt_start[:-1][has] + c]
    max_dist = w + CLEARANCE_MM + 6.0

    def to_unfolded(points_lps) -> np.ndarray:
        """(N,3) LPS mm of the CT -> (N,3) LPS mm of the unfolded volume (NaN where unmapped)."""
        p = np.asarray(points_lps, float).reshape(-1, 3)
        out = np.full((len(p), 3), np.nan)
        if len(p) == 0:
            return out
        dist, vi = tree.query(p)
        cand = inc_tris[vi]                                   # (n, maxdeg)
        valid = cand >= 0
        cf = f[np.where(valid, cand, 0)]                      # (n, maxdeg, 3)
        a, b, c = v[cf[..., 0]], v[cf[..., 1]], v[cf[..., 2]]
        nrm_t = np.cross(b - a, c - a)
        nn = unit(nrm_t)
        q = p[:, None, :] - np.sum((p[:, None, :] - a) * nn, -1, keepdims=True) * nn     # projection on the plane
        v0, v1, v2 = b - a, c - a, q - a
        d00, d01, d11 = np.sum(v0 * v0, -1), np.sum(v0 * v1, -1), np.sum(v1 * v1, -1)
        d20, d21 = np.sum(v2 * v0, -1), np.sum(v2 * v1, -1)
        den = np.where(np.abs(d00 * d11 - d01 ** 2) > 1e-12, d00 * d11 - d01 ** 2, 1.0)
        l1 = (d11 * d20 - d01 * d21) / den
        l2 = (d00 * d21 - d01 * d20) / den
        lam = np.stack([1 - l1 - l2, l1, l2], -1)
        score = np.where(valid, lam.min(-1), -np.inf)
        best = np.argmax(score, axis=1)
        r = np.arange(len(p))
        lb = np.clip(lam[r, best], 0.0, 1.0)
        lb /= np.maximum(lb.sum(1, keepdims=True), 1e-12)
        fb = cf[r, best]
        uvp = np.einsum("nc,ncx->nx", lb, uv[fb])
        sp = np.einsum("nc,ncx->nx", lb, v[fb])
        nb = unit(np.einsum("nc,ncx->nx", lb, vn[fb]))
        depth = np.sum((p - sp) * nb, 1)
        if RAY_INVERSE:  # where a view's ray passes through the point, that ray's pixel and depth instead
            on, uv_r, depth_r = _along_rays(p, cand, tree, inc_tris, v, f, vn, uv)
            uvp[on], depth[on] = uv_r[on], depth_r[on]
        elif RAY_SIDE in ("tissue", "shown"):  # a point in the tissue, where the rays are drawn, by a ray meeting it there
            sel = np.flatnonzero(depth > 0)
            if len(sel):
                on, uv_r, depth_r = _along_rays(p[sel], cand[sel], tree, inc_tris, v, f, vn, uv)
                on &= depth_r > 0
                if RAY_SIDE == "shown":  # not where the view shows the point at its foot and not along the ray
                    on &= ~(shown(uvp[sel], depth[sel]) & ~shown(uv_r, depth_r))
                uvp[sel[on]], depth[sel[on]] = uv_r[on], depth_r[on]
        fk = k0 - depth / s
        res = np.stack([uvp[:, 0], uvp[:, 1], fk * s], 1)
        res[dist > max_dist] = np.nan
        if hidden is not None:  # nearer to a peeled fold than to the map: that mucosa is not shown
            res[hidden.query(p)[0] < dist] = np.nan
        return res

    def to_original(points_lps) -> np.ndarray:
        """(N,3) LPS mm of the unfolded volume -> (N,3) LPS mm of the CT (NaN outside the flattened surface)."""
        q = np.asarray(points_lps, float).reshape(-1, 3)
        out = np.full((len(q), 3), np.nan)
        ii = np.rint(q[:, 0] / s).astype(np.int64)
        jj = np.rint(q[:, 1] / s).astype(np.int64)
        ok = (ii >= 0) & (ii < ni) & (jj >= 0) & (jj < nj)
        t = np.full(len(q), -1, np.int64)
        t[ok] = tri[jj[ok], ii[ok]]
        ok &= t >= 0
        if not ok.any():
            return out
        fb = f[t[ok]]
        a, b, c = uv[fb[:, 0]], uv[fb[:, 1]], uv[fb[:, 2]]
        p = q[ok, :2]
        den = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        den = np.where(np.abs(den) > 1e-12, den, 1.0)
        l1 = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (p[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])) / den
        l2 = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (p[:, 0] - a[:, 0])) / den
        lam = np.stack([1 - l1 - l2, l1, l2], 1)
        sp = np.einsum("nc,ncx->nx", lam, v[fb])
        nb = unit(np.einsum("nc,ncx->nx", lam, vn[fb]))
        depth = (k0 - q[ok, 2] / s) * s
        out[ok] = sp + depth[:, None] * nb
        return out

    return to_unfolded, to_original


#: The map from the CT into the view is the inverse of the view's rays: a point goes to the pixel whose ray (from the
#: surface along the smoothed normal) passes through it, at that depth; not to its foot on the nearest triangle, which
#: parts from the ray by the depth times the normals' tilt. Under a small dome (a bead, a polyp as large as the slices
#: are thick) the rays converge: the dome's whole top passes within RAY_FOCUS_MM (mm) of its centre, and one ray
#: alone would put the centre anywhere on the dome's image. Where the rays passing that near, at depths within
#: RAY_FOCUS_MM of the nearest ray's, start more than 2 RAY_FOCUS_MM apart in the view, the point goes to the mean of
#: their pixels: the middle of the dome's image. A point deeper than RAY_FOCUS_MM is looked for among the triangles of
#: the vertices within RAY_FOCUS_MM + 1 mm of its nearest vertex's distance (at most RAY_FOCUS_VERTICES, the nearest).
#: Rule 33 (docs/RULE33_map_along_the_rays.md): on CT 03's hybrids the markers seen 326 -> 362 of 387 and the mean
#: distance of a marker's place from its drawn bead 0.74 -> 0.31 mm (tuning), but it failed its decision sets: the same
#: map gave LSCM one more mucosa point on hybrid 01-46058, one point ahead of the isometric view. Rule 35
#: (docs/RULE35_ray_map_as_the_correspondence.md) asked again on new sets with criteria on the isometric view: CT 03's
#: hybrids 308 -> 352 of 383 markers, but the small stomachs' median distortion rose 0.00002 and one hybrid lost 0.101
#: point of visible mucosa (0.1 allowed): failed as written. Off (RAY_INVERSE).
RAY_INVERSE = False
#: Rule 38 (docs/RULE38_tissue_side_along_the_rays.md): "tissue" sends only the points on the tissue side of the wall
#: (depth along the normal from their foot over 0) along the view's rays, where the view draws them, and keeps the
#: foot of a point on the lumen side, where no ray is drawn. None: every point by its foot (RAY_INVERSE: every one
#: along the rays). It saw 323 -> 373 of 408 markers on CT 03's new hybrids and lowered the marker distortion on
#: every set, but failed its decision sets when one hybrid already graded fair lost 0.25 point of visible mucosa.
#: Rule 41 (docs/RULE41_ray_where_shown.md), the default: "shown" is rule 38 but a point the view shows at its foot and
#: not along the ray keeps its foot: of the two places, the one where the view draws it (the ray where both or
#: neither do). The view is the same to the bit. On its decision sets CT 03's hybrids showed 325 -> 373 of 402 markers
#: and every criterion held.
RAY_SIDE: str | None = "shown"
#: A point is shown at a pixel when the view's first tissue there lies within SHOWN_VOXELS voxels or SHOWN_MM mm of its
#: depth (the judge's tolerance, quality.visible_points).
SHOWN_VOXELS = 2.0
SHOWN_MM = 2.5
RAY_FOCUS_MM = 1.0
RAY_FOCUS_VERTICES = 400


def _phong_solve(p: np.ndarray, cand: np.ndarray, v, f, vn, iters: int = 8):
    """Where the rays of candidate triangles pass through points: for p (n,3) LPS mm and triangle ids cand (n,m; -1
    none), barycentrics (n,m,3), depth (n,m; mm along the unit interpolated normal), residual (n,m; mm, inf for none).

    Solves p = sum(l v) + t sum(l vn) for (l1, l2, t) by Newton's method from the point's foot on the triangle's plane,
    on the candidates that exist, one coordinate array per axis (x, y, z).
    """
    n, m = cand.shape
    lam = np.zeros((n, m, 3))
    depth = np.zeros((n, m))
    resid = np.full((n, m), np.inf)
    cf = f[np.where(cand >= 0, cand, 0)]
    pi, ci = np.nonzero(cand >= 0)
    if not len(pi):
        return lam, depth, resid, cf
    tri = f[cand[pi, ci]]
    a, na = v[tri[:, 0]].T, vn[tri[:, 0]].T                  # (3, K): one row per axis
    e1, e2 = v[tri[:, 1]].T - a, v[tri[:, 2]].T - a
    d1, d2 = vn[tri[:, 1]].T - na, vn[tri[:, 2]].T - na
    q = p[pi].T - a

    def dot(x, y):
        return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]

    def cross(x, y):
        return np.stack([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]])

    fn = cross(e1, e2)
    fn = fn / np.maximum(np.sqrt(dot(fn, fn)), 1e-12)
    t = dot(q, fn)
    w = q - t * fn
    d00, d01, d11, d20, d21 = dot(e1, e1), dot(e1, e2), dot(e2, e2), dot(w, e1), dot(w, e2)
    den = d00 * d11 - d01 ** 2
    den = np.where(np.abs(den) > 1e-12, den, 1.0)
    l1, l2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    for _ in range(iters):  # Newton: the Jacobian's columns j1, j2, nrm; the step by Cramer's rule
        nrm = na + l1 * d1 + l2 * d2
        F = l1 * e1 + l2 * e2 + t * nrm - q
        j1, j2 = e1 + t * d1, e2 + t * d2
        c23, c31, c12 = cross(j2, nrm), cross(nrm, j1), cross(j1, j2)
        det = dot(j1, c23)
        det = np.where(np.abs(det) > 1e-12, det, np.inf)
        s1, s2, s3 = (np.clip(-dot(F, c) / det, -2.0, 2.0) for c in (c23, c31, c12))
        l1, l2, t = l1 + s1, l2 + s2, t + s3
        if max(np.abs(s1).max(), np.abs(s2).max(), np.abs(s3).max()) < 1e-9:
            break
    nrm = na + l1 * d1 + l2 * d2
    F = l1 * e1 + l2 * e2 + t * nrm - q
    lam[pi, ci] = np.stack([1.0 - l1 - l2, l1, l2], 1)
    depth[pi, ci] = t * np.sqrt(dot(nrm, nrm))
    r = np.sqrt(dot(F, F))
    resid[pi, ci] = np.where(np.isfinite(r), r, np.inf)
    return lam, depth, resid, cf


def _ray_pick(lam, depth, resid, cf, uv):
    """The ray through each point nearest the surface among _phong_solve's answers: (whether one passes, its pixel uv
    mm (n,2), its depth mm (n,), its surface point's barycentrics (n,3) and triangle's vertex ids (n,3))."""
    hit = (resid < 1e-3) & (lam.min(-1) >= -1e-6)
    best = np.argmin(np.where(hit, np.abs(depth), np.inf), 1)
    r = np.arange(len(lam))
    lb = np.clip(lam[r, best], 0.0, 1.0)
    lb = lb / np.maximum(lb.sum(-1, keepdims=True), 1e-12)
    return hit.any(1), np.einsum("nc,ncx->nx", lb, uv[cf[r, best]]), depth[r, best], lb, cf[r, best]


def _focus(p, vk, u0, dep, sp, v, vn, uv):
    """Where the rays of a wide patch of vertices vk (n,m; -1 none) pass within RAY_FOCUS_MM of points p (n,3 LPS mm)
    at about the depth of the ray through it (dep mm, from surface point sp, at pixel u0 mm): the mean of their pixels,
    else u0 (n,2); the vertices across the incision from sp (far apart in the view, near in the CT) left out."""
    ok = vk >= 0
    w = v[np.maximum(vk, 0)]
    n = vn[np.maximum(vk, 0)]
    r = p[:, None, :] - w
    t = np.sum(r * n, -1)
    miss = np.linalg.norm(r - t[..., None] * n, axis=-1)
    u = uv[np.maximum(vk, 0)]
    apart = np.linalg.norm(u - u0[:, None], axis=-1)
    near = ok & (miss <= RAY_FOCUS_MM) & (np.abs(t - dep[:, None]) <= RAY_FOCUS_MM)
    near &= apart <= 1.5 * np.linalg.norm(w - sp[:, None], axis=-1) + 1.0
    spread = np.where(near, apart, 0.0).max(1) > 2.0 * RAY_FOCUS_MM
    mean = np.einsum("nm,nmx->nx", near.astype(float), u) / np.maximum(near.sum(1), 1)[:, None]
    return np.where(spread[:, None], mean, u0)


def _along_rays(p: np.ndarray, cand: np.ndarray, tree, inc_tris, v, f, vn, uv):
    """The view's rays through CT points p (n,3 LPS mm): (whether one passes, pixel uv mm (n,2), depth mm (n,)).

    First among the triangles ``cand`` round each point's nearest vertex; then, for a point deeper than RAY_FOCUS_MM or
    passed by none, among those of the vertices about as near, with the mean pixel where the rays converge.
    """
    on, uvp, dep, _, _ = _ray_pick(*_phong_solve(p, cand, v, f, vn), uv)
    again = np.flatnonzero(~on | (np.abs(dep) > RAY_FOCUS_MM))
    for blk in np.array_split(again, max(1, int(np.ceil(len(again) / 128)))):   # bounded memory
        if not len(blk):
            continue
        d0, _ = tree.query(p[blk])
        balls = tree.query_ball_point(p[blk], d0 + RAY_FOCUS_MM + 1.0)       # vertices about as near as the nearest
        vk = np.full((len(blk), min(max(len(b) for b in balls), RAY_FOCUS_VERTICES)), -1, np.int64)
        for i, b in enumerate(balls):
            b = np.asarray(b, np.int64)
            if len(b) > vk.shape[1]:
                b = b[np.argsort(np.linalg.norm(v[b] - p[blk[i]], axis=1))[:vk.shape[1]]]
            vk[i, :len(b)] = b
        c2 = np.where(vk[..., None] >= 0, inc_tris[np.maximum(vk, 0)], -1).reshape(len(blk), -1)
        c2 = -np.sort(-c2, 1)
        c2[:, 1:][c2[:, 1:] == c2[:, :-1]] = -1                 # each triangle once
        c2 = -np.sort(-c2, 1)
        c2 = c2[:, :max(1, int((c2 >= 0).sum(1).max()))]
        on2, uv2, dep2, lb, fb = _ray_pick(*_phong_solve(p[blk], c2, v, f, vn), uv)
        if on2.any():
            sp = np.einsum("nc,ncx->nx", lb, v[fb])
            uv2[on2] = _focus(p[blk][on2], vk[on2], uv2[on2], dep2[on2], sp[on2], v, vn, uv)
        sel = blk[on2]
        on[sel], uvp[sel], dep[sel] = True, uv2[on2], dep2[on2]
    return on, uvp, dep
