"""Zero clicks on the random phantoms: TotalSegmentator-like label maps and the found points against the truth.

``totalseg_labels(labels, truth, convention)`` turns a random stomach's label array (``random_stomach(...,
labels=True)``) into a label map numbered like TotalSegmentator's ``total`` task (v2 ``"total"`` or v1
``"total_v1"``): stomach = lumen (air, fluid), wall and beads; oesophagus and duodenum = the tube tissue at
the two openings; neighbours: liver, spleen, colon and the lower lung lobes. ``point_errors(seed, ...)`` finds
the points (from the gas, or from such a label map) and measures their distance (mm) to the true ones.
"""
from __future__ import annotations

import time

import numpy as np

from StomachUnfoldLib.landmarks import CLASS_MAPS, find_points

from .random_stomach import LABELS, random_stomach

__all__ = ["totalseg_labels", "point_errors", "found_versus_truth", "TOLERANCE_MM", "AUTO_TUNE_SEEDS",
           "AUTO_FRESH_SEEDS"]

#: A found point within this distance (mm) of the true one counts as found.
TOLERANCE_MM = 10.0
#: Seeds the gas path was tuned on (besides bench.TUNE_SEEDS, 0-29): looked at while the method was shaped.
AUTO_TUNE_SEEDS = tuple(range(100, 160)) + tuple(range(200, 230))
#: Seeds never looked at while the gas path was shaped (drawn once the method was final): the fresh check.
AUTO_FRESH_SEEDS = tuple(range(4000, 4030))


def totalseg_labels(vol, labels: np.ndarray, truth: dict, convention: str = "total") -> np.ndarray:
    """A TotalSegmentator-like label array (uint8, the volume's layout) from a random stomach's labels and truth."""
    cmap = CLASS_MAPS[convention]
    out = np.zeros(labels.shape, np.uint8)
    L = LABELS
    out[np.isin(labels, [L["liver"]])] = cmap["liver"]
    out[labels == L["spleen"]] = cmap["spleen"]
    out[np.isin(labels, [L["colon_gas"], L["colon_wall"]])] = cmap["colon"]
    lung = labels == L["lung"]
    if lung.any():
        x = vol.voxel_lps(lung)[:, 0]
        idx = np.nonzero(lung.ravel())[0]
        flat = out.ravel()
        flat[idx[x >= 0]] = cmap["lung_lower_lobe_left"]
        flat[idx[x < 0]] = cmap["lung_lower_lobe_right"]
    out[np.isin(labels, [L["lumen_air"], L["lumen_fluid"], L["wall"], L["marker"]])] = cmap["stomach"]
    tube = np.isin(labels, [L["tube_wall"], L["tube_lumen"]])
    if tube.any():
        P = vol.voxel_lps(tube)
        d_c = np.linalg.norm(P - np.asarray(truth["cardia_opening_lps"]), axis=1)
        d_p = np.linalg.norm(P - np.asarray(truth["pylorus_opening_lps"]), axis=1)
        idx = np.nonzero(tube.ravel())[0]
        flat = out.ravel()
        flat[idx[d_c <= d_p]] = cmap["esophagus"]
        flat[idx[d_c > d_p]] = cmap["duodenum"]
    return out


def point_errors(seed: int, size: str = "tiny", source: str = "gas", case=None) -> dict:
    """Find the points of random stomach ``seed`` from ``source`` ("gas", "total" or "total_v1" label maps) and
    return their errors (mm) to the true cardia and pylorus, the confidences and whether both lie within
    ``TOLERANCE_MM``; ``case``: an already drawn (vol, truth, labels)."""
    vol, truth, lab = case if case is not None else random_stomach(seed, size=size, labels=True)
    t0 = time.perf_counter()
    seg = totalseg_labels(vol, lab, truth, source) if source != "gas" else None
    found = find_points(vol, labels=seg)
    sec = time.perf_counter() - t0
    e_c = float(np.linalg.norm(found.cardia_lps - np.asarray(truth["cardia_lps"])))
    e_p = float(np.linalg.norm(found.pylorus_lps - np.asarray(truth["pylorus_lps"])))
    return {"seed": int(seed), "size": size, "source": source, "cardia_error_mm": e_c, "pylorus_error_mm": e_p,
            "cardia_confidence": found.cardia_confidence, "pylorus_confidence": found.pylorus_confidence,
            "confident": found.confident, "within_tolerance": bool(max(e_c, e_p) <= TOLERANCE_MM),
            "seconds": sec, "found": found}


def found_versus_truth(ct, truth: dict, labels=None):
    """Points found on ``ct`` (from the gas, or ``labels``) and how far (mm) they lie from the truth's points:
    (cardia LPS, pylorus LPS, a JSON-ready summary with the errors, confidences and evidence)."""
    found = find_points(ct, labels=labels)
    e_c = float(np.linalg.norm(found.cardia_lps - np.asarray(truth["cardia_lps"])))
    e_p = float(np.linalg.norm(found.pylorus_lps - np.asarray(truth["pylorus_lps"])))
    summary = {**found.to_dict(), "cardia_error_mm": e_c, "pylorus_error_mm": e_p, "confidence": found.confidence,
               "confident": found.confident, "within_tolerance": bool(max(e_c, e_p) <= TOLERANCE_MM)}
    return found.cardia_lps, found.pylorus_lps, summary


def point_benchmark(out_dir: str, quick: bool = False, size: str = "tiny", draw=None) -> dict:
    """Bench part ``autopoints``: the found points against the truth on the tuning seeds (0-29), the held-out seeds
    (1000-1029) and the fresh seeds (``AUTO_FRESH_SEEDS``; none when ``quick``), from the gas and from both
    TotalSegmentator numberings; writes autopoints.json and autopoints.md.

    ``draw(seed)``: the (volume, truth, labels) of a seed (default: ``random_stomach(seed, size, labels=True)``)."""
    import json
    import os

    from .bench import HELD_OUT_SEEDS, TUNE_SEEDS

    groups = (("tune", TUNE_SEEDS[:3] if quick else TUNE_SEEDS),
              ("held-out", HELD_OUT_SEEDS[:3] if quick else HELD_OUT_SEEDS),
              ("fresh", () if quick else AUTO_FRESH_SEEDS))
    rows = []
    for group, seeds in groups:
        for seed in seeds:
            case = draw(seed) if draw is not None else random_stomach(seed, size=size, labels=True)
            for source in ("gas", "total", "total_v1"):
                try:
                    r = point_errors(seed, size, source, case=case)
                    r.pop("found")
                    r["ok"] = True
                except Exception as e:  # a failure is data here
                    r = {"seed": int(seed), "source": source, "ok": False, "error": f"{type(e).__name__}: {e}"}
                rows.append(dict(r, group=group))
    summary = {}
    for group, seeds in groups:
        if not seeds:
            continue
        for source in ("gas", "total", "total_v1"):
            rs = [r for r in rows if r["group"] == group and r["source"] == source]
            ok = [r for r in rs if r["ok"]]
            summary[f"{group}/{source}"] = {
                "volumes": len(rs), "failed": len(rs) - len(ok),
                "both_within": sum(r["within_tolerance"] for r in ok),
                "cardia_within": sum(r["cardia_error_mm"] <= TOLERANCE_MM for r in ok),
                "pylorus_within": sum(r["pylorus_error_mm"] <= TOLERANCE_MM for r in ok),
                "cardia_error_median_mm": float(np.median([r["cardia_error_mm"] for r in ok])) if ok else None,
                "pylorus_error_median_mm": float(np.median([r["pylorus_error_mm"] for r in ok])) if ok else None,
                "refused": sum(not r["confident"] for r in ok),
                "refused_but_within": sum(not r["confident"] and r["within_tolerance"] for r in ok),
                "confident_but_off": sum(r["confident"] and not r["within_tolerance"] for r in ok),
                "seconds_median": float(np.median([r["seconds"] for r in ok])) if ok else None}
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "autopoints.json"), "w") as f:
        json.dump({"size": size, "tolerance_mm": TOLERANCE_MM, "tuned_on": "0-29, 100-159, 200-229",
                   "summary": summary, "rows": rows}, f, indent=1)
    L = [f"# Zero clicks: points found against the truth (random stomachs, size {size})\n",
         f"Both points within {TOLERANCE_MM:g} mm of the true cardia and pylorus; 'refused': below the confidence "
         "threshold (the command line refuses, the module asks); 'confident but off': accepted yet over the "
         "tolerance; 'refused but within': refused although both points were within the tolerance. 'tune': seeds "
         "0-29, which (with seeds 100-159 and 200-229) the gas path was tuned on; 'held-out': seeds 1000-1029, "
         "'fresh': seeds 4000-4029, both run once the method was final.\n",
         "| seeds / source | both within | cardia within | pylorus within | median error cardia / pylorus mm | "
         "refused | refused but within | confident but off | failed | s median |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for key, v in summary.items():
        def f1(x):
            return "" if x is None else f"{x:.1f}"
        L.append(f"| {key} | {v['both_within']}/{v['volumes']} | {v['cardia_within']} | {v['pylorus_within']} | "
                 f"{f1(v['cardia_error_median_mm'])} / {f1(v['pylorus_error_median_mm'])} | {v['refused']} | "
                 f"{v['refused_but_within']} | {v['confident_but_off']} | {v['failed']} | {f1(v['seconds_median'])} |")
    with open(os.path.join(out_dir, "autopoints.md"), "w") as f:
        f.write("\n".join(L) + "\n")
    return summary
