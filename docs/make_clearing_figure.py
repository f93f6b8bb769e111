"""Before/after picture of the label clearing fix: rings ("wood grain") across the view of a labelled CT.

Unfolds the two labelled real CTs of ``../shared/data`` (isometric, as the benchmark's ``real`` part runs them) twice:
with the depth profiles cleared by the nearest voxel of the stomach label, as before 2026-12-04 (copied below), and
as ``StomachUnfoldLib.surface.sample_profiles`` clears them now (in proportion across the label's blurred field, on
the surface the profiles start from). Renders both views with ``StomachUnfoldLib.view`` and writes
``docs/images/label_clearing_before_after.png`` (before | after, one row per CT) and ``label_clearing_before_after.md``
(the ripple of the view's height map over its smooth mucosa, mm, and the judge's visible fraction and holes).

    .venv/bin/python docs/make_clearing_figure.py [--out docs/images] [--data ../shared/data]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from StomachUnfoldLib import surface, view  # noqa: E402
from StomachUnfoldLib.geometry import Volume  # noqa: E402


def sample_profiles_before(crop: Volume, surf: np.ndarray, normal: np.ndarray, depths: np.ndarray,
                           lumen: np.ndarray | None, batch: int = 4_000_000) -> np.ndarray:
    """CT HU (N, D) along the profiles, lumen samples cleared by the nearest voxel's label (before the fix)."""
    n, d = len(surf), len(depths)
    out = np.empty((n, d), np.float32)
    rows = max(1, batch // max(d, 1))
    for a in range(0, n, rows):
        b = min(n, a + rows)
        p = surf[a:b, None, :] + depths[None, :, None] * normal[a:b, None, :]
        v = crop.sample(p.reshape(-1, 3), order=1, cval=-1024.0)
        if lumen is not None:
            ijk = np.rint(crop.lps_to_index(p.reshape(-1, 3))).astype(np.int64)
            size = np.array(crop.size)
            ins = np.all((ijk >= 0) & (ijk < size), axis=1)
            ijk = np.clip(ijk, 0, size - 1)
            v[ins & lumen[ijk[:, 2], ijk[:, 1], ijk[:, 0]]] = -1024.0
        out[a:b] = v.reshape(b - a, d)
    return out


def _run(case: dict, before: bool):
    """(RGB view, ripple mm, visible fraction, hole fraction) of one real CT, cleared before or after the fix."""
    from StomachUnfoldEval import bench

    now = surface.sample_profiles
    surface.sample_profiles = sample_profiles_before if before else now
    try:
        res = None
        ct, cardia, pylorus, mask, _ = bench._load(case["source"])
        from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

        res = unfold(ct, cardia, pylorus, UnfoldParameters(method="isometric", wall_thickness_mm=4.0), mask=mask)
    finally:
        surface.sample_profiles = now
    vol = res.unfolded
    k0, hu = view.first_hit(vol)
    hgt, hit = view.surface_height(vol, k_hit=k0)
    smooth = view.smooth_mucosa_mask(hit, hu, float(vol.spacing[0]))
    ripple = view.ripple_mm(hgt, smooth, vol.spacing[1::-1])
    q = res.report["quality"]
    return view.shade_first_hit(vol), ripple, q["visible_fraction"], q["hole_area_fraction"]


def main(argv=None) -> int:
    """Write the before/after figure and its caption; returns 0 (1 when the real CTs are not there)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from StomachUnfoldEval import bench

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "images"))
    ap.add_argument("--data", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared",
                                                   "data"))
    a = ap.parse_args(argv)
    cases = [c for c in bench._cases(False, False, a.data, ("real",))
             if c["method"] == "isometric" and c["source"].get("mask")]
    if not cases:
        print(f"no labelled real CTs in {a.data}", file=sys.stderr)
        return 1
    fig, axes = plt.subplots(len(cases), 2, figsize=(12, 5.5 * len(cases)), squeeze=False)
    lines = ["*The isometric view of the labelled real CTs before and after the label clearing fix "
             "(`docs/make_clearing_figure.py`). Left: profiles cleared by the nearest voxel of the label (its "
             "slices' staircase); right: cleared in proportion across the label's blurred field, on the surface the "
             "profiles start from (`surface.sample_profiles`). Ripple: RMS (mm) of the view's height map less its "
             "2 mm low-pass over the smooth mucosa; visible and holes: the judge's (`quality.py`).*\n",
             "| CT | ripple before / after (mm) | visible before / after % | holes before / after % |",
             "|---|---|---|---|"]
    for row, case in enumerate(cases):
        got = [_run(case, before) for before in (True, False)]
        for col, (img, ripple, vis, holes) in enumerate(got):
            ax = axes[row, col]
            ax.imshow(img)
            ax.set_title(f"{case['name'].split('/')[0]}: {'before' if col == 0 else 'after'} "
                         f"(ripple {ripple:.3f} mm, visible {100 * vis:.1f} %)", fontsize=9)
            ax.axis("off")
        lines.append(f"| {case['name'].split('/')[0]} | {got[0][1]:.3f} / {got[1][1]:.3f} | "
                     f"{100 * got[0][2]:.1f} / {100 * got[1][2]:.1f} | {100 * got[0][3]:.1f} / {100 * got[1][3]:.1f} |")
    fig.tight_layout()
    os.makedirs(a.out, exist_ok=True)
    fig.savefig(os.path.join(a.out, "label_clearing_before_after.png"), dpi=80)
    with open(os.path.join(a.out, "label_clearing_before_after.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines[1:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
