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
(posterior, +y) side on some seeds. Dense beads (400 HU) sit half-embedded on the mucosa everywhere except near
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

import json
import os
import time

import numpy as np
from scipy import sparse
from scipy.interpolate import CubicSpline  # noqa: F401  (kept for callers that build their own core curves)
from scipy.ndimage import gaussian_filter, map_coordinates, zoom
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.geometry import Volume, lps_to_ras

__all__ = ["SIZES", "SHAPES", "HU", "LABELS", "random_stomach", "write_random_stomach", "insert_into_ct",
           "draw_parameters", "StomachModel", "GridSDF", "implicit_surface_mesh", "ring_graph",
           "surface_geodesics", "lps_array", "make_contact_sheet"]

# (in-plane range, slice range) in mm per size: "tiny" and "small" are coarser than clinical for fast tests
SIZES = {"tiny": ((1.7, 2.1), (2.0, 2.5)), "small": ((1.0, 1.4), (1.0, 2.5)), "full": ((0.6, 0.9), (0.6, 2.5))}
SHAPES = ("j", "steer_horn", "cascade")
HU = {"air": -1000, "lung": -850, "fat": -90, "tissue": 30, "muscle": 45, "wall": 40, "liver": 60, "spleen": 50,
      "bone": 350, "colon_wall": 40, "marker": 400, "fluid": 10}
LABELS = {"background": 0, "lumen_air": 1, "lumen_fluid": 2, "wall": 3, "marker": 4, "lung": 5, "colon_gas": 6,
          "tube_wall": 7, "tube_lumen": 8, "liver": 9, "spleen": 10, "outside_air": 11, "colon_wall": 12}
GEODESIC_GRID_MM = 0.8
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
    """The analytic stomach of a parameter draw: lumen field ``f_r`` (mm, < 0 in the lumen), wall ``0 <= f_r``,
    ``f < w``; core curve, greater-curvature line, cardia and pylorus openings, tubes (LPS mm)."""

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
        dist, idx = self.tree.query(P, workers=-1)
        v = P - self.core[idx]
        ft = dist - self.radius[idx]
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
            ridge = (0.5 - 0.5 * np.cos(n * phi + 1.2 * np.sin(s / 11.0))) ** 3
            fr = f + float(self.d["rugae_height_mm"]) * ws * wphi * wdom * ridge
        return {"f_r": fr, "f": f, "idx": idx, "phi": phi, "fe": fe, "ft": ft}

    def _build_coarse(self, h=2.0):
        lo, hi = self.lo, self.hi
        axs = [np.arange(lo[a], hi[a] + h, h) for a in range(3)]
        Z, Y, X = np.meshgrid(axs[2], axs[1], axs[0], indexing="ij")
        P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
        F = self.fields(P)
        self._coarse = (np.array([axs[0][0], axs[1][0], axs[2][0]]), h,
                        F["f_r"].reshape(X.shape).astype(np.float32), F["f"].reshape(X.shape).astype(np.float32))

    def fast(self, P, band: float = 4.0):
        """(f_r, f) at LPS points (N,3): coarse-grid interpolation, exact where within ``band`` mm of a surface."""
        P = np.asarray(P, float)
        o, h, Cr, Cf = self._coarse
        q = (P - o) / h
        c = np.stack([q[:, 2], q[:, 1], q[:, 0]])
        fr = map_coordinates(Cr, c, order=1, mode="nearest").astype(np.float64)
        f = map_coordinates(Cf, c, order=1, mode="nearest").astype(np.float64)
        inside = np.all((P >= self.lo) & (P <= self.hi), axis=1)
        fr[~inside] = 1e3
        f[~inside] = 1e3
        near = inside & ((np.abs(fr) < band) | (np.abs(f - self.w) < band))
        if near.any():
            F = self.fields(P[near])
            fr[near] = F["f_r"]
            f[near] = F["f"]
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
            dist, idx = tree.query(P, distance_upper_bound=float(rw) + 1.0, workers=-1)
            hit = np.isfinite(dist)
            if not hit.any():
                continue
            idx = np.minimum(idx, len(s_arr) - 1)
            s = s_arr[idx]
            wall |= hit & (dist < rw) & (fr >= 0) & (s > -1.0)
            if ro > 0 and not hybrid:
                r_open = ro * np.clip((lo_len - s) / 5.0, 0, 1)
                lum |= hit & (dist < r_open) & (s > -3.0)
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
        gz, gy, gx = np.gradient(self.F, self.h)
        self.G = (gx.astype(np.float32), gy.astype(np.float32), gz.astype(np.float32))

    def _coords(self, P):
        q = (np.asarray(P, float) - self.origin) / self.h
        return np.stack([q[:, 2], q[:, 1], q[:, 0]])

    def value(self, P):
        """Trilinear value at LPS points (N,3) mm."""
        return map_coordinates(self.F, self._coords(P), order=1, mode="nearest")

    def project(self, P, steps: int = 2):
        """Move LPS points (N,3) onto the zero level along the field gradient (Newton steps); returns (N,3)."""
        P = np.array(P, float)
        for _ in range(steps):
            c = self._coords(P)
            f = map_coordinates(self.F, c, order=1, mode="nearest")
            g = np.stack([map_coordinates(G, c, order=1, mode="nearest") for G in self.G], 1)
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


def _shorten(paths, sdf: GridSDF, keep_out=None, levels=(4.0, 2.0, 1.0), iters=(60, 60, 80)):
    """Shorten polylines on the zero level of ``sdf`` with fixed ends (damped Jacobi + projection), coarse to fine.

    ``keep_out`` = (cKDTree of points, radius mm): points are pushed to at least that distance from them.
    Returns the lengths (mm).
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
                d, j = tree.query(Y)
                inside = d < rad
                if inside.any():
                    q = tree.data[j[inside]]
                    v = Y[inside] - q
                    nv = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
                    Y[inside] = sdf.project(q + v / nv * rad, steps=1)
            X[idx] = Y
        X[idx] = sdf.project(X[idx], steps=2)
        cur = [X[a:b + 1] for a, b in zip(starts, ends)]
    return np.array([np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)) for p in cur])


def surface_geodesics(V, T, sources, sdf: GridSDF | None = None, removed=None, keep_out=None, rings: int = 3,
                      endpoints=None, graph=None):
    """Geodesic distances (M,M mm) between mesh vertices ``sources`` along the surface (V LPS mm, T triangles).

    Dijkstra on ``rings``-ring chord edges, then (with ``sdf``) each path is shortened on the implicit surface.
    ``removed``: boolean per vertex the paths may not use (a cut band); ``keep_out`` = (cKDTree, radius) keeps the
    shortened paths out of that band; ``endpoints`` (M,3) replace the sources' vertex positions as path ends.
    NaN where two sources are not connected.
    """
    sources = np.asarray(sources, int)
    G = ring_graph(V, T, rings) if graph is None else graph
    if removed is not None and np.any(removed):
        keep = sparse.diags((~np.asarray(removed, bool)).astype(np.float32))
        G = (keep @ G @ keep).tocsr()
        G.eliminate_zeros()
    D, pred = dijkstra(G, directed=False, indices=sources, return_predecessors=True)
    M = len(sources)
    out = np.full((M, M), np.nan)
    np.fill_diagonal(out, 0.0)
    pairs, polys = [], []
    for a in range(M):
        for b in range(a + 1, M):
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
        L = _shorten(polys, sdf, keep_out=keep_out)
        for (a, b), l in zip(pairs, L):
            if np.isfinite(l) and l <= out[a, b] * 1.02 + 1.0:
                out[a, b] = out[b, a] = l
    return out
