"""Shared fixtures and helpers of the test suite: analytic tubes and abdomens, structured blocks, shared data.

Data outside the repository (the real CTs and Slicer's base classes in ``../shared``) is found through one
setting, the environment variable ``STOMACHUNFOLD_SHARED`` (default: ``../shared`` beside the repository);
tests that need it skip, saying why, when it is absent.
"""
import os
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.incision_line import compute_incision_line, incision_surface_points
from StomachUnfoldLib.wall_model import build_wall_model, grid_steps

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The shared folder (real CTs, Slicer's base classes); one setting for every test.
SHARED_DIR = os.environ.get("STOMACHUNFOLD_SHARED", os.path.join(os.path.dirname(REPO), "shared"))
REAL_CT_NAME = "data/02_totalseg_example_ct_dicom_slab_2mm.nii.gz"
REAL_SEG_NAME = "data/02_totalseg_example_ct_dicom_slab_seg117_stomach6.nii.gz"


def shared_file(relative: str) -> str:
    """Path of a file in the shared folder; skips the calling test, saying why, when it is absent."""
    path = os.path.join(SHARED_DIR, relative)
    if not os.path.exists(path):
        pytest.skip(f"{relative} is not in the shared folder {SHARED_DIR} (set STOMACHUNFOLD_SHARED to it)")
    return path


def real_slab_with_stomach():
    """The real 2 mm CT slab (shared CT 02) and its TotalSegmentator stomach label (6) resampled onto it: (Volume,
    boolean mask (k, j, i)); skips when the shared folder lacks them."""
    import SimpleITK as sitk

    from StomachUnfoldLib.geometry import Volume

    img = sitk.ReadImage(shared_file(REAL_CT_NAME))
    seg = sitk.Resample(sitk.ReadImage(shared_file(REAL_SEG_NAME)), img, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                        sitk.sitkUInt8)
    return Volume.from_sitk(img), sitk.GetArrayFromImage(seg) == 6


# ----------------------------------------------------------------------------------------- abdomen phantoms
R = 12.0       # lumen radius (mm)
WALL = 4.0     # tissue wall (mm)
BEND = 25.0    # bend radius of the J (mm)
CARDIA = np.array([15.0, 0.0, 105.0])
PYLORUS = np.array([-30.0, 0.0, 30.0])
# axis: (15,0,110) -> (15,0,55) straight, quarter circle about (-10,0,55) to (-10,0,30), then to (-35,0,30)
AXIS_LENGTH = 55.0 + BEND * np.pi / 2 + 25.0
TUBE_ML = (np.pi * R ** 2 * AXIS_LENGTH + 4.0 / 3.0 * np.pi * R ** 3) / 1000.0

GEOMETRIES = {
    "iso1.5": (np.full(3, 1.5), np.eye(3)),
    "aniso1x1x2.5": (np.array([1.0, 1.0, 2.5]), np.eye(3)),
    # i runs to the right, j superior, k posterior-to-anterior: flipped (det -1), SI along j
    "permuted-flipped": (np.array([1.2, 2.0, 1.0]), np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])),
}


def seg_dist(q, a, b):
    """Distance (mm) from points q (N,3) to the segment a-b."""
    ab = b - a
    t = np.clip(((q - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(q - (a + t[:, None] * ab), axis=1)


def j_axis_distance(q):
    """Distance (mm) from LPS points q (N,3) to the axis of the J-shaped stomach tube."""
    q = np.atleast_2d(q)
    d1 = seg_dist(q, np.array([15.0, 0, 110]), np.array([15.0, 0, 55]))
    d3 = seg_dist(q, np.array([-10.0, 0, 30]), np.array([-35.0, 0, 30]))
    rel = q - np.array([-10.0, 0, 55])
    rho = np.hypot(rel[:, 0], rel[:, 2])
    in_arc = (rel[:, 0] >= 0) & (rel[:, 2] <= 0)
    d2 = np.where(in_arc, np.hypot(rho - BEND, rel[:, 1]), np.inf)
    return np.minimum(np.minimum(d1, d3), d2)


def make_grid(spacing, direction, lo=(-80.0, -65.0, 0.0), hi=(80.0, 65.0, 140.0)):
    """Empty int16 Volume whose grid covers the LPS box [lo, hi] (mm) with the given spacing and direction."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    D = np.asarray(direction, float)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    local = corners @ D
    n = np.floor((local.max(0) - local.min(0)) / spacing).astype(int) + 1
    return Volume(np.zeros(n[::-1], np.int16), spacing, D @ local.min(0), D)


def voxel_points(vol):
    """LPS centres (K,J,I,3) of all voxels of vol."""
    k, j, i = np.indices(vol.array.shape)
    return vol.index_to_lps(np.stack([i, j, k], -1).reshape(-1, 3)).reshape(vol.array.shape + (3,))


def make_abdomen(spacing, direction, gas=True, septum=False):
    """Phantom CT (HU) and its parts: J stomach (gas or fluid), wall, lungs, colon gas and outside air.

    Returns (ct, parts) with bool masks "lumen", "wall", "lungs", "colon", "outside" on ct's grid.
    """
    vol = make_grid(spacing, direction)
    p = voxel_points(vol)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    body = (x / 70.0) ** 2 + (y / 55.0) ** 2 < 1.0
    # a fold of outside air reaching to 6 mm from the stomach lumen (through the skin at the back)
    fold = (x > 5) & (x < 25) & (y < -18) & (z > 60) & (z < 90)
    outside = ~body | fold
    d = j_axis_distance(p.reshape(-1, 3)).reshape(vol.array.shape)
    lumen = d < R
    if septum:  # a tissue septum cuts the lumen in two at z = 75..79 mm
        lumen &= ~((z > 75) & (z < 79))
    wall = (d >= R) & (d < R + WALL) | (septum & (d < R) & ~lumen)
    lungs = ((np.abs(x) - 40) / 25.0) ** 2 + ((y - 10) / 30.0) ** 2 + ((z - 145) / 22.0) ** 2 < 1.0
    colon = np.linalg.norm(p - np.array([39.0, 0.0, 60.0]), axis=-1) < 8.0
    arr = np.full(vol.array.shape, 40, np.int16)
    arr[wall] = 55
    arr[lungs] = -850
    arr[colon] = -1000
    arr[lumen] = -1000 if gas else 20
    arr[outside] = -1000
    parts = dict(lumen=lumen, wall=wall, lungs=lungs & ~outside, colon=colon, outside=outside)
    return vol.with_array(arr), parts


def big_ct():
    """512x512x400 int16 CT at 0.7 mm with a body, lungs and a ~0.9 L J-shaped gas-filled stomach."""
    K, J, I = 400, 512, 512
    arr = np.full((K, J, I), 40, np.int16)
    y, x = np.mgrid[0:J, 0:I]
    arr[:, ((x - 256) / 240.0) ** 2 + ((y - 256) / 190.0) ** 2 >= 1] = -1000
    arr[300:, 120:380, 60:230] = -850   # right lung, touching the top
    arr[300:, 120:380, 290:460] = -850  # left lung
    kk, jj, ii = [a.astype(np.float32) * 0.7 for a in np.ogrid[100:380, 170:350, 200:460]]
    cx, cy = 250.0, 180.0
    d1 = np.sqrt((ii - cx) ** 2 + (jj - cy) ** 2 + (kk - np.clip(kk, 120, 200)) ** 2)
    d2 = np.sqrt((ii - np.clip(ii, cx - 90, cx)) ** 2 + (jj - cy) ** 2 + (kk - 120) ** 2)
    d = np.minimum(d1, d2)
    blk = arr[100:380, 170:350, 200:460]
    blk[d < 34] = 50
    blk[d < 30] = -1000
    ml = (np.pi * 30 ** 2 * 170 + 4 / 3 * np.pi * 30 ** 3) / 1000
    return Volume(arr, np.full(3, 0.7)), np.array([cx, cy, 190.0]), np.array([cx - 80, cy, 120.0]), ml


# ----------------------------------------------------------------------------------------- tubes
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


def tube_model(kind="straight", d=4, spacing=1.5, direction=None, cut=True):
    vol, lumen, wall, cl = make_tube(kind, spacing=spacing, direction=direction)
    inc = compute_incision_line(lumen, vol, cl)
    cell = float(np.max(np.array(grid_steps(vol.spacing, d)) * vol.spacing))
    pts = incision_surface_points(inc, cl, 4 + 2 * cell, cell, 0.3 * cell, cell) if cut else None
    openings = [(cl.points_lps[0], -cl.tangents[0]), (cl.points_lps[-1], cl.tangents[-1])]
    return vol, lumen, wall, cl, inc, build_wall_model(vol, wall, lumen, d, pts, openings)


# ----------------------------------------------------------------------------------------- structured blocks
HEX_OFFSETS = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)])
RAMP = np.array([3.0, -2.0, 1.0])  # HU per mm along L, P, S
RAMP0 = 100.0


def rotation(axis, deg):
    """Rotation matrix about an axis (Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def ramp(p):
    """The CT's value (HU) at LPS points: a linear function, so trilinear sampling reproduces it exactly."""
    return np.asarray(p, float) @ RAMP + RAMP0


def ramp_ct(direction=np.eye(3), spacing=(0.8, 0.9, 2.0), shape_kji=(30, 70, 70), origin=(-20.0, 15.0, -30.0)):
    """A CT whose voxel values are ramp() of their LPS centre (float32)."""
    vol = Volume(np.zeros(shape_kji, np.float32), spacing, origin, direction)
    k, j, i = np.indices(shape_kji)
    P = vol.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1))
    return vol.with_array(ramp(P).reshape(shape_kji).astype(np.float32))


def block(n, cell_vox, ct: Volume, lo_vox=(5, 5, 3)):
    """A structured block of n=(ni,nj,nk) cells of cell_vox voxels each, aligned with ct's voxel axes.

    Returns rest vertices (LPS mm), hexes (VTK order) and the vertices' continuous CT indices.
    """
    ni, nj, nk = n
    idx = np.stack(np.meshgrid(np.arange(ni + 1), np.arange(nj + 1), np.arange(nk + 1), indexing="ij"), -1)
    idx = idx.reshape(-1, 3)
    ijk = np.asarray(lo_vox, float) + idx * np.asarray(cell_vox, float)
    verts = ct.index_to_lps(ijk)
    vid = np.arange(len(verts)).reshape(ni + 1, nj + 1, nk + 1)
    cells = np.stack(np.meshgrid(np.arange(ni), np.arange(nj), np.arange(nk), indexing="ij"), -1).reshape(-1, 3)
    c = cells[:, None, :] + HEX_OFFSETS[None]
    return verts, vid[c[..., 0], c[..., 1], c[..., 2]], ijk


FLIP = rotation([1, 2, 3], 25) @ np.diag([1.0, -1.0, 1.0])  # det -1, oblique


def bent_slab(rest, R):
    """Bend a slab around a cylinder of radius R (mm) about the P axis through its centre (non-affine)."""
    c = rest.mean(0)
    x = rest - c
    th = x[:, 0] / R
    r = R + x[:, 2]
    return c + np.stack([r * np.sin(th), x[:, 1], r * np.cos(th) - R], 1)


def two_blocks(ct, up_mm):
    """Two separate 2x2x1-cell blocks of the CT; in the deformed state B lies on A, raised by up_mm along +S."""
    ra, ha, ia = block((2, 2, 1), (6, 6, 3), ct, lo_vox=(5, 5, 3))
    rb, hb, ib = block((2, 2, 1), (6, 6, 3), ct, lo_vox=(30, 40, 15))
    rest = np.concatenate([ra, rb])
    hexes = np.concatenate([ha, hb + len(ra)])
    deformed = np.concatenate([ra, ra + [0.0, 0.0, up_mm]])
    return rest, hexes, deformed, len(ra)


def write_dicom_series(folder, vol, series_uid="1.2.826.0.1.3680043.8.498.7.1",
                       study_uid="1.2.826.0.1.3680043.8.498.7", skip=()):
    """Write ``vol`` (int16 HU, identity direction) as a CT DICOM series, one file per slice, leaving out ``skip``."""
    import SimpleITK as sitk

    os.makedirs(folder, exist_ok=True)
    img = vol.to_sitk()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(img.GetDepth()):
        if k in skip:
            continue
        sl = img[:, :, k]
        pos = img.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, value in [("0008|0060", "CT"), ("0020|000d", study_uid), ("0020|000e", series_uid),
                           ("0020|0032", "\\".join(f"{c:.4f}" for c in pos)), ("0020|0037", "1\\0\\0\\0\\1\\0"),
                           ("0020|0013", str(k + 1)), ("0028|0030", f"{vol.spacing[1]:.4f}\\{vol.spacing[0]:.4f}"),
                           ("0018|0050", f"{vol.spacing[2]:.4f}"), ("0008|0018", f"{series_uid}.{k + 1}")]:
            sl.SetMetaData(tag, value)
        writer.SetFileName(os.path.join(folder, f"{series_uid[-3:]}_{k:03d}.dcm"))
        writer.Execute(sl)

