"""Tests of StomachUnfoldLib.preprocessing on analytic phantoms: a gas-filled J-shaped stomach tube with
a tissue wall inside an elliptic body, with lungs, colon gas and outside air placed near it."""
import os
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from StomachUnfoldLib.errors import AnatomyError, InputError, PointError
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.preprocessing import (MAX_STOMACH_ML, air_region, bounding_box, lumen_from_mask,
                                            snap_to_region, wall_region)

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


def _seg_dist(q, a, b):
    """Distance (mm) from points q (N,3) to the segment a-b."""
    ab = b - a
    t = np.clip(((q - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(q - (a + t[:, None] * ab), axis=1)


def j_axis_distance(q):
    """Distance (mm) from LPS points q (N,3) to the axis of the J-shaped stomach tube."""
    q = np.atleast_2d(q)
    d1 = _seg_dist(q, np.array([15.0, 0, 110]), np.array([15.0, 0, 55]))
    d3 = _seg_dist(q, np.array([-10.0, 0, 30]), np.array([-35.0, 0, 30]))
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


@pytest.fixture(scope="module", params=list(GEOMETRIES))
def abdomen(request):
    spacing, direction = GEOMETRIES[request.param]
    return make_abdomen(spacing, direction)


@pytest.fixture(scope="module")
def abdomen_iso():
    return make_abdomen(*GEOMETRIES["iso1.5"])


# ----------------------------------------------------------------------------------------- air region
def test_phantom_is_what_the_tests_assume(abdomen):
    ct, parts = abdomen
    # the distractors exist, are close to the stomach, and do not touch its lumen
    near = wall_region(parts["lumen"], ct.spacing, 10.0)
    for name in ("lungs", "colon", "outside"):
        assert parts[name].any(), name
        assert not (parts[name] & parts["lumen"]).any(), name
    assert (near & parts["colon"]).any() and (near & parts["outside"]).any()
    assert np.all(ct.array[parts["lungs"]] < -500)


def test_air_region_is_the_stomach_gas(abdomen):
    ct, parts = abdomen
    seen = []
    mask, info = air_region(ct, CARDIA, PYLORUS, progress=seen.append)
    assert mask.dtype == bool and mask.shape == ct.array.shape
    assert np.array_equal(mask, parts["lumen"])
    for name in ("lungs", "colon", "outside"):
        assert not (mask & parts[name]).any(), name
    assert info["volume_ml"] == pytest.approx(TUBE_ML, rel=0.10)
    assert info["volume_ml"] == pytest.approx(mask.sum() * np.prod(ct.spacing) / 1000.0)
    assert info["n_components"] == 1 and info["warnings"] == []
    seeds = np.array(info["seeds_lps"])
    assert np.all(j_axis_distance(seeds) < R)
    assert np.linalg.norm(seeds - np.stack([CARDIA, PYLORUS]), axis=1).max() <= np.linalg.norm(ct.spacing) / 2
    assert seen and seen[-1] == 1.0 and all(0 <= f <= 1 for f in seen)


def test_points_on_the_wall_3mm_outside_the_lumen(abdomen):
    ct, parts = abdomen
    cardia_wall = np.array([15.0 + R + 3.0, 0.0, 100.0])  # 3 mm into the wall, beside the lumen
    pylorus_wall = np.array([-30.0, -(R + 3.0), 30.0])
    # both points lie in tissue (the wall), not in air
    assert np.all(ct.sample(np.stack([cardia_wall, pylorus_wall]), order=0) > -500)
    mask, info = air_region(ct, cardia_wall, pylorus_wall)
    assert np.array_equal(mask, parts["lumen"])
    seeds = np.array(info["seeds_lps"])
    moved = np.linalg.norm(seeds - np.stack([cardia_wall, pylorus_wall]), axis=1)
    assert np.all(moved < 3.0 + np.linalg.norm(ct.spacing))


def test_point_outside_the_volume(abdomen_iso):
    ct, _ = abdomen_iso
    with pytest.raises(PointError, match="pylorus.*outside the volume.*bounds"):
        air_region(ct, CARDIA, np.array([0.0, 0.0, 400.0]))


def test_point_in_solid_tissue_far_from_air(abdomen_iso):
    ct, _ = abdomen_iso
    with pytest.raises(AnatomyError, match=r"no gas near the cardia.*--mask"):
        air_region(ct, np.array([-35.0, 20.0, 90.0]), PYLORUS)


def test_point_in_outside_air(abdomen):
    ct, _ = abdomen
    with pytest.raises(AnatomyError, match="outside the body"):
        air_region(ct, np.array([15.0, -40.0, 75.0]), PYLORUS)  # in the fold of outside air


def test_implausibly_large_air_region():
    vol = make_grid(np.full(3, 5.0), np.eye(3), lo=(-150, -150, -150), hi=(150, 150, 150))
    p = voxel_points(vol)
    arr = np.full(vol.array.shape, 40, np.int16)
    arr[np.linalg.norm(p, axis=-1) < 110.0] = -1000  # 5.6 L of gas inside the body
    with pytest.raises(AnatomyError, match="too large for a stomach"):
        air_region(vol.with_array(arr), np.array([0.0, 0, 50]), np.array([0.0, 0, -50]))
    assert MAX_STOMACH_ML == 4000.0


def test_separate_air_pockets_give_union_and_warning():
    ct, parts = make_abdomen(*GEOMETRIES["iso1.5"], septum=True)
    mask, info = air_region(ct, CARDIA, PYLORUS)
    assert info["n_components"] == 2
    assert len(info["warnings"]) == 1 and "separate" in info["warnings"][0]
    assert np.array_equal(mask, parts["lumen"])


def test_threshold_is_honoured(abdomen_iso):
    ct, parts = abdomen_iso
    # the lungs are -850 HU: with a -900 HU threshold they are not air, and the stomach is unchanged
    mask, _ = air_region(ct, CARDIA, PYLORUS, threshold_hu=-900.0)
    assert np.array_equal(mask, parts["lumen"])
    with pytest.raises(AnatomyError, match="no gas"):
        air_region(ct, CARDIA, PYLORUS, threshold_hu=-1100.0)


# ----------------------------------------------------------------------------------------- snapping
@pytest.mark.parametrize("geom", list(GEOMETRIES))
def test_snap_to_region_is_the_nearest_voxel(geom):
    spacing, direction = GEOMETRIES[geom]
    vol = make_grid(spacing, direction, lo=(-20, -20, -20), hi=(20, 20, 20))
    rng = np.random.default_rng(1)
    mask = rng.random(vol.array.shape) < 0.002
    allp = vol.voxel_lps(mask)
    for q in rng.uniform(-15, 15, size=(20, 3)):
        d = np.linalg.norm(allp - q, axis=1)
        if d.min() > 10.0:
            with pytest.raises(PointError, match=r"nearest is \d+\.\d mm away"):
                snap_to_region(mask, vol, q, max_distance_mm=10.0)
            continue
        s = snap_to_region(mask, vol, q, max_distance_mm=10.0)
        assert np.linalg.norm(s - q) == pytest.approx(d.min())
        assert mask[tuple(np.rint(vol.lps_to_index(s[None])[0]).astype(int)[::-1])]


def test_snap_to_region_errors():
    vol = make_grid(np.array([1.0, 1.0, 2.5]), np.eye(3), lo=(0, 0, 0), hi=(50, 50, 50))
    mask = np.zeros(vol.array.shape, bool)
    mask[10, 25, 25] = True  # voxel centre at (25, 25, 25) mm
    assert np.allclose(snap_to_region(mask, vol, [27.0, 24.0, 30.0]), [25, 25, 25])
    with pytest.raises(PointError, match=r"cardia.*nearest is 25\.0 mm away"):
        snap_to_region(mask, vol, [25.0, 25.0, 50.0], 20.0, "cardia")
    with pytest.raises(PointError, match="outside the volume"):
        snap_to_region(mask, vol, [25.0, 25.0, 80.0])
    with pytest.raises(PointError, match="none in the volume"):
        snap_to_region(np.zeros_like(mask), vol, [25.0, 25.0, 25.0])


# ----------------------------------------------------------------------------------------- mask lumen
def test_lumen_from_mask_without_gas():
    ct, parts = make_abdomen(*GEOMETRIES["aniso1x1x2.5"], gas=False)
    with pytest.raises(AnatomyError, match="no gas"):
        air_region(ct, CARDIA, PYLORUS)
    label = parts["lumen"] | parts["colon"]  # a label with an extra, unconnected piece
    mask, info = lumen_from_mask(label, ct, CARDIA, PYLORUS)
    assert np.array_equal(mask, parts["lumen"])
    assert info["volume_ml"] == pytest.approx(TUBE_ML, rel=0.10)
    assert info["n_components"] == 1 and info["warnings"] == []
    # points on the wall, 3 mm outside the label, still work
    mask2, _ = lumen_from_mask(label, ct, np.array([15.0 - R - 3.0, 0, 100.0]), np.array([-30.0, R + 3.0, 30.0]))
    assert np.array_equal(mask2, parts["lumen"])
    with pytest.raises(PointError, match="pylorus"):
        lumen_from_mask(label, ct, CARDIA, np.array([-60.0, 30.0, 120.0]))
    with pytest.raises(AnatomyError, match="empty"):
        lumen_from_mask(np.zeros_like(label), ct, CARDIA, PYLORUS)
    with pytest.raises(InputError, match="shape"):
        lumen_from_mask(label[1:], ct, CARDIA, PYLORUS)


# ----------------------------------------------------------------------------------------- wall region
@pytest.mark.parametrize("geom", list(GEOMETRIES))
def test_wall_region_is_the_shell_within_the_thickness(geom):
    spacing, direction = GEOMETRIES[geom]
    vol = make_grid(spacing, direction, lo=(-25, -25, -25), hi=(25, 25, 25))
    p = voxel_points(vol)
    lumen = (np.linalg.norm(p[..., :2], axis=-1) < 8.0) & (np.abs(p[..., 2]) < 12.0)
    t = 4.3
    wall = wall_region(lumen, vol.spacing, t)
    # brute force: Euclidean distance (mm) of every voxel centre to the nearest lumen voxel centre
    d = cKDTree(p[lumen]).query(p.reshape(-1, 3))[0].reshape(lumen.shape)
    assert not (wall & lumen).any()
    assert np.array_equal(wall, ~lumen & (d <= t))
    # physical check against the analytic cylinder: the shell reaches about t mm beyond the lumen surface
    rad = np.linalg.norm(p[..., :2], axis=-1)
    side = wall & (np.abs(p[..., 2]) < 8.0)
    assert rad[side].max() == pytest.approx(8.0 + t, abs=np.linalg.norm(spacing))
    assert rad[side].min() >= 8.0 - 1e-9


def test_wall_region_on_the_stomach(abdomen_iso):
    ct, parts = abdomen_iso
    wall = wall_region(parts["lumen"], ct.spacing, WALL)
    d = j_axis_distance(ct.voxel_lps(wall))
    assert d.min() >= R - 1e-9 and d.max() < R + WALL + np.linalg.norm(ct.spacing) / 2
    # it covers the analytic wall, away from the edges of the voxelised surfaces
    true_core = ct.voxel_lps(parts["wall"])
    dc = j_axis_distance(true_core)
    inner = true_core[(dc > R + 1.0) & (dc < R + WALL - 1.0)]
    idx = np.rint(ct.lps_to_index(inner)).astype(int)
    assert wall[idx[:, 2], idx[:, 1], idx[:, 0]].all()
    with pytest.raises(InputError):
        wall_region(parts["lumen"], ct.spacing, 0.0)


def test_wall_region_uses_the_bounding_box_only():
    lumen = np.zeros((300, 300, 300), bool)
    lumen[150:160, 150:160, 150:160] = True
    t0 = time.perf_counter()
    wall = wall_region(lumen, (1.0, 1.0, 1.0), 2.0)
    assert time.perf_counter() - t0 < 1.0  # a whole-volume distance transform takes several seconds
    # the same shell as on a small crop around the lumen
    ref = wall_region(lumen[140:170, 140:170, 140:170], (1.0, 1.0, 1.0), 2.0)
    assert wall.sum() == ref.sum() and np.array_equal(wall[140:170, 140:170, 140:170], ref)


# ----------------------------------------------------------------------------------------- bounding box
def test_bounding_box():
    m = np.zeros((10, 20, 30), bool)  # k, j, i
    m[2:5, 7, 11:13] = True
    lo, hi = bounding_box(m)
    assert lo.tolist() == [11, 7, 2] and hi.tolist() == [13, 8, 5]
    lo, hi = bounding_box(m, (20, 1, 3))
    assert lo.tolist() == [0, 6, 0] and hi.tolist() == [30, 9, 8]
    vol = Volume(m)
    assert vol.crop(lo, hi).array.sum() == m.sum()
    with pytest.raises(AnatomyError):
        bounding_box(np.zeros((3, 3, 3), bool))


# ----------------------------------------------------------------------------------------- full size
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


@pytest.mark.slow
def test_air_region_full_size_speed():
    ct, a, b, ml = big_ct()
    air_region(ct, a, b)  # warm up imports
    t0 = time.perf_counter()
    mask, info = air_region(ct, a, b)
    dt = time.perf_counter() - t0
    assert info["volume_ml"] == pytest.approx(ml, rel=0.05)
    assert dt < 3.0, f"air_region took {dt:.2f} s on 512x512x400"
    lo, hi = bounding_box(mask, (10, 10, 10))
    t0 = time.perf_counter()
    wall_region(mask[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]], ct.spacing, 5.0)
    assert time.perf_counter() - t0 < 2.0


# ----------------------------------------------------------------------------------------- real CT
REAL_CT = "/work/shared/data/02_totalseg_example_ct_dicom_slab_2mm.nii.gz"
REAL_SEG = "/work/shared/data/02_totalseg_example_ct_dicom_slab_seg117_stomach6.nii.gz"


@pytest.mark.skipif(not (os.path.exists(REAL_CT) and os.path.exists(REAL_SEG)), reason="real CT not available")
def test_real_ct_slab_stomach_air():
    import SimpleITK as sitk

    img = sitk.ReadImage(REAL_CT)
    ct = Volume.from_sitk(img)
    seg = sitk.Resample(sitk.ReadImage(REAL_SEG), img, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                        sitk.sitkUInt8)
    stomach = sitk.GetArrayFromImage(seg) == 6
    # two points at the two ends of the stomach's main gas pocket
    from scipy import ndimage

    lab, _ = ndimage.label(stomach & (ct.array < -500))
    main = lab == np.argmax(np.bincount(lab.ravel())[1:]) + 1
    gas = ct.voxel_lps(main)
    a, b = gas[np.argmin(gas[:, 0])], gas[np.argmax(gas[:, 0])]
    mask, info = air_region(ct, a, b)
    assert 8.0 < info["volume_ml"] < 30.0  # the README gives 14.6 mL of air in the stomach label
    assert info["n_components"] == 1
    assert (mask & main).sum() == main.sum() and (mask & stomach).sum() >= 0.9 * mask.sum()
    assert ct.voxel_lps(mask)[:, 0].max() < 45.0  # the colon gas next to it (x 50-93 mm) stays out
    lungs_or_bowel = (ct.array < -500) & ~stomach
    assert (mask & lungs_or_bowel).sum() <= 0.1 * mask.sum()
    wall = wall_region(mask, ct.spacing, 5.0)
    assert (wall & stomach).sum() > 0.2 * wall.sum()
    lum, info2 = lumen_from_mask(stomach, ct, a, b)
    assert info2["volume_ml"] == pytest.approx(141.0, rel=0.2)


def test_distance_mm_matches_scipy_with_anisotropic_spacing():
    from scipy import ndimage as ndi

    from StomachUnfoldLib.preprocessing import distance_mm

    rng = np.random.default_rng(3)
    m = ndi.gaussian_filter(rng.random((30, 35, 40)), 2) > 0.5
    sp = np.array([0.7, 0.9, 2.5])  # i, j, k
    for x in (m, ~m):
        ref = ndi.distance_transform_edt(x, sampling=sp[::-1])
        got = distance_mm(x, sp)
        assert got.dtype == np.float32 and np.allclose(got, ref, atol=1e-4)
    assert np.all(distance_mm(np.zeros((4, 4, 4), bool), sp) == 0)
