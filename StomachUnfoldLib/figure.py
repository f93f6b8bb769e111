"""The annotated view (``view.png``): shaded and density panels with a scale bar in mm and orientation labels.

The view's pixels are the unfolded volume's (i, j) columns (``view.py``): i from left to right, j from bottom to
top. Each panel is resampled (bilinear) to ``view_size`` pixels wide with square pixels, framed by margins that
name the ends (cardia, pylorus), the cut edges and the middle line (greater/lesser curvature) and the two halves
(anterior/posterior), found from the method's own model (:func:`orientation`), not assumed. The scale bar is
drawn where the distortion map says lengths hold (within ``distortion.TRUST_LIMIT``), else in the margin. Text
is rendered by VTK's FreeType tools (no display, no plotting library).
"""
from __future__ import annotations

import numpy as np

from .geometry import Volume

__all__ = ["text_mask", "resize_rgb", "orientation", "nice_length_mm", "place_scale_bar", "density_rgb",
           "annotate_panel", "compose_view", "DENSITY_WINDOW_HU", "DENSITY_COLOURS", "OPPOSITE", "write_view"]

#: HU window of the density panel's colour scale (the wall's mean HU just below the mucosa).
DENSITY_WINDOW_HU = (-100.0, 250.0)
#: Colour stops (RGB 0-1) of the density scale, low to high HU.
DENSITY_COLOURS = np.array([[0.05, 0.05, 0.25], [0.1, 0.45, 0.6], [0.55, 0.8, 0.35], [1.0, 0.85, 0.25], [1.0, 1.0, 0.95]])
#: The side opposite each incision side (the middle line of the view).
OPPOSITE = {"greater": "lesser", "lesser": "greater", "anterior": "posterior", "posterior": "anterior"}


def text_mask(text: str, size_px: int, vertical: bool = False) -> np.ndarray:
    """Coverage (0-1, rows top to bottom) of ``text`` rendered in a bold sans font ``size_px`` pixels high."""
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkRenderingCore import vtkTextProperty
    from vtkmodules.vtkRenderingFreeType import vtkFreeTypeTools

    tp = vtkTextProperty()
    tp.SetFontSize(int(size_px))
    tp.SetBold(1)
    tp.SetColor(1.0, 1.0, 1.0)
    img, size = vtkImageData(), [0, 0]
    if not vtkFreeTypeTools.GetInstance().RenderString(tp, str(text), 72, img, size) or size[0] <= 0:
        return np.zeros((int(size_px), 1))
    dims = img.GetDimensions()
    a = ns.vtk_to_numpy(img.GetPointData().GetScalars()).reshape(dims[1], dims[0], -1)[..., -1]
    a = a[::-1][:, :size[0]].astype(float) / 255.0  # VTK rows run bottom to top
    rows = np.flatnonzero(a.max(1) > 0)
    a = a[max(rows[0] - 1, 0):rows[-1] + 2] if len(rows) else a
    return np.rot90(a) if vertical else a


def _paste(canvas: np.ndarray, mask: np.ndarray, x: float, y: float, colour, anchor: str = "centre") -> list:
    """Blend a text mask into ``canvas`` (float RGB 0-1) at (x, y) pixels; returns its box [x0, y0, x1, y1]."""
    h, w = mask.shape
    x0 = int(round(x - {"left": 0, "centre": w / 2, "right": w}[anchor]))
    y0 = int(round(y - h / 2))
    H, W = canvas.shape[:2]
    cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x0 + w, W), min(y0 + h, H)
    if cx1 > cx0 and cy1 > cy0:
        m = mask[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0, None]
        canvas[cy0:cy1, cx0:cx1] = canvas[cy0:cy1, cx0:cx1] * (1 - m) + np.asarray(colour, float) * m
    return [x0, y0, x0 + w, y0 + h]


def _label(canvas, text, x, y, size, anchor="centre", vertical=False, colour=(1.0, 1.0, 1.0), shadow=False):
    """Draw ``text`` (optionally with a one-pixel dark shadow, for text over the view); returns its box."""
    m = text_mask(text, size, vertical)
    if shadow:
        from scipy import ndimage

        _paste(canvas, np.clip(ndimage.maximum_filter(m, 3), 0, 1), x, y, (0.0, 0.0, 0.0), anchor)
    return _paste(canvas, m, x, y, colour, anchor)


def resize_rgb(img: np.ndarray, shape_hw) -> np.ndarray:
    """Resample an image (H, W[, C], any dtype) to ``shape_hw`` pixels by bilinear interpolation (pixel centres kept)."""
    from scipy import ndimage

    h, w = int(shape_hw[0]), int(shape_hw[1])
    src = np.asarray(img, float)
    rr = (np.arange(h) + 0.5) * src.shape[0] / h - 0.5
    cc = (np.arange(w) + 0.5) * src.shape[1] / w - 0.5
    R, C = np.meshgrid(rr, cc, indexing="ij")
    chans = [src] if src.ndim == 2 else [src[..., c] for c in range(src.shape[2])]
    out = [ndimage.map_coordinates(ch, [R, C], order=1, mode="nearest") for ch in chans]
    return out[0] if src.ndim == 2 else np.stack(out, -1)


def orientation(unfolded: Volume, mesh, centerline_lps, incision_lps, side: str) -> dict:
    """Which anatomy each edge and half of the view shows, measured on the method's model (rest LPS mm vs view).

    Every model vertex's view column (i, j) is paired with where it lies around the centreline: its position
    along it (cardia 0 to pylorus 1), its angle from the incision's cut direction, and whether it faces the
    patient's anterior (-y LPS) or the greater curvature. Returns {"left", "right", "edges", "middle",
    "upper_half", "lower_half"} (names; None where the model does not tell) and the correlations behind them.
    """
    from scipy.spatial import cKDTree

    from .incision_line import cutting_directions

    cl = np.asarray(centerline_lps, float)
    inc = np.asarray(incision_lps, float)
    rest = np.asarray(mesh.rest_lps, float)
    ij = unfolded.lps_to_index(np.asarray(mesh.unfolded_lps, float))[:, :2]
    ok = np.all(np.isfinite(ij), 1) & np.all(np.isfinite(rest), 1)
    rest, ij = rest[ok], ij[ok]
    out = {"left": None, "right": None, "edges": None, "middle": None, "upper_half": None, "lower_half": None}
    if len(rest) < 10 or len(cl) < 3 or len(inc) < 1:
        return out
    tang = np.gradient(cl, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    idx = cKDTree(cl).query(rest)[1]
    t = idx / (len(cl) - 1.0)

    def around(vec):  # unit vectors perpendicular to the local tangent
        v = vec - np.sum(vec * tang[idx], 1, keepdims=True) * tang[idx]
        return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)

    off = around(rest - cl[idx])
    cut_cl = inc[cKDTree(inc).query(cl)[1]] - cl  # per centreline point: toward the incision
    cos_cut = np.sum(off * around(cut_cl[idx]), 1)
    ant = np.sum(off * around(np.tile([0.0, -1.0, 0.0], (len(off), 1))), 1)
    radius = float(np.median(np.linalg.norm(cut_cl, axis=1)))
    greater = cutting_directions(cl, tang, np.full(len(cl), max(radius, 1.0)), "greater")
    grt = np.sum(off * around(greater[idx]), 1)
    i, j = ij[:, 0], ij[:, 1]
    j_mid = float(np.median(j))
    rel = np.abs(j - j_mid) / max(np.ptp(j) / 2.0, 1e-9)
    r_i = float(np.corrcoef(i, t)[0, 1]) if np.ptp(t) > 0 else 0.0
    r_cut = float(np.corrcoef(rel, cos_cut)[0, 1]) if np.ptp(rel) > 0 else 0.0
    upper = j > j_mid
    half = ant if side in ("greater", "lesser", "user") else grt
    names = ("anterior", "posterior") if side in ("greater", "lesser", "user") else ("greater", "lesser")
    d_half = float(half[upper].mean() - half[~upper].mean()) if upper.any() and (~upper).any() else 0.0
    if abs(r_i) > 0.5:
        out["left"], out["right"] = ("cardia", "pylorus") if r_i > 0 else ("pylorus", "cardia")
    if r_cut > 0.3:
        out["edges"], out["middle"] = side, OPPOSITE.get(side)
    if abs(d_half) > 0.2:
        out["upper_half"], out["lower_half"] = names if d_half > 0 else names[::-1]
    out["evidence"] = {"i_vs_position_along_centreline": r_i, "edge_distance_vs_cos_to_cut": r_cut,
                       "upper_minus_lower_half": d_half, "half_reference": names[0]}
    return out


def nice_length_mm(width_mm: float) -> float:
    """A round scale-bar length (mm: 1, 2, 5, 10, 20, 50, ...) of about a fifth of ``width_mm``."""
    target = max(width_mm / 5.0, 1e-3)
    cands = [m * 10.0 ** e for e in range(-1, 4) for m in (1, 2, 5)]
    return float(max([c for c in cands if c <= target] or [cands[0]]))


def place_scale_bar(trusted: np.ndarray, bar_px: int, box_h: int, pad: int = 4):
    """Top-left (x, y) pixel of a ``bar_px + 2 pad`` by ``box_h`` box lying wholly on ``trusted`` (rows top to bottom).

    The lowest, then leftmost such box; None when there is none.
    """
    from scipy import ndimage

    bw, bh = int(bar_px) + 2 * pad, int(box_h)
    H, W = trusted.shape
    if bw > W or bh > H:
        return None
    ok = ndimage.minimum_filter(trusted.astype(np.uint8), size=(bh, bw), mode="constant", cval=0,
                                origin=(-(bh // 2), -(bw // 2))) > 0
    ok[H - bh + 1:, :] = False
    ok[:, W - bw + 1:] = False
    ys, xs = np.nonzero(ok)
    if not len(ys):
        return None
    best = np.lexsort((xs, -ys))[0]
    return int(xs[best]), int(ys[best])


def density_rgb(unfolded: Volume, k_hit: np.ndarray, hit: np.ndarray, shade: np.ndarray | None = None,
                depth_mm=(1.0, 4.0)) -> np.ndarray:
    """RGB (0-1, rows = j reversed) of the mean HU from ``depth_mm[0]`` to ``depth_mm[1]`` mm below the first hit.

    The colour scale runs over DENSITY_WINDOW_HU (dark blue, teal, yellow, white); ``shade`` (0-1 per pixel, same
    rows) modulates it so the shape still shows. Off the view: black.
    """
    a = unfolded.array
    dk = float(unfolded.spacing[2])
    ks = np.arange(int(round(depth_mm[0] / dk)), int(round(depth_mm[1] / dk)) + 1)
    acc = np.zeros(k_hit.shape)
    for d in ks:
        kk = np.clip(k_hit - d, 0, a.shape[0] - 1)
        acc += np.take_along_axis(a, kk[None], 0)[0]
    hu = acc / max(len(ks), 1)
    lo, hi = DENSITY_WINDOW_HU
    x = np.clip((hu - lo) / (hi - lo), 0, 1)[::-1]
    stops = DENSITY_COLOURS
    pos = np.linspace(0, 1, len(stops))
    rgb = np.stack([np.interp(x, pos, stops[:, c]) for c in range(3)], -1)
    if shade is not None:
        rgb *= (0.55 + 0.45 * shade)[..., None]
    rgb[~hit[::-1]] = 0.0
    return rgb


def _bar(canvas, x0, y, bar_px, thick, text, size):
    """A white scale bar with a dark outline from (x0, y) rightwards ``bar_px`` long, its label above it."""
    canvas[y - 1:y + thick + 1, x0 - 1:x0 + bar_px + 1] = 0.0
    canvas[y:y + thick, x0:x0 + bar_px] = 1.0
    return _label(canvas, text, x0 + bar_px / 2.0, y - size * 0.75, size, shadow=True)


def _strip_labels(canvas, x, top, H, items, size):
    """Vertical labels centred at fractions of the view's height in a margin strip at x; returns their boxes."""
    boxes = {}
    for key, text, frac in items:
        if text:
            boxes[key] = {"text": text, "box": _label(canvas, text, x, top + frac * H, size, vertical=True)}
    return boxes


#: Ring colours on the view: landmarks (cyan) and peeled folds whose mucosa is not shown (orange, dashed).
LANDMARK_RGB, FOLD_RGB = (0.2, 0.95, 1.0), (1.0, 0.55, 0.1)


def _landmarks(canvas, marks_px: dict, size: int, colour=LANDMARK_RGB, radii: dict | None = None,
               dashed: bool = False, taken: list | None = None) -> dict:
    """Rings and names at view pixels {name: (x, y)} (radius from ``radii`` {name: px}, else a fixed one);
    returns {name: [x, y]}. A name whose place overlaps one already written (``taken``: their boxes (x0, y0, x1,
    y1), appended to) moves down, then up, a line at a time, so that nearby rings' names do not stack."""
    yy, xx = np.mgrid[0:canvas.shape[0], 0:canvas.shape[1]]
    taken = [] if taken is None else taken
    out = {}
    for name, (x, y) in marks_px.items():
        r = max(4.0, size * 0.45, (radii or {}).get(name, 0.0))
        ring = np.abs(np.hypot(xx - x, yy - y) - r) < 1.1
        if dashed:  # eight dashes round the ring
            ring &= (np.floor((np.arctan2(yy - y, xx - x) + np.pi) / (np.pi / 8)) % 2) == 0
        canvas[ring] = colour
        fs = max(9, int(size * 0.7))
        h, w = text_mask(str(name), fs).shape
        x0, y0 = x + 0.7 * r + 2, y - 0.7 * r
        for dy in (0, 1, -1, 2, -2, 3, -3):
            box = (x0, y0 + dy * (h + 2) - h / 2, x0 + w, y0 + dy * (h + 2) + h / 2)
            if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in taken):
                break
        taken.append(box)
        _label(canvas, str(name), x0, (box[1] + box[3]) / 2, fs, anchor="left", colour=colour, shadow=True)
        out[str(name)] = [float(x), float(y)]
    return out


def annotate_panel(rgb: np.ndarray, spacing_ij, trusted: np.ndarray, orient: dict, width_px: int,
                   title: str = "", landmarks_ij: dict | None = None, folds_ij: dict | None = None):
    """One labelled panel: the view ``rgb`` (0-1, rows = j from top (high) to bottom, columns = i) resampled to
    ``width_px`` pixels wide with square pixels, its scale bar (mm) and orientation labels.

    ``trusted`` (j, i) marks the view's pixels where lengths hold; ``orient`` is :func:`orientation`'s;
    ``landmarks_ij`` {name: (i, j) continuous view index}; ``folds_ij`` {name: (i, j, radius mm)} of peeled
    folds (dashed orange rings). Returns (canvas float RGB 0-1, layout dict in pixels).
    """
    nj, ni = rgb.shape[:2]
    si, sj = float(spacing_ij[0]), float(spacing_ij[1])
    W = int(width_px)
    px_mm = ni * si / W
    H = max(1, int(round(nj * sj / px_mm)))
    font = max(11, int(round(W / 36)))
    top, bottom, side = int(2.8 * font), int(3.4 * font), int(1.7 * font)
    canvas = np.zeros((top + H + bottom, side + W + int(2.7 * side), 3))
    left = side
    canvas[top:top + H, left:left + W] = np.clip(resize_rgb(rgb, (H, W)), 0, 1)
    labels = {}
    if title:
        labels["title"] = {"text": title, "box": _label(canvas, title, left, 0.7 * font, font, anchor="left")}
    edge = orient.get("edges")
    if edge:
        name = f"{edge} curvature" if edge in ("greater", "lesser") else f"{edge} wall"
        for key, y in (("top_edge", top - 0.75 * font), ("bottom_edge", top + H + 0.75 * font)):
            labels[key] = {"text": f"{name} (cut)", "box": _label(canvas, f"{name} (cut)", left + W / 2, y, font)}
    labels.update(_strip_labels(canvas, side / 2, top, H, [("left_end", orient.get("left"), 0.5)], font))
    labels.update(_strip_labels(canvas, left + W + side / 2, top, H, [("right_end", orient.get("right"), 0.5)], font))
    mid = orient.get("middle")
    mid_name = (f"{mid} curv." if mid in ("greater", "lesser") else mid) if mid else None
    hs = max(9, int(font * 0.8))
    labels.update(_strip_labels(canvas, left + W + 2.1 * side, top, H,
                                [("upper_half", orient.get("upper_half"), 0.2), ("middle", mid_name, 0.5),
                                 ("lower_half", orient.get("lower_half"), 0.8)], hs))
    if mid_name:  # ticks where the middle line meets the strip
        x = int(left + W + 1.6 * side)
        canvas[top + H // 2 - 1:top + H // 2 + 1, x:x + side // 3] = 1.0
    bar = _scale_bar(canvas, trusted, (top, left, H, W), px_mm, font)

    def to_px(p):  # continuous view index (i, j) -> canvas pixel (x, y), rows from the top
        return left + (p[0] + 0.5) / ni * W, top + (nj - (p[1] + 0.5)) / nj * H
    marks, folds, taken = {}, {}, []     # taken: the names' boxes, shared so that no two names stack
    if landmarks_ij:
        marks = _landmarks(canvas, {n: to_px(p) for n, p in landmarks_ij.items() if np.all(np.isfinite(p[:2]))}, font,
                           taken=taken)
    if folds_ij:
        folds = _landmarks(canvas, {n: to_px(p) for n, p in folds_ij.items()}, font, FOLD_RGB,
                           {n: p[2] / px_mm for n, p in folds_ij.items()}, dashed=True, taken=taken)
    layout = {"title": title, "view_origin_px": [left, top], "view_size_px": [W, H], "pixel_mm": px_mm,
              "scale_bar": bar, "labels": labels, "landmarks_px": marks, "folds_px": folds,
              "ring_name_boxes_px": [list(map(float, b)) for b in taken]}
    return canvas, layout


def _scale_bar(canvas, trusted, box, px_mm, font) -> dict:
    """Draw the scale bar on a trusted part of the view (else in the bottom margin); returns its layout."""
    top, left, H, W = box
    thick = max(3, font // 4)
    tr = resize_rgb(trusted[::-1].astype(float), (H, W)) > 0.99
    length = nice_length_mm(W * px_mm)
    while True:
        bar_px = int(round(length / px_mm))
        pos = place_scale_bar(tr, bar_px, thick + int(1.6 * font))
        if pos is not None or length <= 2.0 or bar_px < 3 * font:
            break
        length = nice_length_mm(length * 5.0 / 2.01)
    bar_px = int(round(length / px_mm))
    if pos is not None:
        x0, y = left + pos[0] + 4, top + pos[1] + int(1.6 * font)
    else:
        x0, y = left, top + H + int(2.2 * font)
    text = f"{length:g} mm"
    tbox = _bar(canvas, x0, y, bar_px, thick, text, font)
    return {"mm": length, "px": bar_px, "x0": x0, "y": y, "thickness": thick, "on_view": pos is not None,
            "text": text, "text_box": tbox}


def compose_view(panels, gap_px: int = 8):
    """Panels (canvas, layout) side by side (black gap) as one uint8 RGB image; layouts shifted to image pixels."""
    h = max(c.shape[0] for c, _ in panels)
    parts, layouts, x = [], [], 0
    for c, lay in panels:
        pad = np.zeros((h, c.shape[1] + gap_px, 3))
        pad[:c.shape[0], :c.shape[1]] = c
        parts.append(pad)
        lay = dict(lay, offset_px=[x, 0])
        layouts.append(lay)
        x += pad.shape[1]
    img = np.concatenate(parts, 1)[:, :-gap_px] if gap_px else np.concatenate(parts, 1)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8), layouts


def write_view(unfolded: Volume, path: str, shaded: np.ndarray, dmap=None, orient: dict | None = None,
               view_size: int | None = None, landmarks_lps: dict | None = None, folds: list | None = None) -> dict:
    """Write ``view.png``: the shaded view (``view.shade_first_hit``'s uint8 RGB) and the density panel side by side,
    each ``view_size`` pixels wide (default: the view's own width, at least 512), labelled and with a scale bar.

    ``dmap``: the DistortionMap (the bar goes where lengths hold; without it, anywhere on the view); ``orient``:
    :func:`orientation`'s labels; ``landmarks_lps``: {name: LPS mm in the unfolded frame} drawn as rings;
    ``folds``: the method's peeled folds (``view_ij``, ``area_mm2``), whose mucosa is not shown, drawn as
    dashed orange rings F1, F2, ... of the same area. Returns the layout {"pixel_mm", "panels": [...],
    "orientation"} (pixels of the PNG, rows top to bottom).
    """
    from .distortion import TRUST_LIMIT
    from .view import first_hit, write_png

    nk, nj, ni = unfolded.array.shape
    width = int(view_size) if view_size else max(512, ni)
    hit = shaded[::-1].any(-1)  # (j, i), j up
    if dmap is not None:
        trusted = dmap.covered & (dmap.length_scale <= TRUST_LIMIT) & hit
    else:
        trusted = hit
    k_hit, _ = first_hit(unfolded)
    shade = np.clip(shaded.max(-1) / 255.0 / 0.93, 0, 1)
    dens = density_rgb(unfolded, k_hit, hit, shade)
    marks = None
    if landmarks_lps:
        marks = {n: unfolded.lps_to_index(np.asarray(p, float)[None])[0] for n, p in landmarks_lps.items()
                 if np.all(np.isfinite(p))}
    fold_marks = {f"F{n}": (*fd["view_ij"], float(np.sqrt(fd["area_mm2"] / np.pi)))
                  for n, fd in enumerate(folds or [], 1) if "view_ij" in fd}
    orient = orient or {}
    lo, hi = DENSITY_WINDOW_HU
    panels = [annotate_panel(shaded.astype(float) / 255.0, unfolded.spacing[:2], trusted, orient, width,
                             "shaded mucosa", marks, fold_marks),
              annotate_panel(dens, unfolded.spacing[:2], trusted, orient, width,
                             f"wall density {lo:g} to {hi:g} HU", marks, fold_marks)]
    _colour_legend(*panels[1])
    img, layouts = compose_view(panels)
    write_png(img, path)
    return {"pixel_mm": layouts[0]["pixel_mm"], "panels": layouts,
            "orientation": {k: v for k, v in orient.items() if k != "evidence"},
            "orientation_evidence": orient.get("evidence"), "image_size_px": [int(img.shape[1]), int(img.shape[0])]}


def _colour_legend(canvas, layout) -> None:
    """The density colour scale as a strip at the bottom right of a panel, its ends labelled in HU."""
    left, top = layout["view_origin_px"]
    W, H = layout["view_size_px"]
    font = max(9, int(round(W / 36 * 0.75)))
    w = max(40, W // 4)
    x0, y0 = left + W - w, top + H + int(2.0 * font)
    stops = DENSITY_COLOURS
    x = np.linspace(0, 1, w)
    pos = np.linspace(0, 1, len(stops))
    strip = np.stack([np.interp(x, pos, stops[:, c]) for c in range(3)], -1)
    canvas[y0:y0 + max(3, font // 2), x0:x0 + w] = strip[None]
    lo, hi = DENSITY_WINDOW_HU
    _label(canvas, f"{lo:g}", x0 - 3, y0 + 2, font, anchor="right")
    _label(canvas, f"{hi:g} HU", x0 + w + 3, y0 + 2, font, anchor="left")
