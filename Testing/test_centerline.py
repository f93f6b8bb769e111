"""Tests of StomachUnfoldLib.centerline on analytic tubes (straight, J and U shaped), with anisotropic
spacing and flipped, permuted direction matrices."""
import time

import numpy as np
import pytest

from StomachUnfoldLib.centerline import Centerline, compute_centerline
from StomachUnfoldLib.errors import AnatomyError, Cancelled, PointError
from StomachUnfoldLib.preprocessing import air_region, bounding_box, snap_to_region
from StomachUnfoldLib.progress import Progress
from conftest import (CARDIA, GEOMETRIES, PYLORUS, R, real_slab_with_stomach, big_ct, j_axis_distance, make_abdomen, make_grid, seg_dist, voxel_points)


def tube(spacing, direction, axis_dist, lo, hi, radius):
    """(Volume, lumen) for a tube of the given radius (mm) around the axis given by axis_dist(points)."""
    vol = make_grid(spacing, direction, lo=lo, hi=hi)
    p = voxel_points(vol)
    lumen = axis_dist(p.reshape(-1, 3)).reshape(vol.array.shape) < radius
    return vol, lumen


def inside(lumen, vol, pts):
    """Lumen value at the voxel nearest each LPS point."""
    idx = np.rint(vol.lps_to_index(pts)).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(vol.size)), axis=1)
    out = np.zeros(len(pts), bool)
    out[ok] = lumen[idx[ok, 2], idx[ok, 1], idx[ok, 0]]
    return out


def check_curve(cl: Centerline, step):
    """Shape and consistency checks shared by all tests."""
    K = len(cl.points_lps)
    assert cl.points_lps.shape == (K, 3) and cl.tangents.shape == (K, 3)
    assert cl.radius_mm.shape == (K,) and cl.arclength_mm.shape == (K,)
    assert np.allclose(np.linalg.norm(cl.tangents, axis=1), 1.0)
    seg = np.linalg.norm(np.diff(cl.points_lps, axis=0), axis=1)
    assert np.allclose(np.diff(cl.arclength_mm), seg) and cl.arclength_mm[0] == 0.0
    assert cl.length_mm == pytest.approx(seg.sum())
    assert np.all(seg > 0.5 * step) and np.all(seg < 1.5 * step)
    # tangents follow the curve
    assert np.all(np.einsum("ij,ij->i", cl.tangents[:-1], np.diff(cl.points_lps, axis=0)) > 0)


# ----------------------------------------------------------------------------------------- straight
A_STRAIGHT = np.array([-20.0, -10.0, 10.0])
B_STRAIGHT = np.array([25.0, 15.0, 110.0])
R_STRAIGHT = 10.0


@pytest.mark.parametrize("geom", list(GEOMETRIES))
def test_straight_tube_axis_and_radius(geom):
    spacing, direction = GEOMETRIES[geom]
    a, b, r = A_STRAIGHT, B_STRAIGHT, R_STRAIGHT
    vol, lumen = tube(spacing, direction, lambda q: seg_dist(q, a, b), lo=(-40, -30, -10), hi=(45, 35, 130),
                      radius=r)
    u = (b - a) / np.linalg.norm(b - a)
    c0, c1 = a + 12.0 * u, b - 12.0 * u  # on the axis, 12 mm from the rounded ends
    cl = compute_centerline(lumen, vol, c0, c1, step_mm=2.0)
    check_curve(cl, 2.0)
    # within a voxel of the true axis (distance to the axis line, mm)
    rel = cl.points_lps - a
    off_axis = np.linalg.norm(rel - (rel @ u)[:, None] * u, axis=1)
    assert off_axis.max() <= spacing.max(), off_axis.max()
    # inner points (the ends are the voxel centres the points snap to): well within half a voxel
    assert off_axis[1:-1].max() <= 0.5 * spacing.min(), off_axis[1:-1].max()
    # the ends are the snapped points
    assert np.allclose(cl.points_lps[0], snap_to_region(lumen, vol, c0))
    assert np.allclose(cl.points_lps[-1], snap_to_region(lumen, vol, c1))
    assert cl.length_mm == pytest.approx(np.linalg.norm(c1 - c0), rel=0.02)
    # radius within 10 % of the true radius away from the caps, and never more than the truth allows
    s = rel @ u
    mid = (s > 12.0 + r) & (s < np.linalg.norm(b - a) - 12.0 - r)
    assert mid.sum() > 20
    assert np.all(np.abs(cl.radius_mm[mid] - r) <= 0.1 * r), cl.radius_mm[mid]
    assert np.all(cl.radius_mm <= r - off_axis + spacing.max())
    assert np.all(np.abs(cl.tangents[mid] @ u) > 0.99)
    # nearest(): indices of the closest centreline point
    q = cl.points_lps[[3, 10]] + np.array([[0.3, -0.2, 0.1], [0.0, 0.4, -0.3]])
    assert cl.nearest(q).tolist() == [3, 10]
    assert cl.nearest(q[0]) == 3


# ----------------------------------------------------------------------------------------- bent tubes
@pytest.fixture(scope="module", params=list(GEOMETRIES))
def stomach(request):
    spacing, direction = GEOMETRIES[request.param]
    ct, parts = make_abdomen(spacing, direction)
    return ct, parts["lumen"]


def test_j_tube_central_and_inside(stomach):
    ct, lumen = stomach
    cl = compute_centerline(lumen, ct, CARDIA, PYLORUS, step_mm=2.0)
    check_curve(cl, 2.0)
    assert inside(lumen, ct, cl.points_lps).all()
    # at least 0.6 R from the wall everywhere
    assert j_axis_distance(cl.points_lps).max() <= 0.4 * R
    vox = np.linalg.norm(ct.spacing)
    assert np.linalg.norm(cl.points_lps[0] - snap_to_region(lumen, ct, CARDIA)) <= 2 * vox
    assert np.linalg.norm(cl.points_lps[-1] - snap_to_region(lumen, ct, PYLORUS)) <= 2 * vox
    # length of the axis from the cardia (z 105) to the pylorus (x -30): 50 + quarter circle + 20 mm
    assert cl.length_mm == pytest.approx(50.0 + 25.0 * np.pi / 2 + 20.0, rel=0.05)
    # radius: the true distance to the wall, within a voxel, away from the ends
    interior = (cl.arclength_mm > R) & (cl.arclength_mm < cl.length_mm - R)
    true_r = R - j_axis_distance(cl.points_lps[interior])
    assert np.all(np.abs(cl.radius_mm[interior] - true_r) <= ct.spacing.max())


def u_axis_distance(q):
    """Distance (mm) to a U: limbs x = -25 and x = +25 from z = 100 down to 40, joined by a half circle below."""
    q = np.atleast_2d(q)
    d1 = seg_dist(q, np.array([-25.0, 0, 100]), np.array([-25.0, 0, 40]))
    d2 = seg_dist(q, np.array([25.0, 0, 100]), np.array([25.0, 0, 40]))
    rel = q - np.array([0.0, 0, 40])
    d3 = np.where(rel[:, 2] <= 0, np.hypot(np.hypot(rel[:, 0], rel[:, 2]) - 25.0, rel[:, 1]), np.inf)
    return np.minimum(np.minimum(d1, d2), d3)


@pytest.mark.parametrize("geom", ["aniso1x1x2.5", "permuted-flipped"])
def test_u_tube_follows_the_bend(geom):
    spacing, direction = GEOMETRIES[geom]
    r = 10.0
    vol, lumen = tube(spacing, direction, u_axis_distance, lo=(-45, -15, 0), hi=(45, 15, 115), radius=r)
    c0, c1 = np.array([-25.0, 0, 90]), np.array([25.0, 0, 90])
    cl = compute_centerline(lumen, vol, c0, c1, step_mm=1.5)
    check_curve(cl, 1.5)
    assert inside(lumen, vol, cl.points_lps).all()
    assert u_axis_distance(cl.points_lps).max() <= 0.4 * r
    assert cl.points_lps[:, 2].min() == pytest.approx(40.0 - 25.0, abs=2.0)  # down to the bottom of the U
    assert cl.length_mm == pytest.approx(2 * 50.0 + 25.0 * np.pi, rel=0.05)


def test_points_on_the_wall(stomach):
    ct, lumen = stomach
    c_wall = np.array([15.0 + R + 3.0, 0.0, 100.0])  # 3 mm outside the lumen
    p_wall = np.array([-30.0, -(R + 3.0), 30.0])
    cl = compute_centerline(lumen, ct, c_wall, p_wall)
    vox = np.linalg.norm(ct.spacing)
    assert np.linalg.norm(cl.points_lps[0] - snap_to_region(lumen, ct, c_wall)) <= 2 * vox
    assert np.linalg.norm(cl.points_lps[-1] - snap_to_region(lumen, ct, p_wall)) <= 2 * vox
    assert inside(lumen, ct, cl.points_lps[1:-1]).all()
    away = (cl.arclength_mm > 2 * R) & (cl.arclength_mm < cl.length_mm - 2 * R)
    assert j_axis_distance(cl.points_lps[away]).max() <= 0.4 * R


def test_crop_gives_the_same_curve(stomach):
    ct, lumen = stomach
    lo, hi = bounding_box(lumen, (3, 3, 3))
    crop = ct.crop(lo, hi)
    c, p = CARDIA + np.array([0.2, 0.3, 0.4]), PYLORUS + np.array([0.3, 0.2, 0.1])  # no ties when snapping
    full = compute_centerline(lumen, ct, c, p)
    part = compute_centerline(lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]], crop, c, p)
    assert np.allclose(full.points_lps, part.points_lps, atol=1e-6)
    assert np.allclose(full.radius_mm, part.radius_mm, atol=1e-6)
    # a point on the wall just outside a tight crop still snaps onto the lumen
    lo, hi = bounding_box(lumen, (1, 1, 1))
    tight = ct.crop(lo, hi)
    c_wall = np.array([15.0, 0.0, 110.0 + R + 3.0])  # 3 mm above the top of the lumen
    assert not tight.contains_lps(c_wall[None], margin=0.0)[0]
    cl = compute_centerline(lumen[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]], tight, c_wall, p)
    assert np.linalg.norm(cl.points_lps[0] - c_wall) <= 3.0 + np.linalg.norm(ct.spacing)


def test_from_air_region_seeds():
    ct, parts = make_abdomen(*GEOMETRIES["iso1.5"])
    mask, info = air_region(ct, CARDIA, PYLORUS)
    cl = compute_centerline(mask, ct, CARDIA, PYLORUS)
    assert np.allclose(cl.points_lps[0], info["seeds_lps"][0])
    assert np.allclose(cl.points_lps[-1], info["seeds_lps"][1])


# ----------------------------------------------------------------------------------------- errors
def test_errors():
    from StomachUnfoldLib.errors import InputError

    ct, parts = make_abdomen(*GEOMETRIES["iso1.5"], septum=True)
    lumen = parts["lumen"]
    with pytest.raises(AnatomyError, match="not connected.*--mask"):
        compute_centerline(lumen, ct, CARDIA, PYLORUS)
    with pytest.raises(PointError, match="pylorus.*from the stomach lumen"):
        compute_centerline(lumen, ct, CARDIA, np.array([-60.0, 40.0, 120.0]))
    with pytest.raises(PointError, match="cardia"):
        compute_centerline(lumen, ct, np.array([0.0, 0.0, 500.0]), PYLORUS)  # off the grid and far away
    with pytest.raises(AnatomyError, match="empty"):
        compute_centerline(np.zeros_like(lumen), ct, CARDIA, PYLORUS)
    with pytest.raises(AnatomyError, match="same place"):
        compute_centerline(lumen, ct, CARDIA, CARDIA + 0.5)
    with pytest.raises(InputError, match="shape"):
        compute_centerline(lumen[1:], ct, CARDIA, PYLORUS)
    with pytest.raises(InputError, match="step"):
        compute_centerline(lumen, ct, CARDIA, PYLORUS, step_mm=0.0)


def test_progress_and_cancel():
    ct, parts = make_abdomen(*GEOMETRIES["iso1.5"])
    seen = []
    compute_centerline(parts["lumen"], ct, CARDIA, PYLORUS, progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == 1.0
    with pytest.raises(Cancelled):
        compute_centerline(parts["lumen"], ct, CARDIA, PYLORUS,
                           progress=Progress(lambda stage, f: f < 0.5, stage="centreline"))


# ----------------------------------------------------------------------------------------- full size, real CT
@pytest.mark.slow
def test_full_size_speed():
    ct, a, b, _ = big_ct()
    mask, _ = air_region(ct, a, b)
    compute_centerline(mask, ct, a, b)  # warm up
    t0 = time.perf_counter()
    cl = compute_centerline(mask, ct, a, b)
    dt = time.perf_counter() - t0
    assert dt < 2.0, f"compute_centerline took {dt:.2f} s on 512x512x400"
    assert np.median(cl.radius_mm) == pytest.approx(30.0, rel=0.05)
    assert 0.85 * 150.0 < cl.length_mm < 150.0  # 70 + 80 mm along the L-shaped axis; the corner is cut


def test_real_ct_slab_with_stomach_label():
    from StomachUnfoldLib.preprocessing import lumen_from_mask

    ct, stomach = real_slab_with_stomach()
    pts = ct.voxel_lps(stomach)
    # the slab cuts the stomach across; take the two ends of the label along its longest extent (y)
    a, b = pts[np.argmin(pts[:, 1])], pts[np.argmax(pts[:, 1])]
    lumen, _ = lumen_from_mask(stomach, ct, a, b)
    cl = compute_centerline(lumen, ct, a, b)
    check_curve(cl, 2.0)
    assert inside(lumen, ct, cl.points_lps).all()
    assert cl.length_mm > 0.8 * np.linalg.norm(b - a)
    assert np.all(cl.radius_mm[1:-1] > 0)
