"""Small analytic tube volumes (straight and bent) with a known axis, for the stage unit tests."""
from types import SimpleNamespace

import numpy as np
from scipy.spatial import cKDTree

from StomachUnfoldLib.geometry import Volume


def make_tube(kind="straight", spacing=1.5, radius=20.0, wall=4.0, length=120.0, direction=None):
    """Gas-filled tube with a tissue wall in soft tissue: (Volume, lumen, wall, centreline) with LPS geometry.

    ``kind`` straight (axis along z) or bent (a quarter circle of radius 60 mm in the x-z plane).
    The centreline object has points_lps, tangents, radius_mm, arclength_mm, length_mm and nearest().
    """
    sp = np.broadcast_to(np.asarray(spacing, float), (3,)).astype(float)
    if kind == "straight":
        s = np.linspace(0, length, 400)
        axis = np.stack([0 * s, 0 * s, s], 1)
    else:
        th = np.linspace(0, np.pi / 2, 400)
        axis = np.stack([60 * np.cos(th) - 30, 0 * th, 60 * np.sin(th)], 1)
    lo = axis.min(0) - radius - wall - 12
    hi = axis.max(0) + radius + wall + 12
    D = np.eye(3) if direction is None else np.asarray(direction, float)
    # choose an origin so that the grid (in its own axes) covers [lo, hi]
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    local = corners @ D  # coordinates along the grid axes
    origin_local = local.min(0)
    n = np.ceil((local.max(0) - origin_local) / sp).astype(int) + 1
    origin = D @ origin_local
    vol = Volume(np.zeros(n[::-1], np.int16), sp, origin, D)
    k, j, i = np.indices(vol.array.shape)
    pts = vol.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1))
    dist, idx = cKDTree(axis).query(pts, distance_upper_bound=radius + wall + 6)
    dist = dist.reshape(vol.array.shape)
    lumen = dist < radius
    wallm = (dist >= radius) & (dist < radius + wall)
    arr = np.full(vol.array.shape, 30, np.int16)
    arr[lumen] = -1000
    arr[wallm] = 45
    vol = vol.with_array(arr)
    t = np.gradient(axis, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    seg = np.linalg.norm(np.diff(axis, axis=0), axis=1)
    arc = np.concatenate([[0], np.cumsum(seg)])
    keep = (arc > 3) & (arc < arc[-1] - 3)
    sel = np.flatnonzero(keep)[::max(1, int(round(2.0 / seg.mean())))]
    pts_c = axis[sel]
    tree = cKDTree(pts_c)
    cl = SimpleNamespace(points_lps=pts_c, tangents=t[sel], radius_mm=np.full(len(sel), radius),
                         arclength_mm=arc[sel] - arc[sel][0], length_mm=float(arc[sel][-1] - arc[sel][0]),
                         nearest=lambda p: tree.query(np.asarray(p, float))[1])
    return vol, lumen, wallm, cl
