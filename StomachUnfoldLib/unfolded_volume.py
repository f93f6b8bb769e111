"""Unfolded volume generation (Oda et al., Sec. 2.5) from the pre/post-deformation correspondence.

Every hexahedron is split into six tetrahedra (the Kuhn split along its 0-6 diagonal, conforming across
neighbouring cells of the grid). For each output voxel the deformed tetrahedron holding it gives, through
its exact affine inverse (barycentric coordinates), the matching point in the original CT, which is
sampled trilinearly. Voxels in no tetrahedron get the background (-1024 HU). Where deformed
tetrahedra overlap (a fold), the one nearest the viewer (largest k) wins and the conflict is counted.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .geometry import Volume

__all__ = ["KUHN_TETS", "hex_to_tets", "tet_inverse", "UnfoldedGrid", "make_grid", "label_map",
           "build_unfolded_volume"]

#: The six tetrahedra of a hexahedron (VTK vertex order), one per path from vertex 0 to vertex 6.
KUHN_TETS = np.array([[0, 1, 2, 6], [0, 1, 5, 6], [0, 3, 2, 6], [0, 3, 7, 6], [0, 4, 5, 6], [0, 4, 7, 6]])


def hex_to_tets(hexes: np.ndarray):
    """Split (M,8) hexahedra into (6M,4) tetrahedra (conforming Kuhn split); also returns the hex id per tet."""
    hexes = np.asarray(hexes, np.int64)
    tets = hexes[:, KUHN_TETS].reshape(-1, 4)
    return tets, np.repeat(np.arange(len(hexes)), 6)


def tet_inverse(points: np.ndarray, tets: np.ndarray):
    """Per tetrahedron: first vertex (T,3), inverse edge matrix (T,3,3), signed volume (T,); degenerate ones get zeros."""
    p = points[tets]  # (T,4,3)
    E = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns = edges
    det = np.linalg.det(E)
    ok = np.abs(det) > 1e-12
    inv = np.zeros_like(E)
    inv[ok] = np.linalg.inv(E[ok])
    return p[:, 0], inv, det / 6.0


def barycentric(q: np.ndarray, p0: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N,4) of points q (N,3) in tetrahedra given by p0 (N,3) and inverse edges (N,3,3)."""
    l123 = np.einsum("nij,nj->ni", inv, q - p0)
    return np.concatenate([1.0 - l123.sum(axis=1, keepdims=True), l123], axis=1)


@dataclass
class UnfoldedGrid:
    """Geometry of the unfolded volume: LPS origin (mm), axes (columns = LPS unit vectors of i, j, k), spacing, shape."""

    origin_lps: np.ndarray
    axes: np.ndarray
    spacing: np.ndarray
    shape_kji: tuple

    def to_volume(self, array) -> Volume:
        """Wrap an array of shape ``shape_kji`` as a Volume with this geometry."""
        return Volume(array, self.spacing, self.origin_lps, self.axes)

    def lps_to_index(self, lps) -> np.ndarray:
        """Continuous (i, j, k) output index of LPS points (mm)."""
        return ((np.asarray(lps, float) - self.origin_lps) @ self.axes) / self.spacing

    def index_to_lps(self, ijk) -> np.ndarray:
        """LPS points (mm) of continuous (i, j, k) output indices."""
        return self.origin_lps + (np.asarray(ijk, float) * self.spacing) @ self.axes.T


def make_grid(deformed: np.ndarray, axes: np.ndarray, spacing, margin_mm: float = 2.0) -> UnfoldedGrid:
    """Smallest grid with the given axes (3x3 LPS columns) and spacing (mm) covering the deformed vertices plus a margin."""
    axes = np.asarray(axes, float)
    spacing = np.broadcast_to(np.asarray(spacing, float), (3,)).astype(float)
    local = np.asarray(deformed, float) @ axes  # coordinates along the axes
    lo = local.min(axis=0) - margin_mm
    hi = local.max(axis=0) + margin_mm
    n = np.maximum(1, np.ceil((hi - lo) / spacing).astype(int) + 1)
    return UnfoldedGrid(origin_lps=axes @ lo, axes=axes, spacing=spacing, shape_kji=(int(n[2]), int(n[1]), int(n[0])))


def label_map(grid: UnfoldedGrid, deformed: np.ndarray, tets: np.ndarray, chunk_candidates: int = 8_000_000,
              progress=None):
    """Tet id per output voxel (int32 array of shape ``grid.shape_kji``, -1 outside) and the number of overlap voxels.

    Rasterises each deformed tetrahedron over its bounding box; where several claim a voxel the one with
    the largest centroid k (nearest the viewer) wins. Returns ``(labels, overlap_voxels)``: voxels strictly
    inside two or more tetrahedra count as overlap (a wall layer over another).
    """
    nk, nj, ni = grid.shape_kji
    q = grid.lps_to_index(deformed)  # (N,3) continuous (i, j, k)
    p0, inv, vol = tet_inverse(q, tets)
    pts = q[tets]
    lo = np.ceil(pts.min(axis=1) - 1e-9).astype(np.int64)
    hi = np.floor(pts.max(axis=1) + 1e-9).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.array([ni - 1, nj - 1, nk - 1]))
    ext = np.maximum(hi - lo + 1, 0)
    count = ext.prod(axis=1)
    prio = pts[:, :, 2].mean(axis=1)
    labels = np.full(nk * nj * ni, -1, np.int32)
    best = np.full(nk * nj * ni, -np.inf, np.float32)
    strict = np.zeros(nk * nj * ni, np.uint8)
    valid = (count > 0) & (np.abs(vol) > 1e-12)
    order = np.flatnonzero(valid)
    csum = np.cumsum(count[order])
    start = 0
    total = int(csum[-1]) if len(csum) else 0
    while start < len(order):
        base = csum[start - 1] if start else 0
        end = int(np.searchsorted(csum, base + chunk_candidates, side="right"))
        end = max(end, start + 1)
        ids = order[start:end]
        cnt = count[ids]
        tid = np.repeat(ids, cnt)
        offs = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        ex = ext[tid]
        a = offs % ex[:, 0]
        b = (offs // ex[:, 0]) % ex[:, 1]
        c = offs // (ex[:, 0] * ex[:, 1])
        vox = lo[tid] + np.stack([a, b, c], axis=1)
        lam = barycentric(vox.astype(float), p0[tid], inv[tid])
        mn = lam.min(axis=1)
        inside = mn >= -1e-7
        vox, tid, mn = vox[inside], tid[inside], mn[inside]
        flat = (vox[:, 2] * nj + vox[:, 1]) * ni + vox[:, 0]
        np.add.at(strict, flat[mn > 1e-6], 1)
        pr = prio[tid].astype(np.float32)
        # within the chunk keep the highest priority per voxel, then merge with what is there
        o = np.lexsort((pr, flat))
        flat, tid, pr = flat[o], tid[o], pr[o]
        last = np.r_[flat[1:] != flat[:-1], True]
        flat, tid, pr = flat[last], tid[last], pr[last]
        win = pr > best[flat]
        labels[flat[win]] = tid[win]
        best[flat[win]] = pr[win]
        start = end
        if progress is not None and total:
            progress(0.8 * float(csum[end - 1]) / total)
    overlap = int((strict > 1).sum())
    return labels.reshape(nk, nj, ni), overlap


def build_unfolded_volume(ct: Volume, rest: np.ndarray, deformed: np.ndarray, hexes: np.ndarray,
                          grid: UnfoldedGrid, background: float = -1024.0, clear_mask: np.ndarray | None = None,
                          progress=None, max_voxels: int = 400_000_000):
    """Resample the CT (HU) into the unfolded grid through the deformed model; returns ``(Volume int16, info)``."""
    t0 = time.perf_counter()
    nvox = int(np.prod(grid.shape_kji))
    if nvox > max_voxels:
        raise InputError(f"the unfolded volume would have {nvox:,} voxels (shape {grid.shape_kji}); use a larger "
                         "--output-spacing-mm")
    tets, _ = hex_to_tets(hexes)
    labels, overlap = label_map(grid, deformed, tets, progress=progress)
    out = np.full(grid.shape_kji, background, np.float32)
    kk, jj, ii = np.nonzero(labels >= 0)
    tid = labels[kk, jj, ii]
    q = np.stack([ii, jj, kk], axis=1).astype(float)
    qd = grid.lps_to_index(deformed)
    p0, inv, _ = tet_inverse(qd, tets)
    lam = barycentric(q, p0[tid], inv[tid])
    src = np.einsum("nk,nkd->nd", lam, rest[tets[tid]])  # LPS in the original CT
    vals = ct.sample(src, order=1, cval=background)
    if clear_mask is not None:
        ijk = np.rint(ct.lps_to_index(src)).astype(np.int64)
        size = np.array(ct.size)
        ok = np.all((ijk >= 0) & (ijk < size), axis=1)
        ijk = np.clip(ijk, 0, size - 1)
        inl = clear_mask[ijk[:, 2], ijk[:, 1], ijk[:, 0]] & ok
        vals[inl] = background
    out[kk, jj, ii] = vals
    if progress is not None:
        progress(1.0)
    _, _, rest_vol = tet_inverse(rest, tets)
    _, _, def_vol = tet_inverse(deformed, tets)
    info = {"filled_voxels": int(len(tid)), "overlap_voxels": overlap,
            "inverted_tets": int((np.sign(rest_vol) != np.sign(def_vol)).sum()),
            "degenerate_tets": int((np.abs(def_vol) < 1e-9).sum()), "seconds": time.perf_counter() - t0}
    arr = np.clip(np.rint(out), -32768, 32767).astype(np.int16)
    return grid.to_volume(arr), info
