"""Before/after pictures of the shaded view's fix: terraced "wood-grain" ripples and edge spikes.

Makes the J-shaped small phantom (binary lumen, as ``stomach-unfold phantom --shape j --size small``) and
the same phantom with a 0.7-voxel scanner blur, unfolds each by the mass-spring model and by cylindrical
unrolling, and renders every view with the renderer before the fix (linear threshold crossing on the raw
volume, 0.7-pixel height blur, no spike removal; copied below) and after (``StomachUnfoldLib.view``).
Writes ``docs/images/view_before_after.png`` (before | after crops) and ``docs/images/view_before_after.md``
(caption with the ripple, the smoothing applied and the visible fractions).

    .venv/bin/python docs/make_view_figure.py [--out docs/images] [--vr]

``--vr`` also renders the unfolded volumes offscreen with VTK's CPU ray caster (``VTK_DEFAULT_OPENGL_WINDOW=
vtkEGLRenderWindow`` where there is no display), as Slicer's volume rendering shows them: the module's
transfer function on the raw volume, and the recommended one on ``view.display_volume`` (staircase-smoothed,
spikes cleared) (``view_before_after_vr.png``, luminance ripple in the caption).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile

import numpy as np
from scipy import ndimage

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from StomachUnfoldLib import view  # noqa: E402
from StomachUnfoldLib.geometry import Volume  # noqa: E402


def shade_before(unfolded: Volume, threshold_hu: float = -400.0, marker_hu: float = 200.0) -> np.ndarray:
    """RGB uint8 view (rows = j reversed) as the renderer drew it before the fix (commit 2f514ce)."""
    k, hu = view.first_hit(unfolded, threshold_hu)
    hit = k >= 0
    a = unfolded.array
    kc = np.clip(k, 0, a.shape[0] - 1)
    above = np.clip(kc + 1, 0, a.shape[0] - 1)
    v0 = np.take_along_axis(a, kc[None], 0)[0].astype(float)
    v1 = np.take_along_axis(a, above[None], 0)[0].astype(float)
    frac = np.where((kc + 1 < a.shape[0]) & (v0 > v1), (v0 - threshold_hu) / np.maximum(v0 - v1, 1e-6), 0.0)
    height = np.where(hit, (k + np.clip(frac, 0, 1)) * unfolded.spacing[2], np.nan)
    fill = np.nanmin(height) if hit.any() else 0.0
    hgt = ndimage.gaussian_filter(np.where(hit, height, fill), 0.7)
    gy, gx = np.gradient(hgt, unfolded.spacing[1], unfolded.spacing[0])
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    light = np.array([-0.35, 0.35, 0.87])
    light /= np.linalg.norm(light)
    shade = 0.25 + 0.75 * np.clip(normal @ light, 0, 1)
    tissue, marker = np.array([0.93, 0.62, 0.58]), np.array([1.0, 0.95, 0.45])
    w = np.clip((np.nan_to_num(hu, nan=0.0) - marker_hu + 100.0) / 200.0, 0, 1)[..., None]
    rgb = (tissue * (1 - w) + marker * w) * shade[..., None]
    rgb[~hit] = 0.0
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)[::-1]


#: The old renderer's height map, for its ripple number (same as shade_before's).
BEFORE = dict(smooth_mm=0.0, clean=False)


def ripple_numbers(unfolded: Volume) -> tuple[float, float, float]:
    """(ripple before, ripple after (mm), share of the view's pixels removed as spikes) on the smooth mucosa."""
    k, hu = view.first_hit(unfolded)
    hit = k >= 0
    sp = float(unfolded.spacing[0])
    mask = view.smooth_mucosa_mask(hit, hu, sp)
    hb, _ = view.surface_height(unfolded, height_sigma_mm=0.7 * sp, **BEFORE)
    ha, clean = view.surface_height(unfolded)
    ji = tuple(unfolded.spacing[1::-1])
    return view.ripple_mm(hb, mask, ji), view.ripple_mm(ha, mask, ji), 1.0 - clean.sum() / max(hit.sum(), 1)


def make_cases(tmp: str):
    """Unfold the binary and the blurred J phantom by massspring and cylindrical; yields (label, method, result)."""
    from StomachUnfoldEval.phantom import make_phantom
    from StomachUnfoldLib.params import UnfoldParameters
    from StomachUnfoldLib.pipeline import unfold

    vol, truth = make_phantom("j", "small")
    rng = np.random.default_rng(1)
    clean_vol, _ = make_phantom("j", "small", noise_hu=0.0)
    blurred = ndimage.gaussian_filter(clean_vol.array.astype(np.float32), 0.7) + rng.normal(0, 15, vol.array.shape)
    blurred = clean_vol.with_array(np.clip(np.rint(blurred), -1024, 3071).astype(np.int16))
    c, p = np.asarray(truth["cardia_lps"]), np.asarray(truth["pylorus_lps"])
    for label, ct in (("binary phantom", vol), ("blurred phantom", blurred)):
        for method in ("massspring", "cylindrical"):
            params = UnfoldParameters()
            params.method = method
            yield label, method, unfold(ct, c, p, params)


def crop_of(img: np.ndarray, method: str) -> np.ndarray:
    """The part of a view (rows top to bottom) shown: the pylorus end with its spikes, or the middle."""
    h, w = img.shape[:2]
    if method == "massspring":
        return img[int(0.1 * h):int(0.9 * h), int(0.55 * w):]
    return img[int(0.15 * h):int(0.75 * h), int(0.2 * w):int(0.8 * w)]


#: The module's transfer function now (StomachUnfold.setMucosaTransferFunctions, threshold -400 HU): HU -> opacity.
TF_MODULE = [(-1024, 0.0), (-500, 0.0), (-250, 0.85), (300, 0.95), (3071, 1.0)]
#: The recommended one: a wider ramp over the air/wall step, no gradient opacity (it shows the noise).
TF_RECOMMENDED = [(-1024, 0.0), (-800, 0.0), (-300, 0.6), (-100, 0.95), (3071, 1.0)]
TF_COLOR = [(-1024, 0.0, 0.0, 0.0), (-400, 0.75, 0.42, 0.38), (60, 0.93, 0.62, 0.58), (200, 0.98, 0.8, 0.6),
            (400, 1.0, 0.95, 0.45), (3071, 1.0, 1.0, 0.8)]


def volume_render(unfolded: Volume, opacity, sample_mm: float, size=(600, 450)) -> np.ndarray:
    """RGB uint8 image (rows top to bottom) of the unfolded volume ray cast from the viewer's side (+k, parallel)."""
    import vtkmodules.vtkRenderingOpenGL2  # noqa: F401
    import vtkmodules.vtkRenderingVolumeOpenGL2  # noqa: F401
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPiecewiseFunction
    from vtkmodules.vtkRenderingCore import (vtkColorTransferFunction, vtkRenderer, vtkRenderWindow, vtkVolume,
                                             vtkVolumeProperty, vtkWindowToImageFilter)
    from vtkmodules.vtkRenderingVolume import vtkFixedPointVolumeRayCastMapper

    a = unfolded.array
    img = vtkImageData()
    img.SetDimensions(a.shape[2], a.shape[1], a.shape[0])
    img.SetSpacing(*[float(v) for v in unfolded.spacing])
    img.GetPointData().SetScalars(ns.numpy_to_vtk(np.ascontiguousarray(a, np.int16).ravel(), deep=True, array_type=4))
    op, col, prop = vtkPiecewiseFunction(), vtkColorTransferFunction(), vtkVolumeProperty()
    for x, y in opacity:
        op.AddPoint(x, y)
    for x, r, g, b in TF_COLOR:
        col.AddRGBPoint(x, r, g, b)
    prop.SetScalarOpacity(op)
    prop.SetColor(col)
    prop.ShadeOn()
    prop.SetAmbient(0.3)
    prop.SetDiffuse(0.7)
    prop.SetSpecular(0.2)
    prop.SetInterpolationTypeToLinear()
    mapper = vtkFixedPointVolumeRayCastMapper()
    mapper.SetInputData(img)
    mapper.SetAutoAdjustSampleDistances(0)
    mapper.SetSampleDistance(float(sample_mm))
    vol = vtkVolume()
    vol.SetMapper(mapper)
    vol.SetProperty(prop)
    ren = vtkRenderer()
    ren.AddVolume(vol)
    win = vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.AddRenderer(ren)
    win.SetSize(*size)
    b = vol.GetBounds()
    c = [(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2]
    cam = ren.GetActiveCamera()
    cam.SetFocalPoint(*c)
    cam.SetPosition(c[0], c[1], c[2] + 500.0)
    cam.SetViewUp(0, 1, 0)
    cam.ParallelProjectionOn()
    cam.SetParallelScale(1.02 * max(b[3] - b[2], (b[1] - b[0]) * size[1] / size[0]) / 2)
    ren.ResetCameraClippingRange()
    win.Render()
    w2i = vtkWindowToImageFilter()
    w2i.SetInput(win)
    w2i.Update()
    out = w2i.GetOutput()
    w, h, _ = out.GetDimensions()
    rgb = ns.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, -1)[::-1, :, :3]
    win.Finalize()
    return np.ascontiguousarray(rgb)


def luminance_ripple(rgb: np.ndarray, sigma_px: float = 3.0, edge_px: int = 12) -> float:
    """RMS (grey levels, 0-255) of the luminance less its Gaussian low-pass over the rendered foreground."""
    g = rgb.astype(float).mean(axis=-1)
    fg = ndimage.binary_erosion(g > 20, iterations=edge_px)
    low = ndimage.gaussian_filter(g, sigma_px)
    return float(np.sqrt(np.mean((g - low)[fg] ** 2))) if fg.any() else float("nan")


def vr_figure(rows, out_dir: str, plt) -> list[str]:
    """Write view_before_after_vr.png (module TF on the raw volume | recommended TF on the smoothed copy); caption lines."""
    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 3.9 * len(rows)))
    lines = ["", "*Volume rendering (VTK ray caster, `--vr`): left the module's transfer function on `unfolded.nrrd`,",
             "right the recommended one on `view.display_volume` (smoothed by `view.staircase_smoothing_vox` voxels,",
             "none on blurred data, and the spike columns cleared). Luminance ripple: RMS grey levels of the image less its 3-pixel low-pass over the sheet.*", "",
             "| volume | method | module TF, raw | recommended TF, raw | recommended TF, smoothed copy |",
             "|---|---|---|---|---|"]
    for ax, r in zip(axes, rows):
        u = r["unfolded"]
        sv = view.staircase_smoothing_vox(u)
        smooth = view.display_volume(u)
        before = volume_render(u, TF_MODULE, 1.0)
        mid = volume_render(u, TF_RECOMMENDED, 0.3)
        after = volume_render(smooth, TF_RECOMMENDED, 0.3)
        lb, lm, la = luminance_ripple(before), luminance_ripple(mid), luminance_ripple(after)
        ax[0].imshow(before)
        ax[0].set_title(f"{r['label']}, {r['method']}: module TF (ripple {lb:.1f})", fontsize=9)
        ax[1].imshow(after)
        ax[1].set_title(f"recommended TF, smoothed {sv:.2f} vox (ripple {la:.1f})", fontsize=9)
        for a in ax:
            a.axis("off")
        lines.append(f"| {r['label']} | {r['method']} | {lb:.1f} | {lm:.1f} | {la:.1f} |")
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "view_before_after_vr.png"), dpi=80)
    return lines


def main(argv=None) -> int:
    """Write the before/after figure and its caption; returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "images"))
    ap.add_argument("--vr", action="store_true", help="also the volume-rendering before/after (VTK, offscreen)")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, method, res in make_cases(tmp):
            u = res.unfolded
            before, after = shade_before(u), view.shade_first_hit(u)
            rb, ra, removed = ripple_numbers(u)
            q = res.report.quality if hasattr(res.report, "quality") else res.report["quality"]
            rows.append(dict(label=label, method=method, before=crop_of(before, method), after=crop_of(after, method),
                             rb=rb, ra=ra, removed=removed, smooth=view.staircase_smoothing_vox(u),
                             sharp=view.edge_sharpness(u), vf=q["visible_fraction"], unfolded=u))
    fig, axes = plt.subplots(len(rows), 2, figsize=(9, 3.3 * len(rows)))
    for ax, r in zip(axes, rows):
        for a, key, rip in ((ax[0], "before", r["rb"]), (ax[1], "after", r["ra"])):
            a.imshow(r[key], interpolation="nearest", aspect="equal")
            a.set_title(f"{r['label']}, {r['method']}: {key} (ripple {rip:.3f} mm)", fontsize=9)
            a.axis("off")
    fig.tight_layout()
    os.makedirs(args.out, exist_ok=True)
    png = os.path.join(args.out, "view_before_after.png")
    fig.savefig(png, dpi=90)
    lines = ["*The shaded view (`view.png`) before and after the fix (`docs/make_view_figure.py`). Left: the old",
             "renderer; right: `StomachUnfoldLib/view.py`. Ripple: RMS (mm) of the height map less its 2 mm Gaussian",
             "low-pass over the smooth mucosa (5 mm inside the outline and from the markers); the visible fraction is",
             "the judge's (`quality.py`, unchanged by the renderer).*", "",
             "| volume | method | edge sharpness | smoothing (voxels) | ripple before (mm) | ripple after (mm) | "
             "spike pixels removed | visible fraction |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['label']} | {r['method']} | {r['sharp']:.2f} | {r['smooth']:.2f} | {r['rb']:.3f} | "
                     f"{r['ra']:.3f} | {r['removed']:.2%} | {r['vf']:.4f} |")
    if args.vr:
        lines += vr_figure(rows, args.out, plt)
    with open(os.path.join(args.out, "view_before_after.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
