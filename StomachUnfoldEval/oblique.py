"""The ``oblique``, ``prone``, ``rolled``, ``contrast``, ``contents`` and ``deep`` parts of ``stomach-unfold bench``:
each method on random stomachs resampled onto oblique voxel grids, as a prone patient's scans, as a patient's rolled
about the S axis, with positive oral contrast in their retained fluid, with contents there that read like the wall, and
with a pool up to half the stomach's height.

The family draws its volumes with axis-aligned, permuted or flipped direction matrices only. A CT reformatted along
an oblique plane, a volume cropped with a turned region of interest in Slicer, or a scan with gantry tilt resampled
to an orthogonal grid has voxel axes that are none of the patient's. The part resamples each held-out random stomach
(never tuned on) onto a grid turned by an angle drawn per seed (OBLIQUE_DEGREES, about a random axis): the same
anatomy at the same LPS places, the voxels the same size, sampled anew (trilinear, so a little more blur). The true
points and markers are unchanged (LPS mm). Its table sets each method's oblique runs beside its own rows on the same
volumes as drawn (the ``stomachs`` part's): grades, visible mucosa, markers, distortion, time, and the volumes that
lose against their axis-aligned run.

The family draws supine patients: the water lies on the posterior wall (LPS +y). The ``prone`` part mirrors each
held-out stomach front to back (:func:`front_to_back`: the same voxels with LPS y negated, the truth mirrored with
them), so its water lies on the anterior wall, as a prone patient's does, and the stomach keeps its left and right
(its greater curvature to the patient's left, where the incision's fallback looks); only its front and back swap.

A patient is rarely lying square in the scanner. The ``rolled`` part turns each held-out stomach's LPS about the S
axis by an angle drawn per seed (ROLL_DEGREES, either way; :func:`rolled`): the same voxels, the anatomy turned in the
patient's frame and gravity not, so the water's level is tilted that much from LPS y = const.

The family's retained fluid is water (5-15 HU). Many abdominal CTs are taken after positive oral contrast, whose fluid
reads 200-1000 HU. The ``contrast`` part draws each held-out stomach that has a pool again with its fluid at a HU drawn
per seed (CONTRAST_HU, :func:`contrast_hu_of`): the same anatomy, markers and level. The ``contents`` part does the
same at 30-150 HU (CONTENTS_HU: food, mucus or blood), where no method can find the wall under the contents; it counts
the runs that say so (CONTENTS_SAID).

The family's pools fill 15-35 % of the stomach's height. After a drink of water (a water-distension protocol) or with
gastric stasis the pool is deeper: the cardia, on the posterior wall of the fundus, and the pre-pyloric canal go under
water, and the gas splits into pockets. The ``deep`` part draws every held-out stomach with a pool filling a fraction of
its height drawn per seed (DEEP_FRACTION, :func:`deep_fraction_of`); it counts the runs whose warnings say a point was
joined to its gas through the water (DEEP_SAID).
"""
from __future__ import annotations

import copy

import numpy as np

from StomachUnfoldLib.geometry import Volume

#: The turn of each volume's grid (degrees, drawn uniformly between the two per seed, about a random axis).
OBLIQUE_DEGREES = (15.0, 40.0)
#: The methods run on the turned grids (mass-spring takes minutes per volume and is left out).
OBLIQUE_METHODS = ("isometric", "cylindrical", "lscm")
#: The rows' group in results.json (part ``oblique``; part ``prone``: PRONE_GROUP).
GROUP = "oblique"
PRONE_GROUP = "prone"
ROLLED_GROUP = "rolled"
CONTRAST_GROUP = "contrast"
CONTENTS_GROUP = "contents"
DEEP_GROUP = "deep"
#: The HU of a volume's fluid in part ``contrast`` (positive oral contrast; drawn uniformly between the two per seed).
CONTRAST_HU = (300.0, 900.0)
#: The HU of a volume's fluid in part ``contents`` (food, mucus or blood: it reads like the wall; drawn per seed).
CONTENTS_HU = (30.0, 150.0)
#: The warning that says such contents (StomachUnfoldLib.preprocessing.fluid_below_level), counted per method.
CONTENTS_SAID = "has contents of about"
#: The fraction of the stomach's height its pool fills in part ``deep`` (drawn uniformly between the two per seed).
DEEP_FRACTION = (0.40, 0.55)
#: The warning that says a point lies under the water and was joined to its gas through it (StomachUnfoldLib.
#: preprocessing.air_region), counted per method in part ``deep``.
DEEP_SAID = "lies under the retained fluid"
#: How far each volume is rolled about the S axis (degrees, drawn uniformly between the two per seed, either way).
ROLL_DEGREES = (5.0, 20.0)
#: LPS mirrored front to back (y negated): a supine scene whose water then lies anteriorly, as a prone patient's.
FRONT_TO_BACK = np.diag([1.0, -1.0, 1.0])
#: A volume counts as losing on its turned grid when its visible mucosa falls by more than this (fraction).
VISIBLE_DROP = 0.005

__all__ = ["turned_grid", "grid_turn", "front_to_back", "rolled", "roll_of", "oblique_cases", "prone_cases",
           "rolled_cases", "contrast_cases", "contrast_hu_of", "contents_cases", "contents_hu_of", "deep_cases",
           "deep_fraction_of", "oblique_summary", "oblique_markdown", "OBLIQUE_DEGREES", "OBLIQUE_METHODS",
           "ROLL_DEGREES", "CONTRAST_HU", "CONTENTS_HU", "DEEP_FRACTION", "GROUP", "PRONE_GROUP", "ROLLED_GROUP",
           "CONTRAST_GROUP", "CONTENTS_GROUP", "DEEP_GROUP"]


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rotation matrix (3x3) by ``degrees`` about the unit vector along ``axis`` (right-handed)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    t = np.radians(float(degrees))
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(t) * K + (1.0 - np.cos(t)) * K @ K


def grid_turn(seed: int) -> dict:
    """The turn of seed's grid: ``{"degrees": angle in OBLIQUE_DEGREES, "axis": unit 3-vector in LPS}``."""
    rng = np.random.default_rng(7_000_003 + int(seed))
    axis = rng.normal(size=3)
    return {"degrees": float(rng.uniform(*OBLIQUE_DEGREES)), "axis": (axis / np.linalg.norm(axis)).tolist()}


def turned_grid(ct: Volume, degrees: float, axis=(1.0, 2.0, 3.0), background_hu: float = -1024.0) -> Volume:
    """The CT (HU) resampled trilinearly onto a grid of the same voxel size turned by ``degrees`` about ``axis`` (LPS).

    The new grid's direction is the rotation times the CT's, its box the smallest one of those axes that holds the
    CT's whole box; voxels outside the CT read ``background_hu``. Every structure keeps its LPS place (mm).
    """
    import SimpleITK as sitk

    D = _rotation(axis, degrees) @ np.asarray(ct.direction, float)
    sp = np.asarray(ct.spacing, float)
    n = np.array(ct.array.shape[::-1], float) - 1.0
    corners = np.array([[i, j, k] for i in (0.0, n[0]) for j in (0.0, n[1]) for k in (0.0, n[2])])
    along = ct.index_to_lps(corners) @ D                  # the corners' coordinates along the new axes (mm)
    lo, hi = along.min(0), along.max(0)
    size = [int(x) for x in np.ceil((hi - lo) / sp).astype(int) + 1]
    ref = sitk.Image(size, sitk.sitkFloat32)
    ref.SetSpacing([float(x) for x in sp])
    ref.SetOrigin([float(x) for x in D @ lo])
    ref.SetDirection([float(x) for x in D.ravel()])
    img = sitk.Cast(ct.to_sitk(), sitk.sitkFloat32)
    out = sitk.Resample(img, ref, sitk.Transform(), sitk.sitkLinear, float(background_hu))
    vol = Volume.from_sitk(out)
    return vol.with_array(np.rint(vol.array).astype(np.int16))


def _mirrored_truth(x, key: str = "", M: np.ndarray = FRONT_TO_BACK):
    """A truth record (dicts, lists) with every LPS or RAS point or vector (a key ending in lps or ras: the last axis
    of length 3) taken through M (a rotation or mirror about the S axis, which maps RAS as it maps LPS), and
    ``fluid_level_lps_y`` (mm) negated for the front-to-back mirror, None otherwise (the level no longer lies at one
    LPS y)."""
    if isinstance(x, dict):
        mirror = bool(np.allclose(M, FRONT_TO_BACK))
        return {k: ((-v if mirror and v is not None else None) if k == "fluid_level_lps_y"
                    else _mirrored_truth(v, k, M)) for k, v in x.items()}
    if key.lower().endswith(("lps", "ras")):
        a = np.asarray(x, float)
        if a.ndim >= 1 and a.shape[-1] == 3:
            return (a @ M.T).tolist()
    if isinstance(x, list):
        return [_mirrored_truth(v, key, M) for v in x]
    return x


def roll_of(seed: int) -> float:
    """The roll of seed's patient about the S axis (degrees, signed, its size within ROLL_DEGREES)."""
    rng = np.random.default_rng(9_000_011 + int(seed))
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(*ROLL_DEGREES))


def rolled(ct: Volume, truth: dict, degrees: float) -> tuple[Volume, dict]:
    """The CT (HU) and its truth as the scan of a patient rolled ``degrees`` about the S axis: the same voxels with the
    LPS frame turned that much about z (the anatomy turns in the patient's frame, gravity stays the scanner's, so
    the water's level tilts from LPS y = const); every LPS point (mm) of the truth turned too."""
    t = np.radians(float(degrees))
    R = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    vol = Volume(ct.array, ct.spacing, R @ np.asarray(ct.origin, float), R @ np.asarray(ct.direction, float))
    return vol, _mirrored_truth(copy.deepcopy(truth), "", R)


def rolled_cases(quick: bool, seeds, cache: str, case) -> list[dict]:
    """The ``rolled`` part's cases (``case`` = bench.Case): every OBLIQUE_METHODS x seed, each patient rolled by
    :func:`roll_of`."""
    seeds = list(seeds[:2]) if quick else list(seeds)
    return [case(f"stomach-{seed}/{m}-rolled", {"random": int(seed), "size": "small", "_cache": cache,
                                                "roll_deg": roll_of(seed)}, {}, method=m, group=ROLLED_GROUP)
            for m in OBLIQUE_METHODS for seed in seeds]


def contrast_hu_of(seed: int) -> float:
    """The HU of seed's fluid in part ``contrast`` (positive oral contrast, within CONTRAST_HU)."""
    return float(np.random.default_rng(9_000_023 + int(seed)).uniform(*CONTRAST_HU))


def contrast_cases(quick: bool, seeds, cache: str, case) -> list[dict]:
    """The ``contrast`` part's cases (``case`` = bench.Case): every OBLIQUE_METHODS x seed whose stomach has a pool,
    drawn again with its fluid at :func:`contrast_hu_of` HU."""
    return _pool_cases(quick, seeds, cache, case, contrast_hu_of, CONTRAST_GROUP)


def _pool_cases(quick: bool, seeds, cache: str, case, hu_of, group: str) -> list[dict]:
    """Every OBLIQUE_METHODS x seed whose stomach has a pool, drawn again with its fluid at ``hu_of(seed)`` HU, in
    ``group`` (also the name's suffix)."""
    from .random_stomach import draw_parameters

    seeds = [int(s) for s in seeds if draw_parameters(int(s), "small")["fluid"]]
    seeds = seeds[:2] if quick else seeds
    return [case(f"stomach-{seed}/{m}-{group}", {"random": seed, "size": "small", "_cache": cache,
                                                 "fluid_hu": round(hu_of(seed), 1)}, {}, method=m, group=group)
            for m in OBLIQUE_METHODS for seed in seeds]


def contents_hu_of(seed: int) -> float:
    """The HU of seed's fluid in part ``contents`` (contents that read like the wall, within CONTENTS_HU)."""
    return float(np.random.default_rng(9_100_037 + int(seed)).uniform(*CONTENTS_HU))


def contents_cases(quick: bool, seeds, cache: str, case) -> list[dict]:
    """The ``contents`` part's cases (``case`` = bench.Case): every OBLIQUE_METHODS x seed whose stomach has a pool,
    drawn again with its fluid at :func:`contents_hu_of` HU (no method can find the wall under it: the part shows what
    each does there, and whether it says so)."""
    return _pool_cases(quick, seeds, cache, case, contents_hu_of, CONTENTS_GROUP)


def deep_fraction_of(seed: int) -> float:
    """The fraction of seed's stomach height its pool fills in part ``deep`` (within DEEP_FRACTION)."""
    return float(np.random.default_rng(9_200_041 + int(seed)).uniform(*DEEP_FRACTION))


def deep_cases(quick: bool, seeds, cache: str, case) -> list[dict]:
    """The ``deep`` part's cases (``case`` = bench.Case): every OBLIQUE_METHODS x seed, each stomach drawn with a pool
    filling :func:`deep_fraction_of` its height (water)."""
    seeds = list(seeds[:2]) if quick else list(seeds)
    return [case(f"stomach-{seed}/{m}-{DEEP_GROUP}", {"random": int(seed), "size": "small", "_cache": cache,
                                                      "fluid_depth": round(deep_fraction_of(seed), 3)}, {}, method=m,
                  group=DEEP_GROUP) for m in OBLIQUE_METHODS for seed in seeds]


def front_to_back(ct: Volume, truth: dict) -> tuple[Volume, dict]:
    """The CT (HU) and its truth as a prone patient's scan: the same voxels with LPS y negated (FRONT_TO_BACK), so the
    water a supine drawing put on the posterior wall lies on the anterior one; every LPS point (mm) of the truth
    mirrored too."""
    vol = Volume(ct.array, ct.spacing, FRONT_TO_BACK @ np.asarray(ct.origin, float),
                 FRONT_TO_BACK @ np.asarray(ct.direction, float))
    return vol, _mirrored_truth(copy.deepcopy(truth))


def prone_cases(quick: bool, seeds, cache: str, case) -> list[dict]:
    """The ``prone`` part's cases (``case`` = bench.Case): every OBLIQUE_METHODS x seed, each stomach mirrored front
    to back (:func:`front_to_back`)."""
    seeds = list(seeds[:2]) if quick else list(seeds)
    return [case(f"stomach-{seed}/{m}-prone", {"random": int(seed), "size": "small", "_cache": cache, "prone": True},
                 {}, method=m, group=PRONE_GROUP) for m in OBLIQUE_METHODS for seed in seeds]


def oblique_cases(quick: bool, seeds, cache: str, case) -> list[dict]:
    """The part's cases (``case`` = bench.Case): every OBLIQUE_METHODS x seed, each seed's grid turned by grid_turn."""
    seeds = list(seeds[:2]) if quick else list(seeds)
    return [case(f"stomach-{seed}/{m}-oblique", {"random": int(seed), "size": "small", "_cache": cache,
                                                 "turn": grid_turn(seed)}, {}, method=m, group=GROUP)
            for m in OBLIQUE_METHODS for seed in seeds]


def _volume(row: dict) -> str:
    """The volume a row ran on (``stomach-SEED``)."""
    return row["name"].split("/")[0]


def oblique_summary(rows: list[dict], aligned_group: str, group: str = GROUP) -> list[dict]:
    """Per method, the oblique runs and the same method's rows on the same volumes as drawn (``aligned_group``'s, the
    true points): runs, failed, excellent, good or better, visible median and minimum, markers, distortion median,
    time median (s), and on the oblique grid the volumes whose visible mucosa falls by over VISIBLE_DROP or that see
    fewer markers than as drawn."""
    turned = [r for r in rows if r.get("group") == group]
    label_turned = {PRONE_GROUP: "prone", ROLLED_GROUP: "rolled", CONTRAST_GROUP: "contrast",
                    CONTENTS_GROUP: "contents", DEEP_GROUP: "deep"}.get(group, "oblique")
    out = []
    for m in OBLIQUE_METHODS:
        mine = {_volume(r): r for r in turned if r["method"] == m}
        if not mine:
            continue
        drawn = {_volume(r): r for r in rows if r.get("group") == aligned_group and r["method"] == m
                 and not r.get("zero_clicks") and _volume(r) in mine}
        for label, rs in (("as drawn", drawn), (label_turned, mine)):
            if not rs:
                continue
            ok = [r for r in rs.values() if r.get("ok")]
            q = [r["quality"] for r in ok]
            vis = [x["visible_fraction"] for x in q]
            mk = [x["markers"] for x in q if "markers" in x]
            dist = [x["pairwise_distance_distortion"] for x in mk if x.get("pairwise_distance_distortion") is not None]
            row = {"method": m, "grid": label, "runs": len(rs), "failed": len(rs) - len(ok),
                   "excellent": sum(x["grade"] == "excellent" for x in q),
                   "good_or_better": sum(x["grade"] in ("excellent", "good") for x in q),
                   "visible_median": float(np.median(vis)) if vis else None,
                   "visible_min": float(np.min(vis)) if vis else None,
                   "markers_seen": sum(x["seen"] for x in mk), "markers_total": sum(x["total"] for x in mk),
                   "distortion_median": float(np.median(dist)) if dist else None,
                   "seconds_median": float(np.median([r["seconds"] for r in ok])) if ok else None}
            if label != "as drawn" and drawn:
                both = [(r, drawn[v]) for v, r in rs.items() if r.get("ok") and v in drawn and drawn[v].get("ok")]
                row["visible_lower"] = sorted(_volume(a) for a, b in both if a["quality"]["visible_fraction"]
                                              < b["quality"]["visible_fraction"] - VISIBLE_DROP)
                row["fewer_markers"] = sorted(_volume(a) for a, b in both
                                              if "markers" in a["quality"] and "markers" in b["quality"]
                                              and a["quality"]["markers"]["seen"] < b["quality"]["markers"]["seen"])
            if label in ("contents", "deep"):
                said = CONTENTS_SAID if label == "contents" else DEEP_SAID
                row["said"] = sum(any(said in w for w in r.get("warnings") or []) for r in ok)
            if label != "as drawn":
                row["errors"] = sorted({str(r.get("error", "")).split(";")[0][:90] for r in rs.values()
                                        if not r.get("ok")})
            out.append(row)
    return out


def oblique_markdown(rows: list[dict], aligned_group: str, group: str = GROUP) -> list[str]:
    """results.md's table of :func:`oblique_summary` for ``group`` (nothing when its part was not run)."""
    summ = oblique_summary(rows, aligned_group, group)
    if not summ:
        return []
    lo, hi = OBLIQUE_DEGREES
    if group == DEEP_GROUP:
        dlo, dhi = DEEP_FRACTION
        head = [f"## Deep pools: the held-out random stomachs with water filling {100 * dlo:g}-{100 * dhi:g} % of "
                "their height\n",
                "Each volume drawn again with a pool of water filling a fraction of the stomach's height drawn per "
                "seed (the family's fill 15-35 %): the cardia and the pre-pyloric canal may lie under it and the gas "
                "split into pockets; *as drawn*: the `stomachs` part's rows on the same volumes. *said*: runs whose "
                "warnings say a point was joined to its gas through the water. *lower*: volumes whose visible mucosa "
                f"falls by over {100 * VISIBLE_DROP:g} point; *fewer markers*: volumes that see fewer markers than as "
                "drawn.\n"]
    elif group == CONTENTS_GROUP:
        clo, chi = CONTENTS_HU
        head = [f"## Contents: the held-out random stomachs with a pool, its fluid drawn at {clo:g}-{chi:g} HU\n",
                "Each volume whose stomach holds fluid drawn again with the fluid at a HU drawn per seed (food, mucus "
                "or blood: it reads like the wall, so no method can find the wall under it); *as drawn*: the "
                "`stomachs` part's rows on the same volumes (water). *said*: runs whose warnings say such contents and "
                f"ask for a label. *lower*: volumes whose visible mucosa falls by over {100 * VISIBLE_DROP:g} point; "
                "*fewer markers*: volumes that see fewer markers than with water.\n"]
    elif group == CONTRAST_GROUP:
        clo, chi = CONTRAST_HU
        head = [f"## Contrast: the held-out random stomachs with a pool, its fluid drawn at {clo:g}-{chi:g} HU\n",
                "Each volume whose stomach holds fluid drawn again with the fluid at a HU drawn per seed (positive oral "
                "contrast; the anatomy, level and markers the same); *as drawn*: the `stomachs` part's rows on the same "
                f"volumes (water). *lower*: volumes whose visible mucosa falls by over {100 * VISIBLE_DROP:g} point; "
                "*fewer markers*: volumes that see fewer markers than with water.\n"]
    elif group == ROLLED_GROUP:
        rlo, rhi = ROLL_DEGREES
        head = [f"## Rolled: the held-out random stomachs as patients rolled {rlo:g}-{rhi:g} degrees about the S "
                "axis\n",
                "Each volume's LPS frame turned about z by an angle drawn per seed (either way; points and markers "
                "turned with it): the anatomy turns in the patient's frame and the water's level tilts that much; "
                f"*as drawn*: the `stomachs` part's rows on the same volumes. *lower*: volumes whose visible mucosa "
                f"falls by over {100 * VISIBLE_DROP:g} point rolled; *fewer markers*: volumes that see fewer markers "
                "than as drawn.\n"]
    elif group == PRONE_GROUP:
        head = ["## Prone: the held-out random stomachs mirrored front to back, their water on the anterior wall\n",
                "Each volume's voxels with LPS y negated (points and markers mirrored with them), as a prone "
                "patient's scan; *as drawn*: the `stomachs` part's rows on the same volumes. *lower*: volumes whose "
                f"visible mucosa falls by over {100 * VISIBLE_DROP:g} point mirrored; *fewer markers*: volumes that "
                "see fewer markers than as drawn.\n"]
    else:
        head = [f"## Oblique voxel grids: the held-out random stomachs resampled onto grids turned {lo:g}-{hi:g} "
                "degrees\n",
                "Each volume's grid turned about a random axis (drawn per seed, the same for every method), the voxels "
                "the same size, the anatomy, points and markers at the same LPS places; *as drawn*: the `stomachs` "
                f"part's rows on the same volumes. *lower*: volumes whose visible mucosa falls by over "
                f"{100 * VISIBLE_DROP:g} point on the turned grid; *fewer markers*: volumes that see fewer markers "
                "than as drawn.\n"]
    L = head + [
        "| method | grid | runs | failed | excellent | good or better | visible median / min % | markers | "
        "distortion median | s median | lower | fewer markers |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def pc(v):
        return "" if v is None else f"{100 * v:.2f}"

    def f3(v, fmt):
        return "" if v is None else fmt.format(v)
    for x in summ:
        lower = ", ".join(x["visible_lower"]) if "visible_lower" in x else ""
        fewer = ", ".join(x["fewer_markers"]) if "fewer_markers" in x else ""
        L.append(f"| {x['method']} | {x['grid']} | {x['runs']} | {x['failed']} | {x['excellent']} | "
                 f"{x['good_or_better']} | {pc(x['visible_median'])} / {pc(x['visible_min'])} | "
                 f"{x['markers_seen']}/{x['markers_total']} | {f3(x['distortion_median'], '{:.4f}')} | "
                 f"{f3(x['seconds_median'], '{:.1f}')} | {lower or ('none' if 'visible_lower' in x else '')} | "
                 f"{fewer or ('none' if 'fewer_markers' in x else '')} |")
    said = [f"{x['method']} {x['said']}/{x['runs'] - x['failed']}" for x in summ if "said" in x]
    if said:
        L.append("")
        L.append(("Said (a point under the water, joined to its gas through it): " if group == DEEP_GROUP else
                  "Said (the warning names the contents and asks for a label): ") + ", ".join(said) + ".")
    errs = [(x["method"], e) for x in summ for e in x.get("errors", [])]
    if errs:
        L.append("")
        L.append("Why runs failed: " + "; ".join(f"{m}: \"{e}\"" for m, e in errs) + ".")
    return L + [""]
