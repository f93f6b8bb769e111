"""The core library runs on what 3D Slicer bundles (numpy, scipy, SimpleITK, vtk): no scikit-image, no tqdm, no zlib-ng.

(a) every module of StomachUnfoldLib imports, and the air region and centreline run and a gzip NRRD is read box by
box, in a subprocess where skimage, tqdm and zlib_ng cannot be imported; (b) the replacements give skimage's results (flood fill, minimal-cost
path); (c) the VTK isosurface matches skimage's marching cubes (area, volume, orientation).
"""
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

BLOCKED_RUN = textwrap.dedent(r'''
    import importlib, importlib.abc, pkgutil, sys

    BLOCKED = ("skimage", "tqdm", "zlib_ng")

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"{name} is blocked in this test (3D Slicer does not bundle it)")
            return None

    sys.meta_path.insert(0, Block())
    for m in list(sys.modules):
        if m.split(".")[0] in BLOCKED:
            del sys.modules[m]

    import numpy as np
    import StomachUnfoldLib

    names = ["StomachUnfoldLib"]
    def onerror(name):
        raise
    for info in pkgutil.walk_packages(StomachUnfoldLib.__path__, "StomachUnfoldLib.", onerror=onerror):
        names.append(info.name)
    for name in names:
        importlib.import_module(name)

    from StomachUnfoldLib.centerline import compute_centerline
    from StomachUnfoldLib.geometry import Volume
    from StomachUnfoldLib.preprocessing import air_region

    # a U-shaped air tube (radius 10 mm) in soft tissue, 2 mm voxels, LPS = index * spacing
    sp = 2.0
    k, j, i = np.mgrid[0:61, 0:46, 0:61].astype(float) * sp
    x, y, z = i, j, k
    phi = np.clip(np.arctan2(z - 60.0, x - 60.0), 0.0, np.pi)
    ax, az = 60.0 + 35.0 * np.cos(phi), 60.0 + 35.0 * np.sin(phi)
    d = np.sqrt((x - ax) ** 2 + (y - 45.0) ** 2 + (z - az) ** 2)
    ct = Volume(np.where(d < 10.0, -1000, 40).astype(np.int16), np.full(3, sp), np.zeros(3), np.eye(3))
    cardia, pylorus = np.array([95.0, 45.0, 60.0]), np.array([25.0, 45.0, 60.0])
    lumen, info = air_region(ct, cardia, pylorus)
    assert lumen.dtype == bool and lumen.shape == ct.array.shape
    assert np.array_equal(lumen, d < 10.0), "the air region is not the tube"
    assert info["n_components"] == 1
    cl = compute_centerline(lumen, ct, cardia, pylorus, step_mm=2.0)
    p = cl.points_lps
    r = np.hypot(p[:, 0] - 60.0, p[:, 2] - 60.0)
    assert np.abs(r - 35.0).max() < 3.0 and np.abs(p[:, 1] - 45.0).max() < 2.0, "the centreline is off the axis"
    assert abs(cl.length_mm - np.pi * 35.0) < 0.1 * np.pi * 35.0, cl.length_mm
    assert np.abs(cl.radius_mm[3:-3] - 10.0).max() < 3.0, cl.radius_mm
    import os, tempfile, zlib
    import StomachUnfoldLib.volume_file as vf
    from StomachUnfoldLib.io import read_volume, write_volume
    assert vf._inflate is zlib
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "ct.nrrd")
        write_volume(ct, path)
        on_file = read_volume(path, stream=True)
        assert isinstance(on_file.array, vf.FileArray) and on_file.array._backend.gzip
        on_file.array.scan(-500.0)
        assert np.array_equal(on_file.array[5:50, ::3, 7:40], ct.array[5:50, ::3, 7:40])
    leaked = [m for m in sys.modules if m.split(".")[0] in BLOCKED]
    assert not leaked, leaked
    print("OK", len(names), "modules")
''')


def test_library_runs_without_skimage_and_tqdm():
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    res = subprocess.run([sys.executable, "-c", BLOCKED_RUN], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.startswith("OK"), res.stdout


# ---------------------------------------------------------------------------------------------- (b) flood
@pytest.mark.parametrize("density", [0.3, 0.55, 0.75])
def test_flood_fill_equals_skimage(density):
    flood = pytest.importorskip("skimage.morphology").flood
    from StomachUnfoldLib.preprocessing import flood_fill

    rng = np.random.default_rng(int(density * 100))
    for trial in range(6):
        shape = tuple(int(s) for s in rng.integers(5, 30, 3))
        img = rng.random(shape) < density
        for on in (True, False):  # seed on the mask and off it (flood then fills the background component)
            cand = np.argwhere(img == on)
            if len(cand) == 0:
                continue
            seed = tuple(int(x) for x in cand[rng.integers(len(cand))])
            got = flood_fill(img, seed)
            want = flood(img, seed, connectivity=1)
            assert got.dtype == bool and got.shape == img.shape
            assert np.array_equal(got, want), (shape, seed, on)
    # larger arrays where the subsampled guess of the region's box is wrong and the box must grow: a blob
    # with one-voxel threads between the subsample's planes, and near-percolation random masks
    img = np.zeros((60, 64, 90), bool)
    k, j, i = np.ogrid[:60, :64, :90]
    img |= (k - 20) ** 2 + (j - 20) ** 2 + (i - 20) ** 2 < 36
    img[21, 21, 20:87] = True
    img[21:58, 22, 86] = True
    img[57, 22:63, 86] = True
    img[50:58, 55:63, 70:86] = True
    for seed in ((20, 20, 20), (57, 60, 80), (0, 0, 0), (21, 22, 50)):
        assert np.array_equal(flood_fill(img, seed), flood(img, seed, connectivity=1)), seed
    for trial in range(4):
        img = rng.random((50, 60, 70)) < 0.3 + 0.01 * trial
        for seed in np.argwhere(img)[rng.integers(0, int(img.sum()), 3)]:
            seed = tuple(int(x) for x in seed)
            assert np.array_equal(flood_fill(img, seed), flood(img, seed, connectivity=1)), seed
    # non-contiguous input and the seed on an array corner
    img = (rng.random((24, 30, 18)) < 0.6)[:, ::2, :]
    for seed in ((0, 0, 0), (23, 14, 17)):
        assert np.array_equal(flood_fill(img, seed), flood(img, seed, connectivity=1))


# ---------------------------------------------------------------------------------------------- (b) path
def _path_cost(cost, path, sampling):
    """MCP_Geometric's cost of a given path: sum over steps of (c_a + c_b) / 2 * step length."""
    d = np.diff(path, axis=0)
    assert np.abs(d).max() <= 1 and np.all(np.abs(d).sum(1) > 0), "not a 26-connected path"
    length = np.sqrt(((d * np.asarray(sampling)) ** 2).sum(1))
    c = cost[tuple(path.T)]
    return float(np.sum(0.5 * (c[:-1] + c[1:]) * length))


@pytest.mark.parametrize("sampling", [(1.0, 1.0, 1.0), (2.5, 0.8, 1.3)])
def test_minimal_path_equals_mcp_geometric(sampling):
    MCP_Geometric = pytest.importorskip("skimage.graph").MCP_Geometric
    from StomachUnfoldLib.centerline import minimal_path

    rng = np.random.default_rng(7)
    n_checked = 0
    for trial in range(8):
        shape = tuple(int(s) for s in rng.integers(8, 26, 3))
        cost = rng.uniform(0.2, 5.0, shape)
        cost[rng.random(shape) < 0.25] = np.inf
        ok = np.argwhere(np.isfinite(cost))
        s, e = (tuple(int(x) for x in ok[rng.integers(len(ok))]) for _ in range(2))
        mcp = MCP_Geometric(cost, sampling=sampling)
        costs, _ = mcp.find_costs([s], [e])
        path, c = minimal_path(cost, s, e, sampling=sampling)
        if not np.isfinite(costs[e]):
            assert path is None and c == np.inf
            continue
        assert path is not None and path.dtype.kind == "i" and path.shape[1] == 3
        assert tuple(path[0]) == s and tuple(path[-1]) == e
        assert np.all(np.isfinite(cost[tuple(path.T)]))
        assert c == pytest.approx(float(costs[e]), rel=1e-9, abs=1e-6)
        assert _path_cost(cost, path, sampling) == pytest.approx(c, rel=1e-9, abs=1e-6)
        assert _path_cost(cost, np.array(mcp.traceback(e)), sampling) == pytest.approx(c, rel=1e-9, abs=1e-6)
        n_checked += 1
    assert n_checked >= 4
    # separated halves: no path
    cost = np.ones((6, 7, 8))
    cost[:, 3, :] = np.inf
    assert minimal_path(cost, (0, 0, 0), (5, 6, 7)) == (None, np.inf)


# ---------------------------------------------------------------------------------------------- (c) isosurface
def _area_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0  # signed: the winding's orientation
    return float(area), float(volume)


def _fields():
    k, j, i = np.mgrid[0:56, 0:52, 0:60].astype(np.float32)
    sphere = np.sqrt((k - 27.3) ** 2 + (j - 25.6) ** 2 + (i - 30.2) ** 2)
    rho = np.sqrt((j - 26.0) ** 2 + (i - 29.5) ** 2)
    torus = np.sqrt((rho - 15.0) ** 2 + (k - 27.8) ** 2)
    return {"sphere": (sphere, 18.0, 4.0 * np.pi * 18.0 ** 2, 4.0 / 3.0 * np.pi * 18.0 ** 3),
            "torus": (torus, 6.0, 4.0 * np.pi ** 2 * 15.0 * 6.0, 2.0 * np.pi ** 2 * 15.0 * 6.0 ** 2)}


@pytest.mark.parametrize("name", ["sphere", "torus"])
@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("step", [1, 2])
def test_isosurface_matches_marching_cubes(name, sign, step):
    marching_cubes = pytest.importorskip("skimage.measure").marching_cubes
    from StomachUnfoldLib.isosurface import isosurface

    field, level, area_true, vol_true = _fields()[name]
    field, level = sign * field, sign * level  # sign -1: the object is the high side
    v0, f0, _, _ = marching_cubes(field, level, step_size=step)
    v1, f1 = isosurface(field, level, step=step)
    assert v1.shape[1] == 3 and f1.shape[1] == 3 and f1.dtype == np.int64
    assert f1.min() >= 0 and f1.max() < len(v1)
    a0, vol0 = _area_volume(v0, f0)
    a1, vol1 = _area_volume(v1, f1)
    assert a1 == pytest.approx(a0, rel=0.01)
    assert vol1 == pytest.approx(vol0, rel=0.01)  # signed: the same orientation as skimage
    assert np.sign(vol1) == np.sign(vol0) != 0
    assert abs(abs(vol1) - vol_true) < 0.03 * vol_true and abs(a1 - area_true) < 0.03 * area_true
    # no degenerate triangles: distinct vertices, non-zero area
    assert np.all((f1[:, 0] != f1[:, 1]) & (f1[:, 1] != f1[:, 2]) & (f1[:, 0] != f1[:, 2]))
    cr = np.cross(v1[f1[:, 1]] - v1[f1[:, 0]], v1[f1[:, 2]] - v1[f1[:, 0]])
    assert np.all(np.linalg.norm(cr, axis=1) > 0)
    # closed, consistently wound surface: every directed edge appears once and its reverse once
    e = np.concatenate([f1[:, [0, 1]], f1[:, [1, 2]], f1[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    assert len(fwd) == len(e) and all((b, a) in fwd for a, b in fwd)
    # vertices in (k, j, i) index order: the sphere's centre
    if name == "sphere":
        assert np.allclose(v1.mean(0), [27.3, 25.6, 30.2], atol=0.3)


def test_isosurface_step_and_edge_cases():
    from StomachUnfoldLib.isosurface import isosurface

    field = _fields()["sphere"][0]
    n1 = len(isosurface(field, 18.0, 1)[0])
    n2 = len(isosurface(field, 18.0, 2)[0])
    n3 = len(isosurface(field, 18.0, 3)[0])
    assert 3.0 < n1 / n2 < 5.0 and 7.0 < n1 / n3 < 11.0  # about step ** 2
    v, f = isosurface(field, 1000.0)  # level not crossed
    assert v.shape == (0, 3) and f.shape == (0, 3)
    # level exactly on grid values (coincident crossing points): still no degenerate triangle
    g = np.rint(field).astype(np.float32)
    v, f = isosurface(g, 18.0)
    cr = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert len(f) > 0 and np.all(np.linalg.norm(cr, axis=1) > 0)
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    with pytest.raises(ValueError):
        isosurface(field, 18.0, 0)


@pytest.mark.parametrize("mask_given", [False, True])
def test_the_inner_surface_blurs_only_the_voxels_its_step_reads_with_the_same_values(mask_given):
    from scipy import ndimage

    from StomachUnfoldLib.geometry import Volume
    from StomachUnfoldLib.isosurface import isosurface
    from StomachUnfoldLib.preprocessing import lumen_edge
    from StomachUnfoldLib.surface import inner_surface, surface_field

    rng = np.random.default_rng(3)
    k, j, i = np.mgrid[:41, :37, :33]
    lumen = ((k - 20) / 15.0) ** 2 + ((j - 18) / 12.0) ** 2 + ((i - 16) / 10.0) ** 2 < 1.0
    hu = np.where(lumen, -1000.0, 40.0) + rng.normal(0.0, 30.0, lumen.shape)
    crop = Volume(ndimage.gaussian_filter(hu, 0.8).astype(np.int16), np.array([0.7, 0.8, 2.5]),
                  np.array([-5.0, 3.0, 7.0]), np.diag([-1.0, 1.0, 1.0]))
    whole, level = surface_field(crop, lumen, mask_given)
    pad = np.pad(whole, 2, constant_values=np.float32(1e4 if not mask_given else 0.0))
    n_edge = int(np.count_nonzero(lumen_edge(lumen)))
    for step in (1, 2, 3, 4):
        start = (-2) % step
        part, _ = surface_field(crop, lumen, mask_given, step, start)
        np.testing.assert_array_equal(part, whole[start::step, start::step, start::step])  # to the bit
        # the mesh of a max_vertices that asks for this step: that of the whole padded field read every step-th voxel
        v, f, got = inner_surface(lumen, crop, max(1, int(n_edge / (step - 0.5) ** 2)), mask_given)
        assert got == step
        v0, f0 = isosurface(pad, level, step)
        np.testing.assert_array_equal(f, f0)
        np.testing.assert_array_equal(v, crop.index_to_lps(v0[:, ::-1] - 2.0))
        assert len(f) > 50


def test_the_gas_field_is_the_lumens_one_voxel_band_of_hu_blurred_even_where_the_lumen_meets_the_grid_edge():
    from scipy import ndimage

    from StomachUnfoldLib.geometry import Volume
    from StomachUnfoldLib.surface import SURFACE_SIGMA_VOX, surface_field

    rng = np.random.default_rng(11)
    k, j, i = np.mgrid[:23, :19, :17]
    # the lumen runs off three faces of the grid, with a few loose voxels beside it
    lumen = ((k - 2) / 12.0) ** 2 + ((j - 9) / 11.0) ** 2 + ((i - 16) / 8.0) ** 2 < 1.0
    lumen |= rng.uniform(size=lumen.shape) > 0.985
    hu = rng.integers(-1000, 300, lumen.shape).astype(np.int16)
    crop = Volume(hu, np.array([0.8, 0.8, 2.0]), np.zeros(3), np.eye(3))
    field, level = surface_field(crop, lumen, mask_given=False)
    band = ndimage.maximum_filter(lumen.view(np.uint8), size=3, mode="constant", cval=0) > 0
    want = ndimage.gaussian_filter(np.where(band, hu.astype(np.float32), np.float32(200.0)), SURFACE_SIGMA_VOX)
    assert level == -500.0 and field.dtype == np.float32
    np.testing.assert_array_equal(field, want)                      # to the bit
    assert band.sum() > lumen.sum() > 100
