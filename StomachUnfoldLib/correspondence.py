"""Correspondence both ways between the original CT and the unfolded volume, through the wall model.

A point of the original CT (LPS mm) lies in a rest tetrahedron of the model; the same barycentric
coordinates in the deformed tetrahedron give its place in the unfolded volume (whose world frame is the
deformed model's LPS frame), and the reverse. This is the same exact per-tetrahedron affine map that
:func:`StomachUnfoldLib.unfolded_volume.build_unfolded_volume` uses, so a point mapped here lands on the
voxel that shows it. Points a little outside the model (up to ``max_outside_mm``) use the nearest
tetrahedron's map (extrapolation); points farther away map to NaN.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .errors import InputError
from .unfolded_volume import barycentric_planes, degenerate_tets, hex_to_tets, tet_edges

__all__ = ["Correspondence", "point_tet_distance", "MapCorrespondence"]

_INSIDE_TOL = 1e-9  # barycentric slack for "inside" (same as the unfolded volume's rasteriser)


def _point_triangle_distance(p, a, b, c):
    """Distance (N,) from points p (N,3) to triangles (a, b, c) (N,3 each), exact (Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = np.clip(np.nan_to_num(d1 / (d1 - d3)), 0, 1)
        t_ac = np.clip(np.nan_to_num(d2 / (d2 - d6)), 0, 1)
        t_bc = np.clip(np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6))), 0, 1)
        den = va + vb + vc
        v = np.nan_to_num(vb / den)
        w = np.nan_to_num(vc / den)
    conds = [(d1 <= 0) & (d2 <= 0),
             (d3 >= 0) & (d4 <= d3),
             (vc <= 0) & (d1 >= 0) & (d3 <= 0),
             (d6 >= 0) & (d5 <= d6),
             (vb <= 0) & (d2 >= 0) & (d6 <= 0),
             (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)]
    choices = [a, b, a + t_ab[:, None] * ab, c, a + t_ac[:, None] * ac, b + t_bc[:, None] * (c - b)]
    closest = a + v[:, None] * ab + w[:, None] * ac
    for cond, ch in zip(conds[::-1], choices[::-1]):  # the first region that matches wins
        closest = np.where(cond[:, None], ch, closest)
    return np.linalg.norm(p - closest, axis=1)


def point_tet_distance(points: np.ndarray, corners: np.ndarray, lam: np.ndarray | None = None) -> np.ndarray:
    """Euclidean distance (N,) in mm from points (N,3, LPS mm) to solid tetrahedra with corners (N,4,3); 0 inside.

    ``lam`` (N,4), the points' barycentric coordinates, saves recomputing the inside test.
    """
    points = np.asarray(points, float)
    corners = np.asarray(corners, float)
    if lam is None:
        E = tet_edges(corners)
        ok = ~degenerate_tets(E, np.linalg.det(E))
        inv = np.zeros_like(E)
        inv[ok] = np.linalg.inv(E[ok])
        l123 = np.einsum("nij,nj->ni", inv, points - corners[:, 0])
        lam = np.concatenate([1.0 - l123.sum(axis=1, keepdims=True), l123], axis=1)
        lam[~ok] = -1.0  # flat: never "inside", distance from the faces
    d = np.full(len(points), np.inf)
    for f in ([1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]):
        d = np.minimum(d, _point_triangle_distance(points, corners[:, f[0]], corners[:, f[1]], corners[:, f[2]]))
    d[lam.min(axis=1) >= -_INSIDE_TOL] = 0.0
    return d


class _Locator:
    """Finds, for query points, the tetrahedron of a mesh that holds them, or the nearest one within a distance."""

    def __init__(self, points: np.ndarray, tets: np.ndarray, candidates: int = 16, priority=None):
        self.points = points
        self.tets = tets
        p = points[tets]  # (T,4,3)
        E = tet_edges(p)
        self.flat = degenerate_tets(E, np.linalg.det(E))
        inv = np.zeros_like(E)
        inv[~self.flat] = np.linalg.inv(E[~self.flat])
        self.B = barycentric_planes(p, inv)  # barycentric planes (T,4,4)
        self.centroids = p.mean(axis=1)
        # any point inside tet t lies within radius[t] of its centroid
        self.radius = float(np.sqrt(((p - self.centroids[:, None]) ** 2).sum(axis=2)).max()) if len(p) else 0.0
        self.tree = cKDTree(self.centroids)
        self.k = max(1, min(candidates, len(tets)))
        self.priority = priority  # (T,) larger wins among tetrahedra that hold the point; None: deepest inside

    def _lam(self, q, cand):
        """Barycentric coordinates (n,k,4) of points q (n,3) in candidate tetrahedra cand (n,k)."""
        Bc = self.B[cand]  # (n,k,4,4)
        lam = np.einsum("nkij,nj->nki", Bc[..., :3], q) + Bc[..., 3]
        lam[self.flat[cand]] = -np.inf
        return lam

    def _pick(self, q, cand, lam, max_outside):
        """Best candidate per point: one that holds it (priority, then deepest) or the nearest within max_outside.

        Returns ``(tet id or -1, barycentric (n,4), inside flag)``.
        """
        n, k = cand.shape
        rows = np.arange(n)
        mn = lam.min(axis=2)
        inside = mn >= -_INSIDE_TOL
        score = np.where(inside, mn, -np.inf)
        if self.priority is not None:
            pr = np.where(inside, self.priority[cand], -np.inf)
            score = np.where(pr == pr.max(axis=1, keepdims=True), score, -np.inf)
        best = np.argmax(score, axis=1)
        found = inside[rows, best]
        tid = np.where(found, cand[rows, best], -1)
        bl = lam[rows, best]
        out = np.flatnonzero(~found)
        if len(out) and max_outside > 0:
            cr = cand[out]
            flat_c = cr.ravel()
            dist = point_tet_distance(np.repeat(q[out], k, axis=0), self.points[self.tets[flat_c]],
                                      lam[out].reshape(-1, 4))
            dist[self.flat[flat_c]] = np.inf
            dist = dist.reshape(len(out), k)
            nb = np.argmin(dist, axis=1)
            ok = dist[np.arange(len(out)), nb] <= max_outside
            sel = out[ok]
            tid[sel] = cr[ok, nb[ok]]
            bl[sel] = lam[sel, nb[ok]]
        bl[tid < 0] = np.nan
        return tid, bl, found

    def locate(self, q: np.ndarray, max_outside: float, chunk: int = 20_000):
        """Tet id (-1: none within ``max_outside`` mm) and barycentric coordinates (N,4) per point (N,3)."""
        n = len(q)
        tid = np.full(n, -1, np.int64)
        lam = np.full((n, 4), np.nan)
        if n == 0 or len(self.tets) == 0:
            return tid, lam
        reach = self.radius + max_outside  # a tet within max_outside of a point has its centroid this near
        for s in range(0, n, chunk):
            qs = q[s:s + chunk]
            dist, cand = self.tree.query(qs, k=self.k)
            cand = cand.reshape(len(qs), -1)
            dist = dist.reshape(len(qs), -1)
            t = np.full(len(qs), -1, np.int64)
            bl = np.full((len(qs), 4), np.nan)
            idx = np.flatnonzero(dist[:, 0] <= reach)
            if len(idx):
                lm = self._lam(qs[idx], cand[idx])
                t[idx], bl[idx], inside = self._pick(qs[idx], cand[idx], lm, max_outside)
                # the k nearest centroids may miss the holder (stretched tetrahedra) or an overlapping layer:
                # then search every tetrahedron whose centroid is near enough (exact), unless the k already
                # covered all of them
                again = idx if self.priority is not None else idx[~inside]
                again = again[dist[again, -1] <= reach] if self.k < len(self.tets) else again[:0]
                if len(again):
                    t[again], bl[again] = self._ball(qs[again], reach, max_outside)
            tid[s:s + chunk] = t
            lam[s:s + chunk] = bl
        return tid, lam

    def _ball(self, q, reach, max_outside, max_pairs: int = 500_000):
        """Exact search over all tetrahedra whose centroid lies within ``reach`` of each point (ragged, chunked)."""
        lists = self.tree.query_ball_point(q, reach)
        lens = np.array([len(x) for x in lists], np.int64)
        tid = np.full(len(q), -1, np.int64)
        lam = np.full((len(q), 4), np.nan)
        order = np.argsort(lens)  # similar widths together keep the padding small
        s = 0
        while s < len(q):
            w = max(int(lens[order[s]]), 1)
            e = s + 1
            while e < len(q) and max(int(lens[order[e]]), 1) * (e - s + 1) <= max_pairs:
                e += 1
            rows = order[s:e]
            w = max(int(lens[rows].max()), 1)
            cand = np.zeros((len(rows), w), np.int64)
            for r, i in enumerate(rows):
                x = lists[i]
                if x:
                    cand[r, :len(x)] = x
                    cand[r, len(x):] = x[0]  # padding repeats a real candidate: harmless
            lm = self._lam(q[rows], cand)
            t, bl, _ = self._pick(q[rows], cand, lm, max_outside)
            empty = lens[rows] == 0
            t[empty] = -1
            bl[empty] = np.nan
            tid[rows] = t
            lam[rows] = bl
            s = e
        return tid, lam


class Correspondence:
    """Maps LPS points (mm) from the original CT to the unfolded volume's frame and back, through the model.

    Parameters
    ----------
    rest, deformed : (N,3) arrays
        Vertex positions (LPS mm) before and after the unfolding.
    hexes : (M,8) int array, optional
        Cells in VTK_HEXAHEDRON order (split into Kuhn tetrahedra as the unfolded volume does).
    tets : (T,4) int array, optional
        Tetrahedra instead of ``hexes``.
    max_outside_mm : float, optional
        Points farther than this from the model map to NaN; nearer ones outside it use the nearest
        tetrahedron's map. Default: one cell (the largest median cell edge of the rest model).
    view_axis : (3,) array, optional
        LPS direction towards the viewer of the unfolded volume (its grid's +k axis). Where deformed
        tetrahedra overlap, ``to_original`` then picks the one nearest the viewer, like the unfolded
        volume does; without it, the one holding the point deepest.
    candidates : int
        Nearest tetrahedra (by centroid) tested first per point; an exact search follows where needed.
    """

    def __init__(self, rest: np.ndarray, deformed: np.ndarray, hexes: np.ndarray | None = None, *,
                 tets: np.ndarray | None = None, max_outside_mm: float | None = None, view_axis=None,
                 candidates: int = 16):
        self.rest = np.asarray(rest, float)
        self.deformed = np.asarray(deformed, float)
        if self.rest.ndim != 2 or self.rest.shape[1] != 3 or self.rest.shape != self.deformed.shape:
            raise InputError(f"rest and deformed vertices must be (N, 3) arrays of the same shape, got "
                             f"{self.rest.shape} and {self.deformed.shape}")
        if (hexes is None) == (tets is None):
            raise InputError("give the model's cells either as hexes (M, 8) or as tets (T, 4), not both or neither")
        if hexes is not None:
            self.tets, self.tet_to_hex = hex_to_tets(hexes)
        else:
            self.tets = np.asarray(tets, np.int64)
            if self.tets.ndim != 2 or self.tets.shape[1] != 4:
                raise InputError(f"tets must be a (T, 4) integer array, got shape {self.tets.shape}")
            self.tet_to_hex = None
        if len(self.tets) and (self.tets.min() < 0 or self.tets.max() >= len(self.rest)):
            raise InputError(f"cells refer to vertex ids outside 0..{len(self.rest) - 1}")
        if not (np.all(np.isfinite(self.rest)) and np.all(np.isfinite(self.deformed))):
            raise InputError("the model has non-finite vertex positions; rerun the unfolding")
        if max_outside_mm is None:
            max_outside_mm = self._cell_size(hexes)
        if not np.isfinite(max_outside_mm) or max_outside_mm < 0:
            raise InputError(f"max_outside_mm must be a finite non-negative number of mm, got {max_outside_mm}")
        self.max_outside_mm = float(max_outside_mm)
        self.view_axis = None if view_axis is None else np.asarray(view_axis, float).reshape(3)
        self.candidates = int(candidates)
        self._rest_loc = None
        self._def_loc = None

    def _cell_size(self, hexes) -> float:
        """Default tolerance (mm): the largest median edge length along the cell axes (or of the tetrahedra)."""
        if len(self.tets) == 0:
            return 0.0
        if hexes is not None:
            h = np.asarray(hexes, np.int64)
            e = [np.median(np.linalg.norm(self.rest[h[:, b]] - self.rest[h[:, 0]], axis=1)) for b in (1, 3, 4)]
            return float(max(e))
        p = self.rest[self.tets]
        return float(np.median(np.linalg.norm(p[:, 1:] - p[:, :1], axis=2)))

    @classmethod
    def from_tets(cls, rest, deformed, tets, **kwargs) -> "Correspondence":
        """Build from tetrahedra (T,4) instead of hexahedra."""
        return cls(rest, deformed, tets=tets, **kwargs)

    def _locator(self, side: str) -> _Locator:
        """The lazily built point locator of the rest or deformed mesh."""
        if side == "rest":
            if self._rest_loc is None:
                self._rest_loc = _Locator(self.rest, self.tets, self.candidates)
            return self._rest_loc
        if self._def_loc is None:
            prio = None
            if self.view_axis is not None:
                prio = self.deformed[self.tets].mean(axis=1) @ self.view_axis
            self._def_loc = _Locator(self.deformed, self.tets, self.candidates, priority=prio)
        return self._def_loc

    def _map(self, points, side: str, dst: np.ndarray) -> np.ndarray:
        """Map points through the located tetrahedra of ``side`` onto ``dst``; NaN rows where none."""
        pts = np.asarray(points, float)
        single = pts.ndim == 1
        pts = np.atleast_2d(pts)
        if pts.shape[-1] != 3 or pts.ndim != 2:
            raise InputError(f"points must be (N, 3) or (3,) LPS mm, got shape {np.shape(points)}")
        out = np.full(pts.shape, np.nan)
        good = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
        if len(good):
            tid, lam = self._locator(side).locate(pts[good], self.max_outside_mm)
            hit = tid >= 0
            out[good[hit]] = np.einsum("nk,nkd->nd", lam[hit], dst[self.tets[tid[hit]]])
        return out[0] if single else out

    def to_unfolded(self, points_lps) -> np.ndarray:
        """Map original-CT points (LPS mm, (N,3) or (3,)) into the unfolded volume's LPS frame; NaN off the wall."""
        return self._map(points_lps, "rest", self.deformed)

    def to_original(self, points_lps) -> np.ndarray:
        """Map points of the unfolded volume (LPS mm, (N,3) or (3,)) back into the original CT; NaN off the wall."""
        return self._map(points_lps, "deformed", self.rest)

    def tet_of(self, points_lps, space: str = "original") -> np.ndarray:
        """Tetrahedron id per LPS point (mm) in "original" or "unfolded" space; -1 beyond max_outside_mm."""
        if space not in ("original", "unfolded"):
            raise InputError(f'space must be "original" or "unfolded", got {space!r}')
        pts = np.atleast_2d(np.asarray(points_lps, float))
        tid = np.full(len(pts), -1, np.int64)
        good = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
        if len(good):
            loc = self._locator("rest" if space == "original" else "deformed")
            tid[good] = loc.locate(pts[good], self.max_outside_mm)[0]
        return tid

    def map_landmarks(self, points: dict, direction: str = "to_unfolded") -> dict:
        """Map named points {name: (3,) LPS mm}; ``direction`` is "to_unfolded" or "to_original"; NaN off the wall."""
        if direction not in ("to_unfolded", "to_original"):
            raise InputError(f'direction must be "to_unfolded" or "to_original", got {direction!r}')
        if not points:
            return {}
        keys = list(points)
        arr = np.array([np.asarray(points[k], float).reshape(3) for k in keys])
        mapped = (self.to_unfolded if direction == "to_unfolded" else self.to_original)(arr)
        return {k: mapped[i] for i, k in enumerate(keys)}


class MapCorrespondence:
    """A correspondence given by two functions: CT LPS mm -> unfolded LPS mm and back ((N,3) arrays, NaN off the wall).

    For methods whose map is analytic (a surface parameterisation sampled along normals) rather than a model's
    tetrahedra; it answers like :class:`Correspondence` (``to_unfolded``, ``to_original``, ``map_landmarks``).
    """

    def __init__(self, to_unfolded, to_original):
        self._fwd, self._inv = to_unfolded, to_original

    def _call(self, fn, points_lps) -> np.ndarray:
        pts = np.asarray(points_lps, float)
        single = pts.ndim == 1
        pts = np.atleast_2d(pts)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"points must be (N, 3) or (3,) LPS mm, got shape {np.shape(points_lps)}")
        out = np.full(pts.shape, np.nan)
        good = np.all(np.isfinite(pts), axis=1)
        if good.any():
            out[good] = fn(pts[good])
        return out[0] if single else out

    def to_unfolded(self, points_lps) -> np.ndarray:
        """Map original-CT points (LPS mm, (N,3) or (3,)) into the unfolded volume's LPS frame; NaN off the wall."""
        return self._call(self._fwd, points_lps)

    def to_original(self, points_lps) -> np.ndarray:
        """Map points of the unfolded volume (LPS mm, (N,3) or (3,)) back into the original CT; NaN off the wall."""
        return self._call(self._inv, points_lps)

    def map_landmarks(self, points: dict, direction: str = "to_unfolded") -> dict:
        """Map named points {name: (3,) LPS mm}; ``direction`` is "to_unfolded" or "to_original"; NaN off the wall."""
        if direction not in ("to_unfolded", "to_original"):
            raise InputError(f'direction must be "to_unfolded" or "to_original", got {direction!r}')
        keys = list(points)
        if not keys:
            return {}
        arr = np.array([np.asarray(points[k], float).reshape(3) for k in keys])
        mapped = (self.to_unfolded if direction == "to_unfolded" else self.to_original)(arr)
        return {k: mapped[i] for i, k in enumerate(keys)}
