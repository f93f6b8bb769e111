"""Before/after picture of the rays' smoothed normals: beads drawn magnified, so that neighbouring beads merged.

Unfolds random stomachs whose beads the judge merged (development seeds 31051 and 31029, tuning seed 6, whose beads
lie at the pyloric notch; two clicks, the bench's default size) twice with ``isometric``: with the rays along the
iso-surface's own vertex normals, as before 2026-12-05's seventh session (``NORMAL_SMOOTH_MM = 0``), and along the
normals averaged over 2 mm (the default). The flat map is the same in both. Writes
``docs/images/normals_before_after.png`` (the shaded view round the beads missed before, before | after, one row per
volume; the judge's bead regions outlined; a cross at each true marker's mapped place, green where the judge sees it,
red where not) and ``normals_before_after.md`` (markers seen, the judge's median bead area).

    .venv/bin/python docs/make_normals_figure.py [--out docs/images] [--seeds 31051,31029,6]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from StomachUnfoldEval.markers import _marker_regions, marker_report  # noqa: E402
from StomachUnfoldEval.random_stomach import random_stomach  # noqa: E402
from StomachUnfoldLib import view  # noqa: E402
from StomachUnfoldLib.methods import isometric  # noqa: E402
from StomachUnfoldLib.pipeline import UnfoldParameters, unfold  # noqa: E402

HALF_MM = 22.0   # half the side of the crop round the beads missed before (mm)


def _run(seed: int, radius_mm: float):
    """Unfold random stomach ``seed`` with the rays' normals averaged over radius_mm; (image, crosses, counts)."""
    vol, truth = random_stomach(seed, size="small")
    keep = isometric.NORMAL_SMOOTH_MM
    isometric.NORMAL_SMOOTH_MM = radius_mm
    try:
        res = unfold(vol, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters())
    finally:
        isometric.NORMAL_SMOOTH_MM = keep
    u = res.unfolded
    mapped = res.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]})
    rep = marker_report(u, mapped)
    ij = {k: u.lps_to_index(np.asarray(p, float)[None])[0][:2] for k, p in mapped.items()}
    lab, regions = _marker_regions(u)
    areas = [r["area_mm2"] for r in regions]
    return (view.shade_first_hit(u), lab[::-1], float(u.spacing[0]), ij, rep,
            {"seen": rep["n_seen"], "total": rep["n_total"], "median_bead_mm2": float(np.median(areas))})


def draw_marked_view(ax, img, lab, s: float, ij: dict, rep: dict) -> None:
    """Draw a shaded view (RGB, rows top = high j; pixel ``s`` mm) on ``ax`` in mm, the judge's bead regions ``lab``
    (same rows) outlined in cyan and a cross at each marker's mapped place ``ij`` (pixels; NaN unmapped), green where
    ``rep`` (:func:`marker_report`) has it seen, red where not."""
    h, w = img.shape[:2]
    ext = (-0.5 * s, (w - 0.5) * s, -0.5 * s, (h - 0.5) * s)
    ax.imshow(img, extent=ext)
    for k in np.unique(lab[lab > 0]):
        ax.contour(lab == k, levels=[0.5], colors=["cyan"], linewidths=0.8, origin="upper", extent=ext)
    for mid, p in ij.items():
        if np.all(np.isfinite(p)):
            ok = rep["markers"][mid]["seen"]
            ax.plot(p[0] * s, p[1] * s, "+", color="lime" if ok else "red", ms=10, mew=1.5)


def main(argv=None) -> int:
    """Write the before/after PNG and its table (markers seen, median bead area mm^2) into --out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "images"))
    ap.add_argument("--seeds", default="31051,31029,6")
    a = ap.parse_args(argv)
    seeds = [int(s) for s in a.seeds.split(",")]
    fig, axes = plt.subplots(len(seeds), 2, figsize=(9, 4.4 * len(seeds)), squeeze=False)
    rows = ["| seed | markers seen, own normals | ... averaged over 2 mm | median bead area (mm^2), before -> after |",
            "|---|---|---|---|"]
    for r, seed in enumerate(seeds):
        counts, centre = [], None
        for c, radius in enumerate((0.0, isometric.NORMAL_SMOOTH_MM)):
            img, lab, s, ij, rep, n = _run(seed, radius)
            counts.append(n)
            if centre is None:                                   # the beads missed with the own normals
                missed = [ij[m] for m, x in rep["markers"].items() if not x["seen"] and np.all(np.isfinite(ij[m]))]
                centre = np.mean(missed, axis=0) * s if missed else np.array(img.shape[1::-1]) * s / 2
            ax = axes[r, c]
            draw_marked_view(ax, img, lab, s, ij, rep)
            ax.set_xlim(centre[0] - HALF_MM, centre[0] + HALF_MM)
            ax.set_ylim(centre[1] - HALF_MM, centre[1] + HALF_MM)
            ax.set_title(f"seed {seed}: {'own normals' if radius == 0 else 'normals averaged over 2 mm'}; "
                         f"{n['seen']}/{n['total']} markers", fontsize=9)
            ax.set_xlabel("mm")
        rows.append(f"| {seed} | {counts[0]['seen']}/{counts[0]['total']} | {counts[1]['seen']}/{counts[1]['total']} | "
                    f"{counts[0]['median_bead_mm2']:.1f} -> {counts[1]['median_bead_mm2']:.1f} |")
    fig.suptitle("Beads the judge merged: rays along the iso-surface's own normals | along normals averaged "
                 "over 2 mm\n(the same flat map; cyan: the judge's bead regions; + a true marker's place: green seen, red not)",
                 fontsize=10)
    fig.tight_layout()
    os.makedirs(a.out, exist_ok=True)
    fig.savefig(os.path.join(a.out, "normals_before_after.png"), dpi=80)
    with open(os.path.join(a.out, "normals_before_after.md"), "w") as fh:
        fh.write("Written by `docs/make_normals_figure.py`.\n\n" + "\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
