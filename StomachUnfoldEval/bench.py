"""``stomach-unfold bench``: the phantom set and real CTs, sweeps, the paper's kappa table, peers, stability, speed.

Every case is a plain function call (picklable) run through Dask: a local cluster by default, or the
scheduler at ``scheduler`` for a real cluster. Failures are data (a row with ``ok: false`` and the error),
never crashes. Writes into the output folder: ``results.json``, ``results.md`` and PNGs (views, Pareto
charts, stability, resolution, scaling). Timings are measurements of this run on this machine.
"""
from __future__ import annotations

import contextlib
import json
import os
import platform
import time
import traceback

import numpy as np

from StomachUnfoldLib.errors import InputError, PointError, StomachUnfoldError

from .click_error import click_error_cases, click_error_markdown, click_error_plot, moved_clicks
from .memory import memory_markdown, memory_plot, memory_runs
from .oblique import (CONTENTS_GROUP, CONTRAST_GROUP, DEEP_GROUP, PRONE_GROUP, ROLLED_GROUP, contents_cases,
                      contrast_cases, deep_cases, front_to_back, oblique_cases, oblique_markdown, prone_cases, rolled,
                      rolled_cases, turned_grid)
from .raster_phase import phase_cases, phase_markdown
from .regional import area_scale_along, area_scale_summary

__all__ = ["Case", "phantom_set", "run_case", "run_cases", "run_benchmark", "replot", "place_labels", "KAPPAS"]

KAPPAS = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]


def Case(name: str, source: dict, params: dict | None = None, method: str = "massspring", group: str = "") -> dict:
    """A benchmark case: where the CT comes from (phantom kwargs or a real file), parameters, method, group."""
    return {"name": name, "source": source, "params": dict(params or {}), "method": method, "group": group}


def phantom_set(size: str = "small") -> list[dict]:
    """Eleven phantoms: curvature (incl. a bend tighter than the lumen), twist, radius, wall, rugae, noise, spacing, direction."""
    aniso = (1.2, 1.2, 2.5) if size == "small" else (1.8, 1.8, 3.0)
    specs = [("straight", {}), ("bent", {}), ("j", {}), ("twisted", {}), ("thin_wall", {}), ("hook", {}),
             ("j-anisotropic", {"spacing": aniso}), ("j-flipped", {"flip_direction": True}),
             ("j-rugae", {"rugae": True}), ("j-noisy", {"noise_hu": 45.0}), ("bent-narrow", {"radius_scale": 0.55})]
    out = []
    for name, extra in specs:
        shape = name.split("-")[0]
        out.append({"shape": shape, "size": size, **extra, "_name": f"{name}-{size}"})
    return out


def _wall(src: dict) -> float:
    return 3.0 if src.get("shape") == "thin_wall" else 4.0


#: Random stomachs: the seeds the defaults were tuned on, and the held-out seeds never tuned on.
TUNE_SEEDS = tuple(range(0, 30))
HELD_OUT_SEEDS = tuple(range(1000, 1030))
#: A second held-out set, drawn on 2026-12-01 after the isometric method's distance terms and fold handling were
#: settled (a failure seen on two volumes of HELD_OUT_SEEDS shaped the fold handling, so those seeds are no longer
#: untouched for that change); never looked at before that run.
FRESH_SEEDS = tuple(range(3000, 3030))
#: A third held-out set for the flat map, first run on 2026-12-04 to decide on the heavy distance terms (held-out
#: seed 1005 had shaped that change, and the fresh seeds had been run with it once). These volumes had been drawn
#: before only by the point finder's study (``auto_points.AUTO_FRESH_SEEDS``), never unfolded.
FRESH2_SEEDS = tuple(range(4000, 4030))
#: A fourth held-out set, first drawn on the evening of 2026-12-04 after every change so far: nothing was decided
#: or looked at on it before its first bench run.
FRESH3_SEEDS = tuple(range(5000, 5030))
#: A fifth held-out set, first drawn late on 2026-12-04 to decide (with the four sets above) on an incision in the
#: stomach's plane, which was not kept; never tuned on. The bench part ``fresh-4`` runs it alone.
FRESH4_SEEDS = tuple(range(6000, 6030))
#: A sixth held-out set, first drawn at night on 2026-12-04 after every change of the day, to report the method as it
#: stands: nothing was decided or looked at on it before its first bench run. The bench part ``fresh-5`` runs it alone.
FRESH5_SEEDS = tuple(range(7000, 7030))
#: A seventh held-out set, first drawn early on 2026-12-05 to decide on the water's floor (rule 12, failed as written
#: on it and on the fluid volumes above); never tuned on. The bench part ``fresh-6`` runs it alone.
FRESH6_SEEDS = tuple(range(8000, 8030))
#: An eighth held-out set, first drawn early on 2026-12-05 to decide on the same floor under rule 13 (kept); never tuned
#: on. The bench part ``fresh-7`` runs it alone.
FRESH7_SEEDS = tuple(range(9000, 9030))
#: A ninth and a tenth held-out set, first drawn on 2026-12-05 (02:33-02:43) to decide on the stomach-plane incision
#: again (rule 14, with a check for slots on the view's grid: failed, per volume 29 better / 31 worse); never tuned on.
#: The bench parts ``fresh-8`` and ``fresh-9`` run them alone.
FRESH8_SEEDS = tuple(range(10000, 10030))
FRESH9_SEEDS = tuple(range(11000, 11030))
#: Every random-stomach seed set by its family group: tuned on, then the ten held out.
FAMILY_SEED_SETS = (("stomachs-tune", TUNE_SEEDS), ("stomachs-held-out", HELD_OUT_SEEDS),
                    ("stomachs-fresh", FRESH_SEEDS), ("stomachs-fresh-2", FRESH2_SEEDS),
                    ("stomachs-fresh-3", FRESH3_SEEDS), ("stomachs-fresh-4", FRESH4_SEEDS),
                    ("stomachs-fresh-5", FRESH5_SEEDS), ("stomachs-fresh-6", FRESH6_SEEDS),
                    ("stomachs-fresh-7", FRESH7_SEEDS), ("stomachs-fresh-8", FRESH8_SEEDS),
                    ("stomachs-fresh-9", FRESH9_SEEDS))
#: Random stomachs at the family's other two sizes (``random_stomach.SIZES``; the sets above are all "small", 1.0-1.4 mm
#: in-plane): "tiny" (1.7-2.1 mm in-plane, 2.0-2.5 mm slices, coarser than clinical) and "full" (512 x 512 at 0.6-0.9
#: mm in-plane, 0.6-2.5 mm slices, the clinical range). First drawn late on 2026-12-05 to check that the defaults
#: carry over to other voxel sizes; nothing was tuned or decided on them. The bench part ``sizes`` runs them.
SIZE_SEED_SETS = (("sizes-tiny", "tiny", tuple(range(34000, 34020))),
                  ("sizes-full", "full", tuple(range(34000, 34020))))
#: Drawn stomachs inserted into each real CT that holds a whole one (``HYBRID_CTS``: 01 at 3 mm, 03 at 4.25 mm slices;
#: the 02 slab is too thin), twenty seeds a set: real organs, colon gas and lung bases round the stomach, on thick
#: slices, where the beads are drawn as large as a slice (4.25 mm in radius in 03). First run on 2026-12-06: rules
#: 26-29 (bumps bridged; 26-28 failed) and rule 30 (rule 29 rebuilt: ``isometric.bridge_bumps``, off by default,
#: ``isometric.BRIDGE_DOMES``) were developed on ``hybrids-dev``; rule 26 was decided on ``hybrids-decide``, which had
#: never been run before. Main's default method was tuned on neither. The bench part ``hybrids-many`` runs them.
HYBRID_SEED_SETS = (("hybrids-dev", tuple(range(40000, 40020))), ("hybrids-decide", tuple(range(41000, 41020))))
#: The real CTs (file name prefixes in ``../shared/data``) the drawn stomachs of HYBRID_SEED_SETS are inserted into.
HYBRID_CTS = ("01_", "03_")
#: The held-out sets a bench part of their own runs alone (each is also in ``stomachs``).
FRESH_PARTS = ("fresh-4", "fresh-5", "fresh-6", "fresh-7", "fresh-8", "fresh-9")
#: The methods compared on every random stomach, on the same volumes in one run.
FAMILY_METHODS = ("isometric", "massspring", "cylindrical", "lscm")
#: Sizes of the isometric method's surface mesh (``isometric_vertices``; its default among them) run in one part
#: (``meshsize``) on the tuning and held-out random stomachs: its speed against its accuracy, in the same hour.
MESH_SIZES = (8000, 12000, 20000)
#: Points of the mucosa laid out with the markers by the ``surfacebound`` part (flat_bound.surface_layout_reference).
SURFACE_EXTRA_POINTS = 150


def _cached(source: dict, cache_dir: str | None):
    """(CT, truth) of a random stomach or hybrid, from the cache folder when it is there, else drawn and cached."""
    from StomachUnfoldLib.io import atomic_write_text, read_volume, write_volume

    from .random_stomach import HYBRID_DRAWING, insert_into_ct, random_stomach

    # parts ``contrast`` and ``contents``: the fluid drawn at another HU; ``deep``: a pool filling more of the stomach;
    # each cached under its own name
    extra, fluid = {}, ""
    if source.get("fluid_hu") is not None:
        extra["fluid_hu"] = float(source["fluid_hu"])
        fluid += f"-fluid{extra['fluid_hu']:g}"
    if source.get("fluid_depth") is not None:
        extra.update(fluid=True, fluid_depth_fraction=float(source["fluid_depth"]))
        fluid += f"-deep{extra['fluid_depth_fraction']:g}"
    key = (f"random-{source['random']}-{source.get('size', 'small')}{fluid}" if "random" in source
           else f"hybrid-{source['hybrid']}-{os.path.basename(source['ct']).split('.')[0]}"
           + (f"-d{HYBRID_DRAWING}" if HYBRID_DRAWING != 1 else ""))
    if cache_dir:
        vol_path, json_path = os.path.join(cache_dir, key + ".nrrd"), os.path.join(cache_dir, key + ".json")
        if os.path.exists(vol_path) and os.path.exists(json_path):
            with open(json_path) as f:
                return read_volume(vol_path), json.load(f)
    if "random" in source:
        ct, truth = random_stomach(int(source["random"]), source.get("size", "small"), **extra)
    else:
        ct, truth = insert_into_ct(read_volume(source["ct"]), int(source["hybrid"]))
    if cache_dir:
        os.makedirs(cache_dir, exist_ok=True)
        write_volume(ct, vol_path)
        atomic_write_text(json_path, json.dumps(truth, default=lambda o: o.tolist() if hasattr(o, "tolist") else o))
        # the volume as every later run reads it: the file's direction matrix differs from the drawn one by about
        # 1e-16, and the flat map is not stable to that (held-out seed 1005: ratio to the bound 1.68 from the file,
        # 2.08 as drawn), so a first run would not be the same as the runs after it
        with open(json_path) as f:
            return read_volume(vol_path), json.load(f)
    return ct, truth


#: Keys of a case's source that say how to run it, not which volume: the raster's and the depth samples' offsets and
#: the set (part ``phase``).
RUN_KEYS = ("raster_offset_px", "depth_offset_px", "phase_set")


def _load(source: dict):
    """CT Volume, cardia/pylorus (LPS), optional mask and marker truth for a case's source."""
    if "random" in source or "hybrid" in source:
        ct, truth = _cached(source, source.get("_cache"))
        if source.get("turn"):  # resampled onto an oblique grid (part ``oblique``): the same anatomy, LPS unchanged
            ct = turned_grid(ct, source["turn"]["degrees"], source["turn"]["axis"])
        if source.get("prone"):  # mirrored front to back (part ``prone``): the water on the anterior wall
            ct, truth = front_to_back(ct, truth)
        if source.get("roll_deg"):  # a patient rolled about the S axis (part ``rolled``): the water's level tilted
            ct, truth = rolled(ct, truth, source["roll_deg"])
        markers = {m["id"]: m["lps"] for m in truth["markers"]}
        if source.get("auto_points"):  # zero clicks: the points found as `unfold --auto-points` finds them
            from .auto_points import found_versus_truth

            cardia, pylorus, auto = found_versus_truth(ct, truth)
            return ct, cardia, pylorus, None, dict(markers, _truth=truth, _auto=auto)
        if "click_error_mm" in source:  # the clicks off their places (part ``clicks``)
            cardia, pylorus = moved_clicks(truth["cardia_lps"], truth["pylorus_lps"], source["click_error_mm"],
                                           source["random"], source.get("click_draw", 0))
            return ct, cardia, pylorus, None, dict(markers, _truth=truth)
        return ct, np.array(truth["cardia_lps"]), np.array(truth["pylorus_lps"]), None, dict(markers, _truth=truth)
    if "real" in source:
        from StomachUnfoldLib.io import read_label_volume, read_volume

        ct = read_volume(source["real"])
        if source.get("mask"):
            mask = read_label_volume(source["mask"], ct, label_value=source.get("label"))
            return (ct, *_long_axis_ends(ct.voxel_lps(mask)), mask, None)
        # no label: the gas pocket holding the point pocket_lps (LPS mm), the lumen as the air threshold finds it
        return (ct, *_long_axis_ends(ct.voxel_lps(_gas_pocket(ct, source["pocket_lps"]))), None, None)
    from .phantom import make_phantom

    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in source.items()
          if not k.startswith("_") and k not in RUN_KEYS}
    ct, truth = make_phantom(**kw)
    markers = {m["id"]: m["lps"] for m in truth["markers"]}
    return ct, np.array(truth["cardia_lps"]), np.array(truth["pylorus_lps"]), None, markers


def _long_axis_ends(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cardia and pylorus (LPS mm) for a real CT: the ends of a region's long axis (points LPS mm), upper = cardia."""
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    proj = (pts - c) @ vt[0]
    a, b = pts[np.argmax(proj)], pts[np.argmin(proj)]
    return (b, a) if a[2] < b[2] else (a, b)


def _gas_pocket(ct, point_lps, threshold_hu: float = -500.0) -> np.ndarray:
    """The voxels below threshold_hu (HU) 6-connected to point_lps (LPS mm): a real CT's gas pocket (bool kji)."""
    from StomachUnfoldLib.preprocessing import flood_fill

    seed = tuple(np.rint(ct.lps_to_index(np.asarray(point_lps, float)[None])[0][::-1]).astype(int))
    gas = np.asarray(ct.array) < threshold_hu
    if not gas[seed]:
        raise ValueError(f"the benchmark's pocket point (LPS {point_lps} mm) is not in gas")
    return flood_fill(gas, seed)


def png_name(case_name: str) -> str:
    """File name of a case's view PNG: the case name with path separators and spaces made safe."""
    return case_name.replace("/", "__").replace(" ", "_").replace(",", "_") + ".png"


def run_case(case: dict, png_dir: str | None = None) -> dict:
    """Run one case (any method, through the one front end) and judge it; a documented failure becomes a row."""
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

    from .markers import family_marker_metrics, marker_metrics

    if case["method"] == SURFACE_LAYOUT:
        return surface_layout_row(case)
    row = {k: case[k] for k in ("name", "method", "group", "params")}
    row["source"] = {k: v for k, v in case["source"].items() if not k.startswith("_")}
    try:
        t = time.perf_counter()
        ct, cardia, pylorus, mask, markers = _load(case["source"])
        row["load_seconds"] = time.perf_counter() - t
        row["size_ijk"] = list(ct.size)
        family = markers.pop("_truth", None) if markers else None
        if markers and "_auto" in markers:
            row["auto_points"] = markers.pop("_auto")
            row["zero_clicks"] = True
            if not row["auto_points"]["confident"]:
                raise PointError(f"refused: the found points are unsure "
                                 f"(confidence {row['auto_points']['confidence']:.2f})")
        wall = {} if family is not None else {"wall_thickness_mm": _wall(case["source"])}  # unseen: defaults
        params = {**wall, **case["params"], "method": case["method"]}
        with _sampling_offsets(case["source"].get("raster_offset_px", 0.0), case["source"].get("depth_offset_px", 0.0)):
            res = unfold(ct, cardia, pylorus, UnfoldParameters(**params), mask=mask)
        rep = res.report
        q = dict(rep["quality"])
        if family is not None:
            q["markers"] = family_marker_metrics(res, family)
            q["area_scale_along"] = area_scale_along(res.mesh, res.centerline_lps)
        elif markers:
            q["markers"] = marker_metrics(res, markers)
        sim = rep["method"].get("simulation", {})
        row.update(ok=True, seconds=rep["seconds"]["total"], stage_seconds=rep["seconds"], quality=q,
                   crop_voxels=rep["input"]["crop_voxels"], peak_memory_mb=rep["peak_memory_mb"],
                   warnings=rep["warnings"], method_report={k: v for k, v in rep["method"].items()
                                                            if k not in ("simulation", "description")})
        if sim:
            row.update(iterations=sim["iterations"], converged=sim["converged"], model=rep["method"]["model"])
        if markers:
            row["markers_seen"] = q["markers"]["seen"]
            row["markers_total"] = q["markers"]["total"]
        if png_dir:
            from StomachUnfoldLib.view import render_view

            os.makedirs(png_dir, exist_ok=True)
            render_view(res.unfolded, os.path.join(png_dir, png_name(case["name"])))
    except StomachUnfoldError as e:
        row.update(ok=False, error=f"{type(e).__name__}: {e}")
    except Exception as e:  # a bug is data here too, with its traceback, so a sweep finishes
        row.update(ok=False, error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=3))
    return row


@contextlib.contextmanager
def _sampling_offsets(offset_px: float, depth_px: float = 0.0):
    """The surface methods' view raster moved ``offset_px`` pixels along i and j, and its depth samples ``depth_px``
    voxels toward the lumen, for the block (part ``phase``)."""
    from StomachUnfoldLib import surface

    old = surface.RASTER_OFFSET_PX, surface.DEPTH_OFFSET_PX
    surface.RASTER_OFFSET_PX, surface.DEPTH_OFFSET_PX = float(offset_px), float(depth_px)
    try:
        yield
    finally:
        surface.RASTER_OFFSET_PX, surface.DEPTH_OFFSET_PX = old


def _run_case_in_worker(case: dict, png_dir: str | None = None) -> dict:
    """:func:`run_case` in a Dask worker, as in a batch worker: freed memory goes back as the command line sets it
    (Dask starts its workers with MALLOC_TRIM_THRESHOLD_=65536, which trims the heap under every freed array of the
    flat map's iterations: the isometric method ran about 2x slower there than from the command line), and nothing
    runs beside the run's main thread."""
    from StomachUnfoldLib import spare_core
    from StomachUnfoldLib.frontend import return_freed_memory

    return_freed_memory()
    spare_core.SPARE_CORES = False
    return run_case(case, png_dir)


def run_cases(cases: list[dict], png_dir: str | None = None, scheduler: str | None = None,
              workers: int | None = None) -> list[dict]:
    """Run cases in parallel through Dask (local cluster, or the scheduler address given); rows in case order."""
    if len(cases) == 0:
        return []
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:  # Dask missing: run here, one after the other
        return [run_case(c, png_dir) for c in cases]
    if scheduler:
        client = Client(scheduler)
        cluster = None
    else:
        cluster = LocalCluster(n_workers=workers or max(1, min(2, os.cpu_count() or 1)), threads_per_worker=1,
                               processes=True, dashboard_address=None)
        client = Client(cluster)
    try:
        futures = client.map(_run_case_in_worker, cases, png_dir=png_dir, pure=False)
        return client.gather(futures)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# ------------------------------------------------------------------------------------------ benchmark
def _cases(quick: bool, full_size: bool, data_dir: str | None, parts) -> list[dict]:
    size = "tiny" if quick else "small"
    shapes = phantom_set(size)
    if quick:
        shapes = shapes[:3]
    cases = []
    if "shapes" in parts:
        for src in shapes:
            cases.append(Case(src["_name"], src, {}, group="shapes"))
            cases.append(Case(src["_name"] + "/paper-forces", src, {}, method="paper", group="shapes-paper"))
    if "kappa" in parts:
        for k in (KAPPAS if not quick else [0.2, 1.0]):
            for src in shapes:
                cases.append(Case(f"{src['_name']}/kappa={k}", src, {"kappa": k}, group="kappa"))
                cases.append(Case(f"{src['_name']}/kappa={k}/paper", src, {"kappa": k}, method="paper",
                                  group="kappa-paper"))
    sweep_src = [s for s in shapes if s["_name"].split("-")[0] in ("j", "twisted", "bent")][:3]
    if "sweep" in parts:
        configs = [{"grid_mm": g} for g in (3.6, 5.6, 8.4)] + [{"kappa": k} for k in (0.2, 1.0)] + \
                  [{"time_step": h} for h in (0.5, 2.0, 4.0)] + \
                  [{"integrator": "explicit", "time_step": h, "max_retries": 0} for h in (0.05, 0.1)]
        if quick:
            configs = configs[:2]
        for cfg in configs:
            label = ",".join(f"{k}={v}" for k, v in cfg.items() if k != "max_retries")
            for src in sweep_src:
                cases.append(Case(f"{src['_name']}/{label}", src, cfg, group="sweep"))
    if "stability" in parts:
        src = sweep_src[0] if sweep_src else shapes[0]
        for h in ((0.1, 1.0, 10.0) if quick else (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)):
            for integ in ("newmark", "explicit"):
                cases.append(Case(f"{src['_name']}/{integ}/h={h}", src,
                                  {"integrator": integ, "time_step": h, "max_retries": 0,
                                   "max_iterations": 400}, group="stability"))
        extremes = [{"shape": "twisted", "size": size, "_name": f"twisted-{size}"},
                    {"shape": "j", "size": size, "wall_thickness_mm": 1.5, "_name": f"j-wall1.5-{size}"},
                    {"shape": "j", "size": size, "radius_scale": 0.3, "_name": f"j-lumen0.3-{size}"}]
        for src in (extremes if not quick else extremes[2:]):
            for k in (0.1, 2.0):
                cases.append(Case(f"{src['_name']}/kappa={k}", src, {"kappa": k}, group="extremes"))
    if "resolution" in parts:
        src = [s for s in shapes if s["_name"].startswith("j-") or s["_name"] == f"j-{size}"][0]
        for g in ((4.2, 8.4) if quick else (2.8, 4.2, 5.6, 8.4, 11.2)):
            cases.append(Case(f"{src['_name']}/grid_mm={g}", src, {"grid_mm": g}, group="resolution"))
    if "peers" in parts:
        for src in shapes:
            for m in ("isometric", "cylindrical", "lscm"):
                cases.append(Case(f"{src['_name']}/{m}", src, {}, method=m, group="peers"))
    if "real" in parts and data_dir and os.path.isdir(data_dir):
        d = data_dir
        reals = [("real-01-3mm", {"real": os.path.join(d, "01_totalseg_example_ct_abdpelvis_3mm.nii.gz"),
                                  "mask": os.path.join(d, "01_totalseg_example_ct_abdpelvis_3mm_seg117_top30slices_DERIVED.nii.gz"),
                                  "label": 6}),
                 ("real-02-slab", {"real": os.path.join(d, "02_totalseg_example_ct_dicom_slab_2mm.nii.gz"),
                                   "mask": os.path.join(d, "02_totalseg_example_ct_dicom_slab_seg117_stomach6.nii.gz"),
                                   "label": 6}),
                 # no label, the stomach collapsed round food: only its 24 mL anterior gas pocket (data/README.txt)
                 # can be unfolded; the points are the pocket's long-axis ends, found from this point in it
                 ("real-03-pocket", {"real": os.path.join(d, "03_tcia_acrin_flt_breast_001_ct_chest_abd_pelvis_"
                                                             "4p25mm.nii.gz"), "pocket_lps": [16.6, -45.9, -493.5]})]
        for name, src in reals:
            if os.path.exists(src["real"]):
                cases.append(Case(name, src, {"grid_size": 2, "wall_thickness_mm": 4.0}, group="real"))
                for m in ("isometric", "cylindrical", "lscm"):  # the other methods on the same CTs and labels
                    cases.append(Case(f"{name}/{m}", src, {}, method=m, group="real"))
    if "stomachs" in parts:
        cases += family_cases(quick, data_dir)
    else:
        if "hybrids" in parts:  # the hybrids alone (they are part of "stomachs")
            cases += hybrid_cases(quick, data_dir)
        fresh = {f"stomachs-{p}" for p in FRESH_PARTS if p in parts}  # held-out sets alone (in "stomachs")
        if fresh:
            cases += [c for c in family_cases(quick, None) if c["group"] in fresh]
    if "zeroclicks" in parts:
        cases += zero_click_cases(quick)
    if "sizes" in parts:
        cases += size_cases(quick)
    if "hybrids-many" in parts:
        cases += hybrid_seed_cases(quick, data_dir)
    if "meshsize" in parts:
        cases += mesh_size_cases(quick)
    if "clicks" in parts:
        cases += click_error_cases(quick, TUNE_SEEDS, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "oblique" in parts:
        cases += oblique_cases(quick, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "prone" in parts:
        cases += prone_cases(quick, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "rolled" in parts:
        cases += rolled_cases(quick, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "contrast" in parts:
        cases += contrast_cases(quick, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "contents" in parts:
        cases += contents_cases(quick, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "deep" in parts:
        cases += deep_cases(quick, HELD_OUT_SEEDS, _phantom_cache(None), Case)
    if "phase" in parts:
        cases += phase_cases(quick, data_dir, _real_cts(data_dir), _phantom_cache(None), Case)
    if "surfacebound" in parts:
        cases += surface_bound_cases(quick)
    if "surfacebound-fresh" in parts:
        cases += surface_bound_cases(quick, fresh=True)
    return cases


def _phantom_cache(cache_dir: str | None) -> str:
    """The folder of drawn phantoms kept between runs: ``cache_dir``, else ~/.cache/stomach-unfold/phantoms."""
    return cache_dir or os.path.join(os.path.expanduser("~"), ".cache", "stomach-unfold", "phantoms")


def mesh_size_cases(quick: bool, cache_dir: str | None = None) -> list[dict]:
    """The default method on the tuning and held-out random stomachs with each of MESH_SIZES as its mesh's size."""
    cache = _phantom_cache(cache_dir)
    seeds = (TUNE_SEEDS[:2] + HELD_OUT_SEEDS[:2]) if quick else (TUNE_SEEDS + HELD_OUT_SEEDS)
    return [Case(f"stomach-{seed}/{FAMILY_METHODS[0]}-v{n}", {"random": int(seed), "size": "small", "_cache": cache},
                 {"isometric_vertices": n}, method=FAMILY_METHODS[0], group="mesh-size")
            for n in MESH_SIZES for seed in seeds]


def mesh_size_summary(rows: list[dict]) -> list[dict]:
    """Per mesh size and seed set (tuning, held-out): median seconds, the marker distortion's ratio to the bound
    (median, volumes within 1.5x), visible median, markers seen, excellent (the ``meshsize`` part's rows)."""
    from StomachUnfoldLib.params import SurfaceParameters

    default = SurfaceParameters().isometric_vertices
    out = []
    for label, seeds in (("tuning", set(TUNE_SEEDS)), ("held-out", set(HELD_OUT_SEEDS))):
        for n in MESH_SIZES:
            rs = [r for r in rows if r.get("ok") and r["group"] == "mesh-size"
                  and r["params"].get("isometric_vertices") == n]
            rs = [r for r in rs if int(r["name"].split("/")[0].split("-")[1]) in seeds and "markers" in r["quality"]]
            if not rs:
                continue
            mk = [r["quality"]["markers"] for r in rs]
            out.append({"set": label, "vertices": n, "default": n == default, "volumes": len(rs),
                        "seconds_median": float(np.median([r["seconds"] for r in rs])),
                        "ratio_median": float(np.median([m["ratio_to_bound"] for m in mk])),
                        "within_1p5": sum(m["ratio_to_bound"] <= 1.5 for m in mk),
                        "visible_median": float(np.median([r["quality"]["visible_fraction"] for r in rs])),
                        "markers_seen": sum(m["seen"] for m in mk), "markers_total": sum(m["total"] for m in mk),
                        "excellent": sum(r["quality"]["grade"] == "excellent" for r in rs)})
    return out


def mesh_size_markdown(rows: list[dict]) -> list[str]:
    """results.md's table of :func:`mesh_size_summary` (nothing when the part was not run)."""
    summ = mesh_size_summary(rows)
    if not summ:
        return []
    L = ["## Isometric mesh size: speed against accuracy (random stomachs, two at once)\n",
         "| set | isometric_vertices | volumes | s median | x bound median | within 1.5x | visible median % | markers "
         "| excellent |", "|---|---|---|---|---|---|---|---|---|"]
    for x in summ:
        L.append(f"| {x['set']} | {x['vertices']}{' (default)' if x['default'] else ''} | {x['volumes']} | "
                 f"{x['seconds_median']:.1f} | {x['ratio_median']:.2f} | {x['within_1p5']} | "
                 f"{100 * x['visible_median']:.2f} | {x['markers_seen']}/{x['markers_total']} | {x['excellent']} |")
    return L + [""]


#: The ``method`` of the ``surfacebound`` part's rows: no method runs, the references are computed.
SURFACE_LAYOUT = "surface-layout"


def surface_bound_cases(quick: bool, fresh: bool = False) -> list[dict]:
    """The tuning and held-out random stomachs' references (part ``surfacebound``), or the nine later held-out sets'
    (``fresh``, part ``surfacebound-fresh``): the markers' flat-layout bound against the best layout of the whole
    mucosa (see :func:`surface_layout_row`)."""
    sets = [seeds for group, seeds in FAMILY_SEED_SETS if (group not in ("stomachs-tune", "stomachs-held-out")) == fresh]
    seeds = tuple(x[0] for x in sets) if quick else tuple(x for s in sets for x in s)
    n = 20 if quick else SURFACE_EXTRA_POINTS
    return [Case(f"stomach-{seed}/{SURFACE_LAYOUT}", {"random": int(seed), "size": "small"}, {"n_extra": n},
                 method=SURFACE_LAYOUT, group="surface-bound") for seed in seeds]


def surface_layout_row(case: dict) -> dict:
    """A ``surfacebound`` row: on one random stomach, the markers' flat-layout bound (as the family rows have it) and
    fitted robustly, and the best layout of the whole mucosa (its markers and ``n_extra`` other points, true cut
    geodesics), plain and robust, scored on the markers (median |log(d2/g)|, pairs 10-80 mm)."""
    from .flat_bound import flat_layout_bound, surface_layout_reference
    from .random_stomach import surface_reference_geodesics

    row = {k: case[k] for k in ("name", "method", "group", "params")}
    row["source"] = dict(case["source"])
    try:
        t = time.perf_counter()
        src = case["source"]
        geo = surface_reference_geodesics(int(src["random"]), src.get("size", "small"), case["params"]["n_extra"])
        G, m = geo["geodesic_cut_mm"], geo["n_markers"]
        whole = surface_layout_reference(G, m)
        whole_r = surface_layout_reference(G, m, robust=True)
        ref = {"n_markers": m, "n_points": whole["n_points"], "n_pairs": whole["n_pairs"],
               "marker_bound": flat_layout_bound(G[:m, :m])["median_relative_error"],
               "marker_bound_robust": flat_layout_bound(G[:m, :m], robust=True)["median_relative_error"],
               "surface_layout": whole["median_relative_error"], "surface_layout_robust": whole_r["median_relative_error"],
               "surface_all_pairs": whole["all_pairs_median"], "surface_all_pairs_robust": whole_r["all_pairs_median"]}
        row.update(ok=True, seconds=time.perf_counter() - t, reference=ref)
    except Exception as e:  # data, as in run_case
        row.update(ok=False, error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=3))
    return row


def _surface_bound_entry(label: str, refs: dict, rows: list[dict], groups: set) -> dict:
    """One line of :func:`surface_bound_summary`: the reference rows ``refs`` (volume name -> reference) of one or
    more seed sets, and the family rows of ``groups`` on those volumes."""
    b = np.array([v["marker_bound"] for v in refs.values()])
    rel = {k: np.array([v[k] for v in refs.values()]) / b
           for k in ("marker_bound_robust", "surface_layout", "surface_layout_robust")}
    entry = {"set": label, "volumes": len(refs), "bound_median": float(np.median(b)),
             "other_points": int(np.median([v["n_points"] - v["n_markers"] for v in refs.values()])),
             **{f"{k}_over_bound_median": float(np.median(x)) for k, x in rel.items()},
             **{f"{k}_over_bound_max": float(np.max(x)) for k, x in rel.items()},
             **{f"{k}_over_1p5": int(np.sum(x > 1.5)) for k, x in rel.items()}, "methods": {}}
    for m in FAMILY_METHODS:
        rs = [r for r in rows if r["group"] in groups and r["method"] == m and r.get("ok")
              and not r.get("zero_clicks") and r["name"].split("/")[0] in refs
              and r["quality"].get("markers", {}).get("pairwise_distance_distortion") is not None]
        if not rs:
            continue
        d = np.array([r["quality"]["markers"]["pairwise_distance_distortion"] for r in rs])
        ref = [refs[r["name"].split("/")[0]] for r in rs]
        xb = d / np.array([v["marker_bound"] for v in ref])
        xs = d / np.array([v["surface_layout"] for v in ref])
        entry["methods"][m] = {"volumes": len(rs), "over_bound_median": float(np.median(xb)),
                               "within_1p5_of_bound": int(np.sum(xb <= 1.5)),
                               "over_surface_median": float(np.median(xs)),
                               "within_1p5_of_surface": int(np.sum(xs <= 1.5))}
    return entry


def surface_bound_summary(rows: list[dict]) -> list[dict]:
    """Per seed set with reference rows (and all held-out sets together, when there are several): the
    ``surfacebound`` references over the bound, and each family method's marker distortion over the bound and over
    the whole mucosa's layout, on the volumes that have both."""
    refs = {r["name"].split("/")[0]: r["reference"] for r in rows if r.get("group") == "surface-bound" and r.get("ok")}
    out, unseen, unseen_groups = [], {}, set()
    for group, seeds in FAMILY_SEED_SETS:
        mine = {f"stomach-{seed}": refs[f"stomach-{seed}"] for seed in seeds if f"stomach-{seed}" in refs}
        if not mine:
            continue
        label = "tuning" if group == "stomachs-tune" else f"{group[len('stomachs-'):]} {seeds[0]}-"
        out.append(_surface_bound_entry(label, mine, rows, {group}))
        if group != "stomachs-tune":
            unseen.update(mine)
            unseen_groups.add(group)
    if len(unseen_groups) > 1:
        out.append(_surface_bound_entry(f"all {len(unseen_groups)} held-out sets", unseen, rows, unseen_groups))
    return out


def surface_bound_markdown(rows: list[dict]) -> list[str]:
    """results.md's section of :func:`surface_bound_summary` (nothing when the part was not run)."""
    summ = surface_bound_summary(rows)
    if not summ:
        return []
    L = ["## The flat-layout bound against the best flat layout of the whole mucosa (random stomachs)\n",
         "Each layout scored on the markers' pairs (median |log(view / true geodesic)|, 10-80 mm), over the markers' "
         "flat-layout bound (the family tables' bound). Robust: polished for the absolute log errors, which the median "
         f"rewards. Whole mucosa: the markers laid out among {summ[0]['other_points']} other points of it, every pair "
         "fitted, so the layout does not know which points are markers.\n",
         "| set | volumes | bound median | markers fitted robustly / bound: median (max) | whole mucosa / bound: "
         "median (max), over 1.5x | whole mucosa, robust / bound: median (max), over 1.5x |", "|---|---|---|---|---|---|"]
    for x in summ:
        L.append(f"| {x['set']} | {x['volumes']} | {x['bound_median']:.4f} | "
                 f"{x['marker_bound_robust_over_bound_median']:.2f} ({x['marker_bound_robust_over_bound_max']:.2f}) | "
                 f"{x['surface_layout_over_bound_median']:.2f} ({x['surface_layout_over_bound_max']:.2f}), "
                 f"{x['surface_layout_over_1p5']} | {x['surface_layout_robust_over_bound_median']:.2f} "
                 f"({x['surface_layout_robust_over_bound_max']:.2f}), {x['surface_layout_robust_over_1p5']} |")
    L += ["", "| set | method | volumes | x bound: median, within 1.5x | x whole-mucosa layout: median, within 1.5x |",
          "|---|---|---|---|---|"]
    for x in summ:
        for m, v in x["methods"].items():
            L.append(f"| {x['set']} | {m} | {v['volumes']} | {v['over_bound_median']:.2f}, {v['within_1p5_of_bound']} | "
                     f"{v['over_surface_median']:.2f}, {v['within_1p5_of_surface']} |")
    return L + [""]


def zero_click_cases(quick: bool, cache_dir: str | None = None) -> list[dict]:
    """The default method on every random stomach from the points found automatically (zero clicks)."""
    cache = _phantom_cache(cache_dir)
    cases = []
    for group, seeds in (("stomachs-tune", TUNE_SEEDS), ("stomachs-held-out", HELD_OUT_SEEDS)):
        for seed in seeds[:3] if quick else seeds:
            src = {"random": int(seed), "size": "small", "_cache": cache, "auto_points": True}
            cases.append(Case(f"stomach-{seed}/{FAMILY_METHODS[0]}-zero-clicks", src, {}, method=FAMILY_METHODS[0],
                              group=group))
    return cases


def size_cases(quick: bool, cache_dir: str | None = None) -> list[dict]:
    """Every FAMILY_METHODS on the random stomachs of SIZE_SEED_SETS (tiny and full size; quick: two tiny ones), and
    the default method from the points found automatically (zero clicks)."""
    cache = _phantom_cache(cache_dir)
    sets = [(g, size, seeds[:2]) for g, size, seeds in SIZE_SEED_SETS[:1]] if quick else SIZE_SEED_SETS
    cases = []
    for group, size, seeds in sets:
        for seed in seeds:
            src = {"random": int(seed), "size": size, "_cache": cache}
            cases += [Case(f"stomach-{seed}-{size}/{m}", src, {}, method=m, group=group) for m in FAMILY_METHODS]
            cases.append(Case(f"stomach-{seed}-{size}/{FAMILY_METHODS[0]}-zero-clicks", dict(src, auto_points=True), {},
                              method=FAMILY_METHODS[0], group=group))
    return cases


def hybrid_seed_cases(quick: bool, data_dir: str | None, cache_dir: str | None = None) -> list[dict]:
    """Every FAMILY_METHODS on the drawn stomachs of HYBRID_SEED_SETS inserted into each real CT of HYBRID_CTS found in
    ``data_dir`` (none without it; quick: the first two seeds of the first set)."""
    cache = _phantom_cache(cache_dir)
    cts = [n for n in _real_cts(data_dir) if n.startswith(HYBRID_CTS)]
    sets = [(g, seeds[:2]) for g, seeds in HYBRID_SEED_SETS[:1]] if quick else HYBRID_SEED_SETS
    cases = []
    for group, seeds in sets:
        for name in cts:
            for seed in seeds:
                src = {"hybrid": int(seed), "ct": os.path.join(data_dir, name), "_cache": cache}
                cases += [Case(f"hybrid-{name.split('_')[0]}-{seed}/{m}", src, {}, method=m, group=group)
                          for m in FAMILY_METHODS]
    return cases


def family_cases(quick: bool, data_dir: str | None, cache_dir: str | None = None) -> list[dict]:
    """Random stomachs (tuned-on and held-out seeds) and hybrids in the real CTs, every FAMILY_METHODS on each."""
    cache = _phantom_cache(cache_dir)
    groups = [(group, (seeds[:3] if group in ("stomachs-tune", "stomachs-held-out") else ()) if quick else seeds)
              for group, seeds in FAMILY_SEED_SETS]
    cases = []
    for group, seeds in groups:
        for seed in seeds:
            src = {"random": int(seed), "size": "small", "_cache": cache}
            for m in FAMILY_METHODS:
                cases.append(Case(f"stomach-{seed}/{m}", src, {}, method=m, group=group))
    return cases + hybrid_cases(quick, data_dir, cache_dir)


#: The drawn stomachs' seeds for the real CTs, in the order of their file names (the hybrids drawn since 2026-12-01;
#: they were once taken from the number of cases before them, so a new set of seeds would have changed them).
HYBRID_SEEDS = (1004, 1001, 1005)


def _real_cts(data_dir: str | None) -> list[str]:
    """File names of the real CTs in ``data_dir`` (NIfTI, not the label files), sorted; none without the folder."""
    if not data_dir or not os.path.isdir(data_dir):
        return []
    return [n for n in sorted(os.listdir(data_dir)) if n.endswith(".nii.gz") and "_seg" not in n and "DERIVED" not in n]


def hybrid_cases(quick: bool, data_dir: str | None, cache_dir: str | None = None) -> list[dict]:
    """A drawn stomach inserted into each real CT of ``data_dir`` that holds one (HYBRID_CTS; seeds HYBRID_SEEDS by
    the files' order), every FAMILY_METHODS on each."""
    cache = _phantom_cache(cache_dir)
    cases = []
    if not quick:
        for n, name in enumerate(_real_cts(data_dir)):
            if not name.startswith(HYBRID_CTS):   # the 02 slab (40 mm) cannot hold a stomach: every method failed on it
                continue
            seed = HYBRID_SEEDS[n] if n < len(HYBRID_SEEDS) else 1000 + n
            src = {"hybrid": seed, "ct": os.path.join(data_dir, name), "_cache": cache}
            for m in FAMILY_METHODS:
                cases.append(Case(f"hybrid-{name.split('_')[0]}/{m}", src, {}, method=m, group="stomachs-hybrid"))
    return cases


def _serial_cases(quick: bool, full_size: bool, parts) -> list[dict]:
    """Cases whose timing matters (scaling with volume size, cell size and crop size): run one at a time, alone."""
    cases = []
    if "scaling" in parts:
        sizes = ("tiny", "small") if quick else ("tiny", "small", "medium") + (("full",) if full_size else ())
        for size in sizes:
            cases.append(Case(f"j-{size}/volume", {"shape": "j", "size": size}, {}, group="scaling-volume"))
        if full_size:
            for g in (4.2, 5.6, 8.4, 11.2):
                cases.append(Case(f"j-full/grid_mm={g}", {"shape": "j", "size": "full"}, {"grid_mm": g},
                                  group="scaling-grid"))
        size = "tiny" if quick else "small"
        for m in ((0.0, 1000.0) if quick else (0.0, 15.0, 40.0, 1000.0)):
            cases.append(Case(f"j-{size}/crop_margin_mm={m:g}", {"shape": "j", "size": size},
                              {"crop_margin_mm": m}, group="crop"))
    return cases


def _isolated(fn, *args, **kwargs):
    """Call fn in a fresh process (spawned), so that its timing and peak memory are its own."""
    import concurrent.futures as cf
    import multiprocessing as mp

    with cf.ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(fn, *args, **kwargs).result()


isolated_call = _isolated  # the public name, for the benchmark's other modules (memory)


def _defects(q: dict) -> dict:
    """The paper's Table 1 categories from the automatic metrics of one view (one definition, the batch's)."""
    from StomachUnfoldLib.batch import paper_categories

    return paper_categories(q)


def floor_seconds(ct_path: str) -> dict:
    """The practical floor of issue 6: seconds to read the CT plus one trilinear resampling pass over it."""
    import SimpleITK as sitk

    t = time.perf_counter()
    img = sitk.ReadImage(ct_path)
    read = time.perf_counter() - t
    t = time.perf_counter()
    tx = sitk.TranslationTransform(3, (0.25, 0.25, 0.25))
    sitk.Resample(img, img, tx, sitk.sitkLinear, -1024.0)
    resample = time.perf_counter() - t
    return {"read_s": read, "resample_s": resample, "floor_s": read + resample}


def write_full_phantom(path: str, slices: int = 500) -> dict:
    """Write the 512 x 512 x ``slices`` J phantom at 0.7 mm to ``path``; returns its truth (LPS/RAS mm)."""
    from StomachUnfoldLib.io import write_volume
    from .phantom import make_phantom

    ct, truth = make_phantom("j", "full", full_slices=slices)
    write_volume(ct, path)
    return truth


def full_size_run(path: str, truth: dict, out_dir: str, profile: bool = False) -> dict:
    """Whole pipeline on a full-size CT file (read, unfold, write), against the read+resample floor.

    Run it in a fresh process (``_isolated``) so that the peak memory is the pipeline's. With ``profile`` the
    run is made under cProfile and the top functions are written to ``out_dir/profile-full-<slices>.txt``
    (profiling slows it; its timings are not the benchmark's).
    """
    import cProfile
    import io as _io
    import pstats
    import resource
    import shutil
    import tempfile

    from StomachUnfoldLib.frontend import return_freed_memory
    from StomachUnfoldLib.io import read_volume
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold
    from .markers import marker_metrics

    floor = _isolated(floor_seconds, path)  # in its own process: its whole read is not this run's peak memory
    out = tempfile.mkdtemp(prefix="su-full-out-")
    try:
        prof = cProfile.Profile() if profile else None
        if prof:
            prof.enable()
        return_freed_memory()  # as the command line does
        t = time.perf_counter()
        vol = read_volume(path, stream=True)  # as the command line: left on file, read box by box by the front end
        read_s = time.perf_counter() - t
        res = unfold(vol, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters())
        t_write = time.perf_counter()
        res.write(out)
        write_s = time.perf_counter() - t_write
        total = time.perf_counter() - t
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        if prof:
            prof.disable()
            buf = _io.StringIO()
            pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(40)
            with open(os.path.join(out_dir, f"profile-full-{vol.size[2]}.txt"), "w") as f:
                f.write(buf.getvalue())
        q = res.report["quality"]
        mk = marker_metrics(res, {m["id"]: m["lps"] for m in truth["markers"]})
        return {"size_ijk": list(vol.size), "pipeline_s": total, "read_volume_s": read_s, "write_outputs_s": write_s,
                "stage_seconds": res.report["seconds"], **floor, "ratio_to_floor": total / floor["floor_s"],
                "peak_memory_mb": peak, "grade": q["grade"], "visible_fraction": q["visible_fraction"],
                "markers_seen": mk["seen"], "markers_total": mk["total"], "method": res.report["method"]["name"],
                "model": res.report["method"].get("model", {"triangles": res.report["method"].get("triangles")}),
                "profiled": profile,
                "iterations": res.report["method"].get("simulation", {}).get("iterations",
                                                                           res.report["method"].get("arap_iterations"))}
    finally:
        shutil.rmtree(out, ignore_errors=True)


def full_size_runs(out_dir: str, slices=(400, 500), profile: bool = True) -> dict:
    """Timed full-size runs (each in a fresh process) for each slice count, and one profiled run of the last."""
    import shutil
    import tempfile

    tmp = tempfile.mkdtemp(prefix="su-full-")
    runs = {}
    try:
        for n in slices:
            path = os.path.join(tmp, f"full{n}.nrrd")
            truth = _isolated(write_full_phantom, path, n)
            runs[str(n)] = _isolated(full_size_run, path, truth, out_dir)
            if profile and n == slices[-1]:
                _isolated(full_size_run, path, truth, out_dir, True)
            os.remove(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return runs


def _plain_log_ticks(ax, axes="xy") -> None:
    """Log axes labelled 2, 5, 10 ... instead of 2x10^0 (every minor tick when the axis spans under a decade)."""
    from matplotlib.ticker import FuncFormatter

    def minor(axis):
        def fmt(v, _):
            lo, hi = sorted(axis.get_view_interval())
            mantissa = round(v / 10 ** np.floor(np.log10(v)), 6) if v > 0 else 0
            few = lo > 0 and hi / lo < 10.0  # under a decade: label every minor tick, else only 2 and 5
            return f"{v:g}" if few or mantissa in (2.0, 5.0) else ""
        return FuncFormatter(fmt)

    for name in axes:
        axis = ax.xaxis if name == "x" else ax.yaxis
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(minor(axis))


def _save(fig, out_dir: str, name: str, made: list[str]) -> None:
    """Lay out, write out_dir/name (PNG, 110 dpi), close the figure and list the name in ``made``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, name), dpi=110)
    plt.close(fig)
    made.append(name)


def _plots(rows: list[dict], out_dir: str, full: dict | None) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    ok = [r for r in rows if r.get("ok")]
    # Pareto: seconds against hidden mucosa and against distortion, one point per configuration, each point the
    # mean over the same phantoms (the sweep's), so that configurations compare on equal ground
    base = {r["name"].split("/")[0] for r in ok if r["group"] == "sweep"}
    pts = [r for r in ok if r["group"] in ("sweep", "peers", "shapes", "shapes-paper") and
           (not base or r["name"].split("/")[0] in base)]
    if pts:
        cfg = {}
        for r in pts:
            label = r["name"].split("/", 1)[1] if "/" in r["name"] else "default"
            if r["method"] not in ("massspring", "paper"):
                label = r["method"]
            cfg.setdefault(label, []).append(r)
        colour = {"cylindrical": "tab:green", "lscm": "tab:red", "paper-forces": "tab:orange"}
        fig, axes = plt.subplots(1, 2, figsize=(14, 5.5))
        for ax, metric, ylabel in ((axes[0], "hidden", "hidden mucosa fraction (1 - visible)"),
                                   (axes[1], "distortion", "area + angle distortion of the mucosa")):
            xy = []
            for label, rs in sorted(cfg.items()):
                if metric == "hidden":
                    vals = [1 - r["quality"]["visible_fraction"] for r in rs if "visible_fraction" in r["quality"]]
                else:
                    vals = [r["quality"]["area_distortion"] + r["quality"]["angle_distortion"] for r in rs
                            if "area_distortion" in r["quality"]]
                if not vals:
                    continue
                x, y = float(np.mean([r["seconds"] for r in rs])), float(np.mean(vals))
                xy.append((x, y, label))
                c = colour.get(label, "tab:red" if label.startswith("explicit") or "integrator=explicit" in label
                               else "tab:blue")
                ax.scatter(x, y, color=c, marker="s" if label in ("cylindrical", "lscm") else "o", s=30)
            front, best = [], np.inf
            for x, y, _ in sorted(xy):
                if y < best:
                    front.append((x, y))
                    best = y
            if len(front) > 1:
                ax.step(*zip(*front), where="post", color="k", ls=":", lw=1, label="Pareto front")
                ax.legend(fontsize=8)
            ax.set_xscale("log")
            _plain_log_ticks(ax, "x")
            ax.set_xlabel("seconds per case (mean)")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3, which="both")
            place_labels(ax, [(x, y, label.replace("integrator=", "")[:30]) for x, y, label in xy])
        fig.suptitle(f"Speed against accuracy on {', '.join(sorted(base)) or 'the phantom set'} "
                     "(lower left is better; blue: ours, orange: the paper's forces, green/red: peers)")
        _save(fig, out_dir, "pareto.png", made)
    stab = [r for r in rows if r["group"] == "stability"]
    if stab:
        fig, ax = plt.subplots(figsize=(7, 4))
        for integ, mk in (("newmark", "o-"), ("explicit", "s--")):
            rs = [r for r in stab if f"/{integ}/" in r["name"]]
            hs = [float(r["name"].rsplit("h=", 1)[1]) for r in rs]
            vis = [r["quality"]["visible_fraction"] if r.get("ok") else 0.0 for r in rs]
            ax.plot(hs, vis, mk, label=integ)
            for h, r in zip(hs, rs):
                if not r.get("ok"):
                    ax.annotate("diverged", (h, 0.0), fontsize=7, rotation=60)
        ax.set_xscale("log")
        _plain_log_ticks(ax, "x")
        ax.set_xlabel("time step h")
        ax.set_ylabel("visible mucosa fraction")
        ax.legend()
        ax.grid(alpha=0.3)
        ax.set_title("Stability: implicit Newmark-beta against explicit integration")
        ax.text(0.32, 0.3, "visibility drops at small h: each step moves the wall less, so |D(a-1) - D(a)|\n"
                "falls under kappa and the run stops before the wall is unfolded", transform=ax.transAxes,
                fontsize=7, va="bottom")
        _save(fig, out_dir, "stability.png", made)
    resr = [r for r in ok if r["group"] == "resolution"]
    if resr:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
        g = [float(r["name"].rsplit("=", 1)[1]) for r in resr]
        axes[0].plot(g, [r["seconds"] for r in resr], "o-")
        axes[0].set_ylabel("seconds")
        axes[1].plot(g, [r["quality"]["visible_fraction"] for r in resr], "o-", label="visible fraction")
        axes[1].plot(g, [r["quality"]["area_distortion"] for r in resr], "s--", label="area distortion")
        axes[1].plot(g, [r["quality"]["angle_distortion"] for r in resr], "^--", label="angle distortion")
        axes[1].legend()
        for a in axes:
            a.set_xlabel("cell size (mm)")
            a.grid(alpha=0.3)
        fig.suptitle(f"Model no more than the scene needs: {resr[0]['name'].split('/')[0]} against cell size")
        _save(fig, out_dir, "resolution.png", made)
    scal = {g: [r for r in ok if r["group"] == g] for g in ("scaling-volume", "scaling-grid", "crop")}
    if any(scal.values()):
        fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
        for ax, grp, xkey, xlabel in ((axes[0], "scaling-volume", "wall_voxels", "wall voxels (volume size grows)"),
                                      (axes[1], "scaling-grid", "hexahedra", "hexahedra (cell size shrinks)"),
                                      (axes[2], "crop", "crop_voxels", "voxels in the crop (margin grows)")):
            rs = scal[grp]
            if not rs:
                ax.set_visible(False)
                continue
            x = np.array([r["crop_voxels"] if xkey == "crop_voxels" else r["model"][xkey] for r in rs], float)
            y = np.array([r["seconds"] for r in rs])
            o = np.argsort(x)
            ax.loglog(x[o], y[o], "o-", label="measured")
            ax.loglog(x[o], y[o][0] * x[o] / x[o][0], "k:", label="linear from the first point")
            for xi, yi, r in zip(x, y, rs):
                ax.annotate(r["name"].split("/")[-1] if grp != "scaling-volume" else r["name"].split("/")[0],
                            (xi, yi), fontsize=7)
            _plain_log_ticks(ax)
            ax.set_xlabel(xlabel)
            ax.set_ylabel("seconds (unfold)")
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8)
        fig.suptitle("Cost against size: volume, model resolution and crop")
        _save(fig, out_dir, "scaling.png", made)
    if full:
        fig, ax = plt.subplots(figsize=(10, 3.4))
        colours, seen = {}, set()
        for yi, (n, f) in enumerate(sorted(full.items())):
            parts = [("read", f["read_volume_s"])] + [(k, v) for k, v in f["stage_seconds"].items() if k != "total"] + \
                    [("write", f["write_outputs_s"])]
            left = 0.0
            for k, v in parts:
                c = colours.setdefault(k, plt.cm.tab20(len(colours) % 20))  # one colour per stage in every bar
                ax.barh(yi, v, left=left, color=c, edgecolor="white", linewidth=0.5, label=k if k not in seen else None)
                seen.add(k)
                if v > 0.25:
                    ax.text(left + v / 2, yi, k, ha="center", va="center", fontsize=7, rotation=90)
                left += v
            ax.axvline(f["floor_s"], color="k", ls=":")
        # every stage, the small ones too, in the legend with its colour
        ax.legend(fontsize=7, ncol=min(len(colours), 6), loc="upper center", bbox_to_anchor=(0.5, -0.35),
                  frameon=False)
        ax.set_yticks(range(len(full)), [f"512x512x{n}" for n in sorted(full)])
        ax.set_xlabel("seconds (dotted: read + one resampling pass)")
        ax.set_title("Full-size CT: where the time goes")
        _save(fig, out_dir, "full_size_stages.png", made)
    _family_plot(ok, out_dir, made, plt)
    _mesh_size_plot(rows, out_dir, made, plt)
    click_error_plot(rows, TUNE_SEEDS, HELD_OUT_SEEDS, out_dir, made, plt, _save)
    _surface_bound_plot(rows, out_dir, made, plt)
    memory_plot(ok, out_dir, made, plt)
    return made


def place_labels(ax, points, fontsize: float = 7.0) -> None:
    """Label scatter points [(x, y, text)] without overlaps: each label goes to the first of 12 offsets (2 rings of
    8 directions, then farther) whose box misses every label placed so far and every point; farther ones get a
    leader line."""
    fig = ax.figure
    fig.canvas.draw()
    to_px = ax.transData.transform
    px_per_pt = fig.dpi / 72.0
    placed = []
    dots = [to_px((x, y)) for x, y, _ in points]
    order = sorted(range(len(points)), key=lambda n: (points[n][0], points[n][1]))
    dirs = [(1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1)]
    for n in order:
        x, y, text = points[n]
        w, h = (0.6 * len(text) * fontsize + 2) * px_per_pt, 1.3 * fontsize * px_per_pt
        px, py = dots[n]
        choice = None
        for ring in (1.0, 2.2, 3.6):
            for dx, dy in dirs:
                ox, oy = dx * 5 * ring, dy * 5 * ring  # points
                cx = px + ox * px_per_pt + (0 if dx >= 0 else -w) - (w / 2 if dx == 0 else 0)
                cy = py + oy * px_per_pt + (0 if dy >= 0 else -h) - (h / 2 if dy == 0 else 0)
                box = (cx, cy, cx + w, cy + h)
                hit = any(not (box[2] < b[0] or box[0] > b[2] or box[3] < b[1] or box[1] > b[3]) for b in placed)
                hit = hit or any(box[0] - 2 < qx < box[2] + 2 and box[1] - 2 < qy < box[3] + 2 for qx, qy in dots)
                if not hit:
                    choice = (ox, oy, dx, dy, box, ring)
                    break
            if choice:
                break
        if choice is None:  # crowded: the last ring's first direction, with a leader line
            ox, oy = 5 * 3.6, 5 * 3.6
            choice = (ox, oy, 1, 1, (px + ox * px_per_pt, py + oy * px_per_pt,
                                     px + ox * px_per_pt + w, py + oy * px_per_pt + h), 3.6)
        ox, oy, dx, dy, box, ring = choice
        placed.append(box)
        ax.annotate(text, (x, y), xytext=(ox, oy), textcoords="offset points", fontsize=fontsize,
                    ha="left" if dx > 0 else "right" if dx < 0 else "center",
                    va="bottom" if dy > 0 else "top" if dy < 0 else "center",
                    arrowprops=dict(arrowstyle="-", lw=0.5, color="0.4") if ring > 1.0 else None)


def _mesh_size_plot(rows: list[dict], out_dir: str, made: list[str], plt) -> None:
    """mesh_size.png: per seed set, the isometric method's median seconds against its ratio to the flat-layout bound
    (left) and volumes within 1.5x of it (right), one point per mesh size."""
    summ = mesh_size_summary(rows)
    if not summ:
        return
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for label, colour in (("tuning", "tab:blue"), ("held-out", "tab:orange")):
        xs = sorted((x for x in summ if x["set"] == label), key=lambda x: x["vertices"])
        t = [x["seconds_median"] for x in xs]
        for ax, key in ((axes[0], "ratio_median"), (axes[1], "within_1p5")):
            ax.plot(t, [x[key] for x in xs], "o-", color=colour, label=label)
            for x in xs:
                ax.annotate(f"{x['vertices']}{'*' if x['default'] else ''}", (x["seconds_median"], x[key]),
                            textcoords="offset points", xytext=(4, 4), fontsize=7)
    axes[0].set(xlabel="median seconds per volume (two at once)", ylabel="median marker distortion / flat-layout bound",
                title="isometric mesh size: accuracy against speed")
    axes[1].set(xlabel="median seconds per volume (two at once)", ylabel="volumes within 1.5x of the bound (of 30)",
                title="* the default isometric_vertices")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    _save(fig, out_dir, "mesh_size.png", made)


def _surface_bound_plot(rows: list[dict], out_dir: str, made: list[str], plt) -> None:
    """surface_bound.png: per random stomach with a ``surfacebound`` row, the default method's marker distortion over
    the flat-layout bound against the whole mucosa's best layout over the same bound (plain and robust)."""
    refs = {r["name"].split("/")[0]: r["reference"] for r in rows if r.get("group") == "surface-bound" and r.get("ok")}
    family = {group for group, _ in FAMILY_SEED_SETS}
    mine = {r["name"].split("/")[0]: r["quality"]["markers"]["pairwise_distance_distortion"] for r in rows
            if r.get("ok") and r["method"] == FAMILY_METHODS[0] and r["group"] in family
            and not r.get("zero_clicks") and r["quality"].get("markers", {}).get("pairwise_distance_distortion")}
    vols = [v for v in refs if v in mine]
    if not vols:
        return
    held = np.array([int(v.split("-")[1]) not in TUNE_SEEDS for v in vols])
    b = np.array([refs[v]["marker_bound"] for v in vols])
    y = np.array([mine[v] for v in vols]) / b
    fig, ax = plt.subplots(figsize=(7.5, 6))
    for key, style, what in (("surface_layout", "o", "whole mucosa, squared log errors"),
                             ("surface_layout_robust", "^", "whole mucosa, robust")):
        x = np.array([refs[v][key] for v in vols]) / b
        for sel, colour, label in ((~held, "tab:blue", "tuning 0-29"), (held, "tab:orange", "held out")):
            ax.scatter(x[sel], y[sel], marker=style, s=22, alpha=0.7, color=colour,
                       facecolors="none" if key.endswith("robust") else colour, label=f"{what}, {label}")
    ax.axvline(1.5, color="k", ls="--", lw=1)
    ax.axhline(1.5, color="k", ls="--", lw=1)
    ax.plot([0, 3], [0, 3], color="0.6", lw=0.8)
    ax.set(xlabel="best flat layout of the whole mucosa, on the markers / flat-layout bound",
           ylabel=f"{FAMILY_METHODS[0]} view, on the markers / flat-layout bound", xlim=(0, None), ylim=(0, None),
           title="the bound's 1.5x line, for any layout that does not know the markers")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _save(fig, out_dir, "surface_bound.png", made)


def _family_plot(ok: list[dict], out_dir: str, made: list[str], plt) -> None:
    """stomachs.png: per method, seconds against pairwise marker distortion (left) and hidden mucosa (right)."""
    fam = [r for r in ok if r["group"].startswith("stomachs") and "markers" in r["quality"]]
    if not fam:
        return
    colour = {"isometric": "tab:blue", "massspring": "tab:orange", "cylindrical": "tab:green", "lscm": "tab:red"}
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for m in FAMILY_METHODS:
        rs = [r for r in fam if r["method"] == m]
        if not rs:
            continue
        t = [r["seconds"] for r in rs]
        d = [r["quality"]["markers"].get("pairwise_distance_distortion") or np.nan for r in rs]
        h = [1 - r["quality"]["visible_fraction"] for r in rs]
        axes[0].scatter(t, d, s=14, alpha=0.6, color=colour.get(m), label=m)
        axes[1].scatter(t, h, s=14, alpha=0.6, color=colour.get(m), label=m)
    b = [r["quality"]["markers"].get("flat_bound") for r in fam if r["quality"]["markers"].get("flat_bound")]
    if b:
        axes[0].axhline(float(np.median(b)), color="k", ls="--", lw=1, label="flat-layout bound (median)")
    axes[0].set(xlabel="seconds per volume", ylabel="median pairwise marker distortion |log(view/geodesic)|",
                yscale="log", title="distortion against speed, random stomachs")
    axes[1].set(xlabel="seconds per volume", ylabel="hidden mucosa fraction", yscale="symlog",
                title="hidden mucosa against speed")
    axes[1].set_yscale("symlog", linthresh=0.01)
    for ax in axes:
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    _save(fig, out_dir, "stomachs.png", made)


def _markdown(rows: list[dict], full: dict | None, meta: dict, made: list[str]) -> str:
    L = [f"# Benchmark\n\nRun {meta['date']} on {meta['machine']['cpus']} CPUs ({meta['machine']['platform']}), "
         f"{meta['wall_seconds']:.0f} s wall time. Every number below is measured in this run"
         + "".join(f"; the rows of {', '.join(m['parts'])}"
                   + (f" ({', '.join(m['methods'])} only)" if m.get("methods") else "")
                   + f" ({m['cases']} cases) were rerun on {m['date']} with --merge" for m in meta.get("merged", []))
         + ".\n"]
    for n, f in (full or {}).items():
        ok15 = "met" if f["pipeline_s"] < 15 else "missed"
        L.append(f"## Full-size CT (512 x 512 x {n} at 0.7 mm), method {f.get('method', 'massspring')}\n")
        L.append(f"Pipeline from file to files (read, unfold, write): **{f['pipeline_s']:.2f} s** (15 s target {ok15}; "
                 f"the paper: 458 s). Floor: read {f['read_s']:.2f} s + one trilinear resampling pass "
                 f"{f['resample_s']:.2f} s = {f['floor_s']:.2f} s; ratio **{f['ratio_to_floor']:.1f}x** (target 5x). "
                 f"Peak memory {f['peak_memory_mb']:.0f} MB (fresh process). Grade {f['grade']}, visible "
                 f"{100 * f['visible_fraction']:.1f}%, markers {f['markers_seen']}/{f['markers_total']}, "
                 f"{f['iterations']} iterations, "
                 + ", ".join(f"{v} {k}" for k, v in f["model"].items() if k in ("hexahedra", "triangles")) + ".\n")
        L.append("Seconds by stage: read " + f"{f['read_volume_s']:.2f}, " +
                 ", ".join(f"{k} {v:.2f}" for k, v in f["stage_seconds"].items() if k != "total") +
                 f", write outputs {f['write_outputs_s']:.2f}.\n")

    def table(group, title):
        rs = [r for r in rows if r["group"] == group]
        if not rs:
            return
        L.append(f"## {title}\n")
        L.append("| case | s | it | grade | visible % | markers | overlap % | inverted % | bend rms mm | area/angle dist |")
        L.append("|---|---|---|---|---|---|---|---|---|---|")
        for r in rs:
            if not r.get("ok"):
                L.append(f"| {r['name']} | failed: {r['error'][:90]} | | | | | | | | |")
                continue
            q = r["quality"]
            mk = f"{r.get('markers_seen', '')}/{r.get('markers_total', '')}" if r.get("markers_total") else ""
            L.append(f"| {r['name']} | {r['seconds']:.2f} | {r.get('iterations', '')} | {q.get('grade', '')} | "
                     f"{100 * q.get('visible_fraction', float('nan')):.1f} | {mk} | "
                     f"{100 * q.get('overlap_area_fraction', 0):.2f} | "
                     f"{100 * q.get('inverted_fraction', q.get('fold_back_fraction', 0)):.1f} | "
                     f"{q.get('bending_plane_rms_mm', float('nan')):.1f} | "
                     f"{q.get('area_distortion', float('nan')):.2f}/{q.get('angle_distortion', float('nan')):.2f} |")
        L.append("")

    table("shapes", "Phantom set, default parameters")
    table("shapes-paper", "Phantom set, the paper's forces alone")
    # the paper's Table 1
    for grp, title in (("kappa", "Table 1 reproduced: our method"), ("kappa-paper", "Table 1 reproduced: the paper's forces")):
        rs = [r for r in rows if r["group"] == grp and r.get("ok")]
        if not rs:
            continue
        ks = sorted({float(r["name"].split("kappa=")[1].split("/")[0]) for r in rs})
        counts = {k: {"good": 0, "overlapping": 0, "bending": 0, "broken": 0, "n": 0} for k in ks}
        for r in rs:
            k = float(r["name"].split("kappa=")[1].split("/")[0])
            d = _defects(r["quality"])
            counts[k]["n"] += 1
            for key in ("good", "overlapping", "bending", "broken"):
                counts[k][key] += int(d[key])
        L.append(f"## {title} (counts over {counts[ks[0]]['n']} phantoms)\n")
        L.append("| kappa | " + " | ".join(f"{k:g}" for k in ks) + " |")
        L.append("|---|" + "---|" * len(ks))
        for key in ("good", "overlapping", "bending", "broken"):
            L.append(f"| {key} | " + " | ".join(str(counts[k][key]) for k in ks) + " |")
        L.append("")
    table("sweep", "Speed against accuracy sweep (grid, kappa, time step, integrator)")
    table("stability", "Stability: time step, Newmark-beta against explicit")
    table("extremes", "Extreme shapes (twisted, 1.5 mm wall, lumen at 0.3 of the radius), small and large kappa")
    table("resolution", "Model resolution")
    table("scaling-volume", "Scaling with volume size (J phantom, 5.6 mm cells; each run alone in a fresh process)")
    table("scaling-grid", "Scaling with cell size at full size (each run alone in a fresh process)")
    table("crop", "Crop size: extra margin around the stomach (each run alone in a fresh process)")
    table("real", "Real CTs (not gas-distended): 01 and 02 with their stomach labels, 03 only its gas pocket "
                  "(no label)")
    table("peers", "Peers on the same phantoms (the inverted column: wall folded back along the unrolling)")
    L += family_markdown(rows)
    L += mesh_size_markdown(rows)
    L += click_error_markdown(rows, TUNE_SEEDS, HELD_OUT_SEEDS)
    L += oblique_markdown(rows, "stomachs-held-out")
    L += oblique_markdown(rows, "stomachs-held-out", PRONE_GROUP)
    L += oblique_markdown(rows, "stomachs-held-out", ROLLED_GROUP)
    L += oblique_markdown(rows, "stomachs-held-out", CONTRAST_GROUP)
    L += oblique_markdown(rows, "stomachs-held-out", CONTENTS_GROUP)
    L += oblique_markdown(rows, "stomachs-held-out", DEEP_GROUP)
    L += phase_markdown(rows)
    L += surface_bound_markdown(rows)
    L += memory_markdown(rows)
    for png in made:
        L.append(f"![{png}]({png})\n")
    return "\n".join(L) + "\n"


FAMILY_GROUPS = (("stomachs-tune", "Random stomachs, seeds 0-29 (the defaults were tuned on these)"),
                 ("stomachs-held-out", "Random stomachs, seeds 1000-1029 (held out: never tuned on)"),
                 ("stomachs-fresh", "Random stomachs, seeds 3000-3029 (a second held-out set, first drawn after the "
                                    "2026-12-01 changes)"),
                 ("stomachs-fresh-2", "Random stomachs, seeds 4000-4029 (a third held-out set, first unfolded after "
                                      "the 2026-12-04 changes)"),
                 ("stomachs-fresh-3", "Random stomachs, seeds 5000-5029 (a fourth held-out set, first drawn on the "
                                      "evening of 2026-12-04: nothing was decided on it)"),
                 ("stomachs-fresh-4", "Random stomachs, seeds 6000-6029 (a fifth held-out set, first drawn late on "
                                      "2026-12-04 to decide on an incision in the stomach's plane, not kept)"),
                 ("stomachs-fresh-5", "Random stomachs, seeds 7000-7029 (a sixth held-out set, first drawn at night "
                                      "on 2026-12-04 after every change of the day: nothing was decided on it)"),
                 ("stomachs-fresh-6", "Random stomachs, seeds 8000-8029 (a seventh held-out set, first drawn early on "
                                      "2026-12-05 to decide on the water's floor, rule 12: failed as written)"),
                 ("stomachs-fresh-7", "Random stomachs, seeds 9000-9029 (an eighth held-out set, first drawn early on "
                                      "2026-12-05 to decide on the same floor, rule 13: kept)"),
                 ("stomachs-fresh-8", "Random stomachs, seeds 10000-10029 (a ninth held-out set, first drawn on "
                                      "2026-12-05 to decide on the stomach-plane incision again, rule 14: not kept)"),
                 ("stomachs-fresh-9", "Random stomachs, seeds 11000-11029 (a tenth held-out set, drawn with the "
                                      "ninth for rule 14)"),
                 ("stomachs-hybrid", "Drawn stomachs inserted into the real CTs (held out)"),
                 ("sizes-tiny", "Random stomachs drawn tiny, seeds 34000-34019 (1.7-2.1 mm in-plane, 2.0-2.5 mm "
                                "slices; never tuned on)"),
                 ("sizes-full", "Random stomachs drawn full size, seeds 34000-34019 (512 x 512 at 0.6-0.9 mm, "
                                "0.6-2.5 mm slices; never tuned on)"),
                 ("hybrids-dev", "Drawn stomachs in real CTs 01 (3 mm) and 03 (4.25 mm slices), seeds 40000-40019 "
                                 "(rules 26-30, none the default, were developed on them)"),
                 ("hybrids-decide", "Drawn stomachs in real CTs 01 (3 mm) and 03 (4.25 mm slices), seeds 41000-41019 "
                                    "(rule 26's decision set; main's method was never tuned on them)"))


def family_summary(rows: list[dict], group: str) -> dict:
    """Per method over one family group: grades, visible fractions, markers, distortion against the bound, speed."""
    out = {}
    zero = [r for r in rows if r["group"] == group and r.get("zero_clicks")]
    rs = [r for r in rows if r["group"] == group and not r.get("zero_clicks")]
    by_volume: dict = {}
    for r in rs:
        by_volume.setdefault(r["name"].split("/")[0], {})[r["method"]] = r
    for m in FAMILY_METHODS:
        mr = [r for r in rs if r["method"] == m]
        ok = [r for r in mr if r.get("ok")]
        if not mr:
            continue
        q = [r["quality"] for r in ok]
        mk = [x["markers"] for x in q if "markers" in x]
        vis = [x["visible_fraction"] for x in q]
        dist = [x["pairwise_distance_distortion"] for x in mk if x.get("pairwise_distance_distortion") is not None]
        ratio = [x["ratio_to_bound"] for x in mk if x.get("ratio_to_bound") is not None]
        not_below_peers = 0
        for vol in by_volume.values():
            mine = vol.get(m)
            if mine and mine.get("ok") and all(
                    (not o.get("ok")) or mine["quality"]["visible_fraction"] >= o["quality"]["visible_fraction"]
                    for n, o in vol.items() if n != m):
                not_below_peers += 1
        err = [x["length_error_mm"]["mean"] for x in mk if x.get("length_error_mm", {}).get("mean") is not None]
        out[m] = {"volumes": len(mr), "failed": len(mr) - len(ok),
                  "excellent": sum(x["grade"] == "excellent" for x in q),
                  "good_or_better": sum(x["grade"] in ("excellent", "good") for x in q),
                  "visible_median": float(np.median(vis)) if vis else None,
                  "visible_min": float(np.min(vis)) if vis else None,
                  "markers_seen": sum(x["seen"] for x in mk), "markers_total": sum(x["total"] for x in mk),
                  "markers_missed": _missed(mk),
                  "under_fluid_seen": sum(x["by_region"].get("under_fluid", [0, 0])[0] for x in mk),
                  "under_fluid_total": sum(x["by_region"].get("under_fluid", [0, 0])[1] for x in mk),
                  "dome_seen": sum(x["by_region"].get("dome", [0, 0])[0] for x in mk),
                  "dome_total": sum(x["by_region"].get("dome", [0, 0])[1] for x in mk),
                  "distortion_median": float(np.median(dist)) if dist else None,
                  "distortion_max": float(np.max(dist)) if dist else None,
                  "ratio_to_bound_median": float(np.median(ratio)) if ratio else None,
                  "ratio_to_bound_max": float(np.max(ratio)) if ratio else None,
                  "stretched_max": float(max(x["broken_springs_fraction"] for x in q)) if q else None,
                  **_unstretched(q),
                  "inverted_max": float(max(x["inverted_fraction"] for x in q)) if q else None,
                  "visible_not_below_every_peer": not_below_peers,
                  "length_error_mm_mean": float(np.mean(err)) if err else None,
                  "length_error_mm_sd_of_means": float(np.std(err)) if err else None,
                  "seconds_median": float(np.median([r["seconds"] for r in ok])) if ok else None,
                  "area_scale_along_median": area_scale_summary(ok)}
    if zero:
        out.update(zero_click_summary(zero, rs))
    return out


def _missed(mk: list[dict]) -> dict | None:
    """Markers not seen summed by reason (markers.MISS_REASONS) over marker sections mk; None where a row lacks them
    (rows run before the reasons were recorded)."""
    from .markers import MISS_REASONS

    if not mk or any("missed" not in x for x in mk):
        return None
    return {r: int(sum(x["missed"].get(r, 0) for x in mk)) for r in MISS_REASONS}


def _unstretched(q: list[dict], limit: float = 1.5) -> dict:
    """Volumes (of quality sections q) with no spring (edge) and with no triangle stretched over ``limit`` x."""
    return {"no_spring_over_limit": sum(x["broken_springs_fraction"] == 0 for x in q),
            "no_triangle_over_limit": sum(x.get("max_stretch", np.inf) <= limit for x in q)}


def zero_click_summary(zero: list[dict], two_click_rows: list[dict]) -> dict:
    """The 'zero clicks' row: the default method from found points, with the family columns it can fill, and the
    share of volumes whose found points lie within 10 mm and whose grade equals the two-click grade."""
    ok = [r for r in zero if r.get("ok")]
    q = [r["quality"] for r in ok]
    mk = [x["markers"] for x in q if "markers" in x]
    vis = [x["visible_fraction"] for x in q]
    two = {r["name"].split("/")[0]: r for r in two_click_rows if r["method"] == FAMILY_METHODS[0] and r.get("ok")}
    paired = [r for r in ok if r["name"].split("/")[0] in two]
    same = sum(two[r["name"].split("/")[0]]["quality"]["grade"] == r["quality"]["grade"] for r in paired)
    auto = [r["auto_points"] for r in zero if r.get("auto_points")]
    dist = [x["pairwise_distance_distortion"] for x in mk if x.get("pairwise_distance_distortion") is not None]
    return {f"{FAMILY_METHODS[0]}, zero clicks": {
        "volumes": len(zero), "failed": len(zero) - len(ok),
        "excellent": sum(x["grade"] == "excellent" for x in q),
        "good_or_better": sum(x["grade"] in ("excellent", "good") for x in q),
        "visible_median": float(np.median(vis)) if vis else None, "visible_min": float(np.min(vis)) if vis else None,
        "markers_seen": sum(x["seen"] for x in mk), "markers_total": sum(x["total"] for x in mk),
        "under_fluid_seen": 0, "under_fluid_total": 0, "dome_seen": 0, "dome_total": 0,
        "distortion_median": float(np.median(dist)) if dist else None,
        "distortion_max": float(np.max(dist)) if dist else None, "ratio_to_bound_median": None,
        "ratio_to_bound_max": None, "stretched_max": float(max(x["broken_springs_fraction"] for x in q)) if q else None,
        **_unstretched(q),
        "inverted_max": float(max(x["inverted_fraction"] for x in q)) if q else None,
        "visible_not_below_every_peer": 0, "length_error_mm_mean": None, "length_error_mm_sd_of_means": None,
        "seconds_median": float(np.median([r["seconds"] for r in ok])) if ok else None,
        "points_within_10mm": sum(a["within_tolerance"] for a in auto), "refused": sum(not a["confident"] for a in auto),
        "grade_as_two_clicks": same, "with_two_click_row": len(paired),
        "cardia_error_mm_median": float(np.median([a["cardia_error_mm"] for a in auto])) if auto else None,
        "pylorus_error_mm_median": float(np.median([a["pylorus_error_mm"] for a in auto])) if auto else None}}


def family_markdown(rows: list[dict]) -> list[str]:
    """The random-stomach sections of results.md: one summary table per group, then every volume."""
    from .markers import MISS_REASONS

    L = []
    for group, title in FAMILY_GROUPS:
        summ = family_summary(rows, group)
        if not summ:
            continue
        n = max(v["volumes"] for v in summ.values())
        L.append(f"## {title}: {n} volumes, every method on the same volumes, default parameters\n")
        L.append("| method | excellent | good or better | failed | visible median / min % | not below any peer | "
                 "markers seen | under fluid | dome | pairwise distortion median / max | x flat-layout bound "
                 "median / max | stretched max % | no spring / triangle over 1.5x | inverted max % | s median |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        def f(v, fmt="{:.3f}"):
            return "" if v is None else fmt.format(v)
        for m, v in summ.items():
            L.append(f"| {m} | {v['excellent']}/{v['volumes']} | {v['good_or_better']}/{v['volumes']} | {v['failed']} | "
                     f"{f(v['visible_median'] and 100 * v['visible_median'], '{:.1f}')} / "
                     f"{f(v['visible_min'] and 100 * v['visible_min'], '{:.1f}')} | "
                     f"{v['visible_not_below_every_peer']}/{v['volumes']} | "
                     f"{v['markers_seen']}/{v['markers_total']} | {v['under_fluid_seen']}/{v['under_fluid_total']} | "
                     f"{v['dome_seen']}/{v['dome_total']} | {f(v['distortion_median'])} / {f(v['distortion_max'])} | "
                     f"{f(v['ratio_to_bound_median'], '{:.2f}')} / {f(v['ratio_to_bound_max'], '{:.2f}')} | "
                     f"{f(v['stretched_max'] and 100 * v['stretched_max'], '{:.1f}')} | "
                     f"{v['no_spring_over_limit']}/{v['no_triangle_over_limit']} | "
                     f"{f(v['inverted_max'] and 100 * v['inverted_max'], '{:.2f}')} | {f(v['seconds_median'], '{:.1f}')} |")
        L.append("")
        shown = MISS_REASONS[:3]                   # "unmapped" is not a view's: every method maps every marker here
        missed = [f"{m} {' / '.join(str(v['markers_missed'][r]) for r in shown)}"
                  for m, v in summ.items() if v.get("markers_missed")]
        if missed:
            L.append("Markers not seen, by what the view shows within 4 mm of the place the map gives them (merged: a "
                     "region also within 4 mm of another marker's place or over twice the median region's size, a "
                     "bead joined to another or to dense tissue / off: a lone bead's region, centred farther / not "
                     "shown): " + "; ".join(missed) + ".\n")
        along = [f"{m} " + " ".join("-" if x is None else f"{x:.2f}" for x in v["area_scale_along_median"])
                 for m, v in summ.items() if v.get("area_scale_along_median")]
        if along:
            L.append("Area scale of the view (view area / mucosa area, 1: true) per tenth of the centreline, cardia "
                     "first, median over the volumes: " + "; ".join(along) + ".\n")
        for m, v in summ.items():
            if "points_within_10mm" in v:
                L.append(f"*{m}*: the points found (no clicks) lie within 10 mm of the true cardia and pylorus on "
                         f"{v['points_within_10mm']}/{v['volumes']} volumes (median errors "
                         f"{f(v['cardia_error_mm_median'], '{:.1f}')} and {f(v['pylorus_error_mm_median'], '{:.1f}')} "
                         f"mm), {v['refused']} refused as unsure; the grade equals the two-click grade on "
                         f"{v['grade_as_two_clicks']}/{v['with_two_click_row']} (volumes with a two-click row).\n")
        L.append("<details><summary>every volume</summary>\n")
        L.append("| volume / method | grade | visible % | parts | markers | distortion | bound | stretched % | s |")
        L.append("|---|---|---|---|---|---|---|---|---|")
        for r in [r for r in rows if r["group"] == group]:
            if not r.get("ok"):
                L.append(f"| {r['name']} | failed: {r.get('error', '')[:80]} | | | | | | | |")
                continue
            q, mk = r["quality"], r["quality"].get("markers", {})
            L.append(f"| {r['name']} | {q['grade']} | {100 * q['visible_fraction']:.1f} | {q['failure_parts']} | "
                     f"{mk.get('seen', '')}/{mk.get('total', '')} | {f(mk.get('pairwise_distance_distortion'))} | "
                     f"{f(mk.get('flat_bound'))} | {100 * q['broken_springs_fraction']:.1f} | {r['seconds']:.1f} |")
        L.append("\n</details>\n")
    return L


def _merge(old: dict, rows: list[dict], full: dict | None, meta: dict, parts) -> tuple[list[dict], dict | None, dict]:
    """Rows of an earlier results.json with those of this run put in place by group and name (new ones appended;
    one name can be a row of several parts, e.g. ``bent-small/kappa=0.2`` of ``kappa`` and of ``sweep``)."""
    mine = {(r.get("group"), r["name"]): r for r in rows}
    run = {"date": meta["date"], "parts": list(parts), "cases": len(rows), "wall_seconds": meta["wall_seconds"],
           **({"packages": meta["machine"]["packages"]} if meta.get("machine", {}).get("packages") else {}),
           **({"methods": meta["methods"]} if meta.get("methods") else {})}
    merged = [mine.pop((r.get("group"), r["name"]), r) for r in old["cases"]] + list(mine.values())
    return merged, full or old.get("full_size"), {**old["meta"], "merged": old["meta"].get("merged", []) + [run]}


#: The packages whose versions a run's figures can depend on: the flat maps are solved in floating point, and a
#: change in the last bits (another numpy, scipy or BLAS) can move a volume's figures as far as the judge's noise.
RESULT_PACKAGES = ("numpy", "scipy", "SimpleITK", "vtk", "scikit-image", "dask")


def package_versions() -> dict:
    """{name: version} of RESULT_PACKAGES installed here (those missing left out), recorded with every run."""
    from importlib import metadata

    out = {}
    for name in RESULT_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def replot(out_dir: str = "docs/benchmark") -> list[str]:
    """Rewrite the PNGs and results.md of out_dir from its results.json, without running anything."""
    path = os.path.join(out_dir, "results.json")
    if not os.path.exists(path):
        raise InputError(f"no {path}: run the benchmark first (stomach-unfold bench -o {out_dir})")
    with open(path) as f:
        data = json.load(f)
    made = _plots(data["cases"], out_dir, data.get("full_size"))
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(_markdown(data["cases"], data.get("full_size"), data["meta"], made))
    return made


def check_methods(methods) -> list[str]:
    """The method names given (blanks dropped), or InputError naming any that is not a registered method."""
    from StomachUnfoldLib.methods import method_names

    names = [m.strip() for m in methods if m.strip()]
    unknown = [m for m in names if m not in method_names()]
    if unknown or not names:
        raise InputError(f"unknown method {', '.join(unknown) or '(none given)'}; choose from "
                         f"{', '.join(method_names())}")
    return names


def _only_methods(cases: list[dict], methods) -> list[dict]:
    """The cases whose method is one of ``methods`` (all of them when None)."""
    if methods is None:
        return cases
    wanted = set(check_methods(methods))
    return [c for c in cases if c["method"] in wanted]


def run_benchmark(out_dir: str = "docs/benchmark", quick: bool = False, full_size: bool = False,
                  scheduler: str | None = None, data_dir: str | None = None,
                  parts=("shapes", "kappa", "sweep", "stability", "resolution", "peers", "real", "scaling",
                         "stomachs", "zeroclicks", "meshsize", "autopoints"),
                  merge: bool = False, methods=None) -> list[dict]:
    """Run the benchmark (all parts, or a quick subset) and write results.json, results.md and PNGs into out_dir.

    With ``merge`` the new rows replace the rows of the same name in an existing results.json and the others
    are kept (the run is listed under meta["merged"]); otherwise results.json holds this run alone. ``methods``
    (names): only the cases of those methods run (e.g. the default method's rows after a change to it alone).
    """
    os.makedirs(out_dir, exist_ok=True)
    t0 = time.perf_counter()
    if data_dir is None:
        here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        data_dir = os.path.join(os.path.dirname(here), "shared", "data")
    cases = _only_methods(_cases(quick, full_size, data_dir, parts), methods)
    views = os.path.join(out_dir, "views")
    rows = run_cases(cases, png_dir=views, scheduler=scheduler)
    for case in _only_methods(_serial_cases(quick, full_size, parts), methods):
        rows.append(_isolated(run_case, case, views))
    full = full_size_runs(out_dir) if full_size else None
    if full_size or "memory" in parts:  # peak memory against crop size, each run alone (docs/benchmark/memory.png)
        rows += memory_runs()
    meta = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
                        "packages": package_versions()},
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "wall_seconds": time.perf_counter() - t0,
            "quick": quick, "scheduler": scheduler or "LocalCluster",
            **({"methods": list(methods)} if methods is not None else {})}
    path = os.path.join(out_dir, "results.json")
    if merge and os.path.exists(path):
        with open(path) as f:
            rows, full, meta = _merge(json.load(f), rows, full, meta, parts)
    made = _plots(rows, out_dir, full)
    with open(path, "w") as f:
        json.dump({"meta": meta, "full_size": full, "cases": rows}, f, indent=1,
                  default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(_markdown(rows, full, meta, made))
    if "autopoints" in parts:  # zero clicks: found points against the truth (autopoints.md), no unfolding
        from .auto_points import point_benchmark

        point_benchmark(out_dir, quick=quick)
    return rows
