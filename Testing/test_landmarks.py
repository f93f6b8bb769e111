"""Zero clicks (StomachUnfoldLib.landmarks): the cardia and pylorus found from TotalSegmentator-like labels (v2 and v1
numbering, Slicer segment names) and from the stomach gas, against the random phantoms' truth; the CLI's
--auto-points (report section, refusal when unsure); the shared real CTs with their labels."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from conftest import shared_file
from StomachUnfoldEval.auto_points import TOLERANCE_MM, point_errors, totalseg_labels
from StomachUnfoldEval.random_stomach import LABELS, random_stomach
from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.geometry import lps_to_ras
from StomachUnfoldLib.landmarks import (CLASS_MAPS, CONFIDENCE_THRESHOLD, find_points, labels_on_grid,
                                        points_from_labels, recognise_labels, stomach_label)

SEEDS = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def cases():
    """Tiny random stomachs with their truth and label arrays (drawn once)."""
    return {s: random_stomach(s, size="tiny", labels=True) for s in SEEDS}


@pytest.mark.parametrize("convention", ["total", "total_v1"])
def test_both_class_maps_are_recognised_by_number(cases, convention):
    vol, truth, lab = cases[0]
    seg = totalseg_labels(vol, lab, truth, convention)
    rec = recognise_labels(seg)
    cmap = CLASS_MAPS[convention]
    assert rec["convention"] == convention
    assert (rec["stomach"], rec["esophagus"], rec["duodenum"]) == (6, cmap["esophagus"], cmap["duodenum"])
    assert stomach_label(seg) == 6


def test_segment_names_and_terminology_codes_name_the_organs(cases):
    vol, truth, lab = cases[0]
    seg = totalseg_labels(vol, lab, truth, "total")
    names = {6: "Stomach", 15: "SCT^32849002^Esophagus", 19: "duodenum", 5: "liver"}
    rec = recognise_labels(seg, names=names)
    assert (rec["stomach"], rec["esophagus"], rec["duodenum"], rec["convention"]) == (6, 15, 19, "names")
    with pytest.raises(InputError, match="stomach"):
        recognise_labels(seg, names={5: "liver", 15: "esophagus"})


@pytest.mark.parametrize("convention", ["total", "total_v1"])
def test_points_from_labels_lie_near_the_true_ones(cases, convention):
    for seed in (0, 3):
        r = point_errors(seed, source=convention, case=cases[seed])
        assert r["within_tolerance"], r
        assert r["confident"]
        assert r["found"].labels["stomach"] == 6 and r["found"].source == "segmentation"


def test_points_from_the_gas_lie_near_the_true_ones_and_are_trusted(cases):
    rows = [point_errors(s, source="gas", case=cases[s]) for s in SEEDS]
    assert all(r["within_tolerance"] and r["confident"] for r in rows), [
        (r["cardia_error_mm"], r["pylorus_error_mm"], r["cardia_confidence"], r["pylorus_confidence"]) for r in rows]
    assert all(r["found"].source == "gas" and r["found"].evidence for r in rows)
    assert all(0.0 <= r["cardia_confidence"] <= 1.0 and 0.0 <= r["pylorus_confidence"] <= 1.0 for r in rows)
    # the found points are in the gas (snapped as the front end snaps them)
    vol = cases[0][0]
    f = rows[0]["found"]
    assert vol.sample(np.array([f.cardia_lps, f.pylorus_lps]), order=0).max() < -500


def test_the_pylorus_is_found_past_an_open_duodenum(cases):
    """Seed 0's duodenum is open (a thin gas tail beyond the pyloric canal): the pylorus is where the canal begins."""
    from StomachUnfoldEval.random_stomach import draw_parameters

    assert draw_parameters(0, "tiny")["duodenum_open_mm"] > 2.0
    vol, truth, lab = cases[0]
    tail = vol.voxel_lps(lab == LABELS["tube_lumen"])
    far = tail[np.argmax(np.linalg.norm(tail - np.asarray(truth["pylorus_lps"]), axis=1))]
    assert np.linalg.norm(far - truth["pylorus_lps"]) > 15.0          # the gas goes on well past the pylorus
    found = find_points(vol)
    assert np.linalg.norm(found.pylorus_lps - np.asarray(truth["pylorus_lps"])) <= 5.0
    assert any("duodenal gas tail" in e for e in found.evidence), found.evidence


def test_point_benchmark_writes_its_table(tmp_path, cases):
    """The autopoints bench part (quick: three tuning and three held-out volumes, here the drawn fixtures)."""
    from StomachUnfoldEval.auto_points import point_benchmark

    summary = point_benchmark(str(tmp_path), quick=True, draw=lambda seed: cases[seed % len(SEEDS)])
    assert set(summary) == {f"{g}/{s}" for g in ("tune", "held-out") for s in ("gas", "total", "total_v1")}
    v = summary["tune/gas"]
    assert v["volumes"] == 3 and v["failed"] == 0 and v["refused_but_within"] <= v["refused"]
    md = open(tmp_path / "autopoints.md").read()
    assert "| tune/gas | " in md and "refused but within" in md and "fresh" not in md.split("|---")[1]
    rows = json.load(open(tmp_path / "autopoints.json"))["rows"]
    assert len(rows) == 18 and all(r["ok"] for r in rows)


def _little_gas(vol, truth, lab):
    """The CT with most of the stomach gas turned to water (a pocket under the dome left): not distended."""
    arr = np.array(vol.array)
    gas = lab == LABELS["lumen_air"]
    P = vol.voxel_lps(gas)
    far = np.linalg.norm(P - np.asarray(truth["dome_top_lps"]), axis=1) > 30.0
    flat = arr.reshape(-1)
    flat[np.nonzero(gas.reshape(-1))[0][far]] = 10
    return vol.with_array(arr)


def test_little_gas_gives_low_confidence_and_best_guesses(cases):
    found = find_points(_little_gas(*cases[0]))
    assert found.confidence < CONFIDENCE_THRESHOLD and not found.confident
    assert "--cardia" in found.guesses_ras_text()


def test_a_missing_tube_label_falls_back_to_the_shape_with_low_confidence(cases):
    vol, truth, lab = cases[0]
    seg = totalseg_labels(vol, lab, truth, "total")
    seg[seg == CLASS_MAPS["total"]["duodenum"]] = 0
    found = points_from_labels(vol, seg)
    assert found.cardia_confidence >= CONFIDENCE_THRESHOLD > found.pylorus_confidence
    assert "duodenum" not in found.labels
    assert np.linalg.norm(found.pylorus_lps - np.asarray(truth["pylorus_lps"])) < 25.0


def _run_cli(args, capsys):
    from StomachUnfoldLib.cli import main

    code = main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_auto_points_grades_as_the_true_points(tmp_path, capsys):
    """An unfold from the found points grades the same as one from the true points (tiny random stomach 0)."""
    from StomachUnfoldEval.random_stomach import write_random_stomach
    from StomachUnfoldLib.io import read_volume
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

    path, json_path = write_random_stomach(str(tmp_path / "r0.nrrd"), 0, size="tiny")
    code, out, err = _run_cli(["unfold", path, "--auto-points", "-o", str(tmp_path / "out"), "--quiet"], capsys)
    assert code == 0, err
    rep = json.load(open(tmp_path / "out" / "report.json"))
    auto = rep["auto_points"]
    assert auto["source"] == "gas" and min(auto["cardia_confidence"], auto["pylorus_confidence"]) >= 0.5
    assert np.allclose(rep["points"]["cardia_lps"], auto["cardia_lps"])
    truth = json.load(open(json_path))
    assert np.linalg.norm(np.array(auto["cardia_lps"]) - truth["cardia_lps"]) <= TOLERANCE_MM
    ref = unfold(read_volume(path), truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters())
    assert rep["quality"]["grade"] == ref.report.quality["grade"]
    assert abs(rep["quality"]["visible_fraction"] - ref.report.quality["visible_fraction"]) < 0.02


def test_cli_refuses_unsure_points_with_the_guesses_in_ras(tmp_path, capsys, cases):
    from StomachUnfoldLib.io import write_volume

    path = str(tmp_path / "littlegas.nrrd")
    write_volume(_little_gas(*cases[0]), path)
    out_dir = tmp_path / "out"
    code, out, err = _run_cli(["unfold", path, "--auto-points", "-o", str(out_dir), "--quiet"], capsys)
    assert code == 2 and not out_dir.exists()
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: ") and len(err.strip().splitlines()) == 1
    assert "--cardia" in line and "--points" in line and "RAS" in line and "unsure" in line


def test_cli_auto_points_with_a_totalsegmentator_mask_uses_its_stomach_label(tmp_path, capsys, cases):
    from StomachUnfoldLib.io import write_volume

    vol, truth, lab = cases[3]
    seg = totalseg_labels(vol, lab, truth, "total_v1")
    seg_path = str(tmp_path / "seg.nii.gz")
    write_volume(vol.with_array(seg), seg_path)
    back = labels_on_grid(__import__("StomachUnfoldLib.io", fromlist=["read_volume"]).read_volume(seg_path), vol)
    assert np.array_equal(back, seg)
    found = find_points(vol, back)
    assert found.convention == "total_v1" and found.labels == {"stomach": 6, "esophagus": 42, "duodenum": 56}
    # --auto-points with explicit points is a contradiction: one-line error, nothing written
    code, out, err = _run_cli(["unfold", seg_path, "--auto-points", "--cardia=1,2,3", "-o", str(tmp_path / "o")],
                              capsys)
    assert code == 2 and "--auto-points" in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("ct_name, seg_name", [
    ("data/01_totalseg_example_ct_abdpelvis_3mm.nii.gz",
     "data/01_totalseg_example_ct_abdpelvis_3mm_seg117_top30slices_DERIVED.nii.gz"),
    ("data/02_totalseg_example_ct_dicom_slab_2mm.nii.gz", "data/02_totalseg_example_ct_dicom_slab_seg117_stomach6.nii.gz")])
def test_shared_real_cts_with_their_labels_run(ct_name, seg_name):
    from StomachUnfoldLib.io import read_volume

    ct_path, seg_path = shared_file(ct_name), shared_file(seg_name)
    ct = read_volume(ct_path)
    labels = labels_on_grid(read_volume(seg_path), ct)
    found = find_points(ct, labels)
    assert found.convention == "total" and found.labels["stomach"] == 6
    stomach = labels == 6
    for p in (found.cardia_lps, found.pylorus_lps):
        ijk = np.rint(ct.lps_to_index(p[None])[0]).astype(int)
        assert stomach[ijk[2], ijk[1], ijk[0]]
    assert 0.0 <= found.confidence <= 1.0 and found.evidence
    d = found.to_dict()
    assert np.allclose(d["cardia_ras"], lps_to_ras(found.cardia_lps))
    # without the labels: no distended stomach in these CTs, so the gas path is unsure (or finds no gas at all)
    from StomachUnfoldLib.errors import AnatomyError

    try:
        gas = find_points(ct)
    except AnatomyError as e:  # no candidate gas region at all
        assert "no stomach gas" in str(e)
    else:
        assert not gas.confident, gas.evidence
