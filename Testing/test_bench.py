"""The benchmark in miniature: cases run through Dask, failures become rows, tables and charts are written."""
import json
import os
import platform

import numpy as np
import pytest

from StomachUnfoldEval import bench

from conftest import SHARED_DIR


def test_quick_stability_bench_reports_explicit_divergence_as_data(tmp_path):
    rows = bench.run_benchmark(str(tmp_path), quick=True, parts=("stability",))
    by = {r["name"]: r for r in rows}
    # the implicit Newmark-beta step stays stable at every step size tried, the explicit one does not
    newmark = [r for n, r in by.items() if "/newmark/" in n]
    explicit = [r for n, r in by.items() if "/explicit/" in n]
    assert newmark and explicit
    assert all(r["ok"] for r in newmark), [r.get("error") for r in newmark]
    big_step = [r for r in explicit if r["name"].endswith("h=10.0")]
    assert big_step and not big_step[0]["ok"] and "diverged" in big_step[0]["error"]
    assert any(r["ok"] for r in explicit)  # explicit works at a small enough step
    # the judged rows carry the metrics the charts need
    for r in newmark:
        assert 0.0 <= r["quality"]["visible_fraction"] <= 1.0
        assert r["markers_total"] == 12
    saved = json.loads((tmp_path / "results.json").read_text())
    assert len(saved["cases"]) == len(rows) and saved["meta"]["scheduler"] == "LocalCluster"
    md = (tmp_path / "results.md").read_text()
    assert "Stability" in md and "failed: SimulationError" in md
    assert (tmp_path / "stability.png").stat().st_size > 5000
    for r in rows:
        if r["ok"]:
            assert (tmp_path / "views" / bench.png_name(r["name"])).exists()
    # --replot redraws the charts and the tables from results.json alone
    os.remove(tmp_path / "stability.png")
    (tmp_path / "results.md").write_text("")
    assert "stability.png" in bench.replot(str(tmp_path))
    assert (tmp_path / "stability.png").exists() and (tmp_path / "results.md").read_text() == md


def test_replot_without_results_says_to_run_the_benchmark(tmp_path):
    from StomachUnfoldLib.errors import InputError

    with pytest.raises(InputError, match="run the benchmark first"):
        bench.replot(str(tmp_path))


def test_a_broken_case_is_a_row_not_a_crash():
    row = bench.run_case(bench.Case("nonsense", {"shape": "no-such-shape", "size": "tiny"}))
    assert row["ok"] is False and "InputError" in row["error"] and "no-such-shape" in row["error"]
    row = bench.run_case(bench.Case("bad-param", {"shape": "straight", "size": "tiny"}, {"kappa": -1.0}))
    assert row["ok"] is False and "kappa" in row["error"]


def test_table1_categories_follow_the_metrics():
    clean = {"grade": "good", "overlap_area_fraction": 0.0, "inverted_fraction": 0.01, "bent_area_fraction": 0.0,
             "bending_plane_rms_mm": 1.0, "broken_springs_fraction": 0.0, "hole_area_fraction": 0.0}
    d = bench._defects(clean)
    assert d == {"good": True, "overlapping": False, "bending": False, "broken": False}
    d = bench._defects({**clean, "grade": "fair", "overlap_area_fraction": 0.05, "bending_plane_rms_mm": 20.0,
                        "hole_area_fraction": 0.02})
    assert d == {"good": False, "overlapping": True, "bending": True, "broken": True}


def test_phantom_set_spans_the_variations():
    names = [s["_name"] for s in bench.phantom_set("tiny")]
    assert len(names) >= 8 and len(set(names)) == len(names)
    kinds = {n.split("-")[0] for n in names}
    assert {"straight", "bent", "j", "twisted", "thin_wall"} <= kinds
    assert any("anisotropic" in n for n in names) and any("rugae" in n for n in names)
    assert any("narrow" in n for n in names) and any("noisy" in n for n in names)


@pytest.mark.skipif(not os.path.isdir(os.path.join(SHARED_DIR, "data")),
                    reason=f"the real CTs are not in {SHARED_DIR}/data (set STOMACHUNFOLD_SHARED)")
def test_real_cases_are_listed_when_the_data_is_there():
    d = os.path.join(SHARED_DIR, "data")
    cases = bench._cases(quick=True, full_size=False, data_dir=d, parts=("real",))
    assert {c["group"] for c in cases} == {"real"} and len(cases) >= 1


@pytest.mark.skipif(not os.path.isfile(os.path.join(SHARED_DIR, "data", "03_tcia_acrin_flt_breast_001_ct_chest_abd_"
                                                    "pelvis_4p25mm.nii.gz")),
                    reason=f"the third real CT is not in {SHARED_DIR}/data (set STOMACHUNFOLD_SHARED)")
def test_the_unlabelled_real_ct_unfolds_its_gas_pocket_at_least_as_fully_as_the_cylindrical_peer():
    d = os.path.join(SHARED_DIR, "data")
    cases = {c["name"]: c for c in bench._cases(quick=True, full_size=False, data_dir=d, parts=("real",))}
    rows = {m: bench.run_case(cases[f"real-03-pocket/{m}"]) for m in ("isometric", "cylindrical")}
    assert all(r["ok"] for r in rows.values()), [r.get("error") for r in rows.values()]
    iso, cyl = rows["isometric"]["quality"], rows["cylindrical"]["quality"]
    # the points are the gas pocket's long-axis ends, in its gas: a sac about 60 mm long, not one point twice
    ct, cardia, pylorus, mask, _ = bench._load(cases["real-03-pocket/isometric"]["source"])
    assert mask is None and 45.0 < float(np.linalg.norm(cardia - pylorus)) < 80.0 and cardia[2] > pylorus[2]
    k, j, i = np.rint(ct.lps_to_index(np.array([cardia, pylorus]))[:, ::-1]).astype(int).T
    assert np.all(np.asarray(ct.array)[k, j, i] < -500)
    assert iso["grade"] in ("good", "excellent") and iso["failure_parts"] == 0
    assert iso["visible_fraction"] >= cyl["visible_fraction"]
    # no hole: one ray met its thin wall at -402 HU (4.25 mm slices), a pinhole filled from its neighbours
    assert iso["hole_area_fraction"] == 0.0 and rows["isometric"]["method_report"]["pinholes_filled"] >= 1
    assert any("gas pocket" in w for w in rows["isometric"]["warnings"]), rows["isometric"]["warnings"]


@pytest.mark.skipif(not os.path.isfile(os.path.join(SHARED_DIR, "data", "02_totalseg_example_ct_dicom_slab_2mm.nii.gz")),
                    reason=f"the second real CT is not in {SHARED_DIR}/data (set STOMACHUNFOLD_SHARED)")
def test_the_slab_shows_only_the_wall_it_imaged_with_no_hole():
    # real CT 02 is a 40 mm slab that cuts the stomach at both ends: its label's surface is closed there by two flat
    # caps (about 30 % of it) whose rays read nothing the scan imaged (the label's content at the edge slices, and a
    # 14 mm^2 hole). The isometric view leaves them out and has no hole. Its cardia and pylorus points lie on the
    # slab's last and first slices, so each cap is one with an opening, and the cut joins them: no slit is needed
    d = os.path.join(SHARED_DIR, "data")
    cases = {c["name"]: c for c in bench._cases(quick=True, full_size=False, data_dir=d, parts=("real",))}
    row = bench.run_case(cases["real-02-slab/isometric"])
    assert row["ok"], row.get("error")
    q, m = row["quality"], row["method_report"]
    assert m["scan_edge_cap_mm2"] > 4000.0 and m["scan_edge_openings"] == 0 and m["scan_edge_slits_mm"] == []
    assert m["euler_characteristic"] == 1 and m["boundary_loops"] == 1
    assert q["grade"] == "excellent" and q["hole_area_fraction"] == 0.0 and q["failure_parts"] == 0
    assert any("scan" in w and "slice" in w for w in row["warnings"]), row["warnings"]


def test_merge_replaces_rows_by_name_and_keeps_the_rest():
    old = {"meta": {"date": "then", "wall_seconds": 9.0}, "full_size": {"500": {"pipeline_s": 5.0}},
           "cases": [{"name": "a", "seconds": 1.0, "group": "real", "ok": False, "error": "x"}, {"name": "b", "seconds": 2.0, "group": "real", "ok": False, "error": "x"}]}
    rows, full, meta = bench._merge(old, [{"name": "b", "seconds": 3.0, "group": "real", "ok": False, "error": "x"},
                                         {"name": "c", "seconds": 4.0, "group": "real", "ok": False, "error": "x"}], None,
                                    {"date": "now", "wall_seconds": 1.0}, ("real",))
    assert [(r["name"], r["seconds"]) for r in rows] == [("a", 1.0), ("b", 3.0), ("c", 4.0)]
    assert full == old["full_size"] and meta["date"] == "then"
    assert meta["merged"] == [{"date": "now", "parts": ["real"], "cases": 2, "wall_seconds": 1.0}]
    assert "rerun on now with --merge" in bench._markdown(rows, None, {**meta, "machine": {"cpus": 2, "platform": "x"}}, [])
    # one name in two parts (kappa and sweep): each row replaces its own
    old = {"meta": {}, "cases": [{"name": "k", "group": "kappa", "seconds": 1.0}, {"name": "k", "group": "sweep", "seconds": 2.0}]}
    rows, _, _ = bench._merge(old, [{"name": "k", "group": "sweep", "seconds": 5.0},
                                    {"name": "k", "group": "kappa", "seconds": 4.0}], None, {"date": "now", "wall_seconds": 1.0},
                              ("kappa", "sweep"))
    assert [(r["group"], r["seconds"]) for r in rows] == [("kappa", 4.0), ("sweep", 5.0)]
    # each merged run says which packages computed its rows (their last bits can move a volume's figures)
    pk = bench.package_versions()
    assert set(pk) >= {"numpy", "scipy", "SimpleITK", "vtk"} and all(isinstance(v, str) and v for v in pk.values())
    _, _, meta = bench._merge(old, [], None, {"date": "now", "wall_seconds": 1.0, "machine": {"packages": pk}}, ("x",))
    assert meta["merged"][-1]["packages"] == pk


def test_family_cases_tune_and_held_out_seeds_every_method_on_each():
    cases = bench.family_cases(quick=False, data_dir=None, cache_dir="/nonexistent")
    groups = {c["group"] for c in cases}
    assert groups == {"stomachs-tune", "stomachs-held-out", "stomachs-fresh", "stomachs-fresh-2", "stomachs-fresh-3",
                      "stomachs-fresh-4", "stomachs-fresh-5", "stomachs-fresh-6", "stomachs-fresh-7",
                      "stomachs-fresh-8", "stomachs-fresh-9"}
    seeds = {c["source"]["random"] for c in cases}
    sets = (set(bench.TUNE_SEEDS), set(bench.HELD_OUT_SEEDS), set(bench.FRESH_SEEDS), set(bench.FRESH2_SEEDS),
            set(bench.FRESH3_SEEDS), set(bench.FRESH4_SEEDS), set(bench.FRESH5_SEEDS), set(bench.FRESH6_SEEDS),
            set(bench.FRESH7_SEEDS), set(bench.FRESH8_SEEDS), set(bench.FRESH9_SEEDS))
    assert seeds == set().union(*sets)
    assert all(not a & b for i, a in enumerate(sets) for b in sets[i + 1:])  # no seed in two sets
    for seed in seeds:
        assert {c["method"] for c in cases if c["source"]["random"] == seed} == set(bench.FAMILY_METHODS)


def test_family_summary_counts_grades_peers_and_the_bound():
    def row(vol, m, grade, vis, dist, bound, fluid=(1, 2), springs=0.0, s1=1.4):
        q = {"grade": grade, "visible_fraction": vis, "broken_springs_fraction": springs, "inverted_fraction": 0.0,
             "failure_parts": 0, "max_stretch": s1,
             "markers": {"seen": 3, "total": 4, "by_region": {"under_fluid": list(fluid), "dome": [1, 1]},
                         "pairwise_distance_distortion": dist, "flat_bound": bound, "ratio_to_bound": dist / bound,
                         "length_error_mm": {"mean": 0.5, "sd": 1.0, "pairs": 3}}}
        return {"name": f"{vol}/{m}", "group": "stomachs-held-out", "method": m, "ok": True, "seconds": 2.0,
                "quality": q}
    rows = [row("a", "isometric", "excellent", 0.995, 0.05, 0.04), row("a", "lscm", "good", 0.99, 0.3, 0.04),
            row("b", "isometric", "good", 0.97, 0.08, 0.04, s1=1.6),
            row("b", "lscm", "good", 0.98, 0.4, 0.04, springs=1e-4, s1=1.7)]
    s = bench.family_summary(rows, "stomachs-held-out")
    # "no spring or triangle stretched over 1.5x", counted per volume: a triangle at 1.6x with no long edge counts
    assert (s["isometric"]["no_spring_over_limit"], s["isometric"]["no_triangle_over_limit"]) == (2, 1)
    assert (s["lscm"]["no_spring_over_limit"], s["lscm"]["no_triangle_over_limit"]) == (1, 1)
    assert s["isometric"]["excellent"] == 1 and s["isometric"]["good_or_better"] == 2
    assert s["isometric"]["visible_not_below_every_peer"] == 1 and s["lscm"]["visible_not_below_every_peer"] == 1
    assert s["isometric"]["ratio_to_bound_max"] == pytest.approx(2.0)
    assert s["lscm"]["under_fluid_seen"] == 2 and s["lscm"]["under_fluid_total"] == 4
    text = "\n".join(bench.family_markdown(rows))
    assert "held out: never tuned on" in text and "| isometric | 1/2 | 2/2 |" in text
    assert "| no spring / triangle over 1.5x |" in text and " | 2/1 | " in text


def test_the_surfacebound_part_scores_methods_against_the_whole_mucosas_layout():
    from StomachUnfoldLib.cli import BENCH_DEFAULT_PARTS, BENCH_PARTS, build_parser

    assert "surfacebound" in BENCH_PARTS and "surfacebound-fresh" in BENCH_PARTS
    # a plain bench leaves out the 85 minutes of the later held-out sets' references
    default = build_parser().parse_args(["bench"]).parts.split(",")
    assert "surfacebound" in default and "surfacebound-fresh" not in default and tuple(default) == BENCH_DEFAULT_PARTS
    cases = bench._cases(False, False, None, ["surfacebound"])
    assert {c["source"]["random"] for c in cases} == set(bench.TUNE_SEEDS) | set(bench.HELD_OUT_SEEDS)
    assert {c["method"] for c in cases} == {bench.SURFACE_LAYOUT}
    assert all(c["params"]["n_extra"] == bench.SURFACE_EXTRA_POINTS for c in cases)
    fresh = {c["source"]["random"] for c in bench._cases(False, False, None, ["surfacebound-fresh"])}
    assert fresh == {x for g, seeds in bench.FAMILY_SEED_SETS[2:] for x in seeds} and len(fresh) == 270
    # one real row on a tiny drawn stomach: the bound as the family rows compute it, the layouts above the robust fit
    row = bench.run_case(bench.Case("stomach-3/surface-layout", {"random": 3, "size": "tiny"}, {"n_extra": 10},
                                    method=bench.SURFACE_LAYOUT, group="surface-bound"))
    assert row["ok"], row.get("error")
    ref = row["reference"]
    assert ref["n_points"] == ref["n_markers"] + 10 and ref["n_pairs"] > 10
    assert ref["marker_bound_robust"] <= ref["marker_bound"] + 1e-12
    assert ref["surface_layout"] > ref["marker_bound_robust"]

    def fam(vol, m, dist, group="stomachs-tune"):
        return {"name": f"{vol}/{m}", "group": group, "method": m, "ok": True,
                "quality": {"markers": {"pairwise_distance_distortion": dist}}}

    def refrow(vol, bound, layout):
        return {"name": f"{vol}/surface-layout", "group": "surface-bound", "method": bench.SURFACE_LAYOUT, "ok": True,
                "reference": {"n_markers": 20, "n_points": 170, "marker_bound": bound, "marker_bound_robust": bound / 4,
                              "surface_layout": layout, "surface_layout_robust": layout / 2}}
    rows = [refrow("stomach-0", 0.02, 0.04), refrow("stomach-1", 0.02, 0.02), fam("stomach-0", "isometric", 0.05),
            fam("stomach-1", "isometric", 0.025), fam("stomach-0", "lscm", 0.5), fam("stomach-1000", "isometric", 0.1)]
    summ = bench.surface_bound_summary(rows)
    assert [x["set"] for x in summ] == ["tuning"]              # no held-out reference row: no held-out line
    t = summ[0]
    assert t["volumes"] == 2 and t["other_points"] == 150 and t["surface_layout_over_1p5"] == 1
    iso = t["methods"]["isometric"]
    assert iso["volumes"] == 2 and iso["within_1p5_of_bound"] == 1 and iso["within_1p5_of_surface"] == 2
    assert iso["over_surface_median"] == pytest.approx(np.median([0.05 / 0.04, 0.025 / 0.02]))
    assert t["methods"]["lscm"]["volumes"] == 1
    text = "\n".join(bench.surface_bound_markdown(rows))
    assert "among 150 other points" in text and "| tuning | isometric | 2 |" in text
    # two held-out sets: a line each and one for both together
    rows += [refrow("stomach-1000", 0.02, 0.02), fam("stomach-1000", "isometric", 0.02, "stomachs-held-out"),
             refrow("stomach-3000", 0.02, 0.01), fam("stomach-3000", "isometric", 0.02, "stomachs-fresh")]
    summ = bench.surface_bound_summary(rows)
    assert [x["set"] for x in summ] == ["tuning", "held-out 1000-", "fresh 3000-", "all 2 held-out sets"]
    both = summ[-1]["methods"]["isometric"]
    assert (both["volumes"], both["within_1p5_of_bound"], both["within_1p5_of_surface"]) == (2, 2, 1)


def test_zero_clicks_row_sits_beside_the_two_click_rows():
    """Issue 17: the 'isometric, zero clicks' row (found points) is summarised apart from the two-click rows."""
    def row(vol, grade, zero=False, within=True, confident=True):
        q = {"grade": grade, "visible_fraction": 0.99, "broken_springs_fraction": 0.0, "inverted_fraction": 0.0,
             "failure_parts": 0}
        r = {"name": f"{vol}/isometric" + ("-zero-clicks" if zero else ""), "group": "stomachs-tune",
             "method": "isometric", "ok": confident, "seconds": 2.0, "quality": q}
        if zero:
            r.update(zero_clicks=True, auto_points={"within_tolerance": within, "confident": confident,
                                                    "cardia_error_mm": 4.0, "pylorus_error_mm": 3.0})
        return r
    rows = [row("a", "excellent"), row("b", "good"), row("a", "excellent", zero=True),
            row("b", "excellent", zero=True, within=False), row("c", "bad", zero=True, within=False, confident=False)]
    s = bench.family_summary(rows, "stomachs-tune")
    assert s["isometric"]["volumes"] == 2 and s["isometric"]["excellent"] == 1  # two clicks untouched
    z = s["isometric, zero clicks"]
    assert (z["volumes"], z["failed"], z["points_within_10mm"], z["refused"], z["grade_as_two_clicks"]) == (3, 1, 1, 1, 1)
    text = "\n".join(bench.family_markdown(rows))
    assert "| isometric, zero clicks | 2/3 |" in text and "within 10 mm of the true cardia and pylorus on 1/3" in text
    assert "two-click grade on 1/2 (volumes with a two-click row)" in text
    cases = bench.zero_click_cases(quick=True)
    assert len(cases) == 6 and all(c["source"]["auto_points"] for c in cases)


_WORKER_PROBE = """
import resource, threading
import numpy as np
from StomachUnfoldEval import bench
def work(out):
    row = bench._run_case_in_worker(bench.Case("missing", {"real": "/nonexistent/ct.nii.gz"}, {}, method="isometric"))
    assert row["ok"] is False
    f0 = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    for _ in range(200):                     # a flat map's temporaries, made and dropped in a worker's thread
        t = np.ones(1 << 17)
        del t
    out.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - f0)
out = []
th = threading.Thread(target=work, args=(out,))
th.start()
th.join()
print(out[0])
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_a_bench_worker_keeps_freed_arrays_on_the_heap_under_dasks_trim_threshold():
    # Dask starts its workers with MALLOC_TRIM_THRESHOLD_=65536: a task's thread then hands every freed 1 MiB array
    # back and faults it in again (about 51,000 page faults here); the worker sets the command line's thresholds
    import subprocess
    import sys

    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536")
    out = subprocess.run([sys.executable, "-c", _WORKER_PROBE], capture_output=True, text=True, check=True, env=env)
    assert int(out.stdout.split()[-1]) < 5000


def test_mesh_size_part_charts_each_size_against_the_default(tmp_path):
    cases = bench.mesh_size_cases(quick=False, cache_dir="/nonexistent")
    assert {c["params"]["isometric_vertices"] for c in cases} == set(bench.MESH_SIZES)
    assert {c["source"]["random"] for c in cases} == set(bench.TUNE_SEEDS) | set(bench.HELD_OUT_SEEDS)
    assert {c["group"] for c in cases} == {"mesh-size"} and {c["method"] for c in cases} == {"isometric"}

    from StomachUnfoldLib.params import SurfaceParameters

    def row(seed, n, s, ratio, vis=0.999, seen=9, grade="excellent", group="mesh-size"):
        q = {"grade": grade, "visible_fraction": vis, "markers": {"ratio_to_bound": ratio, "seen": seen, "total": 10}}
        return {"name": f"stomach-{seed}/isometric-v{n}", "group": group, "method": "isometric", "ok": True,
                "seconds": s, "quality": q, "params": {"isometric_vertices": n}}
    default, small = SurfaceParameters().isometric_vertices, min(bench.MESH_SIZES)
    assert default in bench.MESH_SIZES
    rows = [row(0, default, 6.0, 1.4), row(1, default, 8.0, 1.6), row(0, small, 1.0, 1.7),
            row(1, small, 3.0, 1.3, grade="good"), row(1000, default, 5.0, 1.2),
            row(2, small, 0.5, 1.0, group="stomachs-tune")]                 # another part's row: not counted
    summ = {(x["set"], x["vertices"]): x for x in bench.mesh_size_summary(rows)}
    d = summ[("tuning", default)]
    assert d["default"] and d["seconds_median"] == 7.0 and d["ratio_median"] == pytest.approx(1.5)
    assert d["within_1p5"] == 1 and d["markers_seen"] == 18 and d["excellent"] == 2
    c = summ[("tuning", small)]
    assert not c["default"] and c["seconds_median"] == 2.0 and c["within_1p5"] == 1 and c["excellent"] == 1
    assert ("held-out", small) not in summ and summ[("held-out", default)]["volumes"] == 1
    md = "\n".join(bench.mesh_size_markdown(rows))
    assert f"| tuning | {small} | 2 | 2.0 | 1.50 | 1 |" in md and f"{default} (default)" in md
    assert bench.mesh_size_markdown(rows[-1:]) == []             # not run: no table


def test_a_marker_not_seen_is_told_apart_as_merged_off_not_shown_or_unmapped():
    from StomachUnfoldEval.markers import marker_report
    from StomachUnfoldLib.geometry import Volume

    a = np.full((6, 60, 60), -1000.0)
    a[:3] = 40.0                                             # the wall: the first hit from the viewer is k = 2
    jj, ii = np.mgrid[0:60, 0:60]
    for ci, cj in ((10, 10), (50, 10)):                      # two lone beads
        a[2][(ii - ci) ** 2 + (jj - cj) ** 2 <= 4] = 1000.0
    a[2, 40:46, 5:25] = 1000.0                               # dense tissue a bead lies in (a 120 mm^2 region)
    for ci in (25, 34):                                      # two beads 9 mm apart whose regions touch: one region
        a[2][(ii - ci) ** 2 + (jj - 25) ** 2 <= 16] = 1000.0
    vol = Volume(a, np.ones(3), np.zeros(3), np.eye(3))
    mapped = {"seen": [10.0, 10.0, 2.0], "merged": [6.0, 43.0, 2.0], "off": [50.0, 14.5, 2.0],
              "not shown": [50.0, 50.0, 2.0], "unmapped": [np.nan] * 3,
              "pair 1": [25.0, 25.0, 2.0], "pair 2": [34.0, 25.0, 2.0]}
    rep = marker_report(vol, mapped)
    assert rep["n_seen"] == 1 and rep["markers"]["seen"]["seen"]
    assert "missed" not in rep["markers"]["seen"]
    for why in ("merged", "off", "not shown", "unmapped"):
        assert rep["markers"][why]["missed"] == why, (why, rep["markers"][why])
    assert rep["markers"]["pair 1"]["missed"] == rep["markers"]["pair 2"]["missed"] == "merged"
    assert rep["missed_counts"] == {"merged": 3, "off": 1, "not shown": 1, "unmapped": 1}


def test_the_summary_sums_why_markers_were_not_seen_and_says_it_under_the_table():
    def row(vol, m, missed):
        mk = {"seen": 3, "total": 4, "by_region": {}, "pairwise_distance_distortion": 0.05, "flat_bound": 0.04,
              "ratio_to_bound": 1.25, "length_error_mm": {"mean": 0.1, "sd": 1.0, "pairs": 2}}
        if missed is not None:
            mk["missed"] = missed
        q = {"grade": "excellent", "visible_fraction": 0.99, "broken_springs_fraction": 0.0, "inverted_fraction": 0.0,
             "failure_parts": 0, "max_stretch": 1.2, "markers": mk}
        return {"name": f"{vol}/{m}", "group": "stomachs-fresh", "method": m, "ok": True, "seconds": 1.0, "quality": q}
    reasons = {"merged": 1, "off": 0, "not shown": 0, "unmapped": 0}
    rows = [row("a", "isometric", reasons), row("b", "isometric", dict(reasons, off=2)),
            row("a", "lscm", dict(reasons, merged=0, **{"not shown": 3}))]
    s = bench.family_summary(rows, "stomachs-fresh")
    assert s["isometric"]["markers_missed"] == {"merged": 2, "off": 2, "not shown": 0, "unmapped": 0}
    text = "\n".join(bench.family_markdown(rows))
    assert "Markers not seen, by what the view shows" in text and "isometric 2 / 2 / 0; lscm 0 / 0 / 3." in text
    # rows judged before the reasons were recorded: no sums, no line
    old = [row("a", "isometric", None)]
    assert bench.family_summary(old, "stomachs-fresh")["isometric"]["markers_missed"] is None
    assert "Markers not seen" not in "\n".join(bench.family_markdown(old))


def test_hybrid_seeds_do_not_depend_on_the_other_sets(tmp_path):
    # a drawn stomach per real CT that holds one (not the 02 slab), with the seed pinned to the CT's place among the
    # files: adding a set of random stomachs before them (as seeds 5000-5029 were) must not draw other hybrids
    for name in ("01_a_ct.nii.gz", "01_a_ct_seg6.nii.gz", "02_b_DERIVED.nii.gz", "02_b_ct.nii.gz", "03_c_ct.nii.gz"):
        (tmp_path / name).write_bytes(b"")
    cases = bench.family_cases(quick=False, data_dir=str(tmp_path), cache_dir="/nonexistent")
    hybrids = [c for c in cases if c["group"] == "stomachs-hybrid"]
    seeds = {c["name"].split("/")[0]: c["source"]["hybrid"] for c in hybrids}
    assert seeds == {"hybrid-01": 1004, "hybrid-03": 1005}
    assert len(hybrids) == 2 * len(bench.FAMILY_METHODS)
    assert bench.hybrid_cases(False, str(tmp_path), "/nonexistent") == hybrids
    alone = bench._cases(False, False, str(tmp_path), ["hybrids"])  # the part alone (default phantom cache)
    assert [(c["name"], c["source"]["hybrid"]) for c in alone] == [(c["name"], c["source"]["hybrid"]) for c in hybrids]


def test_the_many_hybrids_part_runs_every_method_on_its_seeds_in_the_cts_that_hold_a_whole_stomach(tmp_path):
    from StomachUnfoldLib.cli import BENCH_DEFAULT_PARTS, BENCH_PARTS

    assert "hybrids-many" in BENCH_PARTS and "hybrids-many" in BENCH_DEFAULT_PARTS
    for name in ("01_a_ct.nii.gz", "01_a_ct_seg6.nii.gz", "02_b_DERIVED.nii.gz", "02_b_ct.nii.gz", "03_c_ct.nii.gz"):
        (tmp_path / name).write_bytes(b"")
    cases = bench._cases(False, False, str(tmp_path), ["hybrids-many"])
    assert {c["group"] for c in cases} == {"hybrids-dev", "hybrids-decide"}
    assert {os.path.basename(c["source"]["ct"]) for c in cases} == {"01_a_ct.nii.gz", "03_c_ct.nii.gz"}  # no slab
    per_set = {g: set(seeds) for g, seeds in bench.HYBRID_SEED_SETS}
    assert all(c["source"]["hybrid"] in per_set[c["group"]] for c in cases)
    assert not per_set["hybrids-dev"] & per_set["hybrids-decide"]
    assert not set(bench.HYBRID_SEEDS) & set().union(*per_set.values())      # not the three hybrids of "stomachs"
    assert len(cases) == 2 * sum(len(s) for s in per_set.values()) * len(bench.FAMILY_METHODS)
    assert len({(c["group"], c["name"]) for c in cases}) == len(cases)
    assert not any(c["group"].startswith("stomachs") for c in cases)        # kept out of the small sets' chart
    titles = dict(bench.FAMILY_GROUPS)
    assert "hybrids-dev" in titles and "hybrids-decide" in titles
    quick = bench.hybrid_seed_cases(True, str(tmp_path))
    assert {c["group"] for c in quick} == {"hybrids-dev"} and len(quick) == 2 * 2 * len(bench.FAMILY_METHODS)
    assert bench.hybrid_seed_cases(False, None) == []                       # no real CTs: no hybrids


@pytest.mark.parametrize("part,seeds", [("fresh-4", "FRESH4_SEEDS"), ("fresh-5", "FRESH5_SEEDS"),
                                        ("fresh-6", "FRESH6_SEEDS"), ("fresh-7", "FRESH7_SEEDS"),
                                        ("fresh-8", "FRESH8_SEEDS"), ("fresh-9", "FRESH9_SEEDS")])
def test_a_fresh_part_runs_that_set_alone_with_every_method(part, seeds):
    from StomachUnfoldLib.cli import BENCH_PARTS

    assert part in bench.FRESH_PARTS and part in BENCH_PARTS       # the command line knows the part the bench runs
    alone = bench._cases(False, False, None, [part])
    assert {c["group"] for c in alone} == {f"stomachs-{part}"}
    assert {c["source"]["random"] for c in alone} == set(getattr(bench, seeds))
    assert len(alone) == len(getattr(bench, seeds)) * len(bench.FAMILY_METHODS)
    whole = [c["name"] for c in bench._cases(False, False, None, ["stomachs"]) if c["group"] == f"stomachs-{part}"]
    assert whole == [c["name"] for c in alone]


def test_the_sizes_part_runs_every_method_on_tiny_and_full_size_stomachs_of_its_own_seeds():
    from StomachUnfoldLib.cli import BENCH_DEFAULT_PARTS, BENCH_PARTS
    from StomachUnfoldEval.random_stomach import SIZES

    assert "sizes" in BENCH_PARTS and "sizes" in BENCH_DEFAULT_PARTS
    cases = bench._cases(False, False, None, ["sizes"])
    assert {(c["group"], c["source"]["size"]) for c in cases} == {("sizes-tiny", "tiny"), ("sizes-full", "full")}
    assert {c["source"]["size"] for c in cases} <= set(SIZES) - {"small"}
    # every method with the two true points, and the default from the points it finds (zero clicks)
    assert len(cases) == sum(len(seeds) for _, _, seeds in bench.SIZE_SEED_SETS) * (len(bench.FAMILY_METHODS) + 1)
    zero = [c for c in cases if c["source"].get("auto_points")]
    assert {c["method"] for c in zero} == {bench.FAMILY_METHODS[0]} and len(zero) == 40
    assert all(c["name"].endswith("-zero-clicks") for c in zero)
    assert len({(c["group"], c["name"]) for c in cases}) == len(cases)
    # never a seed of the small sets: none of these volumes was tuned or decided on
    small = set(bench.TUNE_SEEDS).union(*(seeds for _, seeds in bench.FAMILY_SEED_SETS))
    assert not small & {c["source"]["random"] for c in cases}
    assert not any(c["group"].startswith("stomachs") for c in cases)   # kept out of the small sets' chart
    titles = dict(bench.FAMILY_GROUPS)
    assert "sizes-tiny" in titles and "sizes-full" in titles
    quick = bench.size_cases(quick=True)
    assert {c["group"] for c in quick} == {"sizes-tiny"} and len(quick) == 2 * (len(bench.FAMILY_METHODS) + 1)


def test_clicks_moved_off_their_places_are_that_far_from_the_truth_and_the_same_for_every_method(tmp_path):
    from StomachUnfoldEval import click_error as ce

    c0, p0 = np.array([10.0, -5.0, 30.0]), np.array([-20.0, 4.0, -12.0])
    c, p = ce.moved_clicks(c0, p0, 5.0, seed=7, draw=1)
    assert np.linalg.norm(c - c0) == pytest.approx(5.0) and np.linalg.norm(p - p0) == pytest.approx(5.0)
    again = ce.moved_clicks(c0, p0, 5.0, seed=7, draw=1)
    assert np.array_equal(again[0], c) and np.array_equal(again[1], p)
    other = ce.moved_clicks(c0, p0, 5.0, seed=7, draw=0)
    assert not np.allclose(other[0], c)
    cases = bench._cases(quick=False, full_size=False, data_dir=None, parts=("clicks",))
    n = len(bench.TUNE_SEEDS) + len(bench.HELD_OUT_SEEDS)
    assert len(cases) == n * len(ce.CLICK_METHODS) * len(ce.CLICK_ERRORS_MM) * ce.CLICK_DRAWS
    assert {c["group"] for c in cases} == {ce.GROUP} and {c["method"] for c in cases} == set(ce.CLICK_METHODS)
    assert len({c["name"] for c in cases}) == len(cases)
    # through the bench's own loader and one whole run: the points it unfolds from are the moved ones
    src = {"random": 0, "size": "tiny", "_cache": str(tmp_path), "click_error_mm": 10.0, "click_draw": 0}
    ct, cardia, pylorus, _, markers = bench._load(dict(src))
    truth = markers["_truth"]
    assert np.linalg.norm(cardia - np.asarray(truth["cardia_lps"])) == pytest.approx(10.0)
    assert np.linalg.norm(pylorus - np.asarray(truth["pylorus_lps"])) == pytest.approx(10.0)
    row = bench.run_case(bench.Case("stomach-0/isometric-clicks-10mm-0", src, {}, method="isometric", group=ce.GROUP))
    assert row["ok"], row.get("error")
    assert row["source"]["click_error_mm"] == 10.0 and "markers" in row["quality"]


def test_the_clicks_table_sets_each_method_beside_its_own_rows_with_the_true_points():
    from StomachUnfoldEval import click_error as ce

    def row(seed, method, err=None, seen=10, grade="excellent", ok=True, group=None, vis=1.0, warnings=()):
        r = {"name": f"stomach-{seed}/{method}" + (f"-clicks-{err:g}mm-0" if err else ""), "method": method,
             "group": group or (ce.GROUP if err else "stomachs-tune"), "ok": ok, "warnings": list(warnings),
             "source": {"random": seed, **({"click_error_mm": err} if err else {})}}
        if ok:
            r["quality"] = {"grade": grade, "visible_fraction": vis, "markers": {"seen": seen, "total": 10}}
        else:
            r["error"] = "AnatomyError: no opening after trimming; check the points"
        return r
    rows = [row(0, "isometric"), row(1, "isometric", seen=9), row(2, "isometric"),     # 2: not run moved: left out
            row(0, "isometric", 5.0, seen=9, warnings=[f"the cardia point lies 12 mm off, {ce.DEEP_POINT_WARNING}"]),
            row(1, "isometric", 5.0, grade="good", vis=0.99, warnings=["the points were probably swapped"]),
            row(0, "lscm"), row(1, "lscm"), row(0, "lscm", 5.0, ok=False), row(1, "lscm", 5.0),
            row(1000, "isometric", 5.0, group=ce.GROUP)]
    summ = {(x["set"], x["method"], x["error_mm"]): x for x in ce.click_error_summary(rows, [0, 1, 2], [1000])}
    t0, t5 = summ[("tuning", "isometric", 0.0)], summ[("tuning", "isometric", 5.0)]
    assert (t0["runs"], t0["markers_seen"], t0["fewer_markers"]) == (2, 19, 0)
    assert (t5["runs"], t5["excellent"], t5["good_or_better"], t5["markers_seen"], t5["fewer_markers"]) == (2, 1, 2, 19, 1)
    assert (t0["deep_point_warned"], t5["deep_point_warned"]) == (0, 1)
    assert t5["visible_min"] == pytest.approx(0.99)
    l5 = summ[("tuning", "lscm", 5.0)]
    assert (l5["runs"], l5["failed"]) == (2, 1) and list(l5["errors"].values()) == [1]
    assert summ[("held-out", "isometric", 5.0)]["runs"] == 1 and ("held-out", "isometric", 0.0) not in summ
    md = "\n".join(ce.click_error_markdown(rows, [0, 1, 2], [1000]))
    assert "| tuning | isometric | 5 | 2 | 0 | 1 | 2 | 99.50 / 99.00 | 19/20 | 1 | 1 |" in md
    assert 'lscm 1x "AnatomyError: no opening after trimming"' in md
    assert ce.click_error_markdown(rows[:3], [0, 1, 2], [1000]) == []                 # not run: no table


def test_the_area_scale_along_the_centreline_finds_the_stretch_a_view_draws_larger():
    from types import SimpleNamespace

    from StomachUnfoldEval.regional import area_scale_along, area_scale_summary

    nx, ny = 41, 11
    x, y = np.meshgrid(np.linspace(0, 100, nx), np.linspace(0, 20, ny), indexing="ij")
    rest = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    tris = np.array([t for a in range(nx - 1) for b in range(ny - 1)
                     for t in ([idx[a, b], idx[a + 1, b], idx[a + 1, b + 1]], [idx[a, b], idx[a + 1, b + 1], idx[a, b + 1]])])
    view = rest.copy()
    far = rest[:, 0] >= 50.0                                 # the second half along the centreline: twice as wide
    view[:, 1] = np.where(far, 2.0 * rest[:, 1], rest[:, 1])
    centerline = np.stack([np.linspace(0, 100, 51), np.full(51, 10.0), np.full(51, 5.0)], 1)
    got = area_scale_along(SimpleNamespace(surface=tris, rest_lps=rest, unfolded_lps=view), centerline, parts=4)
    assert got == pytest.approx([1.0, 1.0, 2.0, 2.0])        # (the column at x = 50 splits by its centroids)
    rows = [{"ok": True, "quality": {"area_scale_along": [1.0, 1.0, 2.0, 2.0]}},
            {"ok": True, "quality": {"area_scale_along": [1.0, 1.0, 1.0, None]}}, {"ok": False}]
    assert area_scale_summary(rows) == pytest.approx([1.0, 1.0, 1.5, 2.0])
    assert area_scale_summary([{"ok": False}]) is None


def test_the_bench_runs_only_the_methods_asked_for():
    from StomachUnfoldLib.errors import InputError

    cases = bench._cases(False, False, None, ["sizes", "zeroclicks"])
    assert {c["method"] for c in cases} >= {"isometric", "lscm", "cylindrical", "massspring"}
    only = bench._only_methods(cases, ["isometric"])
    assert only and all(c["method"] == "isometric" for c in only)
    assert len(only) == sum(c["method"] == "isometric" for c in cases)       # zero clicks too (default method)
    assert any(c["name"].endswith("-zero-clicks") for c in only)
    assert bench._only_methods(cases, None) is cases
    with pytest.raises(InputError, match="unknown method isometrik"):
        bench._only_methods(cases, ["isometrik"])


def test_the_phase_part_runs_each_volume_with_the_raster_and_the_depth_samples_where_they_are_and_moved(tmp_path):
    from StomachUnfoldEval import raster_phase as rp
    from StomachUnfoldLib import surface

    cases = bench._cases(quick=True, full_size=False, data_dir=None, parts=("phase",))
    assert {c["group"] for c in cases} == {rp.GROUP} and len({c["name"] for c in cases}) == len(cases)
    assert {(c["source"]["raster_offset_px"], c["source"]["depth_offset_px"]) for c in cases} == set(rp.PHASES)
    assert len(cases) == 2 * 2 * len(rp.PHASE_METHODS) * 4      # no data folder: the two random sets, two volumes each
    # one volume three ways through the bench's own run: the same map drawn on pixels and depths laid elsewhere
    src = {"random": 0, "size": "tiny", "_cache": str(tmp_path), "phase_set": "tiny"}
    rows = [bench.run_case(bench.Case(f"stomach-0-tiny/isometric-phase-{o:g}-depth-{d:g}",
                                      dict(src, raster_offset_px=o, depth_offset_px=d), {},
                                      method="isometric", group=rp.GROUP)) for o, d in rp.PHASES[:3]]
    assert all(r["ok"] for r in rows), [r.get("error") for r in rows]
    assert surface.RASTER_OFFSET_PX == 0.0 and surface.DEPTH_OFFSET_PX == 0.0     # put back after the runs
    q0, q1, q2 = (r["quality"] for r in rows)
    assert q0["distortion_map"] != q1["distortion_map"] or q0["visible_fraction"] != q1["visible_fraction"]
    d0, d1, d2 = (q["markers"]["pairwise_distance_distortion"] for q in (q0, q1, q2))
    assert d0 == pytest.approx(d1, abs=0.01) and d0 == pytest.approx(d2, abs=0.01)   # the map is the same
    summ = rp.phase_summary(rows)
    assert [(e["moved"], e["volumes"], e["method"]) for e in summ] == [("raster", 1, "isometric"),
                                                                        ("depth", 1, "isometric")]
    # a named phantom's source takes the offsets too (its keys are the phantom's arguments otherwise)
    ct, *_ = bench._load({"shape": "j", "size": "tiny", "raster_offset_px": 0.5, "depth_offset_px": 0.5,
                          "phase_set": "x"})
    assert ct.size[0] > 0


def test_the_depth_samples_moved_half_a_voxel_move_every_mapped_depth_and_not_the_map():
    from StomachUnfoldEval.phantom import make_phantom
    from StomachUnfoldLib import surface
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

    ct, truth = make_phantom(shape="j", size="tiny")
    pts = np.array([m["lps"] for m in truth["markers"]], float)
    out = {}
    for d in (0.0, 0.5):
        surface.DEPTH_OFFSET_PX = d
        try:
            res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters(method="lscm"))
        finally:
            surface.DEPTH_OFFSET_PX = 0.0
        out[d] = res
    s = float(out[0.0].unfolded.spacing[2])
    m0, m1 = (out[d].correspondence.to_unfolded(pts) for d in (0.0, 0.5))
    ok = np.all(np.isfinite(m0), 1) & np.all(np.isfinite(m1), 1)
    assert ok.sum() >= len(pts) - 1
    same_pixel = np.all(np.abs(m0[ok, :2] - m1[ok, :2]) < 1e-6, 1)
    assert same_pixel.mean() > 0.8                                   # the flat map: the same places in (i, j)
    assert np.allclose(m1[ok][same_pixel, 2] - m0[ok][same_pixel, 2], -0.5 * s, atol=1e-6)   # half a voxel deeper
    a0, a1 = out[0.0].unfolded.array, out[0.5].unfolded.array
    assert a0.shape == a1.shape and not np.array_equal(a0, a1)       # the view sampled at other depths
    assert out[0.0].mesh.unfolded_lps[0, 2] - out[0.5].mesh.unfolded_lps[0, 2] == pytest.approx(0.5 * s)


def test_the_phase_table_counts_what_moved_with_the_raster_and_the_depth_samples():
    from StomachUnfoldEval import raster_phase as rp

    def row(vol, method, off, vis, seen, grade="excellent", dep=None):
        src = {"raster_offset_px": off, "phase_set": "tiny", **({} if dep is None else {"depth_offset_px": dep})}
        return {"name": f"{vol}/{method}-phase-{off:g}-depth-{dep or 0:g}", "method": method, "group": rp.GROUP,
                "ok": True, "source": src, "markers_seen": seen, "quality": {"grade": grade, "visible_fraction": vis}}
    h, dd = rp.PHASE_OFFSET_PX, rp.DEPTH_OFFSET_PX
    rows = [row("a", "isometric", 0.0, 0.9990, 10), row("a", "isometric", h, 0.9975, 9),          # -0.15 point
            row("b", "isometric", 0.0, 1.0000, 10), row("b", "isometric", h, 1.0000, 10, "good"),
            row("c", "isometric", 0.0, 0.9980, 8),                                             # one offset only
            row("a", "lscm", 0.0, 0.9980, 7), row("a", "lscm", h, 0.9980, 7),
            row("b", "lscm", 0.0, 1.0000, 6), row("b", "lscm", h, 1.0000, 6)]
    summ = {e["method"]: e for e in rp.phase_summary(rows)}
    iso = summ["isometric"]
    assert iso["moved"] == "raster" and iso["volumes"] == 2 and iso["visible_change_max"] == pytest.approx(0.15)
    assert iso["visible_change_median"] == pytest.approx(0.075) and iso["visible_changed_over_0.1"] == 1
    assert iso["markers"] == [20, 19] and iso["markers_volumes_changed"] == 1 and iso["grades_changed"] == ["b"]
    assert iso["behind_lscm_flips"] == ["a"]                    # ahead of LSCM's 99.80 at 0, behind at half a pixel
    assert "behind_lscm_flips" not in summ["lscm"] and summ["lscm"]["visible_change_max"] == 0.0
    md = "\n".join(rp.phase_markdown(rows))
    assert "| tiny | isometric | raster | 2 | 0.075 / 0.150 | 1 | 20 -> 19 | 1 | b | a |" in md
    assert "at all four phases" not in md                      # no volume ran at all four
    assert rp.phase_markdown([]) == []
    # the depth runs, and the volumes behind LSCM at every phase
    rows += [row("a", "isometric", 0.0, 0.9970, 10, dep=dd), row("a", "isometric", h, 0.9975, 10, dep=dd),
             row("a", "lscm", 0.0, 0.9980, 7, dep=dd), row("a", "lscm", h, 0.9985, 7, dep=dd),
             row("b", "isometric", 0.0, 0.9990, 10, dep=dd), row("b", "isometric", h, 1.0000, 10, dep=dd),
             row("b", "lscm", 0.0, 1.0000, 6, dep=dd), row("b", "lscm", h, 1.0000, 6, dep=dd)]
    by = {(e["method"], e["moved"]): e for e in rp.phase_summary(rows)}
    assert set(by) == {(m, mv) for m in ("isometric", "lscm") for mv in ("raster", "depth", "both")}
    assert by["isometric", "depth"]["visible_change_max"] == pytest.approx(0.2)
    assert by["isometric", "depth"]["behind_lscm_flips"] == ["a", "b"]   # a: ahead at 0, behind here; b: tied -> behind
    beh = rp.behind_summary(rows)
    assert beh == [{"set": "tiny", "method": "isometric", "volumes": 2, "behind_every_phase": [],
                    "behind_some_phases": ["a", "b"], "behind_none": 0, "behind_on_the_mean": ["a", "b"]}]
    rows.append(row("c", "lscm", 0.0, 0.9990, 8))                # c still runs at one phase only: left out
    assert rp.behind_summary(rows)[0]["volumes"] == 2
    assert "| tiny | isometric | 2 | none | a, b | 0 | a, b |" in "\n".join(rp.phase_markdown(rows))
    # a volume behind at one phase only by a little and ahead by more at the others is not behind on the mean
    d = [row("d", m, o, v, 5, dep=p) for m, vals in (("isometric", (0.9990, 1.0, 1.0, 1.0)), ("lscm", (0.9995,) * 4))
         for (o, p), v in zip(rp.PHASES, vals)]
    e = rp.behind_summary(d)[0]
    assert e["behind_some_phases"] == ["d"] and e["behind_on_the_mean"] == []
