"""Unfolded volume generation (Oda et al., Sec. 2.5) from the pre/post-deformation correspondence.

Every hexahedron of the wall model is split into six tetrahedra (the Kuhn/Freudenthal split along its
0-6 diagonal, conforming across neighbouring cells of the grid). A tetrahedron is an exact affine map
between its rest (original CT) and deformed (unfolded) positions. For each voxel of the output grid the
deformed tetrahedron holding it gives, through that map, the matching point of the original CT, which is
sampled trilinearly. Voxels in no tetrahedron get the background (-1024 HU). Where deformed tetrahedra
overlap (a fold), the one nearest the viewer (largest output k of its centroid; the viewer looks down -k)
wins and the conflict is counted.

All work is vectorised and chunked: the tetrahedra are rasterised over their bounding boxes by expanding
(tet, candidate voxel) pairs a few million at a time, so extra memory stays bounded whatever the model.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .errors import InputError, SimulationError
from .geometry import Volume

__all__ = ["KUHN_TETS", "hex_to_tets", "tet_volumes", "tet_inverse", "barycentric", "TetAffine", "tet_affine",
           "apply_affine", "UnfoldedGrid", "make_grid", "label_map", "build_unfolded_volume"]

#: The six tetrahedra of a hexahedron (VTK vertex order), one per monotone path from vertex 0 to vertex 6
#: (i-j-k, i-k-j, j-i-k, j-k-i, k-i-j, k-j-i). Every cell of a structured grid uses the same 0-6 diagonal,
#: so the split of neighbouring cells matches on their shared face (Freudenthal triangulation).
KUHN_TETS = np.array([[0, 1, 2, 6], [0, 1, 5, 6], [0, 3, 2, 6], [0, 3, 7, 6], [0, 4, 5, 6], [0, 4, 7, 6]])

#: Relative tolerance under which a tetrahedron counts as degenerate: |6 V| <= tol * (mean edge)^3.
DEGENERATE_RTOL = 1e-9

_INSIDE_TOL = 1e-9  # barycentric slack for "voxel centre inside a tet" (conforming faces claim both sides)
# Overlap is judged at the voxel centre nudged by this tiny generic offset (output voxels): a generic point
# lies strictly inside exactly one tetrahedron of each wall layer covering it, even where the centre itself
# sits on shared faces, so "strictly inside two or more" means two layers, not one conforming mesh.
_NUDGE = 1e-4 * np.array([0.5773502691896258, 0.3141592653589793, 0.7536621283024281])


# ----------------------------------------------------------------------------------------------- tetrahedra
def hex_to_tets(hexes: np.ndarray):
    """Split (M,8) hexahedra (VTK order) into (6M,4) conforming Kuhn tetrahedra; returns ``(tets, tet_to_hex)``.

    ``tet_to_hex`` is ``np.repeat(arange(M), 6)``: tetrahedra ``6h .. 6h+5`` come from hexahedron ``h``.
    """
    hexes = np.asarray(hexes)
    if hexes.ndim != 2 or hexes.shape[1] != 8:
        raise InputError(f"hexahedra must be an (M, 8) integer array of vertex ids, got shape {hexes.shape}")
    hexes = hexes.astype(np.int64, copy=False)
    tets = hexes[:, KUHN_TETS].reshape(-1, 4)
    return tets, np.repeat(np.arange(len(hexes)), 6)


def tet_edges(p: np.ndarray) -> np.ndarray:
    """Edge matrices (T,3,3) whose columns are p1-p0, p2-p0, p3-p0 for tetrahedron corners p (T,4,3)."""
    return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)


def degenerate_tets(E: np.ndarray, det: np.ndarray) -> np.ndarray:
    """True where the tetrahedron with edge matrix E (T,3,3) and determinant det is flat (relative test)."""
    mean_edge = np.sqrt((E ** 2).sum(axis=1)).mean(axis=1)
    return ~(np.abs(det) > DEGENERATE_RTOL * mean_edge ** 3) | ~np.isfinite(det)


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (T,) of tetrahedra (units of ``points`` cubed, e.g. mm^3); positive for right-handed corners."""
    return np.linalg.det(tet_edges(np.asarray(points, float)[tets])) / 6.0


def tet_inverse(points: np.ndarray, tets: np.ndarray):
    """Per tetrahedron: first corner (T,3), inverse edge matrix (T,3,3) and signed volume (T,).

    Degenerate (flat) tetrahedra get an all-zero inverse; test them with ``np.abs(volume)`` or
    :func:`tet_affine`'s ``degenerate`` flag.
    """
    p = np.asarray(points, float)[tets]  # (T,4,3)
    E = tet_edges(p)
    det = np.linalg.det(E)
    ok = ~degenerate_tets(E, det)
    inv = np.zeros_like(E)
    inv[ok] = np.linalg.inv(E[ok])
    return p[:, 0], inv, det / 6.0


def barycentric(q: np.ndarray, p0: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N,4) of points q (N,3) in tetrahedra given by p0 (N,3) and inverse edges (N,3,3)."""
    l123 = np.einsum("nij,nj->ni", inv, q - p0)
    return np.concatenate([1.0 - l123.sum(axis=1, keepdims=True), l123], axis=1)


def barycentric_planes(p: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """(T,4,4) matrices B with barycentric ``lam = B @ (x, y, z, 1)`` for corners p (T,4,3) and inverse edges."""
    B = np.zeros((len(p), 4, 4))
    B[:, 1:, :3] = inv
    B[:, 1:, 3] = -np.einsum("tij,tj->ti", inv, p[:, 0])
    B[:, 0, :3] = -inv.sum(axis=1)
    B[:, 0, 3] = 1.0 - B[:, 1:, 3].sum(axis=1)
    return B


@dataclass
class TetAffine:
    """Exact per-tetrahedron affine maps between the deformed and rest positions (LPS mm).

    ``to_rest[t]`` and ``to_deformed[t]`` are (3,4) matrices ``[A | b]`` with ``x_rest = A @ x_def + b`` and
    the reverse; rows of degenerate tetrahedra (flat in the source space of that map) are NaN and
    flagged in ``degenerate_deformed`` / ``degenerate_rest``. Volumes are signed (mm^3).
    """

    to_rest: np.ndarray
    to_deformed: np.ndarray
    rest_volume: np.ndarray
    deformed_volume: np.ndarray
    degenerate_rest: np.ndarray
    degenerate_deformed: np.ndarray

    @property
    def inverted(self) -> np.ndarray:
        """True per tetrahedron whose deformed signed volume has the opposite sign to its rest one."""
        ok = ~(self.degenerate_rest | self.degenerate_deformed)
        return ok & (np.sign(self.rest_volume) != np.sign(self.deformed_volume))


def _affine_between(src: np.ndarray, dst: np.ndarray):
    """(T,3,4) affine maps taking tetrahedra corners src (T,4,3) onto dst (T,4,3), NaN where src is flat."""
    Es, Ed = tet_edges(src), tet_edges(dst)
    det = np.linalg.det(Es)
    bad = degenerate_tets(Es, det)
    M = np.full((len(src), 3, 4), np.nan)
    if (~bad).any():
        A = Ed[~bad] @ np.linalg.inv(Es[~bad])
        M[~bad, :, :3] = A
        M[~bad, :, 3] = dst[~bad, 0] - np.einsum("tij,tj->ti", A, src[~bad, 0])
    return M, det / 6.0, bad


def tet_affine(rest_tets: np.ndarray, deformed_tets: np.ndarray) -> TetAffine:
    """Exact affine maps deformed -> rest and rest -> deformed (LPS mm) for tetrahedra corners (T,4,3) each.

    The maps send each corner exactly onto its partner (barycentric interpolation); flat tetrahedra
    (zero volume within a relative 1e-9) are flagged instead of raising.
    """
    rest_tets = np.asarray(rest_tets, float)
    deformed_tets = np.asarray(deformed_tets, float)
    if rest_tets.shape != deformed_tets.shape or rest_tets.shape[1:] != (4, 3):
        raise InputError(f"tetrahedra corners must be two (T, 4, 3) arrays of the same shape, got "
                         f"{rest_tets.shape} and {deformed_tets.shape}")
    to_rest, vol_d, bad_d = _affine_between(deformed_tets, rest_tets)
    to_def, vol_r, bad_r = _affine_between(rest_tets, deformed_tets)
    return TetAffine(to_rest, to_def, vol_r, vol_d, bad_r, bad_d)


def apply_affine(maps: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply per-point affine maps (N,3,4) to points (N,3) (mm); returns (N,3)."""
    maps = np.asarray(maps, float)
    return np.einsum("nij,nj->ni", maps[:, :, :3], np.asarray(points, float)) + maps[:, :, 3]


# ----------------------------------------------------------------------------------------------- output grid
@dataclass
class UnfoldedGrid:
    """Geometry of the unfolded volume: LPS origin (mm), axes (columns = LPS unit vectors of i, j, k), spacing, shape.

    The LPS position of continuous output index ``(i, j, k)`` is ``origin_lps + axes @ (spacing * (i, j, k))``;
    arrays on this grid have shape ``shape_kji``. The viewer looks down -k.
    """

    origin_lps: np.ndarray
    axes: np.ndarray
    spacing: np.ndarray
    shape_kji: tuple

    def __post_init__(self):
        self.origin_lps = np.asarray(self.origin_lps, float).reshape(3)
        self.axes = np.asarray(self.axes, float).reshape(3, 3)
        self.spacing = np.broadcast_to(np.asarray(self.spacing, float), (3,)).astype(float)
        self.shape_kji = tuple(int(n) for n in self.shape_kji)
        if len(self.shape_kji) != 3 or min(self.shape_kji) < 1:
            raise InputError(f"the unfolded grid needs three positive sizes, got {self.shape_kji}")
        if np.any(self.spacing <= 0) or not np.all(np.isfinite(self.spacing)):
            raise InputError(f"the unfolded grid spacing must be positive mm, got {self.spacing}")
        if not np.allclose(self.axes.T @ self.axes, np.eye(3), atol=1e-6):
            raise InputError("the unfolded grid axes must be orthonormal LPS unit vectors (columns); "
                             f"got {self.axes.tolist()}")

    @property
    def size(self) -> tuple[int, int, int]:
        """Number of voxels along i, j, k."""
        return self.shape_kji[2], self.shape_kji[1], self.shape_kji[0]

    @property
    def n_voxels(self) -> int:
        """Total number of voxels of the grid."""
        return int(np.prod(self.shape_kji, dtype=np.int64))

    @property
    def index_to_lps_matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix mapping continuous output (i, j, k) to LPS mm."""
        m = np.eye(4)
        m[:3, :3] = self.axes * self.spacing[None, :]
        m[:3, 3] = self.origin_lps
        return m

    def to_volume(self, array) -> Volume:
        """Wrap an array of shape ``shape_kji`` as a Volume with this geometry (direction = axes)."""
        array = np.asarray(array)
        if array.shape != self.shape_kji:
            raise InputError(f"array shape {array.shape} differs from the unfolded grid {self.shape_kji}")
        return Volume(array, self.spacing.copy(), self.origin_lps.copy(), self.axes.copy())

    @classmethod
    def from_volume(cls, volume: Volume) -> "UnfoldedGrid":
        """The grid of an existing (unfolded) Volume: same origin, direction, spacing and shape."""
        return cls(volume.origin, volume.direction, volume.spacing, volume.array.shape)

    def lps_to_index(self, lps) -> np.ndarray:
        """Continuous (i, j, k) output index of LPS points (mm), (N,3) or (3,)."""
        return ((np.asarray(lps, float) - self.origin_lps) @ self.axes) / self.spacing

    def index_to_lps(self, ijk) -> np.ndarray:
        """LPS points (mm) of continuous (i, j, k) output indices, (N,3) or (3,)."""
        return self.origin_lps + (np.asarray(ijk, float) * self.spacing) @ self.axes.T


def make_grid(deformed: np.ndarray, axes: np.ndarray, spacing, margin_mm: float = 2.0) -> UnfoldedGrid:
    """Smallest grid with the given axes (3x3 LPS unit columns) and spacing (mm) covering the points plus margin_mm."""
    deformed = np.asarray(deformed, float)
    if deformed.ndim != 2 or deformed.shape[1] != 3 or len(deformed) == 0:
        raise InputError(f"the deformed vertices must be a non-empty (N, 3) array, got shape {deformed.shape}")
    if not np.all(np.isfinite(deformed)):
        raise SimulationError("the deformed model has non-finite vertex positions (the simulation diverged); "
                              "rerun with a smaller time step or a coarser grid")
    if not np.isfinite(margin_mm) or margin_mm < 0:
        raise InputError(f"margin_mm must be a finite non-negative number of mm, got {margin_mm}")
    axes = np.asarray(axes, float)
    spacing = np.broadcast_to(np.asarray(spacing, float), (3,)).astype(float)
    if np.any(spacing <= 0) or not np.all(np.isfinite(spacing)):
        raise InputError(f"the output spacing must be positive mm, got {spacing}")
    local = deformed @ axes  # coordinates along the (orthonormal) axes
    lo = local.min(axis=0) - margin_mm
    hi = local.max(axis=0) + margin_mm
    n = np.maximum(1, np.ceil((hi - lo) / spacing - 1e-9).astype(np.int64) + 1)
    return UnfoldedGrid(origin_lps=axes @ lo, axes=axes, spacing=spacing,
                        shape_kji=(int(n[2]), int(n[1]), int(n[0])))


# ----------------------------------------------------------------------------------------------- rasterising
def _chunks(count: np.ndarray, budget: int):
    """Split consecutive items with sizes ``count`` into [start, end) runs of at most ``budget`` total (>= 1 item)."""
    csum = np.cumsum(count)
    start = 0
    while start < len(count):
        base = csum[start - 1] if start else 0
        end = int(np.searchsorted(csum, base + budget, side="right"))
        end = max(end, start + 1)
        yield start, end, float(csum[end - 1]) / float(csum[-1])
        start = end


def _runs(counts: np.ndarray) -> np.ndarray:
    """Position of each element inside its run when runs of the given lengths are laid end to end (int64)."""
    total = int(counts.sum())
    return np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)


def _row_interval(a, cm, lo, hi, tol):
    """Narrow the i-intervals [lo, hi] of rows to where ``a * i + cm >= -tol`` (in place); returns rows now empty."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-tol - cm) / a
    np.maximum(lo, t, out=lo, where=a > 0)
    np.minimum(hi, t, out=hi, where=a < 0)
    return (a == 0) & (cm < -tol)


def _strict_interval(a, cm, lo, hi):
    """Narrow integer i-intervals [lo, hi] of rows to where ``a * i + cm > 0`` (in place); returns rows now empty."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -cm / a
        np.maximum(lo, np.floor(t) + 1.0, out=lo, where=a > 0)
        np.minimum(hi, np.ceil(t) - 1.0, out=hi, where=a < 0)
    return (a == 0) & (cm <= 0)


def label_map(grid: UnfoldedGrid, deformed: np.ndarray, tets: np.ndarray, chunk_rows: int = 1_000_000,
              progress=None):
    """Tet id per output voxel (int32, shape ``grid.shape_kji``, -1 outside) and the number of overlap voxels.

    Each deformed tetrahedron (vertices in LPS mm) is scan-converted: for every (j, k) row of its bounding
    box the run of voxel centres with all barycentric coordinates >= -1e-9 is solved exactly, so conforming
    faces never leave holes. Where several tetrahedra claim a voxel, the one whose centroid has the largest
    output k (nearest the viewer, who looks down -k) wins. Returns ``(labels, overlap_voxels)``; a voxel
    counts as overlap when its centre, nudged by a tiny generic offset (1e-4 voxel), lies strictly inside
    two or more tetrahedra: a wall layer over another (shared faces of one conforming layer never count).
    Flat tetrahedra are skipped. ``chunk_rows`` bounds the rows handled at once (about 200 bytes each, plus
    the voxels they hold); ``progress`` is an optional callable taking the fraction done.
    """
    tets = np.asarray(tets, np.int64)
    nk, nj, ni = grid.shape_kji
    q = grid.lps_to_index(np.asarray(deformed, float))  # (N,3) continuous output (i, j, k)
    pts = q[tets]  # (T,4,3)
    lo = np.ceil(pts.min(axis=1) - 2e-4).astype(np.int64)  # also catches nudged centres (see _NUDGE)
    hi = np.floor(pts.max(axis=1) + 2e-4).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.array([ni - 1, nj - 1, nk - 1]))
    ext = np.maximum(hi - lo + 1, 0)
    E = tet_edges(pts)
    valid = (ext.prod(axis=1) > 0) & ~degenerate_tets(E, np.linalg.det(E))
    # nearest the viewer last: process in increasing centroid k and keep the highest rank per voxel
    cand = np.flatnonzero(valid)
    order = cand[np.argsort(pts[cand, :, 2].mean(axis=1), kind="stable")].astype(np.int64)
    rank_map = np.full(nk * nj * ni, -1, np.int32)
    strict = np.zeros(nk * nj * ni, np.uint8)
    if len(order):
        inv = np.linalg.inv(E[order])
        B = barycentric_planes(pts[order] - lo[order, None, :], inv)  # (V,4,4), x measured from the box corner
        col = [[np.ascontiguousarray(B[:, m, c]) for c in range(4)] for m in range(4)]
        nudge = [B[:, m, :3] @ _NUDGE for m in range(4)]
        lo_o = [np.ascontiguousarray(lo[order, c]) for c in range(3)]
        ext_o = [np.ascontiguousarray(ext[order, c]) for c in range(3)]
        nrows = ext_o[1] * ext_o[2]
        del inv, B, E
        one = np.uint8(1)
        cost = nrows + ext_o[0] * nrows // 8  # rows, and a bound on the voxels they may hold
        for start, end, done in _chunks(cost, max(int(chunk_rows), 1)):
            sl = slice(start, end)
            nr = nrows[sl]
            rep = lambda x: np.repeat(x[sl], nr)  # noqa: E731  per-tet value -> per row
            off = _runs(nr)
            ej = rep(ext_o[1])
            b, c = np.divmod(off, ej)[::-1]  # row's j, k offsets inside the box
            del off, ej
            bf, cf = b.astype(float), c.astype(float)
            ilo = np.zeros(len(b))
            ihi = rep(ext_o[0]).astype(float) - 1.0
            slo, shi = ilo.copy(), ihi.copy()
            dead = np.zeros(len(b), bool)
            sdead = np.zeros(len(b), bool)
            for m in range(4):
                a = rep(col[m][0])
                cm = rep(col[m][1]) * bf + rep(col[m][2]) * cf + rep(col[m][3])
                dead |= _row_interval(a, cm, ilo, ihi, _INSIDE_TOL)
                sdead |= _strict_interval(a, cm + rep(nudge[m]), slo, shi)
            del a, cm, bf, cf
            ilo = np.ceil(ilo)
            ihi = np.floor(ihi)
            row_flat = ((c + rep(lo_o[2])) * nj + (b + rep(lo_o[1]))) * ni + rep(lo_o[0])
            rank = np.repeat(np.arange(start, end, dtype=np.int32), nr)
            del b, c
            n_in = np.where(dead, 0, np.maximum(ihi - ilo + 1.0, 0.0)).astype(np.int64)
            first = row_flat + np.minimum(ilo, ni).astype(np.int64)
            flat = np.repeat(first, n_in) + _runs(n_in)
            np.maximum.at(rank_map, flat, np.repeat(rank, n_in))
            n_s = np.where(sdead, 0, np.maximum(shi - slo + 1.0, 0.0)).astype(np.int64)
            first = row_flat + np.minimum(slo, ni).astype(np.int64)
            flat = np.repeat(first, n_s) + _runs(n_s)
            np.add.at(strict, flat, one)  # wraps at 256 claims: irrelevant for ">1"
            del flat, first, row_flat, rank
            if progress is not None:
                progress(done)
    overlap = int(np.count_nonzero(strict > 1))
    del strict
    hit = rank_map >= 0
    rank_map[hit] = order[rank_map[hit]].astype(np.int32)
    return rank_map.reshape(nk, nj, ni), overlap


# ----------------------------------------------------------------------------------------------- resampling
def _suggest_spacing(grid: UnfoldedGrid, max_voxels: int) -> float:
    """Smallest spacing (mm, a multiple of 0.05) at which a grid covering the same extent has at most max_voxels."""
    extent = (np.array(grid.size) - 1) * grid.spacing  # what make_grid had to cover (within one voxel)
    sp = max(0.05, np.floor(grid.spacing.max() * (grid.n_voxels / float(max_voxels)) ** (1 / 3) / 0.05) * 0.05)
    while np.prod(np.ceil(extent / sp) + 1) > max_voxels:
        sp += 0.05
    return float(round(sp, 2))


def _output_to_ct_maps(ct: Volume, grid, rest, deformed, tets):
    """Per tetrahedron, the exact affine map output index -> CT continuous index, as 3x4 columns of arrays."""
    q = grid.lps_to_index(deformed)
    p = q[tets]
    E = tet_edges(p)
    det_q = np.linalg.det(E)
    ok = ~degenerate_tets(E, det_q)
    inv = np.zeros_like(E)
    inv[ok] = np.linalg.inv(E[ok])
    B = barycentric_planes(p, inv)  # barycentric planes in output index space
    R = ct.lps_to_index(rest)[tets].transpose(0, 2, 1)  # (T,3,4): columns = rest corners in CT index
    M = R @ B  # (T,3,4)
    cols = [[np.ascontiguousarray(M[:, r, c]) for c in range(4)] for r in range(3)]
    return cols


def _tet_flags(rest, deformed, tets):
    """(inverted, degenerate) bool per tetrahedron: turned inside out, or flat, after the deformation."""
    rest_vol = tet_volumes(rest, tets)
    def_vol = tet_volumes(deformed, tets)
    E_d = tet_edges(deformed[tets])
    degenerate = degenerate_tets(E_d, np.linalg.det(E_d))
    del E_d
    E_r = tet_edges(rest[tets])
    rest_ok = ~degenerate_tets(E_r, np.linalg.det(E_r))
    del E_r
    inverted = rest_ok & ~degenerate & (np.sign(rest_vol) != np.sign(def_vol))
    return inverted, degenerate


def build_unfolded_volume(ct: Volume, rest: np.ndarray, deformed: np.ndarray, hexes: np.ndarray,
                          grid: UnfoldedGrid, background: float = -1024.0, clear_mask: np.ndarray | None = None,
                          progress=None, max_voxels: int = 400_000_000, dtype=np.int16,
                          chunk_voxels: int = 500_000):
    """Resample the CT (HU) into the unfolded grid through the deformed model; returns ``(Volume, info)``.

    ``rest`` and ``deformed`` are the (N,3) LPS mm vertex positions before and after the unfolding and
    ``hexes`` the (M,8) VTK-order cells. Each output voxel centre in a deformed tetrahedron is mapped by
    that tetrahedron's exact affine inverse to the original CT and sampled trilinearly (as
    ``Volume.sample``); voxels in no tetrahedron, or whose source lies off the CT, get ``background`` (HU).
    With ``clear_mask`` (bool, ct's grid) sources whose nearest CT voxel is in the mask get ``background``
    too. Overlaps are resolved towards the viewer (largest output k). The array is ``dtype``: int16
    (rounded, clipped; default) or a float type for exact values.

    ``info``: filled_voxels, overlap_voxels, inverted_tets (deformed signed volume of opposite sign to the
    rest one), degenerate_tets (flat after deformation), outside_ct_voxels, tets, seconds.
    Raises InputError when the grid would exceed ``max_voxels`` (with the spacing to use instead).
    """
    t0 = time.perf_counter()
    rest = np.asarray(rest, float)
    deformed = np.asarray(deformed, float)
    if rest.shape != deformed.shape or rest.ndim != 2 or rest.shape[1] != 3:
        raise InputError(f"rest and deformed vertices must be (N, 3) arrays of the same shape, got {rest.shape} "
                         f"and {deformed.shape}")
    if not np.all(np.isfinite(deformed)):
        raise SimulationError("the deformed model has non-finite vertex positions (the simulation diverged); "
                              "rerun with a smaller time step or a coarser grid")
    nvox = grid.n_voxels
    if nvox > max_voxels:
        raise InputError(f"the unfolded volume would have {nvox:,} voxels (shape {grid.shape_kji}, spacing "
                         f"{np.round(grid.spacing, 3).tolist()} mm), more than the limit {max_voxels:,}; use an "
                         f"output spacing of at least {_suggest_spacing(grid, max_voxels):.2f} mm "
                         "(--output-spacing-mm)")
    if clear_mask is not None:
        clear_mask = np.asarray(clear_mask, bool)
        if clear_mask.shape != ct.array.shape:
            raise InputError(f"clear_mask has shape {clear_mask.shape}, the CT {ct.array.shape}: give it on the "
                             "CT's grid")
    tets, _ = hex_to_tets(hexes)
    if len(tets) and (tets.min() < 0 or tets.max() >= len(rest)):
        raise InputError(f"hexahedra refer to vertex ids outside 0..{len(rest) - 1}")
    dtype = np.dtype(dtype)

    label_progress = None if progress is None else (lambda f: progress(0.8 * f))
    labels, overlap = label_map(grid, deformed, tets, progress=label_progress)

    cols = _output_to_ct_maps(ct, grid, rest, deformed, tets)

    bg = float(background)
    if dtype.kind in "iu":
        info_t = np.iinfo(dtype)
        fill = np.clip(np.rint(bg), info_t.min, info_t.max)
    else:
        fill = bg
    out = np.full(grid.shape_kji, fill, dtype=dtype)
    labels3 = labels.reshape(grid.shape_kji)
    src = np.ascontiguousarray(ct.array)
    hi_u = np.array(ct.array.shape, float)[:, None] - 1.0  # (k, j, i) upper index bounds
    filled = outside_ct = 0
    from scipy import ndimage

    nk, nj, ni = grid.shape_kji
    slab = max(1, int(chunk_voxels) // max(nj * ni, 1))  # k planes per step
    for k0 in range(0, nk, slab):
        part = labels3[k0:k0 + slab]
        kk, jj, ii = np.nonzero(part >= 0)
        if len(kk) == 0:
            continue
        tid = part[kk, jj, ii]
        kk += k0
        v = (ii.astype(float), jj.astype(float), kk.astype(float))
        u = np.empty((3, len(tid)))  # CT (k, j, i) rows for map_coordinates
        for r in range(3):
            c0, c1, c2, c3 = (x[tid] for x in cols[r])
            u[2 - r] = c0 * v[0] + c1 * v[1] + c2 * v[2] + c3
        del c0, c1, c2, c3, v
        vals = ndimage.map_coordinates(src, u, order=1, mode="constant", cval=bg, output=np.float32,
                                       prefilter=False)
        off = np.any((u < 0) | (u > hi_u), axis=0)
        outside_ct += int(np.count_nonzero(off))
        if clear_mask is not None:
            nearest = np.floor(u + 0.5).astype(np.int64)
            inb = np.all((nearest >= 0) & (nearest <= hi_u), axis=0)
            nb = nearest[:, inb]
            hitm = np.zeros(len(tid), bool)
            hitm[inb] = clear_mask[nb[0], nb[1], nb[2]]
            vals[hitm] = bg
            del nearest, nb, hitm
        if dtype.kind in "iu":
            vals = np.clip(np.rint(vals), info_t.min, info_t.max)
        out[kk, jj, ii] = vals.astype(dtype, copy=False)
        filled += len(tid)
        del u, vals, kk, jj, ii, tid
        if progress is not None:
            progress(0.8 + 0.2 * min(1.0, (k0 + slab) / nk))
    if progress is not None:
        progress(1.0)

    inverted, degenerate = _tet_flags(rest, deformed, tets)
    info = {"filled_voxels": int(filled), "overlap_voxels": int(overlap),
            "inverted_tets": int(np.count_nonzero(inverted)), "degenerate_tets": int(np.count_nonzero(degenerate)),
            "outside_ct_voxels": int(outside_ct), "tets": int(len(tets)), "seconds": time.perf_counter() - t0}
    return grid.to_volume(out), info
