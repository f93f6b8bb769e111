"""Correspondence both ways between the original CT and the unfolded volume, through the wall model.

A point of the original CT (LPS mm) lies in a rest tetrahedron of the model; the same barycentric
coordinates in the deformed tetrahedron give its place in the unfolded volume (whose geometry is the
deformed model's LPS frame), and the reverse. Points off the wall model map to NaN.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .unfolded_volume import barycentric, hex_to_tets, tet_inverse

__all__ = ["Correspondence"]


class _Locator:
    """Finds, for query points, the tetrahedron of a mesh that holds them (or the nearest within a tolerance)."""

    def __init__(self, points: np.ndarray, tets: np.ndarray, candidates: int = 24):
        self.points = points
        self.tets = tets
        self.p0, self.inv, self.vol = tet_inverse(points, tets)
        self.centroids = points[tets].mean(axis=1)
        self.tree = cKDTree(self.centroids)
        self.k = min(candidates, len(tets))

    def locate(self, q: np.ndarray, tolerance: float = 0.25):
        """Tet id and barycentric coordinates per point; id -1 where no tet holds it within ``tolerance`` (barycentric)."""
        q = np.atleast_2d(np.asarray(q, float))
        _, cand = self.tree.query(q, k=self.k)
        cand = cand.reshape(len(q), -1)
        n, k = cand.shape
        qq = np.repeat(q, k, axis=0)
        c = cand.ravel()
        lam = barycentric(qq, self.p0[c], self.inv[c]).reshape(n, k, 4)
        mn = lam.min(axis=2)
        mn[np.abs(self.vol[cand]) < 1e-12] = -np.inf
        best = np.argmax(mn, axis=1)
        rows = np.arange(n)
        tid = cand[rows, best]
        bl = lam[rows, best]
        tid = np.where(mn[rows, best] >= -tolerance, tid, -1)
        return tid, bl


class Correspondence:
    """Maps LPS points (mm) from the original CT to the unfolded volume's frame and back, through the model."""

    def __init__(self, rest: np.ndarray, deformed: np.ndarray, hexes: np.ndarray):
        self.rest = np.asarray(rest, float)
        self.deformed = np.asarray(deformed, float)
        self.tets, _ = hex_to_tets(hexes)
        self._rest_loc = None
        self._def_loc = None

    def _map(self, points, src_loc, dst):
        pts = np.atleast_2d(np.asarray(points, float))
        tid, lam = src_loc.locate(pts)
        out = np.einsum("nk,nkd->nd", lam, dst[self.tets[np.maximum(tid, 0)]])
        out[tid < 0] = np.nan
        return out

    def to_unfolded(self, points_lps) -> np.ndarray:
        """Map points of the original CT (LPS mm, (N,3)) into the unfolded volume's LPS frame; NaN off the wall."""
        if self._rest_loc is None:
            self._rest_loc = _Locator(self.rest, self.tets)
        return self._map(points_lps, self._rest_loc, self.deformed)

    def to_original(self, points_lps) -> np.ndarray:
        """Map points of the unfolded volume (LPS mm, (N,3)) back into the original CT; NaN off the wall."""
        if self._def_loc is None:
            self._def_loc = _Locator(self.deformed, self.tets)
        return self._map(points_lps, self._def_loc, self.rest)

    def map_landmarks(self, points: dict, direction: str = "to_unfolded") -> dict:
        """Map named points {name: (3,) LPS mm}; ``direction`` is "to_unfolded" or "to_original"."""
        if not points:
            return {}
        keys = list(points)
        f = self.to_unfolded if direction == "to_unfolded" else self.to_original
        mapped = f(np.array([points[k] for k in keys], float))
        return {k: mapped[i] for i, k in enumerate(keys)}
