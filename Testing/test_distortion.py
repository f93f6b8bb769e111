"""The distortion map: per-pixel area and length scale of the view from a method's Mesh, and its files."""
import os

import numpy as np
import SimpleITK as sitk

from StomachUnfoldLib.distortion import TRUST_LIMIT, distortion_map, triangle_stretch, write_distortion
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.methods import Mesh


def _sheet(n=20, h=2.0):
    """A flat n x n grid of vertices (mm, spacing h) and its triangles."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v = np.stack([i.ravel() * h, j.ravel() * h, np.zeros(n * n)], 1)
    ids = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    f = np.concatenate([np.stack([ids, ids + n, ids + n + 1], 1), np.stack([ids, ids + n + 1, ids + 1], 1)])
    return v, f


def _view(shape=(6, 60, 60), spacing=1.0):
    a = np.full(shape, -1024, np.int16)
    a[:3] = 40
    return Volume(a, np.full(3, spacing), np.zeros(3), np.eye(3))


def test_rigid_motion_is_distortion_free_and_a_stretch_is_measured():
    v, f = _sheet()
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    s1, s2, area, ok = triangle_stretch(v, v @ R.T + 5.0, f)
    assert ok.all() and np.allclose(s1, 1) and np.allclose(s2, 1) and np.allclose(area, 2.0)
    s1, s2, _, _ = triangle_stretch(v, v * [2.0, 1.0, 1.0], f)
    assert np.allclose(s1, 2) and np.allclose(s2, 1)


def test_map_on_the_view_pixels():
    v, f = _sheet()
    vol = _view()
    rest = v.copy()
    rest[:, 0] *= 0.5            # the view shows the mucosa twice as long along i: area scale 2, length 2
    dm = distortion_map(vol, Mesh(rest, v + [10.0, 10.0, 2.0], f, "triangle", f))
    assert dm.covered.sum() > 0.8 * 38 * 38
    assert np.allclose(dm.area_scale[dm.covered], 2.0) and np.allclose(dm.length_scale[dm.covered], 2.0)
    assert not dm.covered[:5, :5].any()   # outside the sheet
    s = dm.summary()
    assert s["trusted_fraction"] == 0.0 and s["trust_limit"] == TRUST_LIMIT
    true = distortion_map(vol, Mesh(v, v + [10.0, 10.0, 2.0], f, "triangle", f))
    assert true.summary()["trusted_fraction"] == 1.0


def test_files(tmp_path):
    v, f = _sheet()
    vol = _view()
    dm = distortion_map(vol, Mesh(v, v + [10.0, 10.0, 2.0], f, "triangle", f))
    nrrd, png = tmp_path / "distortion.nrrd", tmp_path / "distortion.png"
    write_distortion(vol, dm, str(nrrd), str(png))
    img = sitk.ReadImage(str(nrrd))
    assert img.GetNumberOfComponentsPerPixel() == 2 and img.GetSize() == (60, 60, 1)
    a = sitk.GetArrayFromImage(img)[0]
    assert np.allclose(a[20, 20], [1.0, 1.0]) and np.allclose(a[0, 0], 0.0)
    assert os.path.getsize(png) > 1000
