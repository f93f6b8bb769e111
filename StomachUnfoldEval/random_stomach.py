"""A family of synthetic stomach CTs drawn at random from a seed, with markers and their true geodesic distances.

Patient frame LPS mm (x toward the patient's left, y posterior, z superior), HU. ``random_stomach(seed)`` draws
the anatomy from ``numpy.random.default_rng(seed)``: an analytic lumen made of a fundus dome (an ellipsoid)
smoothly united with a swept tube along a core curve (body, a sharp angular incisure, an antrum tapering to a
pre-pyloric canal of 4-6 mm lumen RADIUS), longitudinal rugae on the greater-curvature side of the body on some
seeds; the wall is the shell between the lumen surface and the offset surface ``f = w`` (2-7 mm). The oesophagus
joins the medial side of the dome (the cardia is an opening in the side of the stomach, below the dome top) and
the duodenum leaves the end of the pyloric canal going right and posterior, both collapsed tubes of wall tissue
(slightly open over their first centimetres on some seeds). Around it: body outline, subcutaneous fat, muscle,
intra-abdominal fat, spine, liver (right), spleen (left, posterior), both lung bases above the diaphragm (4-8 mm
of tissue from the stomach wall over the dome), a gas-filled transverse colon under the greater curvature (3-8 mm
from the wall at the closest). Retained water (~10 HU) fills the lumen below a flat level on the dependent
(posterior, +y) side on some seeds. Dense beads (800 HU, radius max(1.5 mm, the coarsest spacing)) sit half-embedded on the mucosa everywhere except near
the greater curvature (the default incision) and the openings. Then Gaussian scanner blur and noise, spacing
and direction matrix drawn per seed.

True distances between markers are geodesics along the mucosa (the lumen surface ``f_r = 0``): Dijkstra on a
marching-cubes mesh (vtkFlyingEdges3D) gives each path, which is then shortened on the implicit surface (coarse
to fine, projected onto the zero level of a 0.8 mm signed-distance grid). Accuracy: better than 0.2 % on a sphere
and a cylinder (``Testing/test_random_stomach.py``). ``geodesic_cut_mm`` avoids a band around the
greater-curvature line (paths go round the cardia or the pylorus end instead of crossing the incision).

``insert_into_ct`` pastes a drawn stomach into a real CT (below the left lung base), so real organs surround it.
"""
from __future__ import annotations

import os
import time

import numpy as np
from scipy import sparse
from scipy.ndimage import gaussian_filter, map_coordinates, zoom
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.geometry import Volume, lps_to_ras

__all__ = [
    "HU",
    "LABELS",
    "SHAPES",
    "SIZES",
    "GridSDF",
    "StomachModel",
    "draw_parameters",
    "implicit_surface_mesh",
    "insert_into_ct",
    "lps_array",
    "make_contact_sheet",
    "random_stomach",
    "ring_graph",
    "surface_geodesics",
    "surface_reference_geodesics",
    "write_random_stomach",
]

# (in-plane range, slice range) in mm per size: "tiny" and "small" are coarser than clinical for fast tests
SIZES = {"tiny": ((1.7, 2.1), (2.0, 2.5)), "small": ((1.0, 1.4), (1.0, 2.5)), "full": ((0.6, 0.9), (0.6, 2.5))}
SHAPES = ("j", "steer_horn", "cascade")
HU = {"air": -1000, "lung": -850, "fat": -90, "tissue": 30, "muscle": 45, "wall": 40, "liver": 60, "spleen": 50,
      "bone": 350, "colon_wall": 40, "marker": 2500, "fluid": 10}
LABELS = {"background": 0, "lumen_air": 1, "lumen_fluid": 2, "wall": 3, "marker": 4, "lung": 5, "colon_gas": 6,
          "tube_wall": 7, "tube_lumen": 8, "liver": 9, "spleen": 10, "outside_air": 11, "colon_wall": 12}
GEODESIC_GRID_MM = 1.0
CUT_BAND_MM = 3.0
MARKER_MIN_GC_MM = 12.0


def _smin(a, b, k):
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _rot(ax, ay, az):
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _ellipsoid_sdf(P, c, axes, R=None):
    """Approximate signed distance (mm, negative inside) to an ellipsoid (centre c, semi-axes, rotation R)."""
    q = np.asarray(P, float) - c
    if R is not None:
        q = q @ R
    a = np.asarray(axes, float)
    k0 = np.linalg.norm(q / a, axis=-1)
    k1 = np.maximum(np.linalg.norm(q / (a * a), axis=-1), 1e-9)
    return k0 * (k0 - 1.0) / k1


def _fillet_polyline(W, radii, step=0.5):
    """Dense polyline through waypoints W with circular fillets of the given radii at interior vertices."""
    W = np.asarray(W, float)
    pieces = [W[:1]]
    prev_end = W[0]
    for i in range(1, len(W) - 1):
        a = _unit(W[i] - W[i - 1])
        b = _unit(W[i + 1] - W[i])
        th = float(np.arccos(np.clip(a @ b, -1, 1)))
        if th < 1e-3:
            continue
        rho = float(radii[i - 1])
        t = rho * np.tan(th / 2)
        lim = 0.45 * min(np.linalg.norm(W[i] - W[i - 1]), np.linalg.norm(W[i + 1] - W[i]))
        if t > lim:
            t = lim
            rho = t / np.tan(th / 2)
        p0 = W[i] - t * a
        n = _unit(b - (b @ a) * a)
        C = p0 + rho * n
        ph = np.linspace(0, th, max(3, int(np.ceil(rho * th / step)) + 1))
        arc = C + rho * (-np.outer(np.cos(ph), n) + np.outer(np.sin(ph), a))
        pieces.append(np.array([prev_end, p0]))
        pieces.append(arc)
        prev_end = arc[-1]
    pieces.append(np.array([prev_end, W[-1]]))
    pts = np.concatenate(pieces)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    pts = pts[keep]
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, s[-1] + 1e-9, step)
    return np.stack([np.interp(t, s, pts[:, k]) for k in range(3)], 1)


# ---------------------------------------------------------------------------------------------------------------
# drawing the parameters
# ---------------------------------------------------------------------------------------------------------------
def draw_parameters(seed, size: str = "small", **overrides) -> dict:
    """The drawn anatomy and scanner parameters (a JSON-ready dict, mm/degrees/HU) for ``seed``; overrides win."""
    if size not in SIZES:
        raise InputError(f"unknown random stomach size {size!r}; choose one of {', '.join(SIZES)}")
    rng = np.random.default_rng(int(seed))
    u = rng.uniform
    d = {}
    d["shape"] = str(rng.choice(SHAPES, p=[0.5, 0.25, 0.25]))
    d["scale"] = u(0.85, 1.1)
    d["wall_mm"] = u(2.0, 7.0)
    d["body_radius_mm"] = u(26.0, 36.0)
    d["antrum_radius_mm"] = u(4.0, 6.0)          # pre-pyloric canal lumen radius
    d["canal_length_mm"] = u(10.0, 16.0)
    d["dome_axes_mm"] = [u(32, 42), u(28, 36), u(30, 40)]
    d["dome_centre_lps"] = [65 + u(-8, 8), 15 + u(-8, 8), 25 + u(-8, 8)]
    d["rotation_deg"] = [u(-8, 8), u(-10, 10), u(-15, 15)]
    d["body_tilt_deg"] = u(5, 20)
    d["body_length_mm"] = u(45, 62)
    d["antrum_elevation_deg"] = u(10, 35)
    d["antrum_length_mm"] = u(45, 62)
    d["incisure_radius_mm"] = u(8, 16)
    d["smooth_union_mm"] = u(10, 16)
    d["rugae"] = bool(rng.random() < 0.5)
    d["rugae_height_mm"] = u(2.0, 4.0)
    d["rugae_count"] = int(rng.integers(16, 24))
    d["fluid"] = bool(rng.random() < 0.4)
    d["fluid_depth_fraction"] = u(0.15, 0.35)
    d["fluid_hu"] = u(5.0, 15.0)
    d["cardia_elevation_deg"] = u(-5, 20)
    d["cardia_posterior"] = u(0.05, 0.3)
    d["oesophagus_open_mm"] = float(u(1.0, 2.5) if rng.random() < 0.5 else 0.0)
    d["oesophagus_open_length_mm"] = u(12, 25)
    d["oesophagus_wall_radius_mm"] = u(6, 8)
    d["duodenum_open_mm"] = float(u(1.5, 3.0) if rng.random() < 0.5 else 0.0)
    d["duodenum_open_length_mm"] = u(10, 20)
    d["duodenum_wall_radius_mm"] = u(6, 9)
    d["colon_gap_mm"] = u(3.0, 8.0)
    d["colon_radius_mm"] = u(13, 20)
    d["lung_gap_mm"] = u(4.0, 8.0)
    d["body_semi_axes_mm"] = [u(150, 170), u(110, 130)]
    d["subcutaneous_fat_mm"] = u(12, 25)
    d["blur_vox"] = u(0.5, 1.0)
    d["noise_hu"] = u(10.0, 40.0)
    inpl, sl = SIZES[size]
    d["spacing_ijk_mm"] = [u(*inpl)] * 2 + [u(*sl)]
    # direction: identity on about half of the seeds, else a signed permutation (flips, i/j swap, rarely k not z)
    perm, signs = [0, 1, 2], [1, 1, 1]
    if rng.random() < 0.5:
        signs = [int(s) for s in rng.choice([-1, 1], 3)]
        r = rng.random()
        if r < 0.35:
            perm = [1, 0, 2]
        elif r < 0.5:
            perm = [0, 2, 1]          # slices along y (coronal acquisition)
    d["direction_perm"] = perm
    d["direction_signs"] = signs
    d["n_markers"] = int(rng.integers(16, 25))
    d["marker_seed"] = int(rng.integers(0, 2 ** 31 - 1))
    d["noise_seed"] = int(rng.integers(0, 2 ** 31 - 1))
    d["jitter"] = [float(v) for v in rng.uniform(-1, 1, 12)]
    if d["shape"] == "steer_horn":
        d["body_tilt_deg"] = u(40, 58)
        d["body_length_mm"] = u(60, 78)
        d["antrum_elevation_deg"] = u(0, 15)
        d["antrum_length_mm"] = u(30, 45)
        d["incisure_radius_mm"] = u(30, 50)
    for k, v in overrides.items():
        if k not in d:
            raise InputError(f"unknown random stomach parameter {k!r}; known: {', '.join(sorted(d))}")
        d[k] = v
    d["seed"] = int(seed)
    d["size"] = size
    for k, v in list(d.items()):
        if isinstance(v, (np.floating, np.integer)):
            d[k] = v.item()
    return d


# ---------------------------------------------------------------------------------------------------------------
# the analytic stomach
# ---------------------------------------------------------------------------------------------------------------
class StomachModel:
    """The analytic stomach of a parameter draw (LPS mm): lumen field ``f_r`` (< 0 inside), wall ``0 <= f_r, f < w``.

    Also the core curve, greater-curvature line, cardia and pylorus openings and the oesophagus/duodenum tubes.
    """

    def __init__(self, d: dict):
        self.d = d
        sc = float(d["scale"])
        j = np.asarray(d["jitter"], float)
        self.R = _rot(*np.radians(d["rotation_deg"]))
        self.c_f = np.asarray(d["dome_centre_lps"], float)
        self.axes = np.asarray(d["dome_axes_mm"], float) * sc
        self.w = float(d["wall_mm"])
        Rb = float(d["body_radius_mm"]) * sc
        rp = float(d["antrum_radius_mm"])
        tau = np.radians(d["body_tilt_deg"])
        gam = np.radians(d["antrum_elevation_deg"])
        shape = d["shape"]
        if shape == "cascade":
            W1 = np.array([-8 + 3 * j[0], -30 + 4 * j[1], -24 + 3 * j[2]]) * sc
            r1 = 18.0
        elif shape == "steer_horn":
            W1 = np.array([-4 + 3 * j[0], -6 + 3 * j[1], -20 + 3 * j[2]]) * sc
            r1 = 35.0
        else:
            W1 = np.array([2 + 3 * j[0], -6 + 3 * j[1], -26 + 4 * j[2]]) * sc
            r1 = 35.0
        db = _unit(np.array([-np.sin(tau), -0.3 + 0.1 * j[3], -np.cos(tau)]))
        W2 = W1 + float(d["body_length_mm"]) * sc * db
        da = _unit(np.array([-np.cos(gam), -0.15 + 0.1 * j[4], np.sin(gam)]))
        W3 = W2 + float(d["antrum_length_mm"]) * sc * da
        gp = gam + np.radians(20 + 8 * j[5])
        dp = _unit(np.array([-np.cos(gp), 0.25 + 0.1 * j[6], np.sin(gp)]))
        W4 = W3 + float(d["canal_length_mm"]) * 1.3 * dp
        Wm = np.array([np.zeros(3), W1, W2, W3, W4])
        core_m = _fillet_polyline(Wm, [r1, float(d["incisure_radius_mm"]) * sc, 22.0], step=0.5)
        self.core = self.c_f + core_m @ self.R.T
        seg = np.linalg.norm(np.diff(self.core, axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(seg)])
        L = self.arc[-1]
        self.length = L
        t = np.gradient(self.core, axis=0)
        self.tan = _unit(t)
        # arclength of the incisure (closest core point to W2) and radius profile
        W2l = self.c_f + self.R @ W2
        self.s_incisure = float(self.arc[np.argmin(np.linalg.norm(self.core - W2l, axis=1))])
        Lc = float(d["canal_length_mm"])
        s0 = self.s_incisure - 12.0 if shape != "steer_horn" else 0.35 * self.s_incisure
        s1 = L - Lc
        x = np.clip((self.arc - s0) / max(s1 - s0, 1.0), 0, 1)
        self.radius = rp + (Rb - rp) * 0.5 * (1 + np.cos(np.pi * x))
        self.tree = cKDTree(self.core)
        self.split = int(np.clip(np.searchsorted(self.arc, self.s_incisure), 2, len(self.core) - 3))
        self.tree_a = cKDTree(self.core[:self.split + 1])
        self.tree_b = cKDTree(self.core[self.split:])
        # greater-curvature directions: in the stomach's best plane, away from the concave side
        cen = self.core.mean(0)
        _, _, Vt = np.linalg.svd(self.core - cen)
        ns = Vt[2]
        g = _unit(np.cross(ns, self.tan))
        if np.mean(np.sum(g * (self.core - cen), 1)) < 0:
            g = -g
        self.gdir = g
        self.e2 = np.cross(self.tan, self.gdir)
        self.k_union = float(d["smooth_union_mm"])
        # bounding box (conservative) of lumen + wall
        ext = self.radius.max() + self.w + 6
        lo = np.minimum(self.core.min(0) - ext, self.c_f - self.axes.max() - self.w - 6)
        hi = np.maximum(self.core.max(0) + ext, self.c_f + self.axes.max() + self.w + 6)
        self.lo, self.hi = lo, hi
        self._coarse = None
        self._build_coarse()
        # cardia opening: on the medial side of the dome, below the dome top
        al = np.radians(d["cardia_elevation_deg"])
        e_c = self.R @ _unit(np.array([-np.cos(al), d["cardia_posterior"], np.sin(al)]))
        self.cardia_open = self._ray_hit(self.c_f[None], e_c[None])[0]
        self.n_cardia = _unit(self.gradient(self.cardia_open[None]))[0]      # outward normal
        u_e = _unit(self.R @ np.array([-0.55, 0.2, 1.0]) + 0.6 * self.n_cardia)
        self.oes_axis = u_e
        p0 = self.cardia_open - 4.0 * u_e
        p1 = self.cardia_open + 40.0 * u_e
        p2 = p1 + 30.0 * _unit(u_e + np.array([0, 0, 1.5]))
        p3 = p2 + np.array([0.0, 0.0, 250.0])
        self.oes = _fillet_polyline(np.array([p0, p1, p2, p3]), [25.0, 25.0], step=0.5)
        self.oes_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.oes, axis=0), axis=1))]) - 4.0
        # pylorus opening: the end of the canal; duodenum going right and posterior, then down
        self.pylorus_open = self.core[-1] + self.radius[-1] * self.tan[-1]
        t_end = self.tan[-1]
        d1 = _unit(t_end + np.array([-0.4, 1.0, 0.0]))
        q0 = self.pylorus_open - 3.0 * t_end
        q1 = self.pylorus_open + 25.0 * d1
        q2 = q1 + 25.0 * _unit(np.array([-0.3, 0.5, -1.0]))
        q3 = q2 + np.array([0.0, 0.0, -200.0])
        self.duo = _fillet_polyline(np.array([q0, q1, q2, q3]), [15.0, 20.0], step=0.5)
        self.duo_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.duo, axis=0), axis=1))]) - 3.0
        self.oes_tree = cKDTree(self.oes)
        self.duo_tree = cKDTree(self.duo)
        self.cardia_in = self.cardia_open - 5.0 * self.n_cardia
        self.pylorus_in = self.pylorus_open - min(3.0, self.radius[-1]) * t_end
        self._gc_line()

    # ---- fields
    def fields(self, P, rugae: bool = True):
        """Exact fields at LPS points (N,3): dict f_r (lumen, mm), f (smooth, no rugae), idx (core), phi (rad)."""
        P = np.asarray(P, float)
        # two pieces split at the incisure, each with its own closest point: across the incisure the closest
        # core point may jump between the wide body and the narrow antrum, and dist - r with a single closest
        # point would jump by their radius difference (a spurious surface); the union of the pieces does not
        da, ia = self.tree_a.query(P, workers=-1)
        db, ib = self.tree_b.query(P, workers=-1)
        ib = ib + self.split
        fa = da - self.radius[ia]
        fb = db - self.radius[ib]
        use_b = fb < fa
        idx = np.where(use_b, ib, ia)
        ft = np.where(use_b, fb, fa)
        v = P - self.core[idx]
        fe = _ellipsoid_sdf(P, self.c_f, self.axes, self.R)
        f = _smin(ft, fe, self.k_union)
        phi = np.arctan2(np.sum(v * self.e2[idx], 1), np.sum(v * self.gdir[idx], 1))
        fr = f
        if rugae and self.d["rugae"]:
            s = self.arc[idx]
            ws = np.clip((s - 25.0) / 15.0, 0, 1) * np.clip((self.s_incisure + 15.0 - s) / 15.0, 0, 1)
            wphi = np.clip((np.cos(phi) + 0.15) / 1.15, 0, 1) ** 0.7
            wdom = np.clip((fe - ft) / 8.0 + 0.5, 0, 1)
            n = float(self.d["rugae_count"])
            ridge = (0.5 - 0.5 * np.cos(n * phi + 1.2 * np.sin(s / 11.0))) ** 1.5
            fr = f + float(self.d["rugae_height_mm"]) * ws * wphi * wdom * ridge
        return {"f_r": fr, "f": f, "idx": idx, "phi": phi, "fe": fe, "ft": ft}

    def _build_coarse(self, h=2.0):
        """Exact fields f_r and f on a 2 mm grid over the bounding box (the base of ``fast`` and of the mesh)."""
        lo, hi = self.lo, self.hi
        n = np.ceil((hi - lo) / h).astype(int) + 1
        self.hi = lo + (n - 1) * h
        axs = [lo[a] + h * np.arange(n[a]) for a in range(3)]
        Cr = np.empty((n[2], n[1], n[0]), np.float32)
        Cf = np.empty_like(Cr)
        for k0 in range(0, n[2], 24):
            Z, Y, X = np.meshgrid(axs[2][k0:k0 + 24], axs[1], axs[0], indexing="ij")
            F = self.fields(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
            Cr[k0:k0 + 24] = F["f_r"].reshape(X.shape)
            Cf[k0:k0 + 24] = F["f"].reshape(X.shape)
        self._coarse = (lo.copy(), h, Cr, Cf)
        # interpolation error of the 2 mm grid: Lipschitz constant (about 1, more with rugae) x half a diagonal
        self.band = 2.0 * h + (float(self.d["rugae_height_mm"]) if self.d["rugae"] else 0.0)

    def index_box(self, vol: Volume, pad_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (i, j, k) voxel index bounds on ``vol``'s grid (hi exclusive, clipped to it) of the model's box
        (lumen and wall, LPS mm) grown by ``pad_mm`` mm."""
        lo, hi = self.lo - pad_mm, self.hi + pad_mm
        corners = np.array([[a, b, e] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for e in (lo[2], hi[2])])
        ijk = vol.lps_to_index(corners)
        return (np.maximum(np.floor(ijk.min(0)).astype(int), 0),
                np.minimum(np.ceil(ijk.max(0)).astype(int) + 1, np.array(vol.size)))

    def fast(self, P, band: float | None = None, outer: bool = True):
        """(f_r, f) at LPS points (N,3): coarse-grid interpolation, exact where within ``band`` mm of a surface."""
        P = np.asarray(P, float)
        band = self.band if band is None else band
        o, h, Cr, Cf = self._coarse
        fr = np.full(len(P), 1e3)
        f = np.full(len(P), 1e3)
        ins = np.nonzero(np.all((P >= self.lo) & (P <= self.hi), axis=1))[0]
        if len(ins) == 0:
            return fr, f
        Q = P[ins]
        q = (Q - o) / h
        c = np.stack([q[:, 2], q[:, 1], q[:, 0]])
        a = map_coordinates(Cr, c, order=1, mode="nearest").astype(np.float64)
        near = np.abs(a) < band
        if outer:
            b = map_coordinates(Cf, c, order=1, mode="nearest").astype(np.float64)
            near |= np.abs(b - self.w) < band
        else:
            b = a.copy()
        if near.any():
            F = self.fields(Q[near])
            a[near] = F["f_r"]
            b[near] = F["f"]
        fr[ins] = a
        f[ins] = b
        return fr, f

    def gradient(self, P, eps=0.25):
        """Numerical gradient of f_r at LPS points (N,3)."""
        P = np.asarray(P, float)
        g = np.zeros_like(P)
        for a in range(3):
            e = np.zeros(3)
            e[a] = eps
            g[:, a] = (self.fields(P + e)["f_r"] - self.fields(P - e)["f_r"]) / (2 * eps)
        return g

    def _ray_hit(self, C, D, lmax=150.0, step=0.5):
        """First exit of rays C + l D (LPS) from the lumen (f_r = 0), linear refinement; (N,3)."""
        ls = np.arange(0.0, lmax, step)
        n = len(C)
        P = (C[:, None, :] + ls[None, :, None] * D[:, None, :]).reshape(-1, 3)
        f = self.fields(P)["f_r"].reshape(n, len(ls))
        out = np.zeros((n, 3))
        for r in range(n):
            k = np.nonzero((f[r, :-1] < 0) & (f[r, 1:] >= 0))[0]
            k = int(k[0]) if len(k) else len(ls) - 2
            a, b = f[r, k], f[r, k + 1]
            t = ls[k] + step * (-a / (b - a) if b != a else 0.5)
            out[r] = C[r] + t * D[r]
        return out

    def _gc_line(self):
        """Greater-curvature line from the cardia over the dome and along the body and antrum to the pylorus."""
        g0 = self.gdir[0]
        u0 = -self.tan[0] - (-self.tan[0] @ g0) * g0
        u0 = _unit(u0)
        e = self.cardia_open - self.c_f
        th_c = float(np.arctan2(e @ u0, e @ g0))
        if th_c < 0:
            th_c += 2 * np.pi
        ths = np.linspace(th_c - np.radians(12), 0.0, 90)
        Dd = np.cos(ths)[:, None] * g0 + np.sin(ths)[:, None] * u0
        dome = self._ray_hit(np.repeat(self.c_f[None], len(ths), 0), Dd)
        ii = np.arange(0, len(self.core), 4)
        body = self._ray_hit(self.core[ii], self.gdir[ii])
        pts = np.concatenate([self.cardia_open[None], dome, body, self.pylorus_open[None]])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        pts = pts[np.concatenate([[True], seg > 1e-6])]
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        t = np.arange(0.0, s[-1], 0.5)
        self.gc = np.stack([np.interp(t, s, pts[:, k]) for k in range(3)], 1)
        self.gc_tree = cKDTree(self.gc)

    def tubes(self, P, fr, hybrid=False):
        """Oesophagus/duodenum at LPS points: (wall mask, open-lumen mask) with the stomach lumen ``fr`` kept."""
        wall = np.zeros(len(P), bool)
        lum = np.zeros(len(P), bool)
        for tree, s_arr, rw, ro, lo_len in ((self.oes_tree, self.oes_s, self.d["oesophagus_wall_radius_mm"],
                                             self.d["oesophagus_open_mm"], self.d["oesophagus_open_length_mm"]),
                                            (self.duo_tree, self.duo_s, self.d["duodenum_wall_radius_mm"],
                                             self.d["duodenum_open_mm"], self.d["duodenum_open_length_mm"])):
            sel = np.nonzero(np.all((P >= tree.mins - rw - 1) & (P <= tree.maxes + rw + 1), axis=1))[0]
            if len(sel) == 0:
                continue
            dist, idx = tree.query(P[sel], distance_upper_bound=float(rw) + 1.0, workers=-1)
            hit = np.isfinite(dist)
            if not hit.any():
                continue
            sel, dist, idx = sel[hit], dist[hit], np.minimum(idx[hit], len(s_arr) - 1)
            s = s_arr[idx]
            wall[sel] |= (dist < rw) & (fr[sel] >= 0) & (s > -1.0)
            if ro > 0 and not hybrid:
                r_open = ro * np.clip((lo_len - s) / 5.0, 0, 1)
                lum[sel] |= (dist < r_open) & (s > -3.0)
        return wall & ~lum, lum


# ---------------------------------------------------------------------------------------------------------------
# geodesics on an implicit surface: marching-cubes mesh, Dijkstra on ring edges, then path shortening on the
# implicit surface (coarse to fine), which removes the zig-zag overestimate of graph paths
# ---------------------------------------------------------------------------------------------------------------
class GridSDF:
    """A scalar field sampled on an axis-aligned LPS grid F[z, y, x] (origin mm, isotropic step h mm)."""

    def __init__(self, F, origin, h):
        self.F = np.ascontiguousarray(F, dtype=np.float32)
        self.origin = np.asarray(origin, float).reshape(3)
        self.h = float(h)

    def _coords(self, P):
        q = (np.asarray(P, float) - self.origin) / self.h
        return np.stack([q[:, 2], q[:, 1], q[:, 0]])

    def value(self, P):
        """Trilinear value at LPS points (N,3) mm."""
        return map_coordinates(self.F, self._coords(P), order=1, mode="nearest")

    def value_grad(self, P):
        """Trilinear value and its gradient (per mm) at LPS points (N,3); points are clamped into the grid."""
        nz, ny, nx = self.F.shape
        q = (np.asarray(P, float) - self.origin) / self.h
        hi = np.array([nx - 1.001, ny - 1.001, nz - 1.001])
        q = np.clip(q, 0.0, hi)
        i0 = q.astype(np.int64)
        t = q - i0
        base = (i0[:, 2] * ny + i0[:, 1]) * nx + i0[:, 0]
        Ff = self.F.ravel()
        c = [Ff[base + o] for o in (0, 1, nx, nx + 1, nx * ny, nx * ny + 1, nx * ny + nx, nx * ny + nx + 1)]
        tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
        c00 = c[0] + (c[1] - c[0]) * tx
        c10 = c[2] + (c[3] - c[2]) * tx
        c01 = c[4] + (c[5] - c[4]) * tx
        c11 = c[6] + (c[7] - c[6]) * tx
        c0 = c00 + (c10 - c00) * ty
        c1 = c01 + (c11 - c01) * ty
        f = c0 + (c1 - c0) * tz
        dx0 = (c[1] - c[0]) + ((c[3] - c[2]) - (c[1] - c[0])) * ty
        dx1 = (c[5] - c[4]) + ((c[7] - c[6]) - (c[5] - c[4])) * ty
        gx = dx0 + (dx1 - dx0) * tz
        gy = (c10 - c00) + ((c11 - c01) - (c10 - c00)) * tz
        gz = c1 - c0
        return f, np.stack([gx, gy, gz], 1) / self.h

    def project(self, P, steps: int = 2):
        """Move LPS points (N,3) onto the zero level along the field gradient (Newton steps); returns (N,3)."""
        P = np.array(P, float)
        for _ in range(steps):
            f, g = self.value_grad(P)
            g2 = np.maximum(np.sum(g * g, 1), 1e-6)
            step = np.clip(f / g2, -2.0 * self.h, 2.0 * self.h)
            P -= step[:, None] * g
        return P


def implicit_surface_mesh(F, origin, h):
    """Triangle mesh (V (n,3) LPS mm, T (m,3)) of the zero level of F[z,y,x] on a grid (origin mm, step h mm), vtk."""
    import vtkmodules.vtkCommonDataModel as dm
    import vtkmodules.vtkFiltersCore as fc
    from vtkmodules.util import numpy_support as ns

    nz, ny, nx = F.shape
    img = dm.vtkImageData()
    img.SetDimensions(nx, ny, nz)
    img.SetSpacing(h, h, h)
    img.SetOrigin(*[float(v) for v in origin])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(np.ascontiguousarray(F, np.float32).ravel(), deep=1))
    fe = fc.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.0)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    clean = fc.vtkCleanPolyData()
    clean.SetInputConnection(fe.GetOutputPort())
    clean.Update()
    pd = clean.GetOutput()
    if pd.GetNumberOfPoints() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), int)
    V = ns.vtk_to_numpy(pd.GetPoints().GetData()).astype(float)
    T = ns.vtk_to_numpy(pd.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    return V, T


def ring_graph(V, T, rings: int = 3):
    """Sparse symmetric graph joining mesh vertices within ``rings`` edge rings, weights = chord length (mm)."""
    n = len(V)
    e = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
    A = sparse.coo_matrix((np.ones(len(e), np.float32), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.float32)
    R, P = A.copy(), A.copy()
    for _ in range(rings - 1):
        P = ((P @ A) > 0).astype(np.float32)
        R = ((R + P) > 0).astype(np.float32)
    R = sparse.triu(R, 1).tocoo()
    w = np.linalg.norm(V[R.row] - V[R.col], axis=1)
    G = sparse.coo_matrix((w, (R.row, R.col)), shape=(n, n)).tocsr()
    return (G + G.T).tocsr()


def _path(pred_row, src, dst):
    out = [dst]
    v = dst
    while v != src:
        v = pred_row[v]
        if v < 0:
            return None
        out.append(v)
    return out[::-1]


def _resample(poly, step):
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(3, int(np.ceil(s[-1] / step)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, a]) for a in range(3)], 1)


def _shorten(paths, sdf: GridSDF, keep_out=None, levels=(4.0, 2.0, 1.25), iters=(40, 30, 25), return_paths=False):
    """Shorten polylines on the zero level of ``sdf`` with fixed ends (damped Jacobi + projection), coarse to fine.

    ``keep_out`` = (cKDTree of points, radius mm): points are pushed to at least that distance from them.
    Returns the lengths (mm) (and the shortened polylines with ``return_paths``).
    """
    cur = [np.asarray(p, float) for p in paths]
    for step, n_it in zip(levels, iters):
        cur = [_resample(p, step) for p in cur]
        sizes = np.array([len(p) for p in cur])
        X = np.concatenate(cur)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        ends = starts + sizes - 1
        interior = np.ones(len(X), bool)
        interior[starts] = False
        interior[ends] = False
        idx = np.nonzero(interior)[0]
        for _ in range(n_it):
            mid = 0.5 * (X[idx - 1] + X[idx + 1])
            Y = X[idx] + 0.5 * (mid - X[idx])
            Y = sdf.project(Y, steps=1)
            if keep_out is not None:
                tree, rad = keep_out
                d, j = tree.query(Y, distance_upper_bound=rad)
                inside = np.isfinite(d)
                if inside.any():
                    q = tree.data[j[inside]]
                    v = Y[inside] - q
                    nv = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
                    Y[inside] = sdf.project(q + v / nv * rad, steps=1)
            X[idx] = Y
        X[idx] = sdf.project(X[idx], steps=2)
        cur = [X[a:b + 1] for a, b in zip(starts, ends)]
    L = np.array([np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)) for p in cur])
    return (L, cur) if return_paths else L


def surface_geodesics(V, T, sources, sdf: GridSDF | None = None, removed=None, keep_out=None, rings: int = 3,
                      endpoints=None, graph=None, pairs_only=None, return_paths=False):
    """Geodesic distances (M,M mm) between mesh vertices ``sources`` along the surface (V LPS mm, T triangles).

    Dijkstra on ``rings``-ring chord edges, then (with ``sdf``) each path is shortened on the implicit surface.
    ``removed``: boolean per vertex the paths may not use (a cut band); ``keep_out`` = (cKDTree, radius) keeps the
    shortened paths out of that band; ``endpoints`` (M,3) replace the sources' vertex positions as path ends.
    NaN where two sources are not connected. ``pairs_only``: boolean (M,M), compute only those pairs (others NaN);
    ``return_paths``: also a dict (a, b) -> shortened polyline.
    """
    sources = np.asarray(sources, int)
    G = ring_graph(V, T, rings) if graph is None else graph
    if removed is not None and np.any(removed):
        keep = sparse.diags((~np.asarray(removed, bool)).astype(np.float32))
        G = (keep @ G @ keep).tocsr()
        G.eliminate_zeros()
    M = len(sources)
    out = np.full((M, M), np.nan)
    np.fill_diagonal(out, 0.0)
    if pairs_only is not None:
        pairs_only = np.triu(np.asarray(pairs_only, bool) | np.asarray(pairs_only, bool).T, 1)
    rows = np.arange(M) if pairs_only is None else np.nonzero(np.any(pairs_only, axis=1))[0]
    pairs, polys, paths = [], [], {}
    if len(rows) == 0:
        return (out, paths) if return_paths else out
    D, pred = dijkstra(G, directed=False, indices=sources[rows], return_predecessors=True)
    Dfull = np.full((M, D.shape[1]), np.inf)
    Pfull = np.full((M, D.shape[1]), -9999, dtype=pred.dtype)
    Dfull[rows], Pfull[rows] = D, pred
    D, pred = Dfull, Pfull
    for a in range(M):
        for b in range(a + 1, M):
            if pairs_only is not None and not (pairs_only[a, b] or pairs_only[b, a]):
                continue
            d = D[a, sources[b]]
            if not np.isfinite(d):
                continue
            out[a, b] = out[b, a] = d
            if sdf is not None:
                p = _path(pred[a], sources[a], sources[b])
                if p is not None:
                    poly = V[p].copy()
                    if endpoints is not None:
                        poly = np.concatenate([endpoints[a][None], poly, endpoints[b][None]])
                    pairs.append((a, b))
                    polys.append(poly)
    if sdf is not None and polys:
        L, cur = _shorten(polys, sdf, keep_out=keep_out, return_paths=True)
        for (a, b), l, p in zip(pairs, L, cur):
            on_surface = np.max(np.abs(sdf.value(p))) < 0.5 * sdf.h
            if np.isfinite(l) and l <= out[a, b] * 1.02 + 1.0 and on_surface:
                out[a, b] = out[b, a] = l
                paths[(a, b)] = p
    return (out, paths) if return_paths else out


# ---------------------------------------------------------------------------------------------------------------
# markers and their geodesics
# ---------------------------------------------------------------------------------------------------------------
def _regions(model: StomachModel, P, fluid_y):
    """Anatomic region names and the under-fluid flag of mucosa points P (LPS)."""
    F = model.fields(P)
    s = model.arc[F["idx"]]
    phi = np.abs(F["phi"])
    dome = (F["fe"] < F["ft"] + 2.0) & (P[:, 2] > model.cardia_open[2] + 5.0)
    antrum = ~dome & (s > model.s_incisure + 5.0)
    lesser = ~dome & ~antrum & (phi > np.radians(130)) & (s > 15.0)
    greater = ~dome & ~antrum & ~lesser & (phi < np.radians(60))
    names = np.where(dome, "dome", np.where(antrum, "antrum", np.where(lesser, "lesser",
                                                                         np.where(greater, "greater", "body"))))
    under = np.zeros(len(P), bool) if fluid_y is None else P[:, 1] > fluid_y
    return names, under


def _clear_of_openings(model: StomachModel, V):
    """Mucosa points V (LPS mm) far enough from the cardia and pylorus openings and their tubes to carry a marker."""
    ok = (np.linalg.norm(V - model.cardia_open, axis=1) >= 16.0) & (np.linalg.norm(V - model.pylorus_open, axis=1)
                                                                     >= 12.0)
    for tree, rw in ((model.oes_tree, model.d["oesophagus_wall_radius_mm"]),
                     (model.duo_tree, model.d["duodenum_wall_radius_mm"])):
        ok &= tree.query(V)[0] > rw + 3.0
    return ok


def _fluid_level(V, fraction):
    """The air-fluid level's LPS y (mm) for a fluid depth ``fraction`` of the mucosa mesh V's extent in y, or None."""
    ymin, ymax = V[:, 1].min(), V[:, 1].max()
    return None if fraction is None else float(ymax - fraction * (ymax - ymin))


def _pick_markers(model: StomachModel, V, n, rng, fluid_y, sep=12.0):
    ok = (model.gc_tree.query(V)[0] >= MARKER_MIN_GC_MM) & _clear_of_openings(model, V)
    if fluid_y is not None:
        ok &= np.abs(V[:, 1] - fluid_y) >= 4.0
    names, under = _regions(model, V, fluid_y)
    chosen = []

    def take(mask, k):
        """Add up to k spread-out candidates of ``mask`` (at least ``sep`` mm from those chosen)."""
        cand = np.nonzero(mask & ok)[0]
        for _ in range(k):
            if len(cand) == 0:
                return
            if chosen:
                dmin = np.min(np.linalg.norm(V[cand, None, :] - V[None, chosen, :], axis=2), axis=1)
                good = dmin >= sep
                if not good.any():
                    return
                c = cand[good][np.argmax(dmin[good])] if len(chosen) > 1 else cand[good][rng.integers(good.sum())]
            else:
                c = cand[rng.integers(len(cand))]
            chosen.append(int(c))
            cand = cand[cand != c]

    if fluid_y is not None:
        take(under, 3)
    for reg in ("dome", "lesser", "greater", "antrum", "body"):
        take((names == reg) & ~under, 3 if reg != "body" else 2)
    take(np.ones(len(V), bool), n - len(chosen))
    return np.array(chosen[:n], int)


def _fine_surface(model: StomachModel, h=GEODESIC_GRID_MM):
    """The lumen's fine signed-distance grid (GridSDF, step about ``h`` mm), the mucosa mesh the geodesics run on
    (V LPS mm, T) and the lumen volume (mL)."""
    o, hc, Cr, _ = model._coarse
    f = int(round(hc / h))
    h = hc / f
    F = zoom(Cr, [(f * (n - 1) + 1) / n for n in Cr.shape], order=1, grid_mode=False, mode="nearest")
    assert all(a == f * (n - 1) + 1 for a, n in zip(F.shape, Cr.shape))
    band = np.nonzero(np.abs(F.ravel()) < model.band)[0]
    kk, jj, ii = np.unravel_index(band, F.shape)
    P = o + h * np.stack([ii, jj, kk], 1)
    F.ravel()[band] = model.fields(P)["f_r"]
    lumen_ml = float(np.sum(F < 0) * h ** 3 / 1000.0)
    Vc, Tc = implicit_surface_mesh(Cr, o, hc)
    return GridSDF(F, o, h), Vc, Tc, lumen_ml


def _cut_geodesics(model: StomachModel, Vc, Tc, sdf: GridSDF, sel):
    """Geodesics (mm) among mesh vertices ``sel`` over the mucosa (geo) and round the cut along the greater curvature
    (geo_cut: a path that crosses the band is found again outside it), the points on the surface (LPS mm) and the
    paths."""
    ends = sdf.project(Vc[sel], steps=4)
    G = ring_graph(Vc, Tc, 2)
    geo, paths = surface_geodesics(Vc, Tc, sel, sdf, endpoints=ends, graph=G, return_paths=True)
    # pairs whose shortest path keeps clear of the band around the greater curvature: the cut changes nothing
    M = len(sel)
    redo = np.ones((M, M), bool)
    np.fill_diagonal(redo, False)
    for (a, b), p in paths.items():
        if np.min(model.gc_tree.query(p)[0]) > CUT_BAND_MM + 0.5:
            redo[a, b] = redo[b, a] = False
    redo = np.triu(redo, 1)
    removed = model.gc_tree.query(Vc)[0] < CUT_BAND_MM
    geo_cut = surface_geodesics(Vc, Tc, sel, sdf, removed=removed, keep_out=(model.gc_tree, CUT_BAND_MM),
                                endpoints=ends, graph=G, pairs_only=redo)
    geo_cut = np.where(redo | redo.T, geo_cut, geo)
    geo = np.fmin(geo, geo_cut)            # a path that avoids the cut is a path on the closed surface too
    return geo, geo_cut, ends, paths


def _model_geodesics(model: StomachModel, rng, n_markers, fluid_fraction=None, h=GEODESIC_GRID_MM):
    """Fine lumen SDF grid, mucosa mesh, marker choice and both geodesic matrices; returns a dict."""
    sdf, Vc, Tc, lumen_ml = _fine_surface(model, h)
    fluid_y = _fluid_level(Vc, fluid_fraction)
    sel = _pick_markers(model, Vc, n_markers, rng, fluid_y)
    geo, geo_cut, ends, paths = _cut_geodesics(model, Vc, Tc, sdf, sel)
    off = [float(np.max(np.abs(model.fields(p)["f_r"]))) for p in paths.values()]
    area = float(np.sum(np.linalg.norm(np.cross(Vc[Tc[:, 1]] - Vc[Tc[:, 0]], Vc[Tc[:, 2]] - Vc[Tc[:, 0]]), axis=1))
                 / 2)
    return {"markers_lps": ends, "geodesic": geo, "geodesic_cut": geo_cut, "fluid_y": fluid_y,
            "mucosa_area_mm2": area, "lumen_volume_ml": lumen_ml, "n_mesh_vertices": len(Vc),
            "path_offset_mm": float(np.max(off)) if off else 0.0}


def surface_reference_geodesics(seed, size: str = "small", n_extra: int = 150, min_gc_mm: float = 6.0) -> dict:
    """True cut geodesics (mm) among a drawn stomach's markers and ``n_extra`` more points spread over its mucosa.

    The markers come first, in the truth's order and at its places, so the top-left block is the truth's
    ``geodesic_cut_mm``; the other points are farthest-point samples of the mucosa at least ``min_gc_mm`` from the
    greater curvature (the default incision) and as far from the openings as the markers are. For
    ``flat_bound.surface_layout_reference``: the best flat layout of the whole mucosa, scored on the markers.
    Returns ``geodesic_cut_mm`` (M, M), ``n_markers``, ``points_lps`` (M, 3 mm).
    """
    d = draw_parameters(seed, size)
    model = StomachModel(d)
    rng = np.random.default_rng(d["marker_seed"])
    sdf, Vc, Tc, _ = _fine_surface(model)
    fluid = d["fluid_depth_fraction"] if d["fluid"] else None
    sel = _pick_markers(model, Vc, d["n_markers"], rng, _fluid_level(Vc, fluid))
    cand = np.nonzero((model.gc_tree.query(Vc)[0] >= min_gc_mm) & _clear_of_openings(model, Vc))[0]
    near = np.min(np.linalg.norm(Vc[cand, None, :] - Vc[None, sel, :], axis=2), axis=1)
    extra = []
    for _ in range(min(int(n_extra), len(cand))):
        i = int(np.argmax(near))
        extra.append(int(cand[i]))
        np.minimum(near, np.linalg.norm(Vc[cand] - Vc[cand[i]], axis=1), out=near)
    _, geo_cut, ends, _ = _cut_geodesics(model, Vc, Tc, sdf, np.concatenate([sel, extra]).astype(int))
    return {"geodesic_cut_mm": geo_cut, "n_markers": int(len(sel)), "points_lps": ends}


def _marker_truth(model, pos, fluid_y, bead):
    names, under = _regions(model, pos, fluid_y)
    g = model.gradient(pos)
    d_gc = model.gc_tree.query(pos)[0]
    out = []
    for m in range(len(pos)):
        nrm = -_unit(g[m])
        out.append({"id": f"M{m + 1:02d}", "index": m, "lps": pos[m].tolist(), "ras": lps_to_ras(pos[m]).tolist(),
                    "normal_lps": nrm.tolist(), "region": "under_fluid" if under[m] else str(names[m]),
                    "anatomic_region": str(names[m]), "under_fluid": bool(under[m]),
                    "distance_to_greater_curvature_mm": float(d_gc[m]), "radius_mm": bead})
    return out


def _nan_list(A):
    return [[(float(v) if np.isfinite(v) else float("nan")) for v in row] for row in np.asarray(A)]


# ---------------------------------------------------------------------------------------------------------------
# surroundings
# ---------------------------------------------------------------------------------------------------------------
class _Surroundings:
    """Synthetic abdomen around a model: body, fat, muscle, spine, liver, spleen, lungs, transverse colon."""

    def __init__(self, model: StomachModel, d: dict):
        self.m, self.d = model, d
        c = model.c_f
        self.body_ax = np.asarray(d["body_semi_axes_mm"], float)
        self.fat = float(d["subcutaneous_fat_mm"])
        self.liver_c = np.array([c[0] - 140.0, c[1] - 15.0, c[2] - 15.0])
        self.liver_ax = np.array([95.0, 95.0, 85.0])
        self.spleen_c = c + np.array([30.0, 55.0, -25.0])
        self.spleen_ax = np.array([26.0, 38.0, 52.0])
        self.lung_floor = c[2] - 15.0
        # transverse colon under the greater curvature, 3-8 mm of tissue from the wall at the closest
        low = model.core[np.argmin(model.core[:, 2] - model.radius)]
        self.xb = float(low[0])
        self.rc = float(d["colon_radius_mm"])
        self.y0 = float(low[1] - 10.0)
        self.z0 = float(model.core[:, 2].min() - model.radius.max() - model.w - d["colon_gap_mm"] - self.rc - 2.5)
        xs = np.arange(-120.0, 130.0, 2.0)
        an = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        for _ in range(8):
            yc, zc = self.colon_axis(xs)
            R = self.rc + 2.5
            P = np.stack([np.repeat(xs, len(an)), (yc[:, None] + R * np.cos(an)).ravel(),
                          (zc[:, None] + R * np.sin(an)).ravel()], 1)
            gap = float(np.min(model.fields(P, rugae=False)["f"]) - model.w)
            if abs(gap - d["colon_gap_mm"]) < 0.2:
                break
            self.z0 += gap - d["colon_gap_mm"]
        self.colon_gap = gap

    @staticmethod
    def _sdf_box(P, c, ax, margin):
        """Ellipsoid SDF evaluated only inside its bounding box (+margin mm); 1e3 elsewhere."""
        out = np.full(len(P), 1e3)
        m = np.asarray(ax) + margin
        sel = np.nonzero((np.abs(P[:, 0] - c[0]) <= m[0]) & (np.abs(P[:, 1] - c[1]) <= m[1])
                         & (np.abs(P[:, 2] - c[2]) <= m[2]))[0]
        if len(sel):
            out[sel] = _ellipsoid_sdf(P[sel], c, ax)
        return out

    def colon_axis(self, x):
        """(y, z) LPS of the colon axis at x (mm)."""
        return (self.y0 + 8.0 * np.sin(x / 45.0), self.z0 + 12.0 * ((x - self.xb) / 110.0) ** 2)

    def base(self, x, y):
        """z-independent part at points (x, y): HU, labels and the inside-the-muscle mask (body, fat, spine)."""
        a, b = self.body_ax
        r = (x / a) ** 2 + (y / b) ** 2
        inner1 = (x / (a - self.fat)) ** 2 + (y / (b - self.fat)) ** 2
        inner2 = (x / (a - self.fat - 10)) ** 2 + (y / (b - self.fat - 10)) ** 2
        val = np.full(len(x), HU["fat"], np.float32)
        lab = np.full(len(x), LABELS["background"], np.uint8)
        val[inner2 > 1] = HU["muscle"]
        val[inner1 > 1] = HU["fat"]
        val[r > 1] = HU["air"]
        lab[r > 1] = LABELS["outside_air"]
        inside = inner2 <= 1
        spine = (x ** 2 + (y - (b - self.fat - 55)) ** 2) < 20 ** 2
        val[spine & inside] = HU["bone"]
        return val, lab, inside

    def paint(self, P, fr, f, val, lab, base=None):
        """Fill HU ``val`` and labels ``lab`` (N,) of LPS points P for everything but the stomach itself.

        ``base``: ``self.base`` of one z-plane when P is a stack of whole planes (z slowest)."""
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        if base is None:
            base = self.base(x, y)
        v2, l2, in2 = base
        reps = len(P) // len(v2)
        val[:] = np.tile(v2, reps)
        lab[:] = np.tile(l2, reps)
        inside = np.tile(in2, reps)
        w = self.m.w
        free = inside & (f > w + 1.5)
        l_sdf = self._sdf_box(P, self.liver_c, self.liver_ax, 10.0)
        liver = free & (l_sdf < 0)
        val[liver] = HU["liver"]
        lab[liver] = LABELS["liver"]
        s_sdf = self._sdf_box(P, self.spleen_c, self.spleen_ax, 10.0)
        spleen = free & (s_sdf < 0) & ~liver
        val[spleen] = HU["spleen"]
        lab[spleen] = LABELS["spleen"]
        # lungs: above the diaphragm, which follows the fundus dome (lung_gap mm of tissue) and the liver dome
        gap = float(self.d["lung_gap_mm"])
        # the left lung base caps the upper dome; it comes lower behind the dome than in front of it
        cf, ax_ = self.m.c_f, self.m.axes
        floor = cf[2] + ax_[2] * (0.35 + 0.45 * np.clip((cf[1] - y) / ax_[1], 0, 1))
        left = inside & (((x - 85) / 70) ** 2 + ((y - 10) / 95) ** 2 < 1) & (z > floor)
        right = inside & (((x + 85) / 70) ** 2 + ((y - 10) / 95) ** 2 < 1) & (z > self.liver_c[2] + 20)
        chest = left | right
        val[chest & (lab == LABELS["background"])] = HU["muscle"]
        lung = chest & (f > w + gap) & (s_sdf > gap) & (l_sdf > gap)
        t = self.m.oes_tree
        li = np.nonzero(lung & np.all((P >= t.mins - 16) & (P <= t.maxes + 16), axis=1))[0]
        if len(li):
            d_oes = t.query(P[li], distance_upper_bound=16.0)[0]
            lung[li[np.isfinite(d_oes)]] = False
        val[lung] = HU["lung"]
        lab[lung] = LABELS["lung"]
        # transverse colon
        yc, zc = self.colon_axis(x)
        dc = np.sqrt((y - yc) ** 2 + (z - zc) ** 2)
        span = inside & (x > -125) & (x < 135)
        cw = span & (dc < self.rc + 2.5) & (f > w + 1.0)
        val[cw] = HU["colon_wall"]
        lab[cw] = LABELS["colon_wall"]
        cg = span & (dc < self.rc)
        val[cg] = HU["air"]
        lab[cg] = LABELS["colon_gas"]


def _paint_stomach(model: StomachModel, P, fr, f, fluid_y, fluid_hu, val, lab, hybrid=False):
    """Stomach lumen (air / fluid below the level), wall and the oesophagus/duodenum tubes at LPS points P."""
    wall = (fr >= 0) & (f < model.w)
    lum = fr < 0
    tw, tl = model.tubes(P, fr, hybrid=hybrid)
    val[wall] = HU["wall"]
    lab[wall] = LABELS["wall"]
    val[tw] = HU["wall"]
    lab[tw] = LABELS["tube_wall"]
    val[tl] = HU["air"]
    lab[tl] = LABELS["tube_lumen"]
    val[lum] = HU["air"]
    lab[lum] = LABELS["lumen_air"]
    if fluid_y is not None:
        fl = lum & (P[:, 1] > fluid_y)
        val[fl] = fluid_hu
        lab[fl] = LABELS["lumen_fluid"]


def _paint_markers(vals, labs, origin, sp, markers_lps, bead, value=HU["marker"]):
    """Partial-volume beads on a canonical LPS grid vals[z,y,x] (origin, spacing sp x/y/z mm)."""
    delta = float(np.mean(sp))
    for c in markers_lps:
        lo = np.floor((c - bead - 2 * delta - origin) / sp).astype(int)
        hi = np.ceil((c + bead + 2 * delta - origin) / sp).astype(int) + 1
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, np.array(vals.shape[::-1]))
        if np.any(hi <= lo):
            continue
        xs = origin[0] + sp[0] * np.arange(lo[0], hi[0])
        ys = origin[1] + sp[1] * np.arange(lo[1], hi[1])
        zs = origin[2] + sp[2] * np.arange(lo[2], hi[2])
        Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
        r = np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2)
        cov = np.clip(0.5 - (r - bead) / delta, 0.0, 1.0)
        sub = vals[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        sub[:] = sub * (1 - cov) + value * cov
        if labs is not None:
            labs[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]][cov >= 0.5] = LABELS["marker"]


def _reorient(C, lo, sp_lps, perm, signs):
    """Canonical C[z,y,x] (LPS-ordered, origin lo, spacing per LPS axis) -> (array[k,j,i], origin, direction)."""
    T = C.transpose(2, 1, 0).transpose(perm)
    for a in range(3):
        if signs[a] < 0:
            T = np.flip(T, axis=a)
    arr = np.ascontiguousarray(T.transpose(2, 1, 0))
    D = np.zeros((3, 3))
    origin = np.array(lo, float).copy()
    n = np.array(C.shape[::-1])
    for a in range(3):
        D[perm[a], a] = signs[a]
        if signs[a] < 0:
            origin[perm[a]] = lo[perm[a]] + (n[perm[a]] - 1) * sp_lps[perm[a]]
    return arr, origin, D


def lps_array(vol: Volume):
    """A signed-permutation Volume's array as [z, y, x] with x, y, z increasing (LPS); (array, origin mm, spacing mm)."""
    D = np.asarray(vol.direction)
    A = vol.array.transpose(2, 1, 0)              # [i, j, k]
    perm = [int(np.argmax(np.abs(D[:, a]))) for a in range(3)]
    if sorted(perm) != [0, 1, 2] or not np.allclose(np.abs(D).max(0), 1):
        raise InputError("lps_array needs a direction matrix that is a signed permutation")
    signs = [float(np.sign(D[perm[a], a])) for a in range(3)]
    for a in range(3):
        if signs[a] < 0:
            A = np.flip(A, axis=a)
    inv = np.argsort(perm)
    A = A.transpose(inv)                          # [x, y, z]
    sp = np.array([vol.spacing[inv[b]] for b in range(3)])
    n = np.array(A.shape)
    origin = np.array(vol.origin, float).copy()
    for a in range(3):
        if signs[a] < 0:
            origin[perm[a]] -= (n[perm[a]] - 1) * sp[perm[a]]
    return np.ascontiguousarray(A.transpose(2, 1, 0)), origin, sp


# ---------------------------------------------------------------------------------------------------------------
# the public generators
# ---------------------------------------------------------------------------------------------------------------
def random_stomach(seed, size: str = "small", labels: bool = False, **overrides):
    """Draw a stomach CT (int16 HU Volume, LPS) and its truth (LPS/RAS mm) from ``seed``; see the module docstring.

    ``labels=True`` also returns the uint8 label array (``LABELS``, same layout as the volume's array).
    Parameters of ``draw_parameters`` may be overridden by keyword.
    """
    t0 = time.perf_counter()
    d = draw_parameters(seed, size, **overrides)
    model = StomachModel(d)
    mrng = np.random.default_rng(d["marker_seed"])
    G = _model_geodesics(model, mrng, d["n_markers"], d["fluid_depth_fraction"] if d["fluid"] else None)
    t_geo = time.perf_counter()
    fluid_y = G["fluid_y"]
    sur = _Surroundings(model, d)
    # canonical LPS-ordered grid
    perm, signs = list(d["direction_perm"]), list(d["direction_signs"])
    sp_ijk = np.asarray(d["spacing_ijk_mm"], float)
    sp = np.zeros(3)
    for a in range(3):
        sp[perm[a]] = sp_ijk[a]
    colon_lo = np.array([model.lo[0], sur.y0 - sur.rc - 12, sur.z0 - sur.rc - 12])
    lo = np.minimum(model.lo - np.array([25.0, 25.0, 20.0]), colon_lo)
    hi = model.hi + np.array([25.0, 25.0, 40.0])
    if size == "full":
        half = 255.5 * sp[:2]
        lo[:2], hi[:2] = -half, half
    n = np.floor((hi - lo) / sp).astype(int) + 1
    vals = np.empty((n[2], n[1], n[0]), np.float32)
    labs = np.empty((n[2], n[1], n[0]), np.uint8)
    xs = lo[0] + sp[0] * np.arange(n[0])
    ys = lo[1] + sp[1] * np.arange(n[1])
    slab = max(1, int(1_500_000 // (n[0] * n[1])))
    Y2, X2 = np.meshgrid(ys, xs, indexing="ij")
    base2d = sur.base(X2.ravel(), Y2.ravel())
    for k0 in range(0, n[2], slab):
        k1 = min(n[2], k0 + slab)
        zs = lo[2] + sp[2] * np.arange(k0, k1)
        P = np.stack([np.broadcast_to(X2, (k1 - k0,) + X2.shape).ravel(),
                      np.broadcast_to(Y2, (k1 - k0,) + X2.shape).ravel(),
                      np.repeat(zs, X2.size)], 1)
        fr, f = model.fast(P)
        v = np.empty(len(P), np.float32)
        lb = np.empty(len(P), np.uint8)
        sur.paint(P, fr, f, v, lb, base=base2d)
        _paint_stomach(model, P, fr, f, fluid_y, d["fluid_hu"], v, lb)
        vals[k0:k1] = v.reshape(k1 - k0, n[1], n[0])
        labs[k0:k1] = lb.reshape(k1 - k0, n[1], n[0])
    bead = float(max(1.5, 1.0 * sp.max()))
    _paint_markers(vals, labs, lo, sp, G["markers_lps"], bead)
    vals = gaussian_filter(vals, float(d["blur_vox"]), mode="nearest")
    nrng = np.random.default_rng(d["noise_seed"])
    vals += nrng.standard_normal(vals.shape, dtype=np.float32) * np.float32(d["noise_hu"])
    np.clip(vals, -1024, 3071, out=vals)
    arr, origin, D = _reorient(vals.astype(np.int16), lo, sp, perm, signs)
    vol = Volume(arr, sp_ijk, origin, D)
    truth = _truth(model, d, G, sur, vol, bead, fluid_y)
    truth["seconds"] = {"geodesics": t_geo - t0, "total": time.perf_counter() - t0}
    if labels:
        return vol, truth, _reorient(labs, lo, sp, perm, signs)[0]
    return vol, truth


def _truth(model, d, G, sur, vol, bead, fluid_y):
    step = 4
    cl = np.concatenate([np.linspace(model.cardia_in, model.c_f, 20)[:-1], model.core[::step]])
    rad = np.concatenate([np.full(19, float(model.axes.min())), model.radius[::step]])
    return {"kind": "random_stomach", "seed": int(d["seed"]), "size": d["size"], "shape": d["shape"],
            "spacing": [float(v) for v in vol.spacing], "direction": np.asarray(vol.direction).tolist(),
            "origin": [float(v) for v in vol.origin], "size_ijk": [int(v) for v in vol.size],
            "cardia_lps": model.cardia_in.tolist(), "pylorus_lps": model.pylorus_in.tolist(),
            "cardia_ras": lps_to_ras(model.cardia_in).tolist(), "pylorus_ras": lps_to_ras(model.pylorus_in).tolist(),
            "cardia_opening_lps": model.cardia_open.tolist(), "pylorus_opening_lps": model.pylorus_open.tolist(),
            "oesophagus_axis_lps": model.oes_axis.tolist(),
            "centerline_lps": cl.tolist(), "radius_mm": rad.tolist(),
            "greater_curvature_lps": model.gc[::4].tolist(), "cut_band_mm": CUT_BAND_MM,
            "wall_thickness_mm": model.w, "rugae": bool(d["rugae"]),
            "antrum_min_radius_mm": float(model.radius.min()),
            "lumen_kind": "air_fluid" if fluid_y is not None else "air",
            "fluid_level_lps_y": fluid_y, "fluid_hu": float(d["fluid_hu"]) if fluid_y is not None else None,
            "dome_top_lps": _dome_top(model).tolist(),
            "colon_gap_mm": float(sur.colon_gap) if sur is not None else None,
            "lung_gap_mm": float(d["lung_gap_mm"]) if sur is not None else None,
            "lumen_volume_ml": G["lumen_volume_ml"], "mucosa_area_mm2": G["mucosa_area_mm2"],
            "markers": _marker_truth(model, G["markers_lps"], fluid_y, bead), "marker_radius_mm": bead,
            "geodesic_mm": _nan_list(G["geodesic"]), "geodesic_cut_mm": _nan_list(G["geodesic_cut"]),
            "geodesic_path_max_offset_mm": G["path_offset_mm"],
            "hu": dict(HU, fluid=float(d["fluid_hu"])), "labels": dict(LABELS), "draw": d}


def _dome_top(model):
    """Highest lumen point (LPS) of the dome region."""
    D = np.array([[0.0, 0.0, 1.0]])
    best = None
    for dx in np.linspace(-0.6, 0.6, 7):
        for dy in np.linspace(-0.6, 0.6, 7):
            p = model._ray_hit(model.c_f[None], _unit(np.array([[dx, dy, 1.0]])))[0]
            if best is None or p[2] > best[2]:
                best = p
    return best if best is not None else model._ray_hit(model.c_f[None], D)[0]


def write_random_stomach(path, seed, size: str = "small", **kw):
    """Write a drawn stomach volume, its truth JSON (stem + .json) and cardia/pylorus stem.mrk.json; (path, json)."""
    from .phantom import write_case

    vol, truth = random_stomach(seed, size, **kw)
    return write_case(path, vol, truth)


def make_contact_sheet(path, seeds=(0, 1, 2, 3, 4, 5), size: str = "tiny", hybrids=()):
    """Write a PNG contact sheet of drawn stomachs: coronal/axial slices and a coronal minimum projection (HU).

    ``hybrids``: (CT path, seed) pairs pasted with ``insert_into_ct`` get a row each.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [("drawn", s) for s in seeds] + [("hybrid", h) for h in hybrids]
    fig, axs = plt.subplots(len(rows), 4, figsize=(16, 3.6 * len(rows)))
    axs = np.atleast_2d(axs)
    for r, (kind_row, item) in enumerate(rows):
        if kind_row == "drawn":
            vol, truth = random_stomach(item, size)
            seed = item
        else:
            from StomachUnfoldLib.io import read_volume

            ct_path, seed = item
            vol, truth = insert_into_ct(read_volume(ct_path), seed)
        A, o, sp = lps_array(vol)                      # [z, y, x]
        cf = np.asarray(truth["draw"]["dome_centre_lps"])
        mk = np.array([m["lps"] for m in truth["markers"]])
        cl = np.array(truth["centerline_lps"])

        def idx(v, a, A=A, o=o, sp=sp):
            """Array index of LPS coordinate v (mm) along axis a, clipped."""
            return int(np.clip(round((v - o[a]) / sp[a]), 0, A.shape[2 - a] - 1))

        ext_cor = [o[0], o[0] + sp[0] * (A.shape[2] - 1), o[2], o[2] + sp[2] * (A.shape[0] - 1)]
        ext_ax = [o[0], o[0] + sp[0] * (A.shape[2] - 1), o[1] + sp[1] * (A.shape[1] - 1), o[1]]
        y1, y2, z1 = idx(cf[1], 1), idx(cl[-1, 1], 1), idx(cf[2], 2)
        panels = [(A[:, y1, :], ext_cor, "coronal y=%.0f (dome centre)" % (o[1] + y1 * sp[1]), "cor", o[1] + y1 * sp[1]),
                  (A[:, y2, :], ext_cor, "coronal y=%.0f (pylorus)" % (o[1] + y2 * sp[1]), "cor", o[1] + y2 * sp[1]),
                  (A[z1], ext_ax, "axial z=%.0f (dome centre)" % (o[2] + z1 * sp[2]), "ax", o[2] + z1 * sp[2]),
                  (A[:, max(0, y1 - int(90 / sp[1])):y1 + int(90 / sp[1])].min(axis=1), ext_cor,
                   "coronal MinIP (gas), markers, greater curvature", "minip", None)]
        for c, (img, ext, title, kind, level) in enumerate(panels):
            ax = axs[r, c]
            ax.imshow(img[::-1] if kind != "ax" else img, cmap="gray", vmin=-1000 if kind == "minip" else -250,
                      vmax=200 if kind == "minip" else 450, extent=ext, aspect="equal", interpolation="nearest")
            if kind == "cor":
                near = np.abs(mk[:, 1] - level) < 4.0
                ax.plot(mk[near, 0], mk[near, 2], "o", ms=5, mfc="none", mec="y", mew=0.8)
            elif kind == "ax":
                near = np.abs(mk[:, 2] - level) < 4.0
                ax.plot(mk[near, 0], mk[near, 1], "o", ms=5, mfc="none", mec="y", mew=0.8)
                if truth["fluid_level_lps_y"] is not None:
                    ax.axhline(truth["fluid_level_lps_y"], color="c", lw=0.5, ls=":")
            else:
                gc = np.array(truth["greater_curvature_lps"])
                ax.plot(mk[:, 0], mk[:, 2], "o", ms=3, mfc="none", mec="y", mew=0.7)
                ax.plot(gc[:, 0], gc[:, 2], "-", color="r", lw=0.7)
                ax.plot(*np.array(truth["cardia_lps"])[[0, 2]], "c^", ms=6)
                ax.plot(*np.array(truth["pylorus_lps"])[[0, 2]], "m^", ms=6)
            ax.set_title(title, fontsize=8)
            ax.tick_params(labelsize=6)
        d = truth["draw"]
        label = "seed %d: %s, wall %.1f mm, %s%s\nspacing %s mm" % (
            seed, truth["shape"], truth["wall_thickness_mm"], truth["lumen_kind"], ", rugae" if d["rugae"] else "",
            "x".join("%.2f" % v for v in truth["spacing"]))
        if kind_row == "hybrid":
            label = "HYBRID in %s\n" % os.path.basename(item[0])[:28] + label
        axs[r, 0].set_ylabel(label, fontsize=8)
    fig.suptitle("Random stomachs (LPS mm; image left = patient's right, axial top = anterior; yellow: markers within "
                 "4 mm of the slice / all in the MinIP; red: greater curvature; cyan/magenta: cardia/pylorus points; "
                 "dotted: fluid level)", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.25 / (3.6 * len(rows))))
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------------------------
# hybrids: a drawn stomach pasted into a real CT
# ---------------------------------------------------------------------------------------------------------------
def _default_centre(ct: Volume, axes_mm):
    """Dome centre (LPS mm) for a pasted stomach: under the left lung base, else the left upper abdomen."""
    from scipy import ndimage

    A, o, sp = lps_array(ct)                               # [z, y, x]
    f = np.maximum(1, np.round(4.0 / sp).astype(int))     # about 4 mm cells
    a = A[::f[2], ::f[1], ::f[0]].astype(np.float32)
    s = sp * f
    zz = o[2] + s[2] * np.arange(a.shape[0])
    yy = o[1] + s[1] * np.arange(a.shape[1])
    xx = o[0] + s[0] * np.arange(a.shape[2])
    body = a > -500
    lab, n = ndimage.label(body)
    if n:
        sizes = ndimage.sum(body, lab, index=np.arange(1, n + 1))
        body = lab == (1 + int(np.argmax(sizes)))
    body_filled = ndimage.binary_fill_holes(body, structure=np.ones((1, 3, 3)))
    if not body.any():
        c = 0.5 * (ct.bounds_lps()[0] + ct.bounds_lps()[1])
        return c
    _, ky, kx = np.nonzero(body)
    bx0, bx1 = xx[kx].min(), xx[kx].max()
    by = float(np.mean(yy[ky]))
    # lungs: large gas components inside the body's outline that reach the top of the volume
    gas = (a < -400) & body_filled
    lab, n = ndimage.label(gas)
    left_base = None
    if n:
        vox_ml = float(np.prod(s)) / 1000.0
        sizes = ndimage.sum(gas, lab, index=np.arange(1, n + 1)) * vox_ml
        mean_hu = ndimage.mean(a, lab, index=np.arange(1, n + 1))
        # lung: reaches the top, parenchyma HU (vessels in it) rather than the near -1000 of bowel gas
        for comp in np.nonzero((sizes > 30.0) & (mean_hu > -800))[0] + 1:
            cz, cy, cx = np.nonzero(lab == comp)
            if cz.max() < a.shape[0] - 2 or np.mean(xx[cx]) <= 0.5 * (bx0 + bx1):
                continue                                  # not a lung, or the right lung
            zlow = float(np.percentile(zz[cz], 3))
            low = zz[cz] < zlow + 25
            cand = (float(np.mean(xx[cx[low]])), float(np.mean(yy[cy[low]])), zlow)
            if left_base is None or cand[2] < left_base[2]:
                left_base = cand
    lo, hi = ct.bounds_lps()
    if left_base is not None:
        x, y, zb = left_base
        c = np.array([x, y, zb - 8.0 - axes_mm[2]])
    else:
        c = np.array([bx0 + 0.68 * (bx1 - bx0), by, hi[2] - axes_mm[2] - 15.0])
        if hi[2] - lo[2] < 150.0:
            c[2] = 0.5 * (lo[2] + hi[2]) + 20.0       # a thin slab: it crosses the upper body of the stomach
    c[2] = np.clip(c[2], lo[2], hi[2] + 0.5 * axes_mm[2])
    return c


#: The hybrids' drawing. 1: a voxel is partly lumen, wall or bead over the mean spacing (about 2 mm on CT 03) of
#: signed distance from the surface, whatever the surface's direction: on 4.25 mm slices a wall lying flat steps from
#: slice to slice. 2: over the voxel's own extent along the surface's normal (a slice's thickness where the wall lies
#: flat), as a scanner averages over a slice. Drawing 2 made the CT 03 hybrids harder for every method and the causes
#: are not yet separated (docs/benchmark/README.md, fourteenth session), so the bench keeps 1; the phantom cache keys
#: on any other (``-d2``).
HYBRID_DRAWING = 1


def voxel_extent_mm(normals: np.ndarray, vol: Volume) -> np.ndarray:
    """Length (mm) of one voxel of ``vol`` (a box of its spacing along its axes) along unit LPS directions (N,3)."""
    return np.abs(np.asarray(normals, float) @ vol.direction) @ np.asarray(vol.spacing, float)


def paint_beads(arr, vol: Volume, centres, bead, value=HU["marker"], drawing: int | None = None):
    """Partial-volume beads (LPS centres, radius mm) painted into arr (float, the layout of ``vol``). ``drawing``
    (default HYBRID_DRAWING): 2, each voxel covered in proportion to its depth in the bead over its own extent along
    the bead's radius (a slice's thickness through a bead's top and bottom, a pixel's width round its side); 1, over
    the mean spacing."""
    drawing = HYBRID_DRAWING if drawing is None else int(drawing)
    reach = float(np.sum(vol.spacing)) if drawing >= 2 else 2.0 * float(np.mean(vol.spacing))   # the partial shell
    for c in np.asarray(centres, float).reshape(-1, 3):
        ijk = vol.lps_to_index(c[None])[0]
        r_vox = np.ceil((bead + reach) / vol.spacing).astype(int) + 1
        lo = np.maximum(np.floor(ijk).astype(int) - r_vox, 0)
        hi = np.minimum(np.floor(ijk).astype(int) + r_vox + 1, np.array(vol.size))
        if np.any(hi <= lo):
            continue
        k, j, i = np.mgrid[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        P = vol.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1))
        d = P - c
        r = np.linalg.norm(d, axis=-1)
        ext = (voxel_extent_mm(d / np.maximum(r, 1e-9)[:, None], vol) if drawing >= 2
               else float(np.mean(vol.spacing)))
        cov = np.clip(0.5 - (r - bead) / ext, 0.0, 1.0).reshape(k.shape)
        sub = arr[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        sub[:] = sub * (1 - cov) + value * cov


def _surface_extents(model, P: np.ndarray, fr: np.ndarray, f: np.ndarray, vol: Volume, eps: float = 0.1):
    """Each point's voxel extent (mm) along the normals of the lumen's surface (field fr) and of the wall's outer
    surface (f): the width over which a voxel of ``vol`` there is partly one side and partly the other. Computed by
    forward differences (``eps`` mm) where a voxel can straddle a surface; elsewhere the mean spacing (no effect)."""
    ext_r = np.full(len(P), float(np.mean(vol.spacing)))
    ext_f = ext_r.copy()
    half = 0.5 * float(np.sum(vol.spacing))
    band = np.flatnonzero((np.abs(fr) < half) | (np.abs(f - model.w) < half))
    if len(band):
        Q = P[band]
        g_r, g_f = np.zeros((len(band), 3)), np.zeros((len(band), 3))
        for a in range(3):
            step = np.zeros(3)
            step[a] = eps
            r2, f2 = model.fast(Q + step)
            g_r[:, a], g_f[:, a] = (r2 - fr[band]) / eps, (f2 - f[band]) / eps
        for g, ext in ((g_r, ext_r), (g_f, ext_f)):
            n = g / np.maximum(np.linalg.norm(g, axis=1), 1e-9)[:, None]
            ext[band] = np.maximum(voxel_extent_mm(n, vol), 1e-3)
    return ext_r, ext_f


def _refuse_if_outside(ct: Volume, ends: dict) -> None:
    """Raise InputError if a drawn stomach's cardia or pylorus ({name: LPS mm}) falls outside the CT's grid."""
    out = [n for n, p in ends.items() if not ct.contains_lps(np.asarray(p, float)[None])[0]]
    if out:
        lo, hi = ct.bounds_lps()
        raise InputError(f"the drawn stomach does not fit in this CT: its {' and '.join(out)} "
                         f"(RAS {', '.join(f'{x:.1f}' for x in lps_to_ras(np.asarray(ends[out[0]], float)))} mm) lies "
                         f"outside the scan, which covers {hi[2] - lo[2]:.0f} mm head to foot; insert it into a CT of "
                         f"the whole upper abdomen")


def box_slabs(vol: Volume, lo, hi, slices: int = 8):
    """Walk an index box of ``vol`` (lo, hi: (i, j, k), hi exclusive) ``slices`` slices at a time: yields (k0, k1, P),
    P the LPS mm (N, 3) of the slab's voxel centres in (k, j, i) order, so a slab of ``vol.array[k0:k1]`` in the box,
    raveled, lines up with it."""
    for k0 in range(lo[2], hi[2], slices):
        k1 = min(hi[2], k0 + slices)
        k, j, i = np.mgrid[k0:k1, lo[1]:hi[1], lo[0]:hi[0]]
        yield k0, k1, vol.index_to_lps(np.stack([i.ravel(), j.ravel(), k.ravel()], 1).astype(float))


def insert_into_ct(ct: Volume, seed, centre_lps=None, halo_mm: float = 3.0, drawing: int | None = None, **overrides):
    """Paste a drawn stomach (lumen air/fluid, wall, markers; LPS mm, HU) into a real CT; returns (Volume, truth).

    The dome centre goes to ``centre_lps`` (default: under the left lung base, else the left upper abdomen); the
    model is sampled on the CT's own grid (any direction), with partial-volume edges and noise. ``drawing`` (default
    HYBRID_DRAWING): 1, a voxel is partly each side over the mean spacing of depth past a surface; 2, over its own
    extent along the surface's normal, so that on thick slices a flat wall is shared between slices as a scanner
    averages over a slice. Gas of the CT within ``halo_mm`` of the outer wall becomes soft tissue, so the lumen stays
    sealed. The input is not modified. Raises InputError when the cardia or pylorus falls outside the CT (a slab
    too thin to hold a stomach).
    """
    t0 = time.perf_counter()
    d0 = draw_parameters(seed, "small", **overrides)
    axes = np.asarray(d0["dome_axes_mm"]) * d0["scale"]
    c = np.asarray(centre_lps, float) if centre_lps is not None else _default_centre(ct, axes)
    d = draw_parameters(seed, "small", **dict(overrides, dome_centre_lps=[float(v) for v in c]))
    d["oesophagus_open_mm"] = 0.0
    d["duodenum_open_mm"] = 0.0
    model = StomachModel(d)
    _refuse_if_outside(ct, {"cardia": model.cardia_in, "pylorus": model.pylorus_in})
    mrng = np.random.default_rng(d["marker_seed"])
    G = _model_geodesics(model, mrng, d["n_markers"], d["fluid_depth_fraction"] if d["fluid"] else None)
    fluid_y = G["fluid_y"]
    arr = np.array(ct.array, dtype=np.float32, copy=True)
    i0, i1 = model.index_box(ct, halo_mm + 2)  # index box of the model (lumen + wall + halo) and of the tubes near it
    sp = ct.spacing
    drawing = HYBRID_DRAWING if drawing is None else int(drawing)
    level_ext = (float(voxel_extent_mm(np.array([[0.0, 1.0, 0.0]]), ct)[0]) if drawing >= 2  # across the fluid level
                 else float(np.mean(sp)))
    nrng = np.random.default_rng(d["noise_seed"])
    if np.all(i1 > i0):
        for k0, k1, P in box_slabs(ct, i0, i1):
            fr, f = model.fast(P)
            cur = arr[k0:k1, i0[1]:i1[1], i0[0]:i1[0]].reshape(-1)
            if drawing >= 2:                                           # a slice's thickness where a wall lies flat
                ext_r, ext_f = _surface_extents(model, P, fr, f, ct)
            else:
                ext_r = ext_f = float(np.mean(sp))
            alpha = np.clip(0.5 - fr / ext_r, 0, 1)                    # lumen fraction
            beta = np.clip(0.5 - (f - model.w) / ext_f, 0, 1)          # lumen + wall fraction
            lum_hu = np.full(len(P), float(HU["air"]))
            if fluid_y is not None:
                phi = np.clip(0.5 + (P[:, 1] - fluid_y) / level_ext, 0, 1)
                lum_hu = lum_hu * (1 - phi) + float(d["fluid_hu"]) * phi
            model_hu = alpha * lum_hu + (1 - alpha) * HU["wall"]
            halo = (f >= model.w) & (f < model.w + halo_mm) & (cur < -300)
            cur = np.where(halo, HU["tissue"], cur)
            tw, _ = model.tubes(P, fr, hybrid=True)
            cur = np.where(tw & (beta < 0.5), HU["wall"], cur)
            new = (1 - beta) * cur + beta * model_hu
            new += nrng.standard_normal(len(P)).astype(np.float32) * float(d["noise_hu"]) * np.maximum(beta, tw)
            arr[k0:k1, i0[1]:i1[1], i0[0]:i1[0]] = new.reshape(k1 - k0, i1[1] - i0[1], i1[0] - i0[0])
    bead = float(max(1.5, 1.0 * float(np.max(sp))))
    paint_beads(arr, ct, G["markers_lps"], bead, drawing=drawing)
    np.clip(arr, -1024, 3071, out=arr)
    dtype = ct.array.dtype if ct.array.dtype.kind in "iu" and np.iinfo(ct.array.dtype).bits >= 16 else np.int16
    vol = Volume(np.rint(arr).astype(dtype), ct.spacing.copy(), ct.origin.copy(), ct.direction.copy())
    truth = _truth(model, d, G, None, vol, bead, fluid_y)
    truth["kind"] = "hybrid"
    truth["size"] = "hybrid"
    truth["ct_spacing"] = [float(v) for v in ct.spacing]
    inside = vol.contains_lps(np.asarray(G["markers_lps"]))
    for m, ok in zip(truth["markers"], inside):
        m["in_volume"] = bool(ok)
    truth["dome_centre_lps"] = c.tolist()
    truth["seconds"] = {"total": time.perf_counter() - t0}
    return vol, truth
