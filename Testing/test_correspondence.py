"""Correspondence between the original CT and the unfolded volume: exact round trips, extrapolation, NaN."""
import numpy as np
import pytest

from StomachUnfoldLib.correspondence import Correspondence, point_tet_distance
from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.unfolded_volume import build_unfolded_volume, hex_to_tets, make_grid
from conftest import FLIP, bent_slab, block, ramp_ct, rotation, two_blocks


def _slab(direction, n=(10, 3, 2), cell_vox=(5, 5, 2)):
    """A slab of cells aligned with the voxel axes of a CT with the given direction (anisotropic spacing)."""
    ct = Volume(np.zeros((40, 40, 80), np.float32), (0.8, 0.9, 2.0), (-30.0, 12.0, -20.0), direction)
    rest, hexes, ijk = block(n, cell_vox, ct, lo_vox=(3, 4, 5))
    return ct, rest, hexes, ijk


def _inside_points(ct, ijk, n, rng, shrink=1e-3):
    """Random LPS points strictly inside the block spanned by the CT indices ijk."""
    lo, hi = ijk.min(0) + shrink, ijk.max(0) - shrink
    return ct.index_to_lps(rng.uniform(lo, hi, size=(n, 3)))


@pytest.mark.parametrize("direction", [np.eye(3), FLIP])
def test_round_trip_under_bending_is_exact(direction):
    ct, rest, hexes, ijk = _slab(direction)
    deformed = bent_slab(rest, 25.0)
    corr = Correspondence(rest, deformed, hexes)
    rng = np.random.default_rng(1)
    p = _inside_points(ct, ijk, 500, rng)
    there = corr.to_unfolded(p)
    assert np.all(np.isfinite(there))
    assert np.abs(there - p).max() > 5.0  # the bend really moved them
    assert np.allclose(corr.to_original(there), p, atol=1e-6, rtol=0)
    # and the other way round, from points of the deformed model
    q = corr.to_unfolded(_inside_points(ct, ijk, 300, rng))
    assert np.allclose(corr.to_unfolded(corr.to_original(q)), q, atol=1e-6, rtol=0)
    # vertices map exactly onto their partners
    assert np.allclose(corr.to_unfolded(rest), deformed, atol=1e-9)
    assert np.allclose(corr.to_original(deformed), rest, atol=1e-9)


def test_affine_deformation_is_exact_and_extrapolates_within_tolerance():
    ct, rest, hexes, ijk = _slab(rotation([1, 2, 3], 40))
    A = rotation([0, 1, 1], 30) @ np.diag([1.2, 0.7, 1.5])
    t = np.array([5.0, -8.0, 30.0])
    corr = Correspondence(rest, rest @ A.T + t, hexes)
    cell = corr.max_outside_mm
    assert np.isclose(cell, 5 * 0.9)  # default: one cell (largest median edge)
    rng = np.random.default_rng(2)
    p = _inside_points(ct, ijk, 300, rng, shrink=0.0)
    assert np.allclose(corr.to_unfolded(p), p @ A.T + t, atol=1e-9)
    # points off the model along the outward normal of its sides (CT index axes)
    centre = rest.mean(0)
    normals = ct.direction  # columns: LPS unit vectors of i, j, k; the slab's sides are normal to them
    half = (ijk.max(0) - ijk.min(0)) / 2 * ct.spacing
    for ax in range(3):
        for d_mm, finite in ((0.4 * cell, True), (0.9 * cell, True), (1.2 * cell, False), (500.0, False)):
            side = centre + normals[:, ax] * (half[ax] + d_mm)
            got = corr.to_unfolded(side)
            assert got.shape == (3,)
            if finite:
                assert np.allclose(got, A @ side + t, atol=1e-9)  # the nearest tet's map is the affine itself
            else:
                assert np.all(np.isnan(got))
    tight = Correspondence(rest, rest @ A.T + t, hexes, max_outside_mm=0.0)
    assert np.all(np.isnan(tight.to_unfolded(centre + normals[:, 0] * (half[0] + 0.01))))
    assert np.all(np.isfinite(tight.to_unfolded(centre + normals[:, 0] * (half[0] - 0.01))))


def test_stretched_tetrahedra_are_still_found():
    """A strong shear makes the nearest centroids miss the holder: the exact fallback finds it."""
    ct, rest, hexes, ijk = _slab(np.eye(3), n=(6, 6, 3), cell_vox=(4, 4, 2))
    z = rest[:, 2] - rest[:, 2].min()
    deformed = rest.copy()
    deformed[:, 0] += 6.0 * z  # 6 mm of x per mm of z
    deformed[:, 1] += 0.02 * (deformed[:, 0] - 20) ** 2  # and a non-affine bow
    corr = Correspondence(rest, deformed, hexes, candidates=2)
    rng = np.random.default_rng(5)
    p = _inside_points(ct, ijk, 400, rng)
    there = corr.to_unfolded(p)
    back = corr.to_original(there)
    assert np.all(np.isfinite(back))
    assert np.allclose(back, p, atol=1e-6, rtol=0)


def test_matches_the_unfolded_volume_voxel_by_voxel():
    """to_original of an unfolded voxel centre is exactly where build_unfolded_volume sampled the CT."""
    ct = ramp_ct(FLIP)
    rest, hexes, _ = block((6, 3, 2), (5, 5, 3), ct)
    deformed = bent_slab(rest, 20.0)
    grid = make_grid(deformed, rotation([0, 1, 0], 15), 0.6)
    out, info = build_unfolded_volume(ct, rest, deformed, hexes, grid, dtype=np.float32)
    corr = Correspondence(rest, deformed, hexes, view_axis=grid.axes[:, 2])
    kk, jj, ii = np.nonzero(out.array != -1024)
    sel = np.random.default_rng(0).choice(len(kk), 2000, replace=False)
    q = out.index_to_lps(np.stack([ii[sel], jj[sel], kk[sel]], 1).astype(float))
    src = corr.to_original(q)
    assert np.all(np.isfinite(src))
    assert np.allclose(ct.sample(src), out.array[kk[sel], jj[sel], ii[sel]], atol=1e-3)
    # and a CT point lands on the voxel that shows it
    back = corr.to_unfolded(src)
    assert np.allclose(back, q, atol=1e-6)


def test_folds_resolve_towards_the_viewer_like_the_unfolded_volume():
    ct = ramp_ct()
    rest, hexes, deformed, na = two_blocks(ct, 3.5)
    lo, hi = deformed[:na].min(0), deformed[:na].max(0)
    q = np.array([(lo + hi) / 2 + [0.3, -0.2, 2.0]])  # inside both layers
    assert np.all(q[0, 2] > lo[2] + 3.5)
    shift_b = rest[na] - deformed[na]
    up = Correspondence(rest, deformed, hexes, view_axis=[0, 0, 1]).to_original(q)
    down = Correspondence(rest, deformed, hexes, view_axis=[0, 0, -1]).to_original(q)
    assert np.allclose(up, q + shift_b) and np.allclose(down, q)
    for kdir in (1.0, -1.0):
        grid = make_grid(deformed, np.diag([1.0, kdir, kdir]), 0.5, margin_mm=1.23)
        out, _ = build_unfolded_volume(ct, rest, deformed, hexes, grid, dtype=np.float32)
        corr = Correspondence(rest, deformed, hexes, view_axis=grid.axes[:, 2])
        kk, jj, ii = np.nonzero(out.array != -1024)
        c = out.index_to_lps(np.stack([ii, jj, kk], 1).astype(float))
        assert np.allclose(ct.sample(corr.to_original(c)), out.array[kk, jj, ii], atol=1e-3)


def test_point_tet_distance_is_euclidean():
    corners = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]], float)
    pts = np.array([[0.1, 0.1, 0.1], [-1, 0, 0], [2, 0, 0], [0.2, 0.2, -0.5], [1, 1, 1], [-1, -1, -1]], float)
    d = point_tet_distance(pts, np.repeat(corners, len(pts), 0))
    face = (3 - 1) / np.sqrt(3)  # (1,1,1) to the plane x+y+z=1
    assert np.allclose(d, [0, 1, 1, 0.5, face, np.sqrt(3)])


def test_landmarks_nan_and_input_checks():
    ct, rest, hexes, ijk = _slab(np.eye(3))
    deformed = bent_slab(rest, 25.0)
    corr = Correspondence(rest, deformed, hexes)
    inside = rest.mean(0) + [0.3, 0.2, 0.1]
    res = corr.map_landmarks({"a": inside, "far": [1e4, 0, 0], "nan": [np.nan, 0, 0]}, "to_unfolded")
    assert set(res) == {"a", "far", "nan"}
    assert np.allclose(res["a"], corr.to_unfolded(inside)) and np.all(np.isfinite(res["a"]))
    assert np.all(np.isnan(res["far"])) and np.all(np.isnan(res["nan"]))
    back = corr.map_landmarks({"a": res["a"]}, "to_original")
    assert np.allclose(back["a"], inside, atol=1e-6)
    assert corr.map_landmarks({}, "to_original") == {}
    with pytest.raises(InputError, match="to_unfolded"):
        corr.map_landmarks({"a": inside}, "sideways")
    assert corr.to_unfolded(np.zeros((0, 3))).shape == (0, 3)
    tets = hex_to_tets(hexes)[0]
    by_tets = Correspondence.from_tets(rest, deformed, tets, max_outside_mm=corr.max_outside_mm)
    assert np.allclose(by_tets.to_unfolded(inside), corr.to_unfolded(inside))
    assert corr.tet_of(inside)[0] >= 0 and corr.tet_of([1e4, 0, 0])[0] == -1
    with pytest.raises(InputError):
        Correspondence(rest, deformed[:-1], hexes)
    with pytest.raises(InputError):
        Correspondence(rest, deformed, hexes + len(rest))
    with pytest.raises(InputError):
        Correspondence(rest, deformed)
    with pytest.raises(InputError):
        corr.to_unfolded(np.zeros((4, 2)))
