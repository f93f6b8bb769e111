"""Before/after picture of rule 41: where the map from the CT puts each marker on the same view.

Unfolds drawn stomachs in real CT 03 (4.25 mm slices; tuning seeds 40008 and 40005 of the bench part `hybrids-many`)
once with ``isometric`` and reads the map two ways: every point by its foot on the nearest triangle (before
2026-12-06's eighteenth session, ``surface.RAY_SIDE = None``) and rule 41 (``"shown"``, the default: a point in the wall
along the view's ray through it, unless only its foot shows it). The view is the same in both. Writes
``docs/images/marker_map_rule41.png`` (the shaded view, before | after, one row per volume; the judge's bead regions
outlined; a cross at each true marker's mapped place, green where the judge sees it, red where not) and
``marker_map_rule41.md`` (markers seen each way). From the repository root, ../shared beside it:

    .venv/bin/python docs/make_marker_map_figure.py [--out docs/images] [--seeds 40008,40005]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from make_normals_figure import draw_marked_view  # noqa: E402  (docs/, the script's own folder)
from StomachUnfoldEval import bench  # noqa: E402
from StomachUnfoldEval.markers import _marker_regions, marker_report  # noqa: E402
from StomachUnfoldLib import surface, view  # noqa: E402
from StomachUnfoldLib.pipeline import UnfoldParameters, unfold  # noqa: E402

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "..", "shared", "data")
MODES = ((None, "every point by its foot (before)"), ("shown", "rule 41: along the ray unless only the foot shows it"))


def _run(seed: int):
    """Unfold CT 03 hybrid ``seed``; (image, bead labels, pixel mm, {mode: (marker places ij, marker report)})."""
    name = [n for n in bench._real_cts(DATA) if n.startswith("03")][0]
    ct, cardia, pylorus, mask, markers = bench._load({"hybrid": seed, "ct": os.path.join(DATA, name),
                                                      "_cache": bench._phantom_cache(None)})
    truth = markers.pop("_truth")
    res = unfold(ct, cardia, pylorus, UnfoldParameters(method="isometric"), mask=mask)
    u = res.unfolded
    keep, out = surface.RAY_SIDE, {}
    try:
        for mode, _ in MODES:
            surface.RAY_SIDE = mode                    # the map reads it when called; the view is already drawn
            mapped = res.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]})
            ij = {k: u.lps_to_index(np.asarray(p, float)[None])[0][:2] for k, p in mapped.items()}
            out[mode] = (ij, marker_report(u, mapped))
    finally:
        surface.RAY_SIDE = keep
    lab, _ = _marker_regions(u)
    return view.shade_first_hit(u), lab[::-1], float(u.spacing[0]), out


def main(argv=None) -> int:
    """Write the before/after PNG and its table (markers seen each way) into --out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "images"))
    ap.add_argument("--seeds", default="40008,40005")
    a = ap.parse_args(argv)
    if not os.path.isdir(DATA):
        print(f"error: no real CTs at {DATA}: put ../shared beside the repository", file=sys.stderr)
        return 2
    seeds = [int(s) for s in a.seeds.split(",")]
    fig, axes = plt.subplots(len(seeds), 2, figsize=(13, 5.2 * len(seeds)), squeeze=False)
    rows = ["| CT 03 hybrid | markers seen, by the foot | rule 41 |", "|---|---|---|"]
    for r, seed in enumerate(seeds):
        img, lab, s, out = _run(seed)
        for c, (mode, title) in enumerate(MODES):
            ij, rep = out[mode]
            ax = axes[r, c]
            draw_marked_view(ax, img, lab, s, ij, rep)
            ax.set_title(f"hybrid 03-{seed}: {title}; {rep['n_seen']}/{rep['n_total']} markers", fontsize=9)
            ax.set_xlabel("mm")
        rows.append(f"| {seed} | {out[None][1]['n_seen']}/{out[None][1]['n_total']} | "
                    f"{out['shown'][1]['n_seen']}/{out['shown'][1]['n_total']} |")
    fig.suptitle("Where the map from the CT puts each marker on the same view (CT 03, 4.25 mm slices; beads as large "
                 "as a slice)\ncyan: the judge's bead regions; + a true marker's mapped place: green seen (a bead region "
                 "within 4 mm), red not", fontsize=10)
    fig.tight_layout()
    os.makedirs(a.out, exist_ok=True)
    fig.savefig(os.path.join(a.out, "marker_map_rule41.png"), dpi=80)
    with open(os.path.join(a.out, "marker_map_rule41.md"), "w") as fh:
        fh.write("Written by `docs/make_marker_map_figure.py`.\n\n" + "\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
