"""Unfolded volume: conforming Kuhn split, exact per-tet affine maps, resampling through the deformed model."""
import time

import numpy as np
import pytest

from StomachUnfoldLib.errors import Cancelled, InputError, SimulationError
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.progress import Progress
from StomachUnfoldLib.unfolded_volume import (UnfoldedGrid, apply_affine, build_unfolded_volume, hex_to_tets,
                                              label_map, make_grid, tet_affine, tet_volumes)
from conftest import FLIP, bent_slab, block, ramp, ramp_ct, rotation, two_blocks

# ----------------------------------------------------------------------------------------------- tetrahedra
@pytest.mark.parametrize("direction", [np.eye(3), FLIP])
def test_kuhn_split_is_conforming_and_fills_each_cell(direction):
    ct = Volume(np.zeros((4, 4, 4), np.float32), (0.7, 1.1, 2.5), (3.0, -4.0, 5.0), direction)
    rest, hexes, _ = block((3, 3, 3), (2, 3, 1), ct, lo_vox=(0, 0, 0))
    tets, tet_hex = hex_to_tets(hexes)
    assert tets.shape == (27 * 6, 4)
    assert np.array_equal(tet_hex, np.repeat(np.arange(27), 6))
    cell_volume = 2 * 0.7 * 3 * 1.1 * 1 * 2.5
    vol = tet_volumes(rest, tets)
    assert np.all(np.abs(vol) > 0.1 * cell_volume / 6)
    per_hex = np.bincount(tet_hex, weights=np.abs(vol))
    assert np.allclose(per_hex, cell_volume)  # the six tets tile each cell exactly (no gap, no overlap)
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]]), 1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    # 6 sides x 9 quads x 2 triangles on the boundary, each in one tet; every other face in exactly two
    assert (counts == 1).sum() == 6 * 9 * 2
    assert set(counts.tolist()) == {1, 2}
    assert (counts == 2).sum() == (len(faces) - 108) // 2
    # the boundary triangles are exactly those on the block's outer sides (grid index 0 or 3 on one axis)
    gi = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    b = gi[uniq[counts == 1]]  # (F,3 vertices,3 axes)
    on_side = np.any(np.all((b == 0) | (b == 3), axis=1) & (b.min(axis=1) == b.max(axis=1)), axis=1)
    assert on_side.all()


def test_tet_affine_is_exact_both_ways_and_flags_flat_tets():
    rng = np.random.default_rng(3)
    rest = rng.normal(size=(50, 4, 3)) * 5
    deformed = rng.normal(size=(50, 4, 3)) * 8 + 20
    deformed[7] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]  # flat after deformation
    aff = tet_affine(rest, deformed)
    ok = np.arange(50) != 7
    assert aff.degenerate_deformed.tolist() == (~ok).tolist() and not aff.degenerate_rest.any()
    for m in range(4):
        assert np.allclose(apply_affine(aff.to_rest[ok], deformed[ok, m]), rest[ok, m], atol=1e-9)
        assert np.allclose(apply_affine(aff.to_deformed, rest[:, m]), deformed[:, m], atol=1e-9)
    assert np.all(np.isnan(aff.to_rest[7]))
    x = rng.normal(size=(50, 3)) * 10
    there = apply_affine(aff.to_deformed[ok], x[ok])
    assert np.allclose(apply_affine(aff.to_rest[ok], there), x[ok], atol=1e-8)
    # inverted = opposite sign of the signed volumes (flat ones excluded)
    expect = ok & (np.sign(aff.rest_volume) != np.sign(aff.deformed_volume))
    assert np.array_equal(aff.inverted, expect)
    assert np.allclose(aff.rest_volume, tet_volumes(rest.reshape(-1, 3), np.arange(200).reshape(50, 4)))


def test_make_grid_covers_the_model_with_margin():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-30, 40, size=(500, 3))
    axes = rotation([0.2, 1, -0.5], 40) @ np.diag([1, 1, -1])
    grid = make_grid(pts, axes, (0.7, 0.8, 1.3), margin_mm=2.0)
    ijk = grid.lps_to_index(pts)
    lo_mm = ijk.min(0) * grid.spacing
    hi_mm = (np.array(grid.size) - 1 - ijk.max(0)) * grid.spacing
    assert np.all(lo_mm >= 2.0 - 1e-9) and np.all(lo_mm <= 2.0 + 1e-9)  # origin sits exactly at the margin
    assert np.all(hi_mm >= 2.0 - 1e-9) and np.all(hi_mm < 2.0 + grid.spacing + 1e-9)  # smallest cover
    assert np.allclose(grid.index_to_lps(ijk), pts)
    vol = grid.to_volume(np.zeros(grid.shape_kji, np.int16))
    assert np.allclose(vol.lps_to_index(pts), ijk)
    assert UnfoldedGrid.from_volume(vol).shape_kji == grid.shape_kji
    with pytest.raises(InputError, match="orthonormal"):
        make_grid(pts, np.diag([1.0, 2.0, 1.0]), 1.0)
    with pytest.raises(SimulationError, match="non-finite"):
        make_grid(np.array([[0, 0, np.nan]]), np.eye(3), 1.0)


# ----------------------------------------------------------------------------------------------- resampling
def _filled(out: Volume, background=-1024.0):
    """Indices and LPS centres of the output voxels that are not background."""
    kk, jj, ii = np.nonzero(out.array != background)
    return (kk, jj, ii), out.index_to_lps(np.stack([ii, jj, kk], 1).astype(float))


@pytest.mark.parametrize("direction", [rotation([1, 1, 0], 20), FLIP])
def test_identity_deformation_reproduces_the_ct_without_holes(direction):
    ct = ramp_ct(direction)
    rest, hexes, ijk = block((5, 4, 3), (6, 6, 3), ct)
    axes = rotation([0, 0, 1], 30)  # an output grid oblique to the CT's axes
    grid = make_grid(rest, axes, 0.75)
    out, info = build_unfolded_volume(ct, rest, rest.copy(), hexes, grid, dtype=np.float32)
    assert out.array.dtype == np.float32 and out.array.shape == grid.shape_kji
    assert info["overlap_voxels"] == 0 and info["inverted_tets"] == 0 and info["degenerate_tets"] == 0
    assert info["tets"] == 6 * 60 and info["outside_ct_voxels"] == 0
    # every voxel centre inside the block (in CT index space) is filled with the CT's value, others background
    k, j, i = np.indices(grid.shape_kji)
    P = grid.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1))
    u = ct.lps_to_index(P)
    lo, hi = ijk.min(0), ijk.max(0)
    inside = np.all((u > lo + 1e-6) & (u < hi - 1e-6), axis=1)
    outside = np.any((u < lo - 1e-6) | (u > hi + 1e-6), axis=1)
    vals = out.array.ravel()
    assert inside.sum() > 20000
    assert np.all(vals[inside] != -1024.0)
    assert np.max(np.abs(vals[inside] - ramp(P[inside]))) < 1e-3
    assert np.all(vals[outside] == -1024.0)
    assert info["filled_voxels"] == int((vals != -1024.0).sum())


@pytest.mark.parametrize("direction", [np.eye(3), FLIP])
def test_known_affine_deformation_samples_the_inverse_mapped_ramp(direction):
    ct = ramp_ct(direction)
    rest, hexes, _ = block((5, 4, 3), (6, 6, 3), ct)
    A = rotation([1, -2, 0.5], 35) @ np.diag([1.3, 0.8, 1.1])
    t = np.array([40.0, -25.0, 12.0])
    deformed = rest @ A.T + t
    grid = make_grid(deformed, np.eye(3), 0.6)
    out, info = build_unfolded_volume(ct, rest, deformed, hexes, grid, dtype=np.float32)
    assert info["inverted_tets"] == 0 and info["overlap_voxels"] == 0
    _, q = _filled(out)
    src = (q - t) @ np.linalg.inv(A).T
    assert np.max(np.abs(out.array[out.array != -1024.0] - ramp(src))) < 1e-3
    # the filled voxels measure the deformed model's volume
    model_mm3 = np.abs(tet_volumes(deformed, hex_to_tets(hexes)[0])).sum()
    assert abs(info["filled_voxels"] * 0.6 ** 3 / model_mm3 - 1) < 0.03
    # the default int16 output is the same, rounded
    out16, _ = build_unfolded_volume(ct, rest, deformed, hexes, grid)
    assert out16.array.dtype == np.int16
    assert np.array_equal(out16.array, np.rint(out.array).astype(np.int16))
    # a mirroring deformation inverts every tetrahedron (counted, not a crash)
    _, info_m = build_unfolded_volume(ct, rest, deformed * [1, 1, -1], hexes, make_grid(deformed * [1, 1, -1],
                                      np.eye(3), 1.0))
    assert info_m["inverted_tets"] == info_m["tets"]


def test_overlap_is_counted_and_the_layer_nearest_the_viewer_wins():
    ct = ramp_ct()
    # cells are 6 mm thick (2 mm x 3 voxels); raised by 3.5 mm, B's tetrahedra all have centroids above A's
    # (Kuhn centroids sit at 1/4, 1/2, 3/4 of a cell's height), so the per-tet rule makes a whole layer win
    rest, hexes, deformed, na = two_blocks(ct, 3.5)
    shift_b = rest[na:][0] - deformed[na:][0]  # B's deformed -> rest translation
    for kdir in (1.0, -1.0):  # viewer above (+S) then below (-S)
        axes = np.diag([1.0, kdir, kdir])
        grid = make_grid(deformed, axes, 0.5, margin_mm=1.23)  # no voxel centre on a block's side
        out, info = build_unfolded_volume(ct, rest, deformed, hexes, grid, dtype=np.float32)
        (kk, jj, ii), q = _filled(out)
        lo, hi = deformed[:na].min(0), deformed[:na].max(0)
        in_a = np.all((q > lo + 1e-6) & (q < hi - 1e-6), axis=1)
        in_b = np.all((q > lo + [0, 0, 3.5] + 1e-6) & (q < hi + [0, 0, 3.5] - 1e-6), axis=1)
        both = in_a & in_b
        assert both.sum() > 1000
        assert info["overlap_voxels"] == both.sum()
        v = out.array[kk, jj, ii]
        from_b = np.abs(v - ramp(q + shift_b)) < 1e-3
        from_a = np.abs(v - ramp(q)) < 1e-3
        if kdir > 0:
            assert from_b[both].all()  # B is on top (+S) and is seen
        else:
            assert from_a[both].all()  # looking from -S, A is nearer
        assert from_a[in_a & ~in_b].all() and from_b[in_b & ~in_a].all()
        labels, overlap = label_map(grid, deformed, hex_to_tets(hexes)[0])
        assert overlap == info["overlap_voxels"] and (labels >= 0).sum() == info["filled_voxels"]


def test_clear_mask_and_sources_off_the_ct_get_background():
    ct = ramp_ct()
    rest, hexes, ijk = block((4, 4, 2), (6, 6, 3), ct)
    clear = np.zeros(ct.array.shape, bool)
    clear[:, :, :17] = True  # i < 17 (voxels 5..16 of the block's 5..29)
    grid = make_grid(rest, np.eye(3), 0.5)
    out, info = build_unfolded_volume(ct, rest, rest, hexes, grid, clear_mask=clear, dtype=np.float32)
    kk, jj, ii = np.nonzero(out.array > -1e6)
    q = out.index_to_lps(np.stack([ii, jj, kk], 1).astype(float))
    u = ct.lps_to_index(q)
    in_block = np.all((u > ijk.min(0) + 1e-6) & (u < ijk.max(0) - 1e-6), axis=1)
    v = out.array[kk, jj, ii]
    cleared = np.floor(u[:, 0] + 0.5) < 17
    assert np.all(v[in_block & cleared] == -1024.0)
    assert np.allclose(v[in_block & ~cleared], ramp(q[in_block & ~cleared]), atol=1e-3)
    with pytest.raises(InputError, match="CT's grid"):
        build_unfolded_volume(ct, rest, rest, hexes, grid, clear_mask=clear[1:])
    # a model reaching beyond the CT: those voxels get the background and are counted
    rest2, hexes2, _ = block((2, 2, 2), (6, 6, 3), ct, lo_vox=(60, 5, 3))  # i from 60 to 72 > 69
    out2, info2 = build_unfolded_volume(ct, rest2, rest2, hexes2, make_grid(rest2, np.eye(3), 0.5))
    assert info2["outside_ct_voxels"] > 0
    assert (out2.array != -1024).sum() == info2["filled_voxels"] - info2["outside_ct_voxels"]


def test_grid_too_large_is_refused_with_a_spacing_that_fits():
    ct = ramp_ct()
    rest, hexes, _ = block((3, 3, 2), (6, 6, 3), ct)
    grid = make_grid(rest, np.eye(3), 0.05)
    with pytest.raises(InputError, match=r"at least ([0-9.]+) mm") as err:
        build_unfolded_volume(ct, rest, rest, hexes, grid, max_voxels=100_000)
    sp = float(str(err.value).split("at least ")[1].split(" mm")[0])
    assert make_grid(rest, np.eye(3), sp).n_voxels <= 100_000
    assert make_grid(rest, np.eye(3), sp * 0.8).n_voxels > 100_000 * 0.8 ** 3 * 0.5  # not wildly coarse
    with pytest.raises(SimulationError):
        build_unfolded_volume(ct, rest, rest * np.nan, hexes, grid)


def test_progress_is_reported_and_cancel_stops():
    ct = ramp_ct()
    rest, hexes, _ = block((3, 3, 2), (6, 6, 3), ct)
    grid = make_grid(rest, np.eye(3), 0.5)
    seen = []
    build_unfolded_volume(ct, rest, rest, hexes, grid, progress=Progress(lambda s, f: seen.append(f)))
    assert seen and seen[-1] == 1.0 and np.all(np.diff(seen) >= 0)
    with pytest.raises(Cancelled):
        build_unfolded_volume(ct, rest, rest, hexes, grid, progress=Progress(lambda s, f: f < 0.5))


def _brute_force_inside(grid, deformed, tets):
    """(voxels, tets) barycentric minimum of every voxel centre in every tetrahedron (small cases only)."""
    k, j, i = np.indices(grid.shape_kji)
    q = grid.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1))
    p = deformed[tets]
    E = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], 2)
    inv = np.linalg.inv(E)
    lam = np.einsum("tij,vtj->vti", inv, q[:, None, :] - p[None, :, 0])
    return np.minimum(1 - lam.sum(2), lam.min(2))


@pytest.mark.parametrize("fold", [False, True])
def test_scan_conversion_matches_brute_force_and_chunking(fold):
    """Labels equal a brute-force inside test on a bent (non-affine) slab; chunk size does not matter."""
    ct = ramp_ct()
    rest, hexes, _ = block((4, 2, 2), (5, 5, 3), ct)
    deformed = bent_slab(rest, 14.0 if fold else 30.0)  # a tight (14 mm) or gentle (30 mm) bend
    if fold:  # lift the last column of cells over the first: a second layer over the first
        x = rest[:, 0]
        right = x > np.quantile(x, 0.7)
        deformed[right] = rest[right] + [rest[:, 0].min() - rest[right, 0].min() + 1.3, 0.0, 3.7]
    tets = hex_to_tets(hexes)[0]
    grid = make_grid(deformed, rotation([1, 0, 0], 10), 0.6)
    a, oa = label_map(grid, deformed, tets)
    b, ob = label_map(grid, deformed, tets, chunk_rows=37)
    assert np.array_equal(a, b) and oa == ob
    mn = _brute_force_inside(grid, deformed, tets)
    clear_in = (mn > 1e-6).any(axis=1)
    clear_out = (mn < -1e-6).all(axis=1)
    lab = a.ravel()
    assert np.all(lab[clear_in] >= 0) and np.all(lab[clear_out] == -1)
    own = mn[np.flatnonzero(lab >= 0), lab[lab >= 0]]
    assert own.min() > -1e-7  # each labelled voxel centre lies in its tetrahedron
    # the winner is the containing tetrahedron with the largest centroid k
    prio = grid.lps_to_index(deformed[tets].mean(1))[:, 2]
    holders = np.where(mn >= -1e-9, prio[None, :], -np.inf)
    sel = lab >= 0
    assert np.allclose(prio[lab[sel]], holders[sel].max(axis=1))
    if fold:
        assert oa > 0
        layers = (mn > 1e-6).sum(axis=1)
        assert (layers > 1).sum() <= oa <= ((mn > -1e-6).sum(axis=1) > 1).sum()
    else:
        assert oa == 0


@pytest.mark.slow
def test_performance_2e5_tets_3e7_voxels():
    """~2e5 tetrahedra and a ~3e7-voxel output grid resample in a few seconds (2 cores)."""
    shape = (60, 512, 512)
    ct = Volume(np.random.default_rng(0).integers(-1000, 1000, shape).astype(np.int16), (0.7, 0.7, 1.5))
    rest, hexes, _ = block((64, 64, 8), (7, 7, 3), ct, lo_vox=(2, 2, 2))
    assert 1.9e5 < 6 * len(hexes) < 2.1e5
    deformed = bent_slab(rest, 200.0)
    grid = make_grid(deformed, np.eye(3), 0.7)
    assert 2e7 < grid.n_voxels < 5e7
    t = time.perf_counter()
    out, info = build_unfolded_volume(ct, rest, deformed, hexes, grid)
    seconds = time.perf_counter() - t
    print(f"{info['tets']} tets, {grid.n_voxels:,} voxels, {info['filled_voxels']:,} filled: {seconds:.1f} s")
    assert info["filled_voxels"] > 0.9 * np.abs(tet_volumes(deformed, hex_to_tets(hexes)[0])).sum() / 0.7 ** 3
    assert seconds < 15
