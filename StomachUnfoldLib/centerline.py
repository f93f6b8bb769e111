"""Centreline of the stomach lumen from the cardia to the pylorus, with the radius along it (LPS mm).

A minimal-cost path through the lumen, whose cost falls steeply with the distance to the wall, keeps the
curve central. It is found on the lumen's bounding box coarsened to about 2 mm voxels (fast even for a
full CT), then smoothed (ends kept), resampled every ``step_mm`` and given the full-resolution distance
to the lumen boundary as its radius.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .errors import AnatomyError, InputError, PointError
from .geometry import Volume

__all__ = ["Centerline", "compute_centerline", "in_openings", "OPENING_RADIUS_MM", "OPENING_TUBE_FACTOR"]

#: Radius (mm) about the centreline's end points (the cardia and pylorus) of the openings where the oesophagus
#: and the duodenum join: about the oesophagus with its wall (outer radius 6-8 mm) or the pyloric canal, plus the
#: end point's few millimetres from the wall. Mucosa behind an end plane but farther from the end point is the
#: stomach's own (the cardia opens in the side of the fundus dome, not at the end of a tube) and is kept.
OPENING_RADIUS_MM = 10.0
#: At the end of a tube (the end point in the middle of a lumen that ends there) the opening is the whole end: up to
#: this many times the end point's distance from the wall.
OPENING_TUBE_FACTOR = 2.0


@dataclass
class Centerline:
    """Centreline from cardia to pylorus: points (K,3, LPS mm), radius (K, mm), unit tangents (K,3), arc length (K, mm).

    ``radius_mm`` is the distance (mm) from each point to the lumen boundary as the Euclidean distance
    transform of the lumen measures it (to the nearest non-lumen voxel centre); 0 for a point outside.
    """

    points_lps: np.ndarray
    radius_mm: np.ndarray
    tangents: np.ndarray
    arclength_mm: np.ndarray

    @property
    def length_mm(self) -> float:
        """Length of the centreline (mm)."""
        return float(self.arclength_mm[-1]) if len(self.arclength_mm) else 0.0

    def nearest(self, points_lps) -> np.ndarray:
        """Index of the nearest centreline point for each LPS point (mm); int array of the input's leading shape."""
        p = np.asarray(points_lps, float)
        return cKDTree(self.points_lps).query(p.reshape(-1, 3))[1].reshape(p.shape[:-1])


def in_openings(points_lps, centerline_lps, margin_mm: float = 0.0, radius_mm: float = OPENING_RADIUS_MM,
                nearest: np.ndarray | None = None) -> np.ndarray:
    """Which points (N,3, LPS mm) of the inner wall lie in the cardia or pylorus opening.

    A point is in an opening when its nearest centreline point (LPS mm) is an end point, it lies more than
    ``margin_mm`` behind the plane through that end (normal: the end's tangent), and it is within ``radius_mm`` of
    the end point, or OPENING_TUBE_FACTOR times the end point's distance from the nearest of ``points_lps`` when that
    is larger (the whole end of a tube). The rule the isometric method trims by and the quality judge leaves out
    (the peers keep their end planes, so their views lack the wall behind them).
    ``nearest``: each point's nearest centreline index, when already known.
    """
    pts = np.asarray(points_lps, float).reshape(-1, 3)
    cl = np.asarray(centerline_lps, float)
    if len(cl) < 3 or not len(pts):
        return np.zeros(len(pts), bool)
    k = cKDTree(cl).query(pts)[1] if nearest is None else np.asarray(nearest)
    out = np.zeros(len(pts), bool)
    for end, t, sign in ((0, cl[1] - cl[0], -1.0), (len(cl) - 1, cl[-1] - cl[-2], 1.0)):
        t = t / max(float(np.linalg.norm(t)), 1e-12)
        d = np.linalg.norm(pts - cl[end], axis=1)
        r = max(float(radius_mm), OPENING_TUBE_FACTOR * float(d.min()))
        out |= (k == end) & (sign * ((pts - cl[end]) @ t) > margin_mm) & (d < r)
    return out


# ---------------------------------------------------------------------------------------------- helpers
def _resample(points: np.ndarray, step: float) -> np.ndarray:
    """Points (N,3) resampled at equal arc-length steps of about ``step`` (mm); the ends are kept."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return points[[0, -1]].copy()
    n = max(2, int(np.ceil(s[-1] / step - 1e-9)) + 1)
    ss = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(ss, s, points[:, a]) for a in range(3)], axis=1)


def _smooth(points: np.ndarray, sigma_pts: float) -> np.ndarray:
    """Gaussian smoothing of a polyline along its points (sigma in points); the ends stay fixed.

    The curve is extended past each end by its point reflection about the end point, which keeps the
    ends and the direction there.
    """
    n = len(points)
    if n < 4 or sigma_pts <= 0:
        return points.copy()
    pad = min(n - 1, int(np.ceil(3 * sigma_pts)))
    head = 2 * points[0] - points[pad:0:-1]
    tail = 2 * points[-1] - points[-2:-2 - pad:-1]
    ext = np.concatenate([head, points, tail])
    sm = ndimage.gaussian_filter1d(ext, sigma_pts, axis=0, mode="nearest")[pad:pad + n]
    sm[0], sm[-1] = points[0], points[-1]
    return sm


def _block_reduce(mask: np.ndarray, f_kji, majority: bool) -> np.ndarray:
    """Coarsen a bool mask by integer factors (k, j, i): a coarse voxel is set if most (or any) fine voxels are."""
    f = np.asarray(f_kji, int)
    shape = np.array(mask.shape)
    n = -(-shape // f)
    padded = np.zeros(n * f, bool)
    padded[:shape[0], :shape[1], :shape[2]] = mask
    blocks = padded.reshape(n[0], f[0], n[1], f[1], n[2], f[2])
    if not majority:
        return blocks.any(axis=(1, 3, 5))
    count = blocks.sum(axis=(1, 3, 5), dtype=np.int32)
    return 2 * count >= int(np.prod(f))


def _fibonacci_directions(n: int) -> np.ndarray:
    """n nearly uniform unit vectors (n,3) on the sphere (Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _normals(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (K,3) perpendicular to unit vectors t (K,3) and to each other."""
    ref = np.where(np.abs(t[:, [0]]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    n1 = np.cross(t, ref)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    return n1, np.cross(t, n1)


class _RayCaster:
    """Exit distances (mm) of rays from points inside a bool mask, by nearest-voxel sampling along the ray.

    Outside the grid counts as outside the mask. A ray that does not leave the mask within its length
    ``t_max`` gets ``t_max``; a ray from a point outside the mask gets 0.
    """

    def __init__(self, mask: np.ndarray, volume: Volume, step_mm: float, budget: int = 3_000_000):
        self.fwd = volume.direction * volume.spacing[None, :]  # index -> LPS mm (linear part)
        self.inv = np.linalg.inv(self.fwd)
        self.origin = volume.origin
        self.step = float(step_mm)
        self.budget = budget
        # the mask with a rim of False all round, flat: a nearest voxel off the grid is clipped onto the rim
        self._rimmed = np.pad(np.asarray(mask, bool), 1).ravel()
        nk, nj, ni = mask.shape
        self._strides = np.array([1.0, ni + 2.0, (ni + 2.0) * (nj + 2.0)])   # exact in float64
        self._last = np.array([ni, nj, nk], float)

    def _inside(self, ijk: np.ndarray) -> np.ndarray:
        """Mask value at continuous indices (..., 3) (i, j, k) by nearest voxel; False off the grid."""
        idx = np.rint(ijk)
        np.maximum(idx, -1.0, out=idx)
        np.minimum(idx, self._last, out=idx)
        flat = idx @ self._strides
        flat += self._strides.sum()  # the rim: every index one further on
        return self._rimmed[flat.astype(np.intp)]

    def exit_distance(self, p: np.ndarray, u: np.ndarray, t_max: np.ndarray, centre: bool = False) -> np.ndarray:
        """Distance (mm) along unit rays u (K,D,3) from points p (K,3) to the mask boundary, at most t_max (K,).

        With ``centre=True`` the distance (mm) from p to the centre of the first outside voxel each ray
        meets is returned instead (what a Euclidean distance transform measures).
        """
        K, D = u.shape[:2]
        out = np.zeros((K, D))
        p_idx = (p - self.origin) @ self.inv.T
        u_idx = u @ self.inv.T
        start_in = self._inside(p_idx)
        n_s = np.maximum(1, np.ceil(t_max / self.step).astype(int))
        order = np.argsort(n_s)
        a = 0
        while a < K:
            # a chunk of points with similar ray lengths, within the sample budget
            b = a + 1
            while b < K and (b + 1 - a) * D * n_s[order[b]] <= self.budget:
                b += 1
            sel = order[a:b]
            S = int(n_s[sel].max())
            t = (np.arange(S) + 1.0) * self.step
            q = t[None, None, :, None] * u_idx[sel, :, None, :]
            q += p_idx[sel, None, None, :]
            hit = ~(self._inside(q) | (t[None, None, :] > t_max[sel, None, None]))
            first = np.argmax(hit, axis=2)
            any_hit = hit.any(axis=2)
            if centre:
                qf = np.take_along_axis(q, first[:, :, None, None], axis=2)[:, :, 0, :]
                v = (np.rint(qf) - p_idx[sel, None, :]) @ self.fwd.T
                d = np.linalg.norm(v, axis=-1)
            else:
                d = (first + 0.5) * self.step
            out[sel] = np.where(any_hit, np.minimum(d, t_max[sel, None]) if not centre else d, t_max[sel, None])
            a = b
        out[~start_in] = 0.0
        return out


_DIRS = _fibonacci_directions(128)


def _cone(half_angle: float, n_ring: int = 8) -> np.ndarray:
    """Unit vectors around +z: the axis and two rings at half and full ``half_angle`` (radians)."""
    dirs = [np.array([0.0, 0.0, 1.0])]
    for a in (0.5 * half_angle, half_angle):
        phi = 2 * np.pi * np.arange(n_ring) / n_ring + (a == half_angle) * np.pi / n_ring
        dirs.append(np.stack([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.full(n_ring, np.cos(a))], 1))
    return np.vstack([dirs[0][None], dirs[1], dirs[2]])


_CONE = _cone(np.radians(12.0))


def _radius(rc: _RayCaster, pts: np.ndarray, t_max: np.ndarray) -> np.ndarray:
    """Distance transform (mm) of the mask at LPS points (K,3): distance to the nearest outside voxel centre.

    Rays in 128 directions, then a cone of 17 around the best one, find the outside voxels nearest the
    point; the result is at least the exact Euclidean distance transform and in practice within a small
    fraction of a voxel of it. 0 for points outside the mask.
    """
    K = len(pts)
    d = rc.exit_distance(pts, np.broadcast_to(_DIRS, (K,) + _DIRS.shape), t_max, centre=True)
    best = _DIRS[np.argmin(d, axis=1)]  # (K,3)
    n1, n2 = _normals(best)
    local = _CONE[None, :, 0:1] * n1[:, None] + _CONE[None, :, 1:2] * n2[:, None] + _CONE[None, :, 2:3] * best[:, None]
    d2 = rc.exit_distance(pts, local, t_max, centre=True)
    return np.minimum(d.min(axis=1), d2.min(axis=1))


def _centre_points(rc: _RayCaster, pts: np.ndarray, radius: np.ndarray, window_mm: float,
                   n_dirs: int = 16, n_iter: int = 3) -> np.ndarray:
    """Move the inner points (LPS mm) in their normal planes to the middle of the lumen, by at most window_mm.

    From each point, rays in opposite directions of its normal plane meet the wall at t+ and t-; the
    shift is the mean over directions of ``(t+ - t-) u``, which moves a point of a circular section to
    its centre. This removes the offset of up to half a coarse voxel left by the coarse path, without
    letting the curve wander (the shift is bounded).
    """
    if len(pts) < 3:
        return pts
    t = np.gradient(pts, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    n1, n2 = _normals(t)
    th = np.pi * np.arange(n_dirs // 2) / (n_dirs // 2)
    u = np.cos(th)[None, :, None] * n1[:, None] + np.sin(th)[None, :, None] * n2[:, None]  # (K, M, 3)
    u = np.concatenate([u, -u], axis=1)
    t_max = 3.0 * radius + 2.0 * window_mm + rc.step
    cur = pts.copy()
    for _ in range(n_iter):
        d = rc.exit_distance(cur, u, t_max)
        m = n_dirs // 2
        shift = ((d[:, :m] - d[:, m:])[:, :, None] * u[:, :m]).mean(axis=1)
        cur = cur + shift
        off = cur - pts
        off -= (off * t).sum(axis=1, keepdims=True) * t  # stay in the normal plane
        norm = np.linalg.norm(off, axis=1, keepdims=True)
        off *= np.minimum(1.0, window_mm / np.maximum(norm, 1e-12))
        off = ndimage.gaussian_filter1d(off, 1.0, axis=0, mode="nearest")
        off[0] = off[-1] = 0.0
        cur = pts + off
    return cur


def _snap_any(mask: np.ndarray, volume: Volume, p: np.ndarray, max_mm: float):
    """Nearest True voxel centre (LPS mm) of mask to p within max_mm, also for p off the grid; None if none."""
    from .preprocessing import nearest_true

    return nearest_true(mask, volume, p, max_mm)


def minimal_path(cost: np.ndarray, start, end, sampling=(1.0, 1.0, 1.0)):
    """Minimal-cost 26-connected path start -> end (k, j, i), as MCP_Geometric: ((n, 3) int, cost) or (None, inf).

    A step between neighbours a and b costs ``(cost[a] + cost[b]) / 2 * |step|`` (step length in the
    ``sampling`` units, per array axis); voxels of infinite or negative cost are impassable. Dijkstra on
    the sparse graph of the passable voxels (scipy.sparse.csgraph).
    """
    from itertools import product

    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    cost = np.asarray(cost, float)
    shape = cost.shape
    start, end = tuple(int(x) for x in start), tuple(int(x) for x in end)
    ok = np.isfinite(cost) & (cost >= 0)
    if not (ok[start] and ok[end]):
        return None, np.inf
    n = int(np.count_nonzero(ok))
    padded = np.full(tuple(d + 2 for d in shape), -1, np.int32)  # node ids; -1: impassable or outside
    padded[1:-1, 1:-1, 1:-1][ok] = np.arange(n, dtype=np.int32)
    pos = np.flatnonzero(padded >= 0)  # the nodes' flat positions in the padded array, in node order
    pflat = padded.ravel()
    strides = np.array([padded.shape[1] * padded.shape[2], padded.shape[2], 1])
    sp = np.asarray(sampling, float).reshape(3)
    c = cost[ok]
    offsets = np.array([o for o in product((-1, 0, 1), repeat=3) if o != (0, 0, 0)])
    nb = pflat[pos[None, :] + (offsets @ strides)[:, None]]  # (26, n) neighbour ids
    miss = nb < 0  # no neighbour there: a zero-weight self loop keeps every row 26 long (CSR without sorting)
    nb[miss] = np.broadcast_to(np.arange(n, dtype=np.int32), nb.shape)[miss]
    w = (c[None, :] + c[nb]) * (0.5 * np.sqrt(np.sum((offsets * sp) ** 2, axis=1)))[:, None]
    w[miss] = 0.0
    graph = csr_matrix((w.T.ravel(), nb.T.ravel(), np.arange(0, nb.size + 1, nb.shape[0], dtype=np.int32)),
                       shape=(n, n))
    i0, i1 = int(padded[tuple(x + 1 for x in start)]), int(padded[tuple(x + 1 for x in end)])
    dist, pred = dijkstra(graph, directed=True, indices=i0, return_predecessors=True)
    if not np.isfinite(dist[i1]):
        return None, np.inf
    chain = [i1]
    while chain[-1] != i0:
        chain.append(int(pred[chain[-1]]))
    flat = np.flatnonzero(ok)[np.array(chain[::-1])]
    return np.stack(np.unravel_index(flat, shape), axis=1), float(dist[i1])


# ---------------------------------------------------------------------------------------------- main
def _snapped_ends(lumen, volume, cardia_lps, pylorus_lps, max_snap_mm, step_mm) -> list:
    """The cardia and pylorus (LPS mm) snapped into the lumen; PointError or AnatomyError saying why not."""
    from .preprocessing import ras_text

    ends_lps = []
    for name, p in (("cardia", cardia_lps), ("pylorus", pylorus_lps)):
        p = np.asarray(p, float).reshape(3)
        s = _snap_any(lumen, volume, p, max_snap_mm) if lumen.any() else None
        if s is None:
            if not lumen.any():
                raise AnatomyError("the stomach lumen is empty; check the points, the threshold or the mask")
            raise PointError(f"the {name} point (RAS {ras_text(p)} mm) is more than {max_snap_mm:g} mm from the "
                             "stomach lumen; place it in the lumen or on the wall next to it")
        ends_lps.append(s)
    if np.linalg.norm(ends_lps[0] - ends_lps[1]) < 2.0 * step_mm:
        raise AnatomyError("the cardia and pylorus points snap to almost the same place in the lumen "
                           f"({np.linalg.norm(ends_lps[0] - ends_lps[1]):.1f} mm apart); place them at the two "
                           "ends of the stomach")
    return ends_lps


def _coarse_path(sub, f, csp, c_origin, direction, ends_lps, max_snap_mm, progress):
    """Minimal-cost path (coarse (k, j, i) indices, cardia first) through the block-reduced lumen, its grid and DT."""
    path, cvol, dt = None, None, None
    for majority in (True, False):
        coarse = _block_reduce(sub, f[::-1], majority)
        cvol = Volume(np.zeros(coarse.shape, np.uint8), csp, c_origin, direction)
        cends = [_snap_any(coarse, cvol, e, max_snap_mm + 2.0 * float(csp.max())) for e in ends_lps]
        if any(c is None for c in cends):
            continue
        cends = [tuple(np.rint(cvol.lps_to_index(c[None])[0]).astype(int)[::-1]) for c in cends]  # (k, j, i)
        dt = ndimage.distance_transform_edt(coarse, sampling=csp[::-1])
        if progress is not None:
            progress(0.2)
        cost = np.where(coarse, 1.0 / (dt / max(float(dt.max()), 1e-6) + 0.05) ** 2, np.inf)
        found, _ = minimal_path(cost, cends[0], cends[1], sampling=tuple(csp[::-1]))
        if found is not None:
            path = found.astype(float)  # (k, j, i), cardia first
            break
    return path, cvol, dt


def compute_centerline(lumen: np.ndarray, volume: Volume, cardia_lps, pylorus_lps, step_mm: float = 2.0,
                       max_snap_mm: float = 20.0, coarse_mm: float = 2.0, progress=None) -> Centerline:
    """Central curve (LPS mm) through ``lumen`` from the cardia to the pylorus, with the radius (mm) along it.

    Parameters
    ----------
    lumen : (K, J, I) bool array
        Stomach lumen on ``volume``'s grid (may be a crop of the CT).
    volume : Volume
        Gives the geometry of ``lumen`` (its array is not used).
    cardia_lps, pylorus_lps : (3,) array-like
        End points, LPS mm; each is snapped to the nearest lumen voxel within ``max_snap_mm``.
    step_mm : float
        Spacing (mm) of the output points.
    max_snap_mm : float
        How far (mm) a point may lie from the lumen.
    coarse_mm : float
        Voxel size (mm) of the grid the minimal-cost path is searched on.
    progress : Progress or callable(fraction), optional

    Returns
    -------
    Centerline
        Starts at the snapped cardia and ends at the snapped pylorus.

    Raises
    ------
    InputError
        If ``lumen`` is not on ``volume``'s grid or ``step_mm`` is not positive.
    PointError
        If a point lies more than ``max_snap_mm`` from the lumen.
    AnatomyError
        If the lumen is empty, the two points are not connected inside it, or they are too close.

    Notes
    -----
    The path minimises the integral of ``1 / (dt / dt_max + 0.05) ** 2`` (``dt`` the coarse distance to
    the wall in mm), so it runs along the middle of the lumen; it is then smoothed with a Gaussian of
    about 2 coarse voxels along the curve and each point is re-centred in its normal plane on the
    full-resolution lumen (by at most 0.75 coarse voxel). The radius is the full-resolution Euclidean
    distance transform at each point, found by casting 128 rays (then a cone around the best) sampled
    every half voxel on the full-resolution lumen: the distance to the nearest non-lumen voxel centre
    they meet. This avoids a distance transform of the whole full-resolution lumen (seconds on a CT).
    """
    from .preprocessing import bounding_box

    if not step_mm > 0:
        raise InputError(f"the centreline step must be positive, got {step_mm} mm")
    lumen = np.asarray(lumen, bool)
    if lumen.shape != volume.array.shape:
        raise InputError(f"the lumen has shape {lumen.shape} but the volume {volume.array.shape}; pass the lumen "
                         "on the volume's grid")
    ends_lps = _snapped_ends(lumen, volume, cardia_lps, pylorus_lps, max_snap_mm, step_mm)
    if progress is not None:
        progress(0.05)

    # crop to the lumen, then coarsen to about coarse_mm voxels
    lo, hi = bounding_box(lumen, (1, 1, 1))
    sub = lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    crop_origin = volume.index_to_lps(lo.astype(float)[None])[0]
    f = np.maximum(1, np.floor(coarse_mm / volume.spacing + 0.5).astype(int))  # (i, j, k)
    csp = volume.spacing * f
    c_origin = crop_origin + volume.direction @ (volume.spacing * (f - 1) / 2.0)
    path, cvol, dt = _coarse_path(sub, f, csp, c_origin, volume.direction, ends_lps, max_snap_mm, progress)
    if path is None:
        raise AnatomyError("the cardia and pylorus points are not connected through the stomach lumen (separate "
                           "air pockets?); place both points in one lumen, or pass a stomach label with --mask")
    if progress is not None:
        progress(0.6)

    pts = cvol.index_to_lps(path[:, ::-1])
    pts = np.concatenate([ends_lps[0][None], pts[1:-1], ends_lps[1][None]]) if len(pts) > 2 \
        else np.stack(ends_lps)
    fine_step = min(step_mm, float(csp.min())) / 2.0
    pts = _resample(pts, fine_step)
    pts = _smooth(pts, sigma_pts=2.0 * float(csp.max()) / fine_step)
    pts = _resample(pts, step_mm)
    if len(pts) < 3:
        raise AnatomyError(f"the centreline is only {len(pts)} points long: the cardia and pylorus are too close "
                           "together; place them at the two ends of the stomach")
    if progress is not None:
        progress(0.8)

    # centre the points on the full-resolution lumen, then measure the radius there
    geo = Volume(np.zeros((1, 1, 1), np.uint8), volume.spacing, crop_origin, volume.direction)
    rc = _RayCaster(sub, geo, step_mm=0.5 * float(volume.spacing.min()))
    dt_vol = Volume(dt.astype(np.float32), csp, c_origin, volume.direction)
    bound = 1.8 * float(np.linalg.norm(csp)) + float(volume.spacing.max())  # coarse DT -> fine DT error bound

    def t_max(p):
        return dt_vol.sample(p, order=1, cval=0.0).astype(float) + bound

    r0 = _radius(rc, pts, t_max(pts))
    pts = _centre_points(rc, pts, r0, window_mm=0.75 * float(csp.max()))
    pts = _resample(pts, step_mm)
    radius = _radius(rc, pts, t_max(pts))
    t = np.gradient(pts, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    if progress is not None:
        progress(1.0)
    return Centerline(points_lps=pts, radius_mm=radius, tangents=t, arclength_mm=arc)
