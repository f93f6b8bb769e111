"""Near-isometric flattening of the inner wall: As-Rigid-As-Possible parameterisation (Liu et al. 2008) of the cut-open
lumen surface, then sampling the CT along the wall's normals.

Stages: the inner wall's iso-surface (``surface.inner_surface``), either trimmed at the centreline's end planes
(``isometric_surface="trimmed"``, as the lscm peer) or the whole lumen's closed surface with small holes at the
cardia and pylorus openings (``"whole"``: keeps the fundus dome); a cut along the incision line (on the whole
surface a Dijkstra path on the mesh's edges from opening to opening, its vertices duplicated) makes a disc; the
flat map starts from the tube's conformal map (or LSCM with two pins) and is relaxed by ARAP local/global
iterations (cotangent Laplacian factorised once, per-triangle closest rotations, free boundary); the flat map is
turned so that the mucosa faces +k and the cardia->pylorus axis runs along +i, not rescaled; the unfolded volume is
sampled along the vertex normals (``surface.sample_flat_map``). Expected behaviour: lengths and areas kept where
the surface is developable (a tube, a bent tube), curvature of the dome and the bends spread evenly over the map,
no overlap unless the flat map flips triangles (counted in the report).
"""
from __future__ import annotations

import time

import numpy as np

from ..correspondence import MapCorrespondence
from ..errors import AnatomyError, SimulationError
from ..frontend import timed_stage
from ..surface import cut_surface, lscm, signed_area_2d, sample_flat_map, tube_conformal
from . import Method, Unfolding, register

__all__ = ["IsometricFlattening", "arap", "triangle_frames", "cot_laplacian", "stretch_stats", "cut_along_path",
           "MAX_MESH_VERTICES"]

MAX_MESH_VERTICES = 40000


def triangle_frames(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's vertices in its own isometric 2D frame ((F,3,2) mm) and its area (F, mm^2)."""
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    n = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(n, axis=1)
    l1 = np.maximum(np.linalg.norm(e1, axis=1), 1e-12)
    u = e1 / l1[:, None]
    w = np.cross(n / np.maximum(2 * area, 1e-12)[:, None], u)
    x = np.zeros((len(f), 3, 2))
    x[:, 1, 0] = l1
    x[:, 2, 0] = np.sum(e2 * u, 1)
    x[:, 2, 1] = np.sum(e2 * w, 1)
    return x, area


def _half_edge_cot(x: np.ndarray) -> np.ndarray:
    """Cotangent (F,3) of the angle opposite half-edge c = (c+1, c+2) of each 2D triangle x (F,3,2)."""
    cot = np.empty(x.shape[:2])
    for c in range(3):
        a = x[:, (c + 1) % 3] - x[:, c]
        b = x[:, (c + 2) % 3] - x[:, c]
        cr = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        cot[:, c] = np.sum(a * b, 1) / np.maximum(np.abs(cr), 1e-12)
    return cot


def cot_laplacian(f: np.ndarray, w: np.ndarray, nv: int):
    """Sparse (V,V) weighted graph Laplacian sum_e w_e (x_i - x_j)^2 from half-edge weights w (F,3) (csc)."""
    from scipy.sparse import coo_matrix

    i = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    ww = np.concatenate([w[:, 0], w[:, 1], w[:, 2]])
    off = coo_matrix((-ww, (i, j)), shape=(nv, nv))
    L = off + off.T
    d = -np.asarray(L.sum(axis=1)).ravel()
    from scipy.sparse import diags

    return (L + diags(d)).tocsc()


def arap(v: np.ndarray, f: np.ndarray, uv0: np.ndarray, max_iter: int = 50, tol: float = 1e-5, progress=None,
         weight_clip: tuple = (1e-3, 1e3)) -> tuple[np.ndarray, dict]:
    """ARAP flat map (V,2 mm) of a disc mesh (v LPS mm, f triangles) from the start map uv0; free boundary.

    Local/global iterations (Liu et al. 2008): per-triangle closest rotations of the current Jacobians, then one
    solve with the cotangent Laplacian (factorised once; one vertex pinned for translation). Stops when the
    relative energy change is under ``tol``. Returns (uv, info with iterations, energy trace, flipped count).
    """
    from scipy.sparse.linalg import splu

    progress = progress or (lambda fraction: None)
    nv, nf = len(v), len(f)
    x, area = triangle_frames(v, f)
    good = area > 1e-10 * max(float(np.median(area)), 1e-12)
    w = np.clip(_half_edge_cot(x), *weight_clip) * good[:, None]     # half-edge weights (F,3)
    L = cot_laplacian(f, w, nv)
    # edge vectors of the rest triangles for half-edge c: from vertex c+1 to vertex c+2
    i1, i2 = [(c + 1) % 3 for c in range(3)], [(c + 2) % 3 for c in range(3)]
    dx = x[:, i2] - x[:, i1]                                          # (F,3,2)
    pin = int(np.argmax(np.bincount(f.ravel(), minlength=nv)))
    keep = np.ones(nv, bool)
    keep[pin] = False
    Lr = L[keep][:, keep].tocsc()
    try:
        lu = splu(Lr, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as e:
        raise SimulationError(f"the ARAP system of the surface could not be factorised ({e}); the mesh is broken") from e
    col_pin = L[:, pin].toarray().ravel()[keep]
    uv = np.array(uv0, float)
    energies = []
    fa, fb = f[:, i1].ravel(), f[:, i2].ravel()                          # half-edge tails and heads (3F)
    wr = w.ravel()
    dxr = dx.reshape(-1, 2)

    def rotations(uv):
        du = (uv[fb] - uv[fa])                                          # (3F,2) current half-edge vectors
        wd = wr[:, None] * du
        s00 = (wd[:, 0] * dxr[:, 0]).reshape(nf, 3).sum(1)
        s01 = (wd[:, 0] * dxr[:, 1]).reshape(nf, 3).sum(1)
        s10 = (wd[:, 1] * dxr[:, 0]).reshape(nf, 3).sum(1)
        s11 = (wd[:, 1] * dxr[:, 1]).reshape(nf, 3).sum(1)
        ang = np.arctan2(s10 - s01, s00 + s11)
        cs, sn = np.repeat(np.cos(ang), 3), np.repeat(np.sin(ang), 3)
        rdx = np.stack([cs * dxr[:, 0] - sn * dxr[:, 1], sn * dxr[:, 0] + cs * dxr[:, 1]], 1)
        return du, rdx

    it = 0
    for it in range(1, max_iter + 1):
        du, rdx = rotations(uv)
        energies.append(float(np.sum(wr[:, None] * (du - rdx) ** 2)))
        # global step: L u = b, b_head += w R dx, b_tail -= w R dx
        c = wr[:, None] * rdx
        b = np.stack([np.bincount(fb, c[:, k], nv) - np.bincount(fa, c[:, k], nv) for k in range(2)], 1)
        rhs = b[keep] - col_pin[:, None] * uv[pin][None, :]
        new = uv.copy()
        new[keep] = lu.solve(np.ascontiguousarray(rhs))
        if not np.all(np.isfinite(new)):
            raise SimulationError("the ARAP flat map diverged (non-finite coordinates); the surface mesh is broken")
        uv = new
        progress(it / max_iter)
        if len(energies) >= 2 and abs(energies[-2] - energies[-1]) <= tol * max(energies[-1], 1e-12):
            break
    du, rdx = rotations(uv)
    e_final = float(np.sum(wr[:, None] * (du - rdx) ** 2))
    sa = signed_area_2d(uv, f)
    major = np.sign(np.sum(np.sign(sa[good]))) or 1.0
    flipped = int(np.sum((np.sign(sa) != major) & good))
    total_w = float(np.sum(wr[:, None] * dxr ** 2))
    return uv, {"arap_iterations": it, "arap_energy": e_final, "arap_energy_relative": e_final / max(total_w, 1e-12),
                "arap_energy_trace": [float(e) for e in energies[:: max(1, len(energies) // 10)]],
                "flipped_triangles": flipped, "degenerate_triangles": int((~good).sum())}


def stretch_stats(v: np.ndarray, f: np.ndarray, uv: np.ndarray) -> dict:
    """Per-triangle singular values of the flat map's Jacobian: max / 95th percentile of the stretch (s1) and of 1/s2."""
    x, area = triangle_frames(v, f)
    y = uv[f]
    ok = area > 1e-10
    A = np.stack([x[ok, 1] - x[ok, 0], x[ok, 2] - x[ok, 0]], -1)      # (n,2,2) columns = edges
    B = np.stack([y[ok, 1] - y[ok, 0], y[ok, 2] - y[ok, 0]], -1)
    J = B @ np.linalg.inv(A)
    s = np.linalg.svd(J, compute_uv=False)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    l0 = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    l1 = np.linalg.norm(uv[e[:, 0]] - uv[e[:, 1]], axis=1)
    r = l1 / np.maximum(l0, 1e-12)
    return {"stretch_max": float(s[:, 0].max()), "stretch_p95": float(np.percentile(s[:, 0], 95)),
            "shrink_max": float((1 / np.maximum(s[:, 1], 1e-12)).max()),
            "edge_ratio_max": float(r.max()), "edges_over_1p5": float(np.mean(r > 1.5))}


def orient_rigid(uv: np.ndarray, cut, s: float) -> tuple[np.ndarray, float]:
    """Mirror/rotate a flat map (V,2 mm) so the mucosa faces +k and cardia->pylorus runs along +i; no rescaling.

    Returns (uv mm shifted to one pixel ``s`` of margin, fraction of triangles flipped against the mucosa side).
    """
    v, f, vn, near = cut.v, cut.f, cut.vn, cut.near
    bv = np.unique(cut.boundary_edges)
    uv = np.array(uv, float)
    sa = signed_area_2d(uv, f)
    n3 = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inward = -np.sum(n3 * (vn[f[:, 0]] + vn[f[:, 1]] + vn[f[:, 2]]), 1)
    if np.sum(np.sign(sa) == np.sign(inward)) < 0.5 * len(f):
        uv[:, 1] *= -1.0
    ref = bv if len(bv) else np.arange(len(v))
    end_a = ref[near[ref] <= np.percentile(near[ref], 10)]
    end_b = ref[near[ref] >= np.percentile(near[ref], 90)]
    axis = uv[end_b].mean(0) - uv[end_a].mean(0)
    ang = np.arctan2(axis[1], axis[0])
    R = np.array([[np.cos(ang), np.sin(ang)], [-np.sin(ang), np.cos(ang)]])
    uv = uv @ R.T
    flipped = float(np.mean(np.sign(signed_area_2d(uv, f)) != np.sign(inward)))
    return uv - uv.min(0) + s, flipped


def cut_along_path(v: np.ndarray, f: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut an oriented manifold mesh open along a simple vertex path: its interior vertices are duplicated.

    The triangles on one side (swept counter-clockwise about each path vertex from the previous path vertex to
    the next) get the copies. Returns (v with copies appended, f renumbered, source vertex of each copy).
    """
    path = np.asarray(path, np.int64)
    on = np.zeros(len(v), bool)
    on[path[1:-1]] = True
    tri_of = {}
    sel = np.flatnonzero(on[f].any(1))
    for t in sel:
        a, b, c = f[t]
        for p, q, r in ((a, b, c), (b, c, a), (c, a, b)):
            if on[p]:
                tri_of[(int(p), int(q))] = (int(t), int(r))
    f = f.copy()
    copies = []
    nv = len(v)
    for n in range(1, len(path) - 1):
        c, prev, nxt = int(path[n]), int(path[n - 1]), int(path[n + 1])
        new = nv + len(copies)
        copies.append(c)
        q = prev
        for _ in range(64):                       # walk the fan from the edge (c, prev) to the edge (c, next)
            if (c, q) not in tri_of:
                raise AnatomyError("the cut path crosses a non-manifold or boundary part of the lumen surface")
            t, r = tri_of[(c, q)]
            f[t][f[t] == c] = new
            if r == nxt:
                break
            q = r
        else:
            raise AnatomyError("the cut path could not be followed around a vertex of the lumen surface")
    src = np.array(copies, np.int64)
    return np.concatenate([v, v[src]]), f, src


@register
class IsometricFlattening(Method):
    """ARAP (as-rigid-as-possible) flattening of the cut-open inner wall (LPS mm in, unfolded Volume in mm)."""

    name = "isometric"
    description = "as-rigid-as-possible (near-isometric) flattening of the cut-open inner wall"
    stages = (("surface", 0.3), ("flat map", 0.3), ("volume", 0.4))

    def unfold(self, prep, progress) -> Unfolding:
        """Cut the inner wall open along the incision, flatten it near-isometrically, sample the CT along the normals."""
        warnings, seconds = [], {}
        with timed_stage(progress, "surface", seconds, 0.0, 0.3) as report:
            cut = cut_surface(prep, MAX_MESH_VERTICES, warnings)
            report(1.0)
        with timed_stage(progress, "flat map", seconds, 0.3, 0.6) as report:
            t0 = time.perf_counter()
            uv0 = _start_map(cut)
            t_init = time.perf_counter() - t0
            uv, info = arap(cut.v, cut.f, uv0, progress=report)
            uv, flipped_frac = orient_rigid(uv, cut, prep.pixel_mm)
            st = stretch_stats(cut.v, cut.f, uv)
        if info["flipped_triangles"]:
            warnings.append(f"the ARAP flat map has {info['flipped_triangles']} flipped triangles")
        with timed_stage(progress, "volume", seconds, 0.6, 1.0) as report:
            vol, fwd, inv, mesh, vinfo = sample_flat_map(prep, cut, uv, report)
        cut_len = float(np.linalg.norm(cut.v[cut.boundary_edges[:, 0]] - cut.v[cut.boundary_edges[:, 1]],
                                       axis=1).sum()) if len(cut.boundary_edges) else 0.0
        section = {**cut.info, **vinfo, **info, **st, "boundary_length_mm": cut_len,
                   "flipped_triangle_fraction": flipped_frac, "start_map_seconds": t_init}
        return Unfolding(vol, MapCorrespondence(fwd, inv), mesh, section, warnings, seconds)


def _start_map(cut) -> np.ndarray:
    """Start map for ARAP (V,2 mm): arc length along the centreline and arc around it (theta times the radius)."""
    v, near, theta = cut.v, cut.near, cut.theta
    step = float(np.linalg.norm(np.diff(cut.Pd, axis=0), axis=1).mean()) if len(cut.Pd) > 1 else 1.0
    r = np.linalg.norm(v - cut.Pd[near], axis=1)
    # the radius of each cross-section (median over its vertices), so one ring maps to one straight line
    bins = near // max(1, int(round(4.0 / max(step, 1e-6))))
    med = np.zeros(bins.max() + 1)
    for b in np.unique(bins):
        med[b] = np.median(r[bins == b])
    return np.stack([near * step, theta * med[bins]], 1)
