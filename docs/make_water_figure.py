"""Figure (docs/images/water_by_evidence.png): CT 03 hybrid 46187 across its retained water, the drawn lumen against
the lumen each water rule finds (preprocessing.WATER_RUNS). From the repository root, ../shared beside it:
    python docs/make_water_figure.py docs/images/water_by_evidence.png
"""
import os
import sys

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import StomachUnfoldLib.preprocessing as pre  # noqa: E402
from StomachUnfoldEval import bench  # noqa: E402
from StomachUnfoldEval.random_stomach import StomachModel  # noqa: E402

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "..", "shared", "data")
SEED, COLUMN_I = 46187, 341          # the hybrid and the CT column (i) of the slice shown


def main(out: str) -> None:
    name = [n for n in bench._real_cts(DATA) if n.startswith("03")][0]
    src = {"hybrid": SEED, "ct": os.path.join(DATA, name), "_cache": bench._phantom_cache(None)}
    ct, cardia, pylorus, _, markers = bench._load(src)
    model = StomachModel(markers["_truth"]["draw"])
    lumens = {}
    for mode in ("threshold", "evidence"):
        pre.WATER_RUNS = mode
        lumens[mode] = pre.air_region(ct, cardia, pylorus)[0]
    lo, hi = model.index_box(ct)
    k, j = np.mgrid[lo[2]:hi[2], lo[1]:hi[1]]
    P = ct.index_to_lps(np.stack([np.full(k.size, COLUMN_I), j.ravel(), k.ravel()], 1).astype(float))
    drawn = model.fast(P)[0].reshape(k.shape)          # signed distance to the drawn lumen (mm, negative inside)
    hu = ct.array[lo[2]:hi[2], lo[1]:hi[1], COLUMN_I]
    fig, axs = plt.subplots(1, 2, figsize=(12, 6.5))
    titles = {"threshold": "main: each ray ends at its first voxel over 25 HU",
              "evidence": "rule 39: where the summed evidence for water is largest"}
    for ax, mode in zip(axs, ("threshold", "evidence")):
        found = lumens[mode][lo[2]:hi[2], lo[1]:hi[1], COLUMN_I]
        ax.imshow(hu, cmap="gray", vmin=-100, vmax=150, aspect=ct.spacing[2] / ct.spacing[1], interpolation="nearest")
        ax.contour(drawn, [0], colors="lime", linewidths=1.5)
        ax.contour(found.astype(float), [0.5], colors="red", linewidths=1.2)
        ax.set_title(titles[mode], fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle("CT 03 hybrid 46187 (4.25 mm slices, 39 HU noise on water at 9 HU), a slice across the body:\n"
                 "green the drawn lumen, red the lumen found (air + water); the water lies right of the flat level",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=80)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/images/water_by_evidence.png")
