"""Automatic incision line on the inner stomach wall from cardia to pylorus (Oda et al., after Suito et al.).

For every centreline point a cutting direction is chosen in the cross-section plane: by default away from
the bend of the stomach (the greater curvature, where pathologists open a resected stomach); or toward it
(lesser curvature), anterior or posterior. A ray from the centreline along that direction meets the inner
wall at the incision point. Ray lengths are median-filtered along the stomach so that rugae and small
polyps do not make the line jump, and the directions are smoothed so the line is a connected curve.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import AnatomyError, InputError
from .geometry import Volume
from .params import INCISION_SIDES

__all__ = ["Incision", "cutting_directions", "compute_incision_line", "incision_from_curve",
           "incision_surface_points", "SIDES"]

SIDES = INCISION_SIDES  # defined once, in params


@dataclass
class Incision:
    """The incision line: points on the inner wall (LPS mm), cut directions and matching centreline indices."""

    points_lps: np.ndarray      # (J,3) u_j on the inner wall, cardia to pylorus
    directions: np.ndarray      # (J,3) unit vectors from the centreline point to u_j
    centerline_index: np.ndarray  # (J,) index k of the centreline point each u_j was cast from
    side: str = "greater"

    @property
    def length_mm(self) -> float:
        """Length of the incision polyline in mm."""
        return float(np.linalg.norm(np.diff(self.points_lps, axis=0), axis=1).sum())


def _perpendicular(vectors, tangents):
    """Component of each vector perpendicular to the matching unit tangent."""
    return vectors - np.sum(vectors * tangents, axis=1, keepdims=True) * tangents


def _normalise(v, eps=1e-9):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, eps)


def cutting_directions(points_lps, tangents, radius_mm, side: str = "greater",
                       smooth_mm: float = 15.0, spacing_mm: float = 2.0) -> np.ndarray:
    """Unit cut directions (LPS) per centreline point for the chosen side, smooth along the curve.

    ``greater`` points away from the centre of the bend (the centroid of the centreline, and where the
    curve is nearly straight the patient's left, +x in LPS); ``lesser`` is its opposite; ``anterior``
    is -y and ``posterior`` +y (LPS), each made perpendicular to the centreline tangent.
    """
    if side not in SIDES:
        raise InputError(f"unknown incision side {side!r}; choose one of {', '.join(SIDES)}")
    points_lps = np.asarray(points_lps, float)
    tangents = _normalise(np.asarray(tangents, float))
    if side in ("greater", "lesser"):
        centre = points_lps.mean(axis=0)
        d = _perpendicular(points_lps - centre, tangents)
        fallback = _perpendicular(np.tile([1.0, 0.0, 0.0], (len(points_lps), 1)), tangents)
        # where the bend is weak compared with the radius, blend toward the patient's left
        w = np.clip(np.linalg.norm(d, axis=1) / np.maximum(2.0 * np.asarray(radius_mm, float), 1e-6), 0, 1)
        d = _normalise(d) * w[:, None] + _normalise(fallback) * (1 - w[:, None])
        if side == "lesser":
            d = -d
    else:
        ref = np.array([0.0, -1.0, 0.0]) if side == "anterior" else np.array([0.0, 1.0, 0.0])
        d = _perpendicular(np.tile(ref, (len(points_lps), 1)), tangents)
        # near-vertical tangents along y: fall back on the patient's left
        weak = np.linalg.norm(d, axis=1) < 0.2
        d[weak] = _perpendicular(np.tile([1.0, 0.0, 0.0], (int(weak.sum()), 1)), tangents[weak])
    d = _normalise(d)
    sigma = max(smooth_mm / max(spacing_mm, 1e-6), 0.5)
    d = ndimage.gaussian_filter1d(d, sigma, axis=0, mode="nearest")
    return _normalise(_perpendicular(d, tangents))


def _ray_lengths(lumen: np.ndarray, volume: Volume, origins, directions, max_len_mm: float) -> np.ndarray:
    """Distance (mm) along each ray from its origin until the lumen mask ends (nearest-voxel lookup)."""
    step = 0.25 * float(volume.spacing.min())
    t = np.arange(0.0, max_len_mm + step, step)
    pts = origins[:, None, :] + t[None, :, None] * directions[:, None, :]  # (K,T,3)
    ijk = np.rint(volume.lps_to_index(pts.reshape(-1, 3))).astype(np.int64)
    size = np.array(volume.size)
    inside = np.all((ijk >= 0) & (ijk < size), axis=1)
    ijk = np.clip(ijk, 0, size - 1)
    val = lumen[ijk[:, 2], ijk[:, 1], ijk[:, 0]] & inside
    val = val.reshape(len(origins), len(t))
    val[:, 0] = True  # the centreline point itself counts as lumen
    first_out = np.argmin(val, axis=1)  # first False
    never = val.all(axis=1)
    first_out[never] = len(t) - 1
    return t[first_out] - 0.5 * step


def compute_incision_line(lumen: np.ndarray, volume: Volume, centerline, side: str = "greater",
                          smooth_mm: float = 15.0) -> Incision:
    """Cast a ray from every centreline point along the chosen side to the inner wall; return the incision.

    Parameters
    ----------
    lumen : bool ndarray on ``volume``'s grid
        The stomach lumen (air region or mask).
    centerline : Centerline
        Cardia-to-pylorus centreline with ``points_lps``, ``tangents`` and ``radius_mm``.
    side : one of params.INCISION_SIDES
    """
    pts = np.asarray(centerline.points_lps, float)
    if len(pts) < 3:
        raise AnatomyError("the centreline is too short to place an incision line; place the cardia and "
                           "pylorus further apart")
    step = float(np.median(np.linalg.norm(np.diff(pts, axis=0), axis=1))) if len(pts) > 1 else 1.0
    dirs = cutting_directions(pts, centerline.tangents, centerline.radius_mm, side, smooth_mm, step)
    max_len = float(4.0 * np.max(centerline.radius_mm) + 10.0)
    lengths = _ray_lengths(lumen, volume, pts, dirs, max_len)
    # robust along the stomach: a fold or polyp must not make the line jump
    win = max(3, int(round(10.0 / max(step, 1e-6))) | 1)
    lengths = ndimage.median_filter(lengths, size=win, mode="nearest")
    u = pts + lengths[:, None] * dirs
    return Incision(points_lps=u, directions=dirs, centerline_index=np.arange(len(pts)), side=side)


def incision_from_curve(curve_lps, centerline) -> Incision:
    """Incision from a user-given curve (LPS mm): resampled, each point tied to its nearest centreline point."""
    curve = np.asarray(curve_lps, float)
    if curve.ndim != 2 or curve.shape[1] != 3 or len(curve) < 2:
        raise InputError("a user incision curve needs at least two 3D points")
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    step = float(np.median(np.linalg.norm(np.diff(centerline.points_lps, axis=0), axis=1)))
    n = max(3, int(np.ceil(s[-1] / max(step, 1e-6))) + 1)
    ss = np.linspace(0, s[-1], n)
    u = np.stack([np.interp(ss, s, curve[:, a]) for a in range(3)], axis=1)
    k = centerline.nearest(u)
    # keep the curve ordered from cardia to pylorus
    if k[0] > k[-1]:
        u, k = u[::-1], k[::-1]
    c = np.asarray(centerline.points_lps)[k]
    t = _normalise(np.asarray(centerline.tangents, float)[k])
    dirs = _normalise(_perpendicular(u - c, t))
    return Incision(points_lps=u, directions=dirs, centerline_index=k, side="user")


def incision_surface_points(incision: Incision, centerline, depth_mm: float, inside_mm: float,
                            sample_mm: float, extend_mm: float = 0.0) -> np.ndarray:
    """Points (LPS mm) sampling the cut surface: from ``inside_mm`` inside the lumen to ``depth_mm`` past the wall.

    The surface is ruled by the segments ``u_j + t * dir_j`` for t in [-inside_mm, depth_mm], between
    consecutive incision points, sampled every ``sample_mm``; ``extend_mm`` prolongs it past both ends along
    the centreline tangent so that the cut reaches the openings.
    """
    u = np.asarray(incision.points_lps, float)
    d = np.asarray(incision.directions, float)
    if extend_mm > 0:
        t0 = _normalise(u[0] - u[1])
        t1 = _normalise(u[-1] - u[-2])
        u = np.vstack([u[0] + extend_mm * t0, u, u[-1] + extend_mm * t1])
        d = np.vstack([d[:1], d, d[-1:]])
    t = np.arange(-inside_mm, depth_mm + 1e-9, sample_mm)
    out = []
    for a in range(len(u) - 1):
        seg = np.linalg.norm(u[a + 1] - u[a])
        ns = max(2, int(np.ceil(seg / sample_mm)) + 1)
        w = np.linspace(0.0, 1.0, ns)[:, None]
        base = u[a] * (1 - w) + u[a + 1] * w
        dirs = _normalise(d[a] * (1 - w) + d[a + 1] * w)
        out.append((base[:, None, :] + t[None, :, None] * dirs[:, None, :]).reshape(-1, 3))
    return np.vstack(out)
