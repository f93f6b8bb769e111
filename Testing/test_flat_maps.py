"""The surface methods' map between the CT and the view: with rule 33 (``surface.RAY_INVERSE``, off on main) a point
goes to the pixel whose ray passes through it; without it, to its foot on the nearest triangle; with rule 41
(``surface.RAY_SIDE = "shown"``, the default) a point in the wall to the ray through it unless only its foot shows it."""
import numpy as np
import pytest

from StomachUnfoldLib import surface
from StomachUnfoldLib.surface import flat_maps, unit, view_raster


def _maps(v, f, vn, uv, s=0.5, k0=8.0, w=4.0):
    """The surface methods' two maps over a mesh (v LPS mm, normals vn toward the tissue) laid flat at uv (mm)."""
    uv = uv - uv.min(0) + s
    ni, nj = int(np.ceil(uv[:, 0].max() / s)) + 2, int(np.ceil(uv[:, 1].max() / s)) + 2
    tri, bary, _ = view_raster(uv, f, (nj, ni), s, None, open_mouths=True)
    fwd, inv = flat_maps(v, f, vn, uv, tri, bary, s, k0, w)
    return fwd, inv, uv


def _grid_faces(nu, nv):
    """Two triangles per cell of an nu x nv vertex grid (row-major)."""
    f = []
    for a in range(nu - 1):
        for b in range(nv - 1):
            i = a * nv + b
            f += [[i, i + nv, i + 1], [i + 1, i + nv, i + nv + 1]]
    return np.array(f)


def _bent_sheet():
    """A sheet bent round a cylinder of 20 mm (the tissue outside), normals tilted along the axis as smoothing
    leaves them: (v, f, vn, uv)."""
    th, z = np.meshgrid(np.linspace(0.0, 2.0, 25), np.linspace(0.0, 30.0, 31), indexing="ij")
    th, z = th.ravel(), z.ravel()
    v = np.stack([20.0 * np.cos(th), 20.0 * np.sin(th), z], 1)
    radial = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    vn = unit(radial + 0.4 * np.sin(z / 5.0)[:, None] * np.array([0.0, 0.0, 1.0]))
    return v, _grid_faces(25, 31), vn, np.stack([20.0 * th, z], 1)


@pytest.mark.parametrize("ray_inverse", [True, False])
def test_a_point_in_the_wall_goes_to_the_ray_through_it(monkeypatch, ray_inverse):
    monkeypatch.setattr(surface, "RAY_INVERSE", ray_inverse)
    monkeypatch.setattr(surface, "RAY_SIDE", None)             # off, so without rule 33 every point goes by its foot
    v, f, vn, uv = _bent_sheet()
    fwd, inv, uv = _maps(v, f, vn, uv)
    rng = np.random.default_rng(3)
    t = rng.choice(np.flatnonzero(uv[f].min((1, 2)) > 4.0), 400)        # away from the rim
    lam = rng.dirichlet(np.ones(3), len(t))
    depth = rng.uniform(-1.5, 4.0, len(t))                               # from the lumen side into the wall (mm)
    sp = np.einsum("nc,ncx->nx", lam, v[f[t]])
    p = sp + depth[:, None] * unit(np.einsum("nc,ncx->nx", lam, vn[f[t]]))
    there = fwd(p)
    assert np.all(np.isfinite(there))
    err_uv = np.linalg.norm(there[:, :2] - np.einsum("nc,ncx->nx", lam, uv[f[t]]), axis=1)
    back = np.linalg.norm(inv(there) - p, axis=1)
    if ray_inverse:                       # the view's own ray: exact both ways
        assert err_uv.max() < 1e-6 and np.abs((8.0 - there[:, 2] / 0.5) * 0.5 - depth).max() < 1e-6
        assert np.nanmax(back) < 0.26     # to_original reads the pixel's triangle: within half a pixel's offset
    else:                                 # the foot on the nearest triangle: off by the depth times the tilt
        assert err_uv.max() > 0.5


def _domed_plane(r_dome=4.0, n_theta=24, rho_max=16.0, n_rho=20):
    """A plane (tissue below, z < 0) with a hemisphere of r_dome mm standing on it into the lumen (a bead), in geodesic
    polar coordinates round its top, vertices about 1 mm apart as on a CT's wall; normals toward the tissue: -z on the plane, toward the sphere's centre on the
    dome. Returns (v, f, vn, uv), uv the geodesic polar map (the dome unrolled round its top at uv (0, 0))."""
    rho = np.linspace(0.0, rho_max, n_rho)[1:]
    th = np.linspace(0.0, 2 * np.pi, n_theta, endpoint=False)
    R, T = np.meshgrid(rho, th, indexing="ij")
    R, T = R.ravel(), T.ravel()
    q = r_dome * np.pi / 2
    phi = np.minimum(R, q) / r_dome
    rad = np.where(R <= q, r_dome * np.sin(phi), r_dome + (R - q))
    v = np.stack([rad * np.cos(T), rad * np.sin(T), np.where(R <= q, r_dome * np.cos(phi), 0.0)], 1)
    v = np.vstack([[0.0, 0.0, r_dome], v])
    vn = np.where((np.r_[0.0, R] <= q)[:, None], -v / r_dome, [0.0, 0.0, -1.0])
    uv = np.vstack([[0.0, 0.0], np.stack([R * np.cos(T), R * np.sin(T)], 1)])
    f = [[0, 1 + (b + 1) % n_theta, 1 + b] for b in range(n_theta)]
    for a in range(len(rho) - 1):
        for b in range(n_theta):
            i, j = 1 + a * n_theta + b, 1 + a * n_theta + (b + 1) % n_theta
            f += [[i, j, i + n_theta], [j, j + n_theta, i + n_theta]]
    return v, np.array(f), unit(vn), uv


def test_the_centre_under_a_dome_goes_to_the_middle_of_its_image(monkeypatch):
    monkeypatch.setattr(surface, "RAY_INVERSE", True)
    v, f, vn, uv0 = _domed_plane()
    fwd, inv, uv = _maps(v, f, vn, uv0)
    apex = uv[0]
    for centre in ([0.0, 0.0, 0.0], [0.3, -0.2, 0.2]):   # the bead's centre, and a little off it
        there = fwd(np.array([centre]))[0]
        assert np.all(np.isfinite(there))
        assert np.linalg.norm(there[:2] - apex) < 1.0, there[:2] - apex
    # a point under the plane, away from the dome, keeps its own ray
    p = np.array([[10.0, 3.0, -2.0]])
    there = fwd(p)[0]
    assert np.allclose(inv(there[None])[0], p[0], atol=0.3)


def _canal_crop(spacing):
    """A crop (HU) of soft tissue with an air canal 5 mm wide along i, centred on a slice, partial voxels over their
    extent across it (as a scanner averages over a slice), and its lumen mask (under -500 HU); voxels of ``spacing``."""
    from StomachUnfoldLib.geometry import Volume

    sp = np.asarray(spacing, float)
    n = (np.ceil(np.array([30.0, 30.0, 40.0]) / sp[::-1])).astype(int)           # k, j, i
    k, j, i = np.meshgrid(*(np.arange(m) for m in n), indexing="ij")
    zc = (n[0] // 2 + 0.5) * sp[2]
    z, y = (k + 0.5) * sp[2] - zc, (j + 0.5) * sp[1] - 15.0
    r = np.maximum(np.hypot(z, y), 1e-9)
    ext = np.abs(y) / r * sp[1] + np.abs(z) / r * sp[2]
    air = np.clip(0.5 + (2.5 - r) / ext, 0.0, 1.0)
    hu = (40.0 - 1040.0 * air).astype(np.float32)
    return Volume(hu, sp, np.zeros(3), np.eye(3)), hu < -500.0


@pytest.mark.parametrize("in_mm", [False, True])
def test_the_inner_walls_blur_in_mm_keeps_a_narrow_canal_on_thick_slices(monkeypatch, in_mm):
    monkeypatch.setattr(surface, "SURFACE_BLUR_IN_MM", in_mm)
    crop, lumen = _canal_crop((1.0, 1.0, 4.0))
    assert lumen.any()
    field, level = surface.surface_field(crop, lumen, False)
    kept = bool(np.any(field[lumen] < level))
    assert kept == in_mm                       # one voxel's blur along 4 mm slices closes the canal; 1 mm does not


def test_the_inner_walls_blur_in_mm_is_the_same_on_isotropic_voxels(monkeypatch):
    crop, lumen = _canal_crop((1.5, 1.5, 1.5))
    got = []
    for in_mm in (False, True):
        monkeypatch.setattr(surface, "SURFACE_BLUR_IN_MM", in_mm)
        got.append([surface.surface_field(crop, lumen, False, step, start)[0] for step, start in ((1, 0), (2, 1))])
    assert all(np.array_equal(a, b) for a, b in zip(*got))


def test_tissue_side_points_go_along_the_rays_and_lumen_side_ones_keep_their_foot(monkeypatch):
    """Rule 38 (``surface.RAY_SIDE = "tissue"``): a point in the wall goes to the ray through it, exactly; a point on
    the lumen side, where no ray is drawn, to the same place as with every point by its foot; a bead's centre under
    its dome to the middle of the dome's image."""
    v, f, vn, uv0 = _bent_sheet()
    fwd, inv, uv = _maps(v, f, vn, uv0)     # the map reads RAY_SIDE when it is called
    rng = np.random.default_rng(5)
    t = rng.choice(np.flatnonzero(uv[f].min((1, 2)) > 4.0), 400)
    lam = rng.dirichlet(np.ones(3), len(t))
    sp = np.einsum("nc,ncx->nx", lam, v[f[t]])
    n = unit(np.einsum("nc,ncx->nx", lam, vn[f[t]]))
    inside = sp + rng.uniform(0.5, 4.0, len(t))[:, None] * n
    lumen = sp - rng.uniform(0.5, 1.5, len(t))[:, None] * n
    monkeypatch.setattr(surface, "RAY_SIDE", None)
    foot_in, foot_lumen = fwd(inside), fwd(lumen)
    monkeypatch.setattr(surface, "RAY_SIDE", "tissue")
    there = fwd(inside)
    assert np.abs(there[:, :2] - np.einsum("nc,ncx->nx", lam, uv[f[t]])).max() < 1e-6
    assert np.abs(there[:, :2] - foot_in[:, :2]).max() > 0.5          # where the foot would have put them
    assert np.array_equal(fwd(lumen), foot_lumen)
    v, f, vn, uv0 = _domed_plane()
    fwd, _, uvd = _maps(v, f, vn, uv0)
    assert np.linalg.norm(fwd(np.array([[0.0, 0.0, 0.0]]))[0, :2] - uvd[0]) < 1.0


def test_a_wall_point_keeps_its_foot_only_where_the_view_shows_it_there_and_not_along_the_ray(monkeypatch):
    """Rule 41 (``surface.RAY_SIDE = "shown"``): of the two places, the ray through a wall point and its foot, the map
    takes the one where the view shows the point (the judge's test), and the ray where both or neither do; so no point
    the foot showed is lost, and without a view it is rule 38."""
    from StomachUnfoldLib.geometry import Volume
    from StomachUnfoldLib.quality import visible_points
    from StomachUnfoldLib.view import first_hit

    v, f, vn, uv0 = _bent_sheet()
    s, k0 = 0.5, 8.0
    uv = uv0 - uv0.min(0) + s
    ni, nj = int(np.ceil(uv[:, 0].max() / s)) + 2, int(np.ceil(uv[:, 1].max() / s)) + 2
    tri, bary, _ = view_raster(uv, f, (nj, ni), s, None, open_mouths=True)
    rng = np.random.default_rng(11)
    # the view's first tissue at depth 0 or 4 mm, in blocks of 2 x 2 mm
    top = k0 - rng.choice([0.0, 4.0], size=(nj // 4 + 1, ni // 4 + 1)).repeat(4, 0).repeat(4, 1)[:nj, :ni] / s
    arr = np.where(np.arange(16)[:, None, None] <= top[None], 40.0, -1024.0).astype(np.float32)
    view = Volume(arr, np.full(3, s), np.zeros(3), np.eye(3))
    k_hit = first_hit(view)[0]
    t = rng.choice(np.flatnonzero(uv[f].min((1, 2)) > 4.0), 3000)
    lam = rng.dirichlet(np.ones(3), len(t))
    sp = np.einsum("nc,ncx->nx", lam, v[f[t]])
    p = sp + rng.uniform(0.5, 4.0, len(t))[:, None] * unit(np.einsum("nc,ncx->nx", lam, vn[f[t]]))
    got = {}
    for mode in (None, "tissue", "shown"):
        monkeypatch.setattr(surface, "RAY_SIDE", mode)
        fwd, _ = flat_maps(v, f, vn, uv, tri, bary, s, k0, 4.0, view=view)
        m = fwd(p)
        got[mode] = (m, visible_points(view, m, k_hit))
    foot, ray, both = got[None], got["tissue"], got["shown"]
    kept = np.any(both[0] != ray[0], axis=1)
    assert kept.sum() > 20                                              # the rule acted
    assert np.array_equal(both[0][kept], foot[0][kept])                 # ... by keeping the foot
    assert np.all(foot[1][kept] & ~ray[1][kept])                        # ... only where the foot alone shows it
    assert np.all(both[1] >= foot[1]) and np.all(both[1] >= ray[1])     # no point lost against either
    assert np.any(both[1] & ~foot[1])                                   # and some shown only along the ray
    monkeypatch.setattr(surface, "RAY_SIDE", "shown")
    fwd, _ = flat_maps(v, f, vn, uv, tri, bary, s, k0, 4.0)             # no view: rule 38
    assert np.array_equal(fwd(p), ray[0])
