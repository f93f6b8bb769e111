"""Figure (docs/images/water_by_evidence.png): CT 03 hybrid 46187 across its retained water, the drawn lumen against
the lumen each water rule finds (preprocessing.WATER_RUNS). From the repository root, ../shared beside it:
    python docs/make_water_figure.py docs/images/water_by_evidence.png
"""
import os
import sys, numpy as np
from StomachUnfoldEval import bench
from StomachUnfoldEval.random_stomach import StomachModel
import StomachUnfoldLib.preprocessing as pre
import matplotlib; matplotlib.use("Agg"); import matplotlib.pyplot as plt
DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "..", "shared", "data")
name = [n for n in bench._real_cts(DATA) if n.startswith("03")][0]
ct, c, p, mask, markers = bench._load({"hybrid": 46187, "ct": os.path.join(DATA, name), "_cache": bench._phantom_cache(None)})
truth = markers["_truth"]; fy = truth["fluid_level_lps_y"]; model = StomachModel(truth["draw"])
lums = {}
for mode in ("threshold", "evidence"):
    pre.WATER_RUNS = mode
    lums[mode] = pre.air_region(ct, c, p)[0]
ijk = ct.lps_to_index(np.array([[a, b, e] for a in (model.lo[0], model.hi[0]) for b in (model.lo[1], model.hi[1]) for e in (model.lo[2], model.hi[2])]))
lo = np.maximum(np.floor(ijk.min(0)).astype(int), 0); hi = np.minimum(np.ceil(ijk.max(0)).astype(int) + 1, np.array(ct.size))
x = 341
k, j = np.mgrid[lo[2]:hi[2], lo[1]:hi[1]]
P = ct.index_to_lps(np.stack([np.full(k.size, x), j.ravel(), k.ravel()], 1).astype(float))
fr = model.fast(P)[0].reshape(k.shape)
hu = ct.array[lo[2]:hi[2], lo[1]:hi[1], x]
fig, axs = plt.subplots(1, 2, figsize=(12, 6.5))
for a, (mode, lab) in zip(axs, (("threshold", "main: each ray ends at its first voxel over 25 HU"), ("evidence", "rule 39: where the summed evidence for water is largest"))):
    L = lums[mode][lo[2]:hi[2], lo[1]:hi[1], x]
    a.imshow(hu, cmap="gray", vmin=-100, vmax=150, aspect=ct.spacing[2] / ct.spacing[1], interpolation="nearest")
    a.contour(fr, [0], colors="lime", linewidths=1.5)
    a.contour(L.astype(float), [0.5], colors="red", linewidths=1.2)
    a.set_title(lab, fontsize=10); a.set_xticks([]); a.set_yticks([])
fig.suptitle("CT 03 hybrid 46187 (4.25 mm slices, 39 HU noise on water at 9 HU), a slice across the body:\n"
             "green the drawn lumen, red the lumen found (air + water); the water lies right of the flat level", fontsize=10)
fig.tight_layout()
fig.savefig(sys.argv[1], dpi=80)
