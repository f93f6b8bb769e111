"""Where a measurement on the view can be trusted: the local area and length scale of the view, per pixel.

Every method's Mesh maps mucosa triangles (rest, LPS mm) to the view (unfolded LPS mm). Per triangle the 2D
Jacobian's singular values s1 >= s2 give the view's local length scales (1: true length); their product is
the area scale. ``distortion_map`` rasterises them onto the unfolded volume's (j, i) pixel grid;
``write_distortion`` writes ``distortion.nrrd`` (one slice on the view's grid, two components: area scale and
worst length scale max(s1, 1/s2)) and ``distortion.png`` (the shaded view under a colour overlay).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import Volume

__all__ = ["triangle_stretch", "DistortionMap", "distortion_map", "write_distortion", "mucosa_slice_origin_lps",
           "area_scale_volume", "TRUST_LIMIT"]

#: A length on the view within this factor of the truth (10 %) counts as measurable.
TRUST_LIMIT = 1.10


def _frames(p: np.ndarray):
    """Per triangle (T,3,3 corners, mm) its 2x2 edge matrix in its own plane's frame, and its area (mm^2)."""
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    n = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(n, axis=1)
    u = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
    w = np.cross(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12), u)
    m = np.stack([np.einsum("ij,ij->i", e1, u), np.einsum("ij,ij->i", e1, w),
                  np.einsum("ij,ij->i", e2, u), np.einsum("ij,ij->i", e2, w)], 1).reshape(-1, 2, 2)
    return m, area


def triangle_stretch(rest: np.ndarray, deformed: np.ndarray, tris: np.ndarray):
    """Singular values (s1 >= s2) of each triangle's map rest -> deformed (both mm), its rest area, and a valid mask."""
    A, a0 = _frames(np.asarray(rest, float)[tris])
    B, a1 = _frames(np.asarray(deformed, float)[tris])
    ok = (a0 > 1e-9) & (a1 > 1e-9)
    s = np.ones((len(tris), 2))
    if ok.any():
        J = np.einsum("nij,njk->nik", np.transpose(B[ok], (0, 2, 1)), np.linalg.inv(np.transpose(A[ok], (0, 2, 1))))
        s[ok] = np.linalg.svd(J, compute_uv=False)
    return s[:, 0], s[:, 1], a0, ok


@dataclass
class DistortionMap:
    """Per pixel (j, i) of the view: area scale (view / mucosa), worst length scale (>= 1), covered mask, and where
    more than one piece of the mucosa maps (the flat map folds over itself there)."""

    area_scale: np.ndarray
    length_scale: np.ndarray
    covered: np.ndarray
    multiple: np.ndarray | None = None

    def summary(self) -> dict:
        """Report figures: covered pixels, the share where lengths are within TRUST_LIMIT, area-scale percentiles."""
        c = self.covered
        if not c.any():
            return {"covered_pixels": 0, "trusted_fraction": 0.0}
        a = self.area_scale[c]
        return {"covered_pixels": int(c.sum()),
                "trusted_fraction": float(np.mean(self.length_scale[c] <= TRUST_LIMIT)),
                "area_scale_p5_p50_p95": [float(np.percentile(a, q)) for q in (5, 50, 95)],
                "length_scale_p95": float(np.percentile(self.length_scale[c], 95)), "trust_limit": TRUST_LIMIT}


def distortion_map(unfolded: Volume, mesh, progress=None) -> DistortionMap:
    """Rasterise the Mesh's surface triangles' area and length scales onto the unfolded view's (j, i) pixels.

    ``progress`` (callable(fraction)) is called as the triangles are rasterised."""
    from .progress import Progress
    from .surface import rasterise

    nk, nj, ni = unfolded.array.shape
    tris = np.asarray(mesh.surface, np.int64)
    area = np.ones((nj, ni))
    length = np.ones((nj, ni))
    covered = np.zeros((nj, ni), bool)
    if len(tris) == 0:
        return DistortionMap(area, length, covered, np.zeros((nj, ni), bool))
    s1, s2, _, ok = triangle_stretch(mesh.rest_lps, mesh.unfolded_lps, tris)
    ijk = unfolded.lps_to_index(np.asarray(mesh.unfolded_lps, float))
    if progress is not None:
        progress(0.3)
    # pixel units: rasterise in a square grid of unit pixels, (i, j) of the view
    prog = Progress(None if progress is None else (lambda stage, fraction: progress(0.3 + 0.7 * fraction)))
    tri, _, hits = rasterise(ijk[:, :2], tris[ok], (nj, ni), 1.0, prog, batch=500_000)
    hit = tri >= 0
    t = np.flatnonzero(ok)[tri[hit]]
    area[hit] = s1[t] * s2[t]
    length[hit] = np.maximum(s1[t], 1.0 / np.maximum(s2[t], 1e-12))
    covered[hit] = True
    return DistortionMap(area, length, covered, hits > 1)


def _overlay(view_rgb: np.ndarray, dmap: DistortionMap) -> np.ndarray:
    """The shaded view (rows top = high j) under a diverging colour of log2(area scale); dark where lengths > 1.5x."""
    la = np.clip(np.log2(np.maximum(dmap.area_scale, 1e-6)), -1.0, 1.0)[::-1]
    cov = dmap.covered[::-1]
    red = np.array([0.84, 0.19, 0.15])
    blue = np.array([0.19, 0.42, 0.84])
    white = np.array([1.0, 1.0, 1.0])
    w = np.abs(la)[..., None]
    colour = np.where(la[..., None] > 0, white * (1 - w) + red * w, white * (1 - w) + blue * w)
    base = view_rgb.astype(float) / 255.0
    out = np.where(cov[..., None], 0.45 * base + 0.55 * colour * np.maximum(base.mean(-1, keepdims=True), 0.35) / 0.6,
                   base)
    bad = cov & (dmap.length_scale[::-1] > 1.5)
    out[bad] *= 0.35
    return (np.clip(out, 0, 1) * 255).astype(np.uint8)


def mucosa_slice_origin_lps(unfolded: Volume) -> np.ndarray:
    """LPS origin (mm) of the one-slice distortion map: the unfolded volume's corner at its median mucosa height."""
    from .view import first_hit

    k, _ = first_hit(unfolded)
    k0 = float(np.median(k[k >= 0])) if (k >= 0).any() else 0.0
    return unfolded.index_to_lps(np.array([[0.0, 0.0, k0]]))[0]


def area_scale_volume(unfolded: Volume, dmap: DistortionMap) -> Volume:
    """The area scale (0 outside the view) as a one-slice Volume on the unfolded volume's (i, j) grid, LPS mm."""
    area = np.where(dmap.covered, dmap.area_scale, 0.0).astype(np.float32)[None]
    return Volume(area, unfolded.spacing, mucosa_slice_origin_lps(unfolded), unfolded.direction)


def write_distortion(unfolded: Volume, dmap: DistortionMap, nrrd_path: str, png_path: str,
                     view_rgb: np.ndarray | None = None) -> None:
    """Write ``distortion.nrrd`` (area scale, worst length scale on the view's grid, one slice) and its PNG overlay.

    ``view_rgb`` is the shaded view (``view.shade_first_hit``) when the caller has it already.
    """
    import SimpleITK as sitk

    from .view import save_png, shade_first_hit

    arr = np.stack([dmap.area_scale, dmap.length_scale], -1).astype(np.float32)
    arr[~dmap.covered] = 0.0
    img = sitk.GetImageFromArray(arr[None], isVector=True)
    img.SetSpacing([float(v) for v in unfolded.spacing])
    # the slice lies at the view's median mucosa height, on the unfolded volume's own axes
    img.SetOrigin([float(v) for v in mucosa_slice_origin_lps(unfolded)])
    img.SetDirection([float(v) for v in unfolded.direction.ravel()])
    sitk.WriteImage(img, str(nrrd_path), useCompression=True)
    if view_rgb is None:
        view_rgb = shade_first_hit(unfolded)
    save_png(_overlay(view_rgb, dmap), png_path, unfolded.spacing)
