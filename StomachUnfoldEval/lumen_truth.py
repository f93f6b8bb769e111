"""A lumen found by the method against the lumen the phantom drew (random stomachs and hybrids).

The drawn lumen is the phantom's own model (``random_stomach.StomachModel`` rebuilt from ``truth["draw"]``): its
signed distance to the inner wall, negative inside (mm). A voxel more than ``margin_mm`` inside it is lumen for
certain, one more than ``margin_mm`` outside it wall for certain; the partial-volume shell between counts neither
way. Rules 39 and 40 (``docs/RULE39_water_by_evidence.md``) were measured with it under the retained water.
"""
from __future__ import annotations

import numpy as np

from StomachUnfoldLib.geometry import Volume

from .random_stomach import StomachModel, box_slabs

__all__ = ["lumen_against_drawn"]


def lumen_against_drawn(ct: Volume, truth: dict, lumen: np.ndarray, region: str = "water",
                        margin_mm: float = 1.5, below_level_mm: float = 1.0) -> dict:
    """Voxels of the drawn lumen a lumen mask (bool, on ``ct``'s grid) leaves out and wall voxels it takes in.

    ``region``: ``"water"`` counts only voxels more than ``below_level_mm`` below the drawn air-fluid level (LPS y
    larger; none when the phantom has no fluid), ``"all"`` the whole lumen; both within the drawn stomach's box (a
    leak beyond it is not counted). Distances in mm.

    Returns a dict: ``drawn`` (voxels certainly inside the drawn lumen, in the region), ``missed`` (of those, not in
    ``lumen``), ``over`` (voxels of ``lumen`` certainly outside the drawn lumen, in the region), ``missed_fraction``,
    ``missed_depth_mm`` (median and 95th percentile of how deep inside the drawn lumen the missed voxels lie; zeros
    when none) and ``level_lps_y`` (mm, or None).
    """
    lumen = np.asarray(lumen, bool)
    if lumen.shape != tuple(ct.size[::-1]):
        raise ValueError(f"the lumen mask's shape {lumen.shape} is not the CT's {tuple(ct.size[::-1])}")
    if region not in ("water", "all"):
        raise ValueError(f"region must be 'water' or 'all', not {region!r}")
    level = truth.get("fluid_level_lps_y")
    out = {"drawn": 0, "missed": 0, "over": 0, "missed_fraction": 0.0, "missed_depth_mm": [0.0, 0.0],
           "level_lps_y": level}
    if region == "water" and level is None:
        return out
    model = StomachModel(truth["draw"])
    lo, hi = model.index_box(ct)
    if np.any(hi <= lo):
        return out
    drawn = missed = over = 0
    depths = []
    for k0, k1, P in box_slabs(ct, lo, hi):             # a slab of slices at a time: the box can be large
        fr = model.fast(P)[0]
        inside = P[:, 1] > level + below_level_mm if region == "water" else np.ones(len(P), bool)
        found = lumen[k0:k1, lo[1]:hi[1], lo[0]:hi[0]].ravel()
        sure_in = inside & (fr < -margin_mm)
        miss = sure_in & ~found
        drawn += int(np.count_nonzero(sure_in))
        missed += int(np.count_nonzero(miss))
        over += int(np.count_nonzero(inside & (fr > margin_mm) & found))
        depths.append(-fr[miss])
    n = drawn
    d = np.concatenate(depths) if depths else np.zeros(0)
    out.update(drawn=n, missed=missed, over=over, missed_fraction=missed / n if n else 0.0,
               missed_depth_mm=[float(np.percentile(d, 50)), float(np.percentile(d, 95))] if len(d) else [0.0, 0.0])
    return out
