"""The ``clicks`` part of ``stomach-unfold bench``: each method with the cardia and pylorus clicked off their places.

A reader clicks the cardia and pylorus by eye. The part moves each true point (LPS mm) by a fixed distance in a
random direction (CLICK_ERRORS_MM, CLICK_DRAWS draws per distance, the same draws for every method) and runs
CLICK_METHODS on the tuning and held-out random stomachs. Its table sets each method's runs beside its own rows with
the true points (the ``stomachs`` part's): runs that fail and why, grades, visible mucosa, markers, and the volumes
that lose a marker the true points show.
"""
from __future__ import annotations

import numpy as np

from StomachUnfoldLib.plausibility import DEEP_POINT_WARNING
from StomachUnfoldLib.quality import GRADE_THRESHOLDS

#: How far (mm) each click is moved from the true cardia and pylorus, in a random 3D direction.
CLICK_ERRORS_MM = (5.0, 10.0)
#: Random directions drawn per distance and volume.
CLICK_DRAWS = 2
#: The methods run with moved clicks (mass-spring takes minutes per volume and is left out).
CLICK_METHODS = ("isometric", "cylindrical", "lscm")
#: The rows' group in results.json.
GROUP = "click-error"


def moved_clicks(cardia_lps, pylorus_lps, error_mm: float, seed: int, draw: int) -> tuple[np.ndarray, np.ndarray]:
    """The cardia and pylorus (LPS mm) each moved ``error_mm`` (mm) in a random direction, drawn from (seed, draw)."""
    rng = np.random.default_rng(1000 * int(seed) + int(draw))
    out = []
    for p in (cardia_lps, pylorus_lps):
        d = rng.normal(size=3)
        out.append(np.asarray(p, float) + float(error_mm) * d / np.linalg.norm(d))
    return out[0], out[1]


def click_error_cases(quick: bool, tune_seeds, held_out_seeds, cache: str, case) -> list[dict]:
    """The part's cases (``case`` = bench.Case): every CLICK_METHODS x CLICK_ERRORS_MM x CLICK_DRAWS x seed."""
    seeds = (list(tune_seeds[:2]) + list(held_out_seeds[:2])) if quick else (list(tune_seeds) + list(held_out_seeds))
    errors = CLICK_ERRORS_MM[-1:] if quick else CLICK_ERRORS_MM
    return [case(f"stomach-{seed}/{m}-clicks-{e:g}mm-{k}",
                 {"random": int(seed), "size": "small", "_cache": cache, "click_error_mm": float(e), "click_draw": k},
                 {}, method=m, group=GROUP)
            for m in CLICK_METHODS for e in errors for k in range(1 if quick else CLICK_DRAWS) for seed in seeds]


def _volume(row: dict) -> str:
    """The volume a row ran on (``stomach-SEED``)."""
    return row["name"].split("/")[0]


def click_error_summary(rows: list[dict], tune_seeds, held_out_seeds) -> list[dict]:
    """Per seed set, method and click error (0: the ``stomachs`` part's rows with the true points, on the volumes the
    part ran): runs, failed (and the first words of each error), excellent, good or better, visible median and
    minimum, markers seen, and the runs that see fewer markers than the same method with the true points."""
    moved = [r for r in rows if r.get("group") == GROUP]
    if not moved:
        return []
    sets = (("tuning", set(tune_seeds), "stomachs-tune"), ("held-out", set(held_out_seeds), "stomachs-held-out"))
    out = []
    for label, seeds, group in sets:
        for m in CLICK_METHODS:
            mine = [r for r in moved if r["method"] == m and int(r["source"]["random"]) in seeds]
            if not mine:
                continue
            vols = {_volume(r) for r in mine}
            true = {_volume(r): r for r in rows if r.get("group") == group and r["method"] == m
                    and not r.get("zero_clicks") and _volume(r) in vols}
            for e in (0.0,) + tuple(sorted({float(r["source"]["click_error_mm"]) for r in mine})):
                rs = list(true.values()) if e == 0.0 else [r for r in mine if r["source"]["click_error_mm"] == e]
                if not rs:
                    continue
                ok = [r for r in rs if r.get("ok")]
                q = [r["quality"] for r in ok]
                vis = [x["visible_fraction"] for x in q]
                mk = [(r, r["quality"]["markers"]) for r in ok if "markers" in r["quality"]]
                fewer = sum(1 for r, x in mk if _volume(r) in true and true[_volume(r)].get("ok")
                            and x["seen"] < true[_volume(r)]["quality"]["markers"]["seen"])
                errors: dict = {}
                for r in rs:
                    if not r.get("ok"):
                        key = str(r.get("error", "")).split(";")[0][:90]
                        errors[key] = errors.get(key, 0) + 1
                out.append({"set": label, "method": m, "error_mm": e, "runs": len(rs), "failed": len(rs) - len(ok),
                            "errors": errors, "excellent": sum(x["grade"] == "excellent" for x in q),
                            "good_or_better": sum(x["grade"] in ("excellent", "good") for x in q),
                            "visible_median": float(np.median(vis)) if vis else None,
                            "visible_min": float(np.min(vis)) if vis else None,
                            "markers_seen": sum(x["seen"] for _, x in mk),
                            "markers_total": sum(x["total"] for _, x in mk), "fewer_markers": fewer,
                            "deep_point_warned": sum(any(DEEP_POINT_WARNING in w for w in r.get("warnings") or [])
                                                     for r in ok)})
    return out


def click_error_markdown(rows: list[dict], tune_seeds, held_out_seeds) -> list[str]:
    """results.md's table of :func:`click_error_summary` (nothing when the part was not run)."""
    summ = click_error_summary(rows, tune_seeds, held_out_seeds)
    if not summ:
        return []
    dist = " or ".join(f"{e:g}" for e in CLICK_ERRORS_MM)
    L = [f"## Clicks off their places: each click moved {dist} mm in a random direction (random stomachs)\n",
         f"Each volume {CLICK_DRAWS} draws per distance, the same draws for every method; 0 mm: the `stomachs` part's "
         "rows with the true points on the same volumes. *fewer markers*: runs that see fewer markers than the same "
         "method with the true points. *warned*: runs whose warnings say a point lies deep in a wide lumen (the opening "
         f"left out about it takes over {100 * GRADE_THRESHOLDS['excellent']['max_hidden']:g} % of the wall).\n",
         "| set | method | click error mm | runs | failed | excellent | good or better | visible median / min % | "
         "markers | fewer markers | warned |", "|---|---|---|---|---|---|---|---|---|---|---|"]

    def pc(v):
        return "" if v is None else f"{100 * v:.2f}"
    for x in summ:
        L.append(f"| {x['set']} | {x['method']} | {x['error_mm']:g} | {x['runs']} | {x['failed']} | {x['excellent']} | "
                 f"{x['good_or_better']} | {pc(x['visible_median'])} / {pc(x['visible_min'])} | "
                 f"{x['markers_seen']}/{x['markers_total']} | {x['fewer_markers']} | {x['deep_point_warned']} |")
    why = {}
    for x in summ:
        for msg, n in x["errors"].items():
            why.setdefault((x["method"], msg), 0)
            why[(x["method"], msg)] += n
    if why:
        L.append("")
        L.append("Why runs failed: " + "; ".join(f"{m} {n}x \"{msg}\"" for (m, msg), n in sorted(why.items())) + ".")
    return L + [""]


def click_error_plot(rows: list[dict], tune_seeds, held_out_seeds, out_dir: str, made: list[str], plt, save) -> None:
    """click_error.png: per method (tuning and held-out together), the share of runs excellent and the share of
    markers seen against the click error (mm)."""
    summ = click_error_summary(rows, tune_seeds, held_out_seeds)
    if not summ:
        return
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    colour = {"isometric": "tab:blue", "cylindrical": "tab:green", "lscm": "tab:red"}
    for m in CLICK_METHODS:
        xs = [x for x in summ if x["method"] == m]
        errs = sorted({x["error_mm"] for x in xs})
        runs = [sum(x["runs"] for x in xs if x["error_mm"] == e) for e in errs]
        exc = [sum(x["excellent"] for x in xs if x["error_mm"] == e) for e in errs]
        seen = [sum(x["markers_seen"] for x in xs if x["error_mm"] == e) for e in errs]
        total = [sum(x["markers_total"] for x in xs if x["error_mm"] == e) for e in errs]
        axes[0].plot(errs, [100 * a / max(b, 1) for a, b in zip(exc, runs)], "o-", color=colour.get(m), label=m)
        axes[1].plot(errs, [100 * a / max(b, 1) for a, b in zip(seen, total)], "o-", color=colour.get(m), label=m)
    axes[0].set(xlabel="click error (mm, each of cardia and pylorus)", ylabel="runs graded excellent (%; a failed "
                "run counts as not)", title="stability to where the reader clicks")
    axes[1].set(xlabel="click error (mm, each of cardia and pylorus)", ylabel="markers seen (% of those of runs "
                "that finished)", title="tuning and held-out random stomachs together")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save(fig, out_dir, "click_error.png", made)
