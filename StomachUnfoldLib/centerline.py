"""Centreline of the stomach lumen from the cardia to the pylorus, with the radius along it (mm, LPS).

A minimal-cost path through the lumen whose cost falls steeply with the distance to the wall keeps the
curve central. It is found on a grid coarsened to about 2 mm voxels (fast even for a full CT), smoothed,
resampled every ``step_mm`` and given the full-resolution distance to the wall as its radius.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .errors import AnatomyError, PointError
from .geometry import Volume, lps_to_ras

__all__ = ["Centerline", "compute_centerline"]


@dataclass
class Centerline:
    """Centreline points (LPS mm) from cardia to pylorus, radius (mm), unit tangents and arc length (mm)."""

    points_lps: np.ndarray
    radius_mm: np.ndarray
    tangents: np.ndarray
    arclength_mm: np.ndarray

    @property
    def length_mm(self) -> float:
        """Length of the centreline in mm."""
        return float(self.arclength_mm[-1]) if len(self.arclength_mm) else 0.0

    def nearest(self, points_lps) -> np.ndarray:
        """Index of the nearest centreline point for each LPS point (mm)."""
        return cKDTree(self.points_lps).query(np.asarray(points_lps, float))[1]


def _resample(points: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(np.ceil(s[-1] / step)) + 1)
    ss = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(ss, s, points[:, a]) for a in range(3)], axis=1)


def compute_centerline(lumen: np.ndarray, volume: Volume, cardia_lps, pylorus_lps, step_mm: float = 2.0,
                       max_snap_mm: float = 20.0, coarse_mm: float = 2.0, progress=None) -> Centerline:
    """Central path through ``lumen`` (bool on volume's grid) from the cardia to the pylorus (LPS mm); see module doc."""
    from skimage.graph import MCP_Geometric

    from .preprocessing import snap_to_region

    f = np.maximum(1, np.floor(coarse_mm / volume.spacing).astype(int))  # (i, j, k)
    # a coarse voxel is lumen when most of it is lumen (so the path keeps off the wall)
    sub = lumen[::f[2], ::f[1], ::f[0]]
    csp = volume.spacing * f
    coarse = Volume(sub.astype(np.uint8), csp, volume.origin, volume.direction)
    if progress is not None:
        progress(0.1)
    dt = ndimage.distance_transform_edt(sub, sampling=csp[::-1])
    if progress is not None:
        progress(0.4)
    ends = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        s = snap_to_region(sub, coarse, p, max_snap_mm, name)
        if s is None:
            raise PointError(f"the {name} point (RAS {np.round(lps_to_ras(np.asarray(p, float)), 1).tolist()} mm) "
                             f"is more than {max_snap_mm:g} mm from the stomach lumen; place it in the lumen")
        ends.append(np.rint(coarse.lps_to_index(s[None])[0]).astype(int)[::-1])  # (k, j, i)
    rmax = float(dt.max())
    cost = np.where(sub, 1.0 / (dt / max(rmax, 1e-6) + 0.05) ** 2, np.inf)
    mcp = MCP_Geometric(cost, sampling=tuple(csp[::-1]))
    costs, _ = mcp.find_costs([tuple(ends[0])], [tuple(ends[1])])
    if not np.isfinite(costs[tuple(ends[1])]):
        raise AnatomyError("the cardia and pylorus are not connected through the stomach lumen (separate air "
                           "pockets?); pass a stomach label with --mask or place the points in one lumen")
    path = np.array(mcp.traceback(tuple(ends[1])))[::-1]  # (k, j, i), cardia first
    if progress is not None:
        progress(0.7)
    pts = coarse.index_to_lps(path[:, ::-1].astype(float))
    pts = _resample(pts, min(step_mm, float(csp.min())))
    # smooth the staircase path, keeping the ends
    if len(pts) > 5:
        sigma = max(1.0, 4.0 / min(step_mm, float(csp.min())))
        sm = ndimage.gaussian_filter1d(pts, sigma, axis=0, mode="nearest")
        w = np.minimum(np.arange(len(pts)), np.arange(len(pts))[::-1]) / (2.0 * sigma)
        w = np.clip(w, 0, 1)[:, None]
        pts = sm * w + pts * (1 - w)
    pts = _resample(pts, step_mm)
    # radius: full-resolution distance to the wall, sampled on a fine crop of the lumen
    fine_dt = ndimage.distance_transform_edt(lumen, sampling=volume.spacing[::-1]).astype(np.float32)
    radius = volume.with_array(fine_dt).sample(pts, order=1, cval=0.0).astype(float)
    if progress is not None:
        progress(1.0)
    t = np.gradient(pts, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if len(pts) < 3:
        raise AnatomyError("the centreline is shorter than 3 points: the cardia and pylorus are too close")
    return Centerline(points_lps=pts, radius_mm=radius, tangents=t, arclength_mm=arc)
