"""Unfolded plane, base line, stomach radius, destination points and unfolding forces (Oda et al., Sec. 2.3).

All positions are LPS mm. Equation numbers refer to the paper.

Sign conventions. The paper's printed signs for v1 (Eq. 6) and for the side of a destination point
(Eq. 8) would mirror the base line; taken together they are meant to unroll the wall with the mucosa
toward the viewer. Here they are written so that holds by construction: ``v1`` runs along the base line
from the cardia end to the pylorus end, ``v2 = n x v1`` (so ``(v1, v2, n)`` is right-handed) and a vertex
goes to the side of the base line on which it lies when the wall is unrolled with its inner surface
facing ``+n``. The viewer looks down ``-n``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["UnfoldingTargets", "wall_depth", "unfolded_plane", "base_line", "stomach_radius", "destination_points",
           "unfolding_targets", "unfolding_force", "distance_metric"]


def _unit(v):
    v = np.asarray(v, float)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def wall_depth(points_lps, lumen: np.ndarray, volume, target_mm: float = 1.5, progress=None) -> np.ndarray:
    """Signed depth (mm) of LPS points below the inner wall: distance to the lumen, negative inside it.

    Computed from Euclidean distance transforms on a grid coarsened to about ``target_mm`` voxels, then
    interpolated trilinearly; accurate to about one coarse voxel, which is all the heights need.
    """
    from .geometry import Volume
    from .preprocessing import distance_mm

    f = np.maximum(1, np.floor(target_mm / volume.spacing).astype(int))  # (i, j, k) factors
    sub = lumen[::f[2], ::f[1], ::f[0]]
    sp = volume.spacing * f
    outside = distance_mm(~sub, sp)
    if progress is not None:
        progress(0.5)
    inside = distance_mm(sub, sp)
    sd = (outside - inside).astype(np.float32)
    coarse = Volume(sd, sp, volume.origin, volume.direction)
    return coarse.sample(points_lps, order=1, cval=float(sd.max())).astype(float)


def unfolded_plane(incision_lps, inner_vertices_lps, centerline_lps=None) -> tuple[np.ndarray, np.ndarray]:
    """Normal n (unit) and point b (LPS mm) of the unfolded plane Omega (Eqs. 1-2).

    ``n = (u_{J/2} - x) / |u_{J/2} - x|`` with x the foot of the perpendicular from the middle incision
    point on the chord u_1 u_J; ``b`` is the inner-surface vertex furthest along n. When the incision is
    nearly straight (the foot lies closer to u_{J/2} than half the local radius, so its direction is set by
    noise) n falls back on the direction from the nearest centreline point to u_{J/2}.
    """
    u = np.asarray(incision_lps, float)
    mid = u[len(u) // 2]
    a, c = u[0], u[-1]
    chord = c - a
    t = np.clip(np.dot(mid - a, chord) / max(np.dot(chord, chord), 1e-12), 0.0, 1.0)
    x = a + t * chord
    n = mid - x
    if centerline_lps is not None:
        cl = np.asarray(centerline_lps, float)
        k = int(np.argmin(np.linalg.norm(cl - mid, axis=1)))
        radial = mid - cl[k]
        if np.linalg.norm(n) < max(1.0, 0.5 * np.linalg.norm(radial)):
            n = radial
    n = _unit(n)
    r = np.asarray(inner_vertices_lps, float)
    b = r[int(np.argmax(r @ n))]
    return n, b


def base_line(incision_lps, n, b, arc: str = "3d"):
    """Base line (Eq. 7) of the incision projected on Omega: points p_j, unit v1 (cardia to pylorus), v2 = n x v1.

    Returns ``(p, v1, v2, u_proj)``: p (J,3) lies along v1 through the projection of the middle incision
    point. With ``arc="projected"`` the spacing of p is the arc length of the projected incision (Eq. 7 as
    printed); with ``arc="3d"`` (default) it is the incision's own arc length, so a stomach that leaves
    the plane (twisted) keeps the length of its cut edges instead of buckling them.
    """
    u = np.asarray(incision_lps, float)
    n = _unit(n)
    up = u - ((u - b) @ n)[:, None] * n[None, :]
    centred = up - up.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    v1 = _unit(vt[0] - np.dot(vt[0], n) * n)
    if np.dot(v1, up[-1] - up[0]) < 0:
        v1 = -v1
    v2 = np.cross(n, v1)
    seg = np.linalg.norm(np.diff(u if arc == "3d" else up, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    h = len(u) // 2
    p = up[h][None, :] + (s - s[h])[:, None] * v1[None, :]
    return p, v1, v2, up


def stomach_radius(vertices_lps, incision_lps, centerline_lps):
    """Radius epsilon (mm) per vertex (Eqs. 3-5): |c_k' - u_j'| for the nearest incision point and its nearest centreline point.

    Returns ``(eps, j_idx, k_idx)``.
    """
    u = np.asarray(incision_lps, float)
    c = np.asarray(centerline_lps, float)
    _, j = cKDTree(u).query(np.asarray(vertices_lps, float))
    _, k_of_u = cKDTree(c).query(u)
    k = k_of_u[j]
    eps = np.linalg.norm(c[k] - u[j], axis=1)
    return eps, j, k


def destination_points(vertices_lps, incision_lps, centerline_lps, n, b, p, v2, depth=None, side_vectors=None):
    """Destination g (LPS mm) per incision vertex (Eq. 8): pi*epsilon from the base line on the vertex's side.

    Returns ``(g, eps, side)``; side is +1 or -1 (toward +v2 or -v2). Each destination is lowered below
    the plane by the vertex's depth in the wall (mm; ``depth`` if given, else its radial distance from the
    centreline minus epsilon), so the mucosa lies on the plane and the wall keeps its thickness.
    ``side_vectors`` (I',3), if given, replace ``r - c`` in the side test of Eq. 8: for a vertex on a cut
    face, the direction from the removed cell to the kept one says its side even when the vertex lies
    on the cut plane itself.
    """
    r = np.asarray(vertices_lps, float)
    u = np.asarray(incision_lps, float)
    c = np.asarray(centerline_lps, float)
    eps, j, k = stomach_radius(r, u, c)
    jm = np.maximum(j - 1, 0)
    jp = np.minimum(j + 1, len(u) - 1)
    tangent = u[jp] - u[jm]
    # the vertex lies on the +v2 side when ((r - c) x (u - c)) . t >= 0 (see the module docstring)
    a = r - c[k] if side_vectors is None else np.asarray(side_vectors, float)
    s = np.einsum("ij,ij->i", np.cross(a, u[j] - c[k]), tangent)
    side = np.where(s >= 0, 1.0, -1.0)
    g = p[j] + (np.pi * eps * side)[:, None] * np.asarray(v2, float)[None, :]
    if depth is None:
        depth = np.linalg.norm(r - c[k], axis=1) - eps
    g = g - np.asarray(depth, float)[:, None] * np.asarray(n, float)[None, :]
    return g, eps, side


@dataclass
class UnfoldingTargets:
    """Everything the simulation needs about where the wall goes: plane, base line, destinations."""

    n: np.ndarray           # plane normal (toward the viewer)
    b: np.ndarray           # point on the plane
    v1: np.ndarray          # base-line direction, cardia to pylorus
    v2: np.ndarray          # in-plane direction across the base line
    base_line: np.ndarray   # (J,3) p_j
    vertex_ids: np.ndarray  # (I',) ids of the S_vb vertices that are pulled
    destinations: np.ndarray  # (I',3) g_i'
    epsilon: np.ndarray     # (I',) radius per pulled vertex, mm
    side: np.ndarray        # (I',) +1/-1
    heights: np.ndarray     # (N,) final height of every vertex above the plane (minus its wall depth), mm

    @property
    def frame(self) -> np.ndarray:
        """3x3 matrix with columns v1, v2, n (LPS): the unfolded volume's i, j, k axes."""
        return np.stack([self.v1, self.v2, self.n], axis=1)


def unfolding_targets(model, incision, centerline, depth=None, arc: str = "3d") -> UnfoldingTargets:
    """Compute the unfolded plane, base line and destination points of the S_vb vertices of ``model``.

    ``depth`` (N,) is each vertex's signed depth below the inner wall in mm (see :func:`wall_depth`);
    without it the radial distance from the centreline minus the local radius is used.
    """
    u = np.asarray(incision.points_lps, float)
    c = np.asarray(centerline.points_lps, float)
    n, b = unfolded_plane(u, model.vertices[model.inner], c)
    p, v1, v2, _ = base_line(u, n, b, arc=arc)
    ids = np.flatnonzero(model.boundary)
    if depth is None:
        eps_all, _, k_all = stomach_radius(model.vertices, u, c)
        depth = np.linalg.norm(model.vertices - c[k_all], axis=1) - eps_all
    depth = np.asarray(depth, float)
    sv = getattr(model, "cut_normal", None)
    sv = None if sv is None else sv[ids]
    if sv is not None:
        # vertices whose cut faces point both ways (a sliver between two cuts) fall back on r - c
        weak = np.linalg.norm(sv, axis=1) < 1e-6
        sv[weak] = (model.vertices[ids] - c[stomach_radius(model.vertices[ids], u, c)[2]])[weak]
    g, eps, side = destination_points(model.vertices[ids], u, c, n, b, p, v2, depth=depth[ids], side_vectors=sv)
    return UnfoldingTargets(n=n, b=b, v1=v1, v2=v2, base_line=p, vertex_ids=ids, destinations=g,
                            epsilon=eps, side=side, heights=-depth)


def unfolding_force(positions, destinations, stiffness: float = 1.0) -> np.ndarray:
    """Unfolding force on the pulled vertices: ``stiffness * e`` with ``e = g - r`` (Eq. 9), per vertex."""
    return stiffness * (np.asarray(destinations, float) - np.asarray(positions, float))


def distance_metric(positions, destinations) -> float:
    """D: mean distance (mm) between the pulled vertices and their destination points (Eq. 10)."""
    d = np.linalg.norm(np.asarray(positions, float) - np.asarray(destinations, float), axis=1)
    return float(d.mean()) if len(d) else 0.0
