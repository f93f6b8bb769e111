"""Unfolded volume and correspondence: exact element inverses, conforming split, round trips."""
import numpy as np
import pytest

from StomachUnfoldLib.correspondence import Correspondence
from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.unfolded_volume import (build_unfolded_volume, hex_to_tets, label_map, make_grid,
                                              tet_inverse)
from StomachUnfoldLib.wall_model import HEX_OFFSETS


def _block(n=(4, 3, 2), h=5.0, origin=(10.0, -20.0, 5.0)):
    """A structured block of n cells of edge h: vertices (LPS mm) and hexes (VTK order)."""
    ni, nj, nk = n
    idx = np.stack(np.meshgrid(np.arange(ni + 1), np.arange(nj + 1), np.arange(nk + 1), indexing="ij"), -1)
    verts = idx.reshape(-1, 3) * h + np.array(origin)
    vid = np.arange(len(verts)).reshape(ni + 1, nj + 1, nk + 1)
    cells = np.stack(np.meshgrid(np.arange(ni), np.arange(nj), np.arange(nk), indexing="ij"), -1).reshape(-1, 3)
    c = cells[:, None, :] + HEX_OFFSETS[None]
    hexes = vid[c[..., 0], c[..., 1], c[..., 2]]
    return verts.astype(float), hexes


def _ramp_ct(direction=np.eye(3)):
    origin = np.array([-10.0, -40.0, -20.0]) if np.linalg.det(direction) > 0 else np.array([-10.0, 20.0, -20.0])
    vol = Volume(np.zeros((40, 40, 40), np.float32), [1.5, 1.5, 1.5], origin, direction)
    k, j, i = np.indices(vol.array.shape)
    P = vol.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1))
    return vol.with_array((3.0 * P[:, 0] - 2.0 * P[:, 1] + P[:, 2]).reshape(vol.array.shape).astype(np.float32))


def test_kuhn_split_is_conforming_and_fills_the_cells():
    v, h = _block((3, 3, 3), 2.0)
    tets, hid = hex_to_tets(h)
    _, _, vol = tet_inverse(v, tets)
    assert np.isclose(np.abs(vol).sum(), 27 * 8.0)  # Kuhn tets come in mirrored pairs: signs alternate
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]), 1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2  # every face is shared by at most two tetrahedra (no T-junctions)
    assert (counts == 1).sum() == 6 * 9 * 2  # boundary triangles: 6 sides of 3x3 faces, 2 each


@pytest.mark.parametrize("direction", [np.eye(3), np.diag([1.0, -1.0, 1.0])])
def test_affine_deformation_samples_the_ramp_exactly(direction):
    ct = _ramp_ct(direction)
    rest, hexes = _block()
    # rotate 30 degrees about z, scale 1.3, shift
    a = np.radians(30)
    A = 1.3 * np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    t = np.array([5.0, 3.0, -2.0])
    deformed = rest @ A.T + t
    grid = make_grid(deformed, np.eye(3), 1.0)
    out, info = build_unfolded_volume(ct, rest, deformed, hexes, grid, background=-1024)
    assert info["inverted_tets"] == 0 and info["overlap_voxels"] == 0
    kk, jj, ii = np.nonzero(out.array > -1024)
    q = out.index_to_lps(np.stack([ii, jj, kk], 1))
    src = (q - t) @ np.linalg.inv(A).T
    expect = 3.0 * src[:, 0] - 2.0 * src[:, 1] + src[:, 2]
    assert np.max(np.abs(out.array[kk, jj, ii] - expect)) <= 0.5 + 1e-6  # int16 rounding only
    # the volume filled equals the deformed model's volume
    assert abs(len(kk) - 1.3 ** 3 * 24 * 125) / (1.3 ** 3 * 24 * 125) < 0.1


def test_overlap_counted_and_top_layer_wins():
    ct = _ramp_ct()
    rest, hexes = _block((2, 2, 1))
    deformed = rest.copy()
    # fold the second half of the block (i >= 1 column) on top of the first
    right = rest[:, 0] > 10.0 + 5.0 + 1e-6
    deformed[right, 0] = 2 * (10.0 + 5.0) - rest[right, 0]
    deformed[right, 2] += 5.3
    grid = make_grid(deformed, np.eye(3), 0.7)
    labels, overlap = label_map(grid, deformed, hex_to_tets(hexes)[0])
    assert overlap > 0
    out, info = build_unfolded_volume(ct, rest, deformed, hexes, grid)
    assert info["inverted_tets"] > 0 and info["overlap_voxels"] == overlap
    # where the folded half lies over the first, the viewer (top, +k) sees the folded half's tissue:
    # its source points come from the right half of the rest block (x > 15)
    tets = hex_to_tets(hexes)[0]
    cols = np.argwhere((labels >= 0).sum(axis=0) > 0)
    k_first = np.array([np.flatnonzero(labels[:, j, i] >= 0).max() for j, i in cols])
    tid = labels[k_first, cols[:, 0], cols[:, 1]]
    src_x = rest[tets[tid]].mean(axis=1)[:, 0]
    x_here = grid.index_to_lps(np.stack([cols[:, 1], cols[:, 0], k_first], 1))[:, 0]
    over = x_here < 15.0 - 1.0  # columns over the unfolded first half
    assert np.mean(src_x[over] > 15.0) > 0.9


def test_grid_too_large_is_refused():
    ct = _ramp_ct()
    rest, hexes = _block()
    grid = make_grid(rest, np.eye(3), 0.01)
    with pytest.raises(InputError, match="output-spacing"):
        build_unfolded_volume(ct, rest, rest, hexes, grid, max_voxels=1000)


def test_correspondence_round_trip_under_bending():
    rest, hexes = _block((8, 3, 2), 4.0, origin=(0.0, 0.0, 0.0))
    # bend the slab around a cylinder of radius 40 mm about the y axis
    R = 40.0
    th = rest[:, 0] / R
    r = R - rest[:, 2]
    deformed = np.stack([r * np.sin(th), rest[:, 1], R - r * np.cos(th)], 1)
    corr = Correspondence(rest, deformed, hexes)
    rng = np.random.default_rng(1)
    pts = rng.uniform([1, 1, 1], [31, 11, 7], size=(200, 3))
    there = corr.to_unfolded(pts)
    back = corr.to_original(there)
    assert np.all(np.isfinite(back))
    assert np.allclose(back, pts, atol=1e-6)
    far = corr.to_unfolded(np.array([[500.0, 500.0, 500.0]]))
    assert np.all(np.isnan(far))


@pytest.mark.parametrize("direction", [np.eye(3), np.diag([1.0, -1.0, 1.0])])
def test_sample_gives_an_edge_voxels_value_across_its_whole_extent_and_cval_beyond(direction):
    # a voxel spans half a voxel either side of its centre: a CT cut through the stomach at its last slice shows that
    # slice up to the volume's edge, not -1024 from its centre on (a hole along a slab's edge in the view)
    vol = _ramp_ct(direction)
    n = vol.array.shape[0]
    inner = np.array([[5.0, 7.0, 0.0], [5.0, 7.0, n - 1.0], [0.0, 3.0, 9.0], [n - 1.0, 3.0, 9.0]])  # i, j, k
    half = inner + np.array([[0, 0, -0.45], [0, 0, 0.45], [-0.45, 0, 0], [0.45, 0, 0]])
    beyond = inner + np.array([[0, 0, -0.55], [0, 0, 0.55], [-0.55, 0, 0], [0.55, 0, 0]])
    at_centre = vol.sample(vol.index_to_lps(inner))
    assert np.allclose(vol.sample(vol.index_to_lps(half)), at_centre, atol=1e-3)
    assert np.all(vol.sample(vol.index_to_lps(beyond), cval=-1024.0) == -1024.0)
    mid = np.array([[5.3, 7.6, 9.2]])
    P = vol.index_to_lps(mid)[0]
    assert vol.sample(vol.index_to_lps(mid))[0] == pytest.approx(3.0 * P[0] - 2.0 * P[1] + P[2], abs=1e-3)
