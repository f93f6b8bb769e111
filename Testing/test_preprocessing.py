"""Tests of StomachUnfoldLib.preprocessing on analytic phantoms: a gas-filled J-shaped stomach tube with
a tissue wall inside an elliptic body, with lungs, colon gas and outside air placed near it."""
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from StomachUnfoldLib.errors import AnatomyError, InputError, PointError
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.preprocessing import (MAX_STOMACH_ML, air_region, bounding_box, lumen_from_mask,
                                            snap_to_region, wall_region)
from conftest import (CARDIA, GEOMETRIES, PYLORUS, R, TUBE_ML, WALL, big_ct, j_axis_distance, make_abdomen, make_grid, real_slab_with_stomach, voxel_points)

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
def test_real_ct_slab_stomach_air():
    ct, stomach = real_slab_with_stomach()
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


def test_a_labels_overlap_with_a_neighbouring_gas_body_is_left_out_and_its_own_gas_kept():
    # a label that runs two voxels into a gas loop beside the stomach (an automatic label's edge) and clips its own
    # gas pocket: the loop's voxels go, the pocket's stay, the rest of the label is untouched
    from StomachUnfoldLib.preprocessing import drop_neighbour_gas

    hu = np.full((30, 30, 60), 40.0, np.float32)
    label = np.zeros(hu.shape, bool)
    label[5:25, 5:25, 5:35] = True
    hu[5:25, 5:25, 33:50] = -900.0          # a neighbouring loop: 17 columns, two of them inside the label
    hu[8:14, 8:14, 8:16] = -900.0           # the stomach's own pocket, one column past the label's edge at i = 4..5
    hu[8:14, 8:14, 4:5] = -900.0
    ct = Volume(hu, spacing=np.array([1.0, 1.0, 1.0]))
    out, n = drop_neighbour_gas(label, ct, -500.0)
    assert n == 20 * 20 * 2 and out is not label
    assert not out[:, :, 33:35].any() and out[5:25, 5:25, 5:33].all()
    assert out[8:14, 8:14, 8:16].all()      # the pocket, mostly inside, is kept
    assert label[5:25, 5:25, 33:35].all()   # the given label is not modified
    same, none = drop_neighbour_gas(label[:, :, :30].copy(), Volume(hu[:, :, :30].copy(), spacing=ct.spacing), -500.0)
    assert none == 0
    lum, info = lumen_from_mask(label, ct, ct.voxel_lps(label)[0], ct.voxel_lps(label)[-1], gas_hu=-500.0)
    assert not lum[:, :, 33:35].any() and info["neighbour_gas_ml"] == pytest.approx(0.8)


def test_neighbouring_gas_is_found_the_same_on_a_ct_left_on_file(tmp_path):
    # the command line leaves a CT on file and reads boxes of it: the label's overlap with a gas loop is the same
    from StomachUnfoldLib.io import read_volume, write_volume
    from StomachUnfoldLib.preprocessing import drop_neighbour_gas

    hu = np.full((30, 30, 60), 40, np.int16)
    hu[5:25, 5:25, 33:50] = -900
    label = np.zeros(hu.shape, bool)
    label[5:25, 5:25, 5:35] = True
    ct = Volume(hu, spacing=np.array([0.8, 0.9, 1.5]))
    path = str(tmp_path / "ct.nrrd")
    write_volume(ct, path)
    on_file = read_volume(path, stream=True)
    assert not isinstance(on_file.array, np.ndarray)
    a, na = drop_neighbour_gas(label, ct, -500.0)
    b, nb = drop_neighbour_gas(label, on_file, -500.0)
    assert na == nb == 800 and np.array_equal(a, b)
