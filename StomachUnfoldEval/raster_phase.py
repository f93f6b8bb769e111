"""The ``phase`` part of ``stomach-unfold bench``: how much the judge's figures move when the view's sampling does.

A surface method draws its view on a raster of square pixels laid from the flat map's own corner, and samples each
pixel's ray at depths counted from the surface the map was made of. Where the pixel centres fall on the map, and where
the depth samples fall along the rays, is arbitrary: half a pixel or half a voxel either way is the same view, sampled
elsewhere. The part runs PHASE_METHODS on PHASE_SETS at each of PHASES: as in use, the raster moved PHASE_OFFSET_PX
pixels along i and j (``StomachUnfoldLib.surface.RASTER_OFFSET_PX``), the depth samples moved DEPTH_OFFSET_PX voxels
(``surface.DEPTH_OFFSET_PX``), and both (the flat map, the CT and the judge are the same), and reports per set, method
and move how far the judge's figures moved: visible mucosa (points of 100), markers seen, grades, and the volumes whose
standing against LSCM on visible mucosa flips; and per set the volumes behind LSCM at every phase and on the mean over
the phases. A difference between two methods, or two versions of one, smaller than this is not a measured difference
on one volume.
"""
from __future__ import annotations

import os
import statistics

#: How far (pixels, along i and j) the second run moves the view's raster.
PHASE_OFFSET_PX = 0.5
#: How far (voxels, toward the lumen) the third run moves the view's depth samples along the rays
#: (``StomachUnfoldLib.surface.DEPTH_OFFSET_PX``); the fourth moves both.
DEPTH_OFFSET_PX = 0.5
#: The runs of each volume and method: (raster offset px, depth offset voxels); the first is the view as in use.
PHASES = ((0.0, 0.0), (PHASE_OFFSET_PX, 0.0), (0.0, DEPTH_OFFSET_PX), (PHASE_OFFSET_PX, DEPTH_OFFSET_PX))
#: What each moved phase is called in the tables.
MOVED = {PHASES[1]: "raster", PHASES[2]: "depth", PHASES[3]: "both"}
#: The methods run (both draw their view through ``surface.sample_flat_map``).
PHASE_METHODS = ("isometric", "lscm")
#: The volumes: (label, kind, seeds); kind "small" / "tiny" are random stomachs of that size, "hybrid-NN" the drawn
#: stomachs inserted into the real CT whose file name starts with NN (skipped when ``../shared/data`` lacks it).
PHASE_SETS = (("held-out small", "small", tuple(range(1000, 1030))),
              ("hybrids in CT 01", "hybrid-01", tuple(range(40000, 40020))),
              ("hybrids in CT 03", "hybrid-03", tuple(range(40000, 40020))),
              ("tiny", "tiny", tuple(range(34000, 34020))))
#: The rows' group in results.json.
GROUP = "raster-phase"


def phase_cases(quick: bool, data_dir: str | None, real_cts: list[str], cache: str, case) -> list[dict]:
    """The part's cases (``case`` = bench.Case): every PHASE_METHODS x PHASES x volume of PHASE_SETS (quick: two
    volumes of each set); ``real_cts``: the CT file names found in ``data_dir``."""
    out = []
    for label, kind, seeds in PHASE_SETS:
        seeds = seeds[:2] if quick else seeds
        if kind.startswith("hybrid-"):
            names = [n for n in real_cts if n.startswith(kind.split("-")[1] + "_")]
            if not names or not data_dir:
                continue
            srcs = [(f"hybrid-{kind.split('-')[1]}-{s}", {"hybrid": int(s), "ct": os.path.join(data_dir, names[0])})
                    for s in seeds]
        else:
            srcs = [(f"stomach-{s}-{kind}", {"random": int(s), "size": kind}) for s in seeds]
        for vol, src in srcs:
            for off, dep in PHASES:
                out += [case(f"{vol}/{m}-phase-{off:g}" + (f"-depth-{dep:g}" if dep else ""),
                             dict(src, _cache=cache, raster_offset_px=off, depth_offset_px=dep, phase_set=label),
                             {}, method=m, group=GROUP) for m in PHASE_METHODS]
    return out


def _phase(src: dict) -> tuple[float, float]:
    """A row's (raster offset px, depth offset voxels); rows run before the depth offset existed have depth 0."""
    return float(src["raster_offset_px"]), float(src.get("depth_offset_px", 0.0))


def _pairs(rows: list[dict]) -> dict:
    """{(set, method, volume): {phase: row}} of the part's rows that ran."""
    out: dict = {}
    for r in rows:
        if r.get("group") != GROUP or not r.get("ok"):
            continue
        src = r["source"]
        out.setdefault((src["phase_set"], r["method"], r["name"].split("/")[0]), {})[_phase(src)] = r
    return out


def phase_summary(rows: list[dict]) -> list[dict]:
    """Per set, method and move (each phase of PHASES against the view as in use, where both ran): volumes run at both,
    the visible mucosa's change (points of 100: median and largest absolute, volumes changed by over 0.1), markers seen
    at each phase and the volumes whose count changed, grades changed, and (for each method but LSCM) the volumes
    behind LSCM at one phase and not at the other."""
    pairs = _pairs(rows)
    out = []
    for label, _, _ in PHASE_SETS:
        for m in PHASE_METHODS:
            for ph in PHASES[1:]:
                both = {k[2]: v for k, v in pairs.items() if k[0] == label and k[1] == m and PHASES[0] in v and ph in v}
                if not both:
                    continue
                a = {vol: v[PHASES[0]] for vol, v in both.items()}
                b = {vol: v[ph] for vol, v in both.items()}
                dv = [100.0 * (b[k]["quality"]["visible_fraction"] - a[k]["quality"]["visible_fraction"]) for k in a]
                mk = [(a[k].get("markers_seen"), b[k].get("markers_seen")) for k in a]
                mk = [(x, y) for x, y in mk if x is not None and y is not None]
                entry = {"set": label, "method": m, "moved": MOVED[ph], "volumes": len(a),
                         "visible_change_median": statistics.median(abs(d) for d in dv),
                         "visible_change_max": max(abs(d) for d in dv),
                         "visible_changed_over_0.1": sum(abs(d) > 0.1 for d in dv),
                         "markers": [sum(x for x, _ in mk), sum(y for _, y in mk)],
                         "markers_volumes_changed": sum(x != y for x, y in mk),
                         "grades_changed": sorted(k for k in a if a[k]["quality"]["grade"] != b[k]["quality"]["grade"])}
                if m != "lscm":
                    entry["behind_lscm_flips"] = _flips(pairs, label, m, ph)
                out.append(entry)
    return out


def _behind(pairs: dict, label: str, m: str, vol: str, ph: tuple) -> bool | None:
    """Whether method m shows less mucosa than LSCM on volume ``vol`` of set ``label`` at phase ``ph`` (None: a run
    missing)."""
    mine, peer = pairs.get((label, m, vol), {}), pairs.get((label, "lscm", vol), {})
    if ph not in mine or ph not in peer:
        return None
    return peer[ph]["quality"]["visible_fraction"] > mine[ph]["quality"]["visible_fraction"]


def _flips(pairs: dict, label: str, m: str, ph: tuple = PHASES[1]) -> list[str]:
    """The volumes of set ``label`` where method m shows less mucosa than LSCM at the phase in use and not at ``ph``,
    or the other way round."""
    flips = []
    for (lab, meth, vol) in pairs:
        if lab != label or meth != m:
            continue
        b = [_behind(pairs, label, m, vol, p) for p in (PHASES[0], ph)]
        if None not in b and b[0] != b[1]:
            flips.append(vol)
    return sorted(flips)


def behind_summary(rows: list[dict]) -> list[dict]:
    """Per set and method but LSCM, over the volumes run at every phase of PHASES: those behind LSCM on visible mucosa
    at every phase (a measured difference), at some (the sampling's), and at none; and those whose visible mucosa
    averaged over the four phases is below LSCM's so averaged (the judge's sampling noise averaged out)."""
    pairs = _pairs(rows)
    out = []
    for label, _, _ in PHASE_SETS:
        for m in PHASE_METHODS:
            if m == "lscm":
                continue
            every, some, none, mean = [], [], 0, []
            for (lab, meth, vol) in sorted(pairs):
                if lab != label or meth != m:
                    continue
                b = [_behind(pairs, label, m, vol, p) for p in PHASES]
                if None in b:
                    continue
                if all(b):
                    every.append(vol)
                elif any(b):
                    some.append(vol)
                else:
                    none += 1
                if _mean_visible(pairs[(label, m, vol)]) < _mean_visible(pairs[(label, "lscm", vol)]):
                    mean.append(vol)
            if every or some or none:
                out.append({"set": label, "method": m, "volumes": len(every) + len(some) + none,
                            "behind_every_phase": every, "behind_some_phases": some, "behind_none": none,
                            "behind_on_the_mean": mean})
    return out


def _mean_visible(runs: dict) -> float:
    """Visible mucosa (fraction) of one method's runs of a volume ({phase: row}), averaged over PHASES."""
    return statistics.fmean(runs[p]["quality"]["visible_fraction"] for p in PHASES)


def phase_markdown(rows: list[dict]) -> list[str]:
    """The part's section of results.md (nothing when it did not run)."""
    summ = phase_summary(rows)
    if not summ:
        return []
    L = ["\n## The judge's noise: the view's raster and depth samples moved (part `phase`)\n",
         f"Each volume run per method as in use and moved: the raster {PHASE_OFFSET_PX:g} pixel along i and j "
         f"(\"raster\"), the depth samples {DEPTH_OFFSET_PX:g} voxel along the rays (\"depth\"), and both; the flat map, "
         "the CT and the judge unchanged. Visible mucosa in points of 100; each move against the view as in use.\n",
         "| set | method | moved | volumes | visible change: median / largest | changed over 0.1 | markers (in use -> "
         "moved) | volumes whose markers changed | grades changed | behind LSCM at one of the two only |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for e in summ:
        flips = e.get("behind_lscm_flips")
        L.append(f"| {e['set']} | {e['method']} | {e['moved']} | {e['volumes']} | {e['visible_change_median']:.3f} / "
                 f"{e['visible_change_max']:.3f} | {e['visible_changed_over_0.1']} | {e['markers'][0]} -> "
                 f"{e['markers'][1]} | {e['markers_volumes_changed']} | {', '.join(e['grades_changed']) or 'none'} | "
                 f"{'-' if flips is None else (', '.join(flips) or 'none')} |")
    beh = behind_summary(rows)
    if beh:
        L += ["", "Behind LSCM on visible mucosa, over the volumes run at all four phases (the last column: the visible "
              "mucosa averaged over the four phases, each method's own, below LSCM's):", "",
              "| set | method | volumes | behind at every phase | behind at some phases only | behind at none | "
              "behind on the four phases' mean |",
              "|---|---|---|---|---|---|---|"]
        for e in beh:
            L.append(f"| {e['set']} | {e['method']} | {e['volumes']} | {', '.join(e['behind_every_phase']) or 'none'} | "
                     f"{', '.join(e['behind_some_phases']) or 'none'} | {e['behind_none']} | "
                     f"{', '.join(e['behind_on_the_mean']) or 'none'} |")
    return L + [""]
