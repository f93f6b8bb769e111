"""The bench's ``oblique`` and ``prone`` parts: a CT resampled onto a turned voxel grid keeps its anatomy in place and
unfolds as drawn; a stomach mirrored front to back (its water on the anterior wall, as a prone patient's) too."""
import numpy as np

from conftest import FLIP
from StomachUnfoldEval.oblique import GROUP, grid_turn, oblique_cases, oblique_markdown, oblique_summary, turned_grid
from StomachUnfoldLib.geometry import Volume


def _ball_ct(direction) -> tuple[Volume, np.ndarray]:
    """A -1000 HU box (1.2 x 1.2 x 2 mm voxels, the given direction) with an 800 HU ball of 4 mm radius, and its centre
    (LPS mm)."""
    shape = (30, 50, 50)                                          # (k, j, i)
    vol = Volume(np.full(shape, -1000, np.int16), np.array([1.2, 1.2, 2.0]), np.array([10.0, -20.0, 5.0]),
                 np.asarray(direction, float))
    centre = vol.index_to_lps(np.array([[27.0, 21.0, 13.0]]))[0]
    kk, jj, ii = np.mgrid[:shape[0], :shape[1], :shape[2]]
    lps = vol.index_to_lps(np.stack([ii.ravel(), jj.ravel(), kk.ravel()], 1).astype(float))
    inside = (np.linalg.norm(lps - centre, axis=1) <= 4.0).reshape(shape)
    return vol.with_array(np.where(inside, 800, -1000).astype(np.int16)), centre


def test_turned_grid_keeps_the_voxel_size_and_every_structure_at_its_lps_place():
    ct, centre = _ball_ct(FLIP)
    out = turned_grid(ct, 30.0, (1.0, 2.0, 3.0))
    D = np.asarray(out.direction)
    assert np.allclose(D @ D.T, np.eye(3), atol=1e-9) and np.allclose(out.spacing, ct.spacing)
    assert not np.allclose(D, ct.direction, atol=0.1)             # a grid turned off the CT's axes
    assert np.min(np.abs(D[np.abs(D) > 1e-6])) < 0.9              # oblique: some axis mixes patient directions
    assert out.array.dtype == np.int16
    # the ball: the same centre (LPS) and size on the new grid; outside the old box the background
    dense = out.voxel_lps(out.array > 0)
    assert np.linalg.norm(dense.mean(0) - centre) < 0.5
    vol_old = (ct.array > 0).sum() * np.prod(ct.spacing)
    vol_new = (out.array > 0).sum() * np.prod(out.spacing)
    assert abs(vol_new - vol_old) < 0.2 * vol_old
    assert out.array.min() == -1024 and out.array.max() > 600


def test_each_seed_has_its_own_turn_within_the_range():
    turns = [grid_turn(s) for s in range(1000, 1030)]
    assert all(15.0 <= t["degrees"] <= 40.0 and abs(np.linalg.norm(t["axis"]) - 1.0) < 1e-9 for t in turns)
    assert len({round(t["degrees"], 6) for t in turns}) == 30 and grid_turn(1000) == turns[0]


def test_a_stomach_on_an_oblique_grid_unfolds_as_drawn(tmp_path):
    """Tiny random stomach 4 (a seed the defaults were not tuned on) on a grid turned 30 degrees: the default method
    grades excellent and sees as much of the mucosa and as many markers as on the grid it was drawn on."""
    from StomachUnfoldEval.bench import Case, run_case

    src = {"random": 4, "size": "tiny", "_cache": str(tmp_path)}
    drawn = run_case(Case("stomach-4/isometric", src, {}, method="isometric", group="stomachs-held-out"))
    turned = run_case(Case("stomach-4/isometric-oblique", {**src, "turn": {"degrees": 30.0, "axis": [1.0, 2.0, 3.0]}},
                           {}, method="isometric", group=GROUP))
    assert drawn["ok"] and turned["ok"], (drawn.get("error"), turned.get("error"))
    a, b = drawn["quality"], turned["quality"]
    assert b["grade"] == "excellent" and b["visible_fraction"] >= a["visible_fraction"] - 0.005
    assert b["markers"]["seen"] >= a["markers"]["seen"] - 1 and b["markers"]["total"] == a["markers"]["total"]
    assert b["markers"]["pairwise_distance_distortion"] < 0.1
    # the part's table sets the two side by side
    table = "\n".join(oblique_markdown([drawn, turned], "stomachs-held-out"))
    assert "| isometric | as drawn | 1 |" in table and "| isometric | oblique | 1 |" in table


def test_the_summary_counts_volumes_that_lose_on_the_turned_grid():
    def row(seed, group, vis, seen, ok=True):
        r = {"name": f"stomach-{seed}/isometric" + ("-oblique" if group == GROUP else ""), "method": "isometric",
             "group": group, "ok": ok, "seconds": 2.0}
        if ok:
            r["quality"] = {"grade": "excellent", "visible_fraction": vis,
                            "markers": {"seen": seen, "total": 20, "pairwise_distance_distortion": 0.04}}
        else:
            r["error"] = "AnatomyError: nothing; check the points"
        return r
    rows = [row(1, "stomachs-held-out", 1.0, 20), row(1, GROUP, 0.99, 20),      # 1 point lower
            row(2, "stomachs-held-out", 1.0, 20), row(2, GROUP, 0.999, 19),     # a marker fewer, within the drop
            row(3, "stomachs-held-out", 1.0, 20), row(3, GROUP, 0, 0, ok=False)]
    s = {x["grid"]: x for x in oblique_summary(rows, "stomachs-held-out")}
    assert s["oblique"]["runs"] == 3 and s["oblique"]["failed"] == 1 and s["as drawn"]["failed"] == 0
    assert s["oblique"]["visible_lower"] == ["stomach-1"] and s["oblique"]["fewer_markers"] == ["stomach-2"]
    assert s["oblique"]["errors"] == ["AnatomyError: nothing"]
    assert "Why runs failed" in "\n".join(oblique_markdown(rows, "stomachs-held-out"))
    alone = oblique_summary([r for r in rows if r["group"] == GROUP], "stomachs-held-out")   # the part run alone
    assert [x["grid"] for x in alone] == ["oblique"] and alone[0]["errors"] == ["AnatomyError: nothing"]


def test_the_part_runs_the_held_out_seeds_with_every_method():
    cases = oblique_cases(False, tuple(range(1000, 1030)), "/nowhere", lambda n, s, p, method, group: (n, s, method))
    assert len(cases) == 90 and {m for _, _, m in cases} == {"isometric", "cylindrical", "lscm"}
    assert all(s["turn"] == grid_turn(s["random"]) for _, s, _ in cases)


def test_water_on_an_oblique_grid_is_the_pool_as_drawn(monkeypatch):
    """Tiny random stomach 38 on its grid turned 40 degrees (the part's turn for it): with the rays along the tilted
    grid axis closest to +y the level left whole columns out and their water out of the lumen (526 of the 5097 voxels
    certainly in the drawn water missed: cracks of "wall" in the lumen); on the grid turned upright the lumen holds
    the drawn water, as on the grid it was drawn on."""
    import StomachUnfoldLib.preprocessing as pre
    from StomachUnfoldEval.lumen_truth import lumen_against_drawn
    from StomachUnfoldEval.random_stomach import random_stomach

    ct, truth = random_stomach(38, "tiny")[:2]
    cardia, pylorus = np.array(truth["cardia_lps"]), np.array(truth["pylorus_lps"])
    t = grid_turn(38)
    turned = turned_grid(ct, t["degrees"], t["axis"])
    assert pre._tilt_deg(turned) > 30.0
    lumen, info = pre.air_region(turned, cardia, pylorus)
    r = lumen_against_drawn(turned, truth, lumen, region="water")
    assert r["drawn"] > 4000 and r["missed"] < 0.03 * r["drawn"] and r["over"] < 0.12 * r["drawn"]
    drawn_ml = pre.air_region(ct, cardia, pylorus)[1]["fluid_ml"]
    assert abs(info["fluid_ml"] - drawn_ml) < 0.1 * drawn_ml
    assert abs(info["fluid_level_lps_y"] - truth["fluid_level_lps_y"]) < 1.5
    monkeypatch.setattr(pre, "UPRIGHT_TILT_DEG", 90.0)          # the rays along the tilted grid axis
    old = lumen_against_drawn(turned, truth, pre.air_region(turned, cardia, pylorus)[0], region="water")
    assert old["missed"] > 0.05 * old["drawn"]


def test_front_to_back_keeps_the_voxels_and_mirrors_every_lps_point_of_the_truth():
    from StomachUnfoldEval.oblique import FRONT_TO_BACK, front_to_back

    ct, _ = _ball_ct(np.eye(3))
    truth = {"cardia_lps": [1.0, 2.0, 3.0], "fluid_level_lps_y": 20.0, "spacing": [1.0, 1.0, 2.0],
             "markers": [{"id": "M01", "lps": [4.0, -5.0, 6.0], "normal_lps": [0.0, 1.0, 0.0],
                          "ras": [-4.0, 5.0, 6.0]}],
             "centerline_lps": [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]}
    vol, t = front_to_back(ct, truth)
    assert vol.array is ct.array and np.allclose(vol.spacing, ct.spacing)
    ijk = np.array([[3.0, 7.0, 2.0]])
    assert np.allclose(vol.index_to_lps(ijk), ct.index_to_lps(ijk) @ FRONT_TO_BACK.T)   # each voxel mirrored
    assert t["cardia_lps"] == [1.0, -2.0, 3.0] and t["fluid_level_lps_y"] == -20.0 and t["spacing"] == [1.0, 1.0, 2.0]
    m = t["markers"][0]
    assert m["lps"] == [4.0, 5.0, 6.0] and m["normal_lps"] == [0.0, -1.0, 0.0] and m["ras"] == [-4.0, -5.0, 6.0]
    assert t["centerline_lps"] == [[0.0, -1.0, 2.0], [3.0, -4.0, 5.0]]
    assert truth["cardia_lps"] == [1.0, 2.0, 3.0]                   # the truth given is left as it was


def test_a_prone_stomachs_water_is_found_on_its_anterior_wall_and_the_markers_under_it_seen(tmp_path):
    """Tiny random stomach 2 (57 mL of water) mirrored front to back: the water is found on the anterior wall, said
    so, and the default method sees the markers under it as it does supine (before, the water's surface was drawn as
    mucosa and the judge, bounded by the same lumen, graded the view excellent all the same)."""
    from StomachUnfoldEval.bench import Case, run_case

    src = {"random": 2, "size": "tiny", "_cache": str(tmp_path)}
    supine = run_case(Case("stomach-2/isometric", src, {}, method="isometric", group="stomachs-held-out"))
    prone = run_case(Case("stomach-2/isometric-prone", {**src, "prone": True}, {}, method="isometric",
                          group="prone"))
    assert supine["ok"] and prone["ok"], (supine.get("error"), prone.get("error"))
    said = [w for w in prone["warnings"] if "retained fluid below an air-fluid level" in w]
    assert len(said) == 1 and "on the anterior wall (a prone scan)" in said[0]
    a = supine["quality"]["markers"]["by_region"]["under_fluid"]
    b = prone["quality"]["markers"]["by_region"]["under_fluid"]
    assert a[1] == b[1] >= 2 and b[0] >= a[0] - 1 and b[0] >= b[1] - 1
    assert prone["quality"]["grade"] == "excellent"


def test_a_rolled_patients_water_is_found_under_its_tilted_level(tmp_path):
    """Tiny random stomach 2 (57 mL of water) as a patient rolled 10 degrees about the S axis, and 25 degrees the other
    way: the level tilts that much from LPS y = const; the water is found under it, said so, and the markers under it
    seen as unrolled (a level off LPS y had been missed without a word; at 25 degrees a plane fit started from the side
    alone settled on another flat part of the wall)."""
    from StomachUnfoldEval.bench import Case, run_case
    from StomachUnfoldEval.oblique import ROLLED_GROUP

    src = {"random": 2, "size": "tiny", "_cache": str(tmp_path)}
    flat = run_case(Case("stomach-2/isometric", src, {}, method="isometric", group="stomachs-held-out"))
    assert flat["ok"], flat.get("error")
    a = flat["quality"]["markers"]["by_region"]["under_fluid"]
    for degrees in (10.0, -25.0):
        roll = run_case(Case("stomach-2/isometric-rolled", {**src, "roll_deg": degrees}, {}, method="isometric",
                             group=ROLLED_GROUP))
        assert roll["ok"], roll.get("error")
        said = [w for w in roll["warnings"] if "retained fluid below an air-fluid level" in w]
        assert len(said) == 1 and f"tilted {abs(degrees):.0f} degrees" in said[0], said
        b = roll["quality"]["markers"]["by_region"]["under_fluid"]
        assert a[1] == b[1] >= 2 and b[0] >= a[0] - 1 and roll["quality"]["grade"] == "excellent", (degrees, b)


def test_rolled_turns_the_frame_about_s_and_every_lps_point_with_it():
    from StomachUnfoldEval.oblique import roll_of, rolled

    ct, _ = _ball_ct(np.eye(3))
    truth = {"cardia_lps": [10.0, 0.0, 3.0], "fluid_level_lps_y": 20.0,
             "markers": [{"id": "M01", "lps": [0.0, 10.0, 0.0]}]}
    vol, t = rolled(ct, truth, 90.0)
    assert vol.array is ct.array and np.allclose(t["cardia_lps"], [0.0, 10.0, 3.0])
    assert np.allclose(t["markers"][0]["lps"], [-10.0, 0.0, 0.0]) and t["fluid_level_lps_y"] is None
    ijk = np.array([[3.0, 7.0, 2.0]])
    p0, p1 = ct.index_to_lps(ijk)[0], vol.index_to_lps(ijk)[0]
    assert np.allclose(p1, [-p0[1], p0[0], p0[2]])
    r = [roll_of(s) for s in range(1000, 1030)]
    assert all(5.0 <= abs(x) <= 20.0 for x in r) and min(r) < 0 < max(r)


def test_the_contrast_part_draws_each_pool_at_its_contrast_hu_and_caches_it_apart(tmp_path):
    """Part ``contrast``: only held-out stomachs with a pool, each drawn again with its fluid at a HU within
    CONTRAST_HU (the same anatomy, level and markers), cached under its own name beside the water's draw."""
    from StomachUnfoldEval import bench
    from StomachUnfoldEval.bench import Case
    from StomachUnfoldEval.oblique import CONTRAST_GROUP, CONTRAST_HU, contrast_cases, contrast_hu_of
    from StomachUnfoldEval.random_stomach import draw_parameters

    seeds = list(range(1000, 1030))
    cases = contrast_cases(False, seeds, str(tmp_path), Case)
    wet = [s for s in seeds if draw_parameters(s, "small")["fluid"]]
    assert 0 < len(wet) < len(seeds) and len(cases) == 3 * len(wet)
    assert {c["source"]["random"] for c in cases} == set(wet) and all(c["group"] == CONTRAST_GROUP for c in cases)
    hus = [contrast_hu_of(s) for s in seeds]
    assert all(CONTRAST_HU[0] <= h <= CONTRAST_HU[1] for h in hus) and len(set(hus)) == len(hus)
    src = {"random": 2, "size": "tiny", "fluid_hu": 350.0}
    ct, truth = bench._cached(src, str(tmp_path))
    ct_w, truth_w = bench._cached({"random": 2, "size": "tiny"}, str(tmp_path))
    assert sorted(p.name for p in tmp_path.glob("*.nrrd")) == ["random-2-tiny-fluid350.nrrd", "random-2-tiny.nrrd"]
    assert truth["hu"]["fluid"] == 350.0 and truth_w["hu"]["fluid"] < 25.0
    assert truth["fluid_level_lps_y"] == truth_w["fluid_level_lps_y"] and truth["markers"] == truth_w["markers"]
    pool = ct.array > 250
    assert np.count_nonzero(pool & (ct_w.array < 100)) > 1000      # the pool: water in one draw, contrast in the other


def test_the_contents_part_draws_each_pool_like_the_wall_and_its_table_counts_what_is_said(tmp_path):
    """Part ``contents``: the held-out stomachs with a pool, each with its fluid at a HU within CONTENTS_HU (food, mucus,
    blood), apart from the contrast part's HU; the part's summary counts the runs whose warnings say such contents."""
    from StomachUnfoldEval.bench import Case
    from StomachUnfoldEval.oblique import (CONTENTS_GROUP, CONTENTS_HU, CONTENTS_SAID, contents_cases, contents_hu_of,
                                           contrast_cases, oblique_markdown, oblique_summary)

    seeds = list(range(1000, 1030))
    cases = contents_cases(False, seeds, str(tmp_path), Case)
    assert [c["source"]["random"] for c in cases] == [c["source"]["random"] for c in
                                                      contrast_cases(False, seeds, str(tmp_path), Case)]
    assert all(c["group"] == CONTENTS_GROUP and c["name"].endswith("-contents") for c in cases)
    hus = [c["source"]["fluid_hu"] for c in cases]
    assert all(CONTENTS_HU[0] <= h <= CONTENTS_HU[1] for h in hus) and len(set(hus)) == len(cases) // 3
    assert contents_hu_of(1000) != contents_hu_of(1001)

    def row(seed, said):
        q = {"visible_fraction": 0.99, "grade": "excellent", "markers": {"seen": 10, "total": 12}}
        return {"name": f"stomach-{seed}/isometric-contents", "method": "isometric", "group": CONTENTS_GROUP,
                "ok": True, "seconds": 3.0, "quality": q,
                "warnings": [f"a flat air-fluid level at ... {CONTENTS_SAID} 60 HU under it"] if said else []}
    rows = [row(1000, True), row(1002, True), row(1004, False)]
    summ = [x for x in oblique_summary(rows, "stomachs-held-out", CONTENTS_GROUP) if x["grid"] == "contents"]
    assert len(summ) == 1 and summ[0]["said"] == 2 and summ[0]["runs"] == 3
    assert any("isometric 2/3" in line for line in oblique_markdown(rows, "stomachs-held-out", CONTENTS_GROUP))


def test_the_deep_part_draws_each_stomach_with_a_deeper_pool_cached_apart_and_counts_what_is_said(tmp_path):
    """Part ``deep``: every held-out stomach drawn with a pool filling a fraction of its height within DEEP_FRACTION
    (above the family's 15-35 %), cached under its own name; the part's summary counts the runs that say a point was
    joined to its gas through the water."""
    from StomachUnfoldEval import bench
    from StomachUnfoldEval.bench import Case
    from StomachUnfoldEval.oblique import (DEEP_FRACTION, DEEP_GROUP, DEEP_SAID, deep_cases, deep_fraction_of,
                                           oblique_markdown, oblique_summary)

    seeds = list(range(1000, 1030))
    cases = deep_cases(False, seeds, str(tmp_path), Case)
    assert len(cases) == 3 * len(seeds) and all(c["group"] == DEEP_GROUP and c["name"].endswith("-deep") for c in cases)
    fr = [deep_fraction_of(s) for s in seeds]
    assert all(DEEP_FRACTION[0] <= f <= DEEP_FRACTION[1] for f in fr) and len(set(fr)) == len(fr)
    ct, truth = bench._cached({"random": 2, "size": "tiny", "fluid_depth": 0.5}, str(tmp_path))
    ct_w, truth_w = bench._cached({"random": 2, "size": "tiny"}, str(tmp_path))
    assert sorted(p.name for p in tmp_path.glob("*.nrrd")) == ["random-2-tiny-deep0.5.nrrd", "random-2-tiny.nrrd"]
    assert truth["fluid_level_lps_y"] < truth_w["fluid_level_lps_y"]        # a higher level (LPS y is posterior)
    assert np.count_nonzero(np.abs(ct.array.astype(int) - 10) < 30) > np.count_nonzero(np.abs(ct_w.array.astype(int)
                                                                                               - 10) < 30)

    def row(seed, said, ok=True):
        q = {"visible_fraction": 0.99, "grade": "excellent", "markers": {"seen": 10, "total": 12}}
        return {"name": f"stomach-{seed}/isometric-deep", "method": "isometric", "group": DEEP_GROUP, "ok": ok,
                "seconds": 3.0, "quality": q if ok else None, "error": None if ok else "AnatomyError: not connected",
                "warnings": [f"the cardia point {DEEP_SAID}, 22 mm from the gas"] if said else []}
    rows = [row(1000, True), row(1002, False), row(1004, False, ok=False)]
    summ = [x for x in oblique_summary(rows, "stomachs-held-out", DEEP_GROUP) if x["grid"] == "deep"]
    assert len(summ) == 1 and summ[0]["said"] == 1 and summ[0]["failed"] == 1
    md = "\n".join(oblique_markdown(rows, "stomachs-held-out", DEEP_GROUP))
    assert "## Deep pools" in md and "isometric 1/2" in md and "AnatomyError: not connected" in md
