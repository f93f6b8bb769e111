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

__all__ = ["totalseg_labels", "point_errors", "found_versus_truth", "TOLERANCE_MM"]

#: A found point within this distance (mm) of the true one counts as found.
TOLERANCE_MM = 10.0


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
