"""The ``phase`` part of ``stomach-unfold bench``: how much the judge's figures move when the view's raster does.

A surface method draws its view on a raster of square pixels laid from the flat map's own corner. Where the pixel
centres fall on the map is arbitrary: half a pixel either way is the same view, sampled elsewhere. The part runs
PHASE_METHODS on PHASE_SETS twice, with the raster where it is (offset 0) and moved PHASE_OFFSET_PX pixels along i and
j (``StomachUnfoldLib.surface.RASTER_OFFSET_PX``; the flat map, the CT and the judge are the same), and reports per set
and method how far the judge's figures moved: visible mucosa (points of 100), markers seen, grades, and the volumes
whose standing against LSCM on visible mucosa flips. A difference between two methods, or two versions of one, smaller
than this is not a measured difference on one volume.
"""
from __future__ import annotations

import os
import statistics

#: How far (pixels, along i and j) the second run moves the view's raster.
PHASE_OFFSET_PX = 0.5
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
    """The part's cases (``case`` = bench.Case): every PHASE_METHODS x offset (0, PHASE_OFFSET_PX) x volume of
    PHASE_SETS (quick: two volumes of each set); ``real_cts``: the CT file names found in ``data_dir``."""
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
            for off in (0.0, PHASE_OFFSET_PX):
                out += [case(f"{vol}/{m}-phase-{off:g}", dict(src, _cache=cache, raster_offset_px=off, phase_set=label),
                             {}, method=m, group=GROUP) for m in PHASE_METHODS]
    return out


def _pairs(rows: list[dict]) -> dict:
    """{(set, method, volume): {offset: row}} of the part's rows that ran."""
    out: dict = {}
    for r in rows:
        if r.get("group") != GROUP or not r.get("ok"):
            continue
        src = r["source"]
        out.setdefault((src["phase_set"], r["method"], r["name"].split("/")[0]), {})[float(src["raster_offset_px"])] = r
    return out


def phase_summary(rows: list[dict]) -> list[dict]:
    """Per set and method: volumes run at both offsets, the visible mucosa's change (points of 100: median and
    largest absolute, volumes changed by over 0.1), markers seen at each offset and the volumes whose count changed,
    grades changed, and (for each method but LSCM) the volumes behind LSCM at one offset and not at the other."""
    pairs = {k: v for k, v in _pairs(rows).items() if len(v) == 2}
    out = []
    for label, _, _ in PHASE_SETS:
        for m in PHASE_METHODS:
            both = {k[2]: v for k, v in pairs.items() if k[0] == label and k[1] == m}
            if not both:
                continue
            a = {vol: v[0.0] for vol, v in both.items()}
            b = {vol: v[PHASE_OFFSET_PX] for vol, v in both.items()}
            dv = [100.0 * (b[k]["quality"]["visible_fraction"] - a[k]["quality"]["visible_fraction"]) for k in a]
            mk = [(a[k].get("markers_seen"), b[k].get("markers_seen")) for k in a]
            mk = [(x, y) for x, y in mk if x is not None and y is not None]
            entry = {"set": label, "method": m, "volumes": len(a),
                     "visible_change_median": statistics.median(abs(d) for d in dv),
                     "visible_change_max": max(abs(d) for d in dv),
                     "visible_changed_over_0.1": sum(abs(d) > 0.1 for d in dv),
                     "markers": [sum(x for x, _ in mk), sum(y for _, y in mk)],
                     "markers_volumes_changed": sum(x != y for x, y in mk),
                     "grades_changed": sorted(k for k in a if a[k]["quality"]["grade"] != b[k]["quality"]["grade"])}
            if m != "lscm":
                entry["behind_lscm_flips"] = _flips(pairs, label, m)
            out.append(entry)
    return out


def _flips(pairs: dict, label: str, m: str) -> list[str]:
    """The volumes of set ``label`` where method m shows less mucosa than LSCM at one raster offset and not at the
    other."""
    flips = []
    for (lab, meth, vol), v in pairs.items():
        peer = pairs.get((lab, "lscm", vol))
        if lab != label or meth != m or peer is None:
            continue
        behind = [peer[o]["quality"]["visible_fraction"] > v[o]["quality"]["visible_fraction"]
                  for o in (0.0, PHASE_OFFSET_PX)]
        if behind[0] != behind[1]:
            flips.append(vol)
    return sorted(flips)


def phase_markdown(rows: list[dict]) -> list[str]:
    """The part's section of results.md (nothing when it did not run)."""
    summ = phase_summary(rows)
    if not summ:
        return []
    L = ["\n## The judge's noise: the view's raster moved half a pixel (part `phase`)\n",
         f"Each volume run twice per method, the raster where it is and moved {PHASE_OFFSET_PX:g} pixel along i and j "
         "(the flat map, the CT and the judge unchanged). Visible mucosa in points of 100.\n",
         "| set | method | volumes | visible change: median / largest | changed over 0.1 | markers (0 -> moved) "
         "| volumes whose markers changed | grades changed | behind LSCM at one offset only |",
         "|---|---|---|---|---|---|---|---|---|"]
    for e in summ:
        flips = e.get("behind_lscm_flips")
        L.append(f"| {e['set']} | {e['method']} | {e['volumes']} | {e['visible_change_median']:.3f} / "
                 f"{e['visible_change_max']:.3f} | {e['visible_changed_over_0.1']} | {e['markers'][0]} -> "
                 f"{e['markers'][1]} | {e['markers_volumes_changed']} | {', '.join(e['grades_changed']) or 'none'} | "
                 f"{'-' if flips is None else (', '.join(flips) or 'none')} |")
    return L + [""]
