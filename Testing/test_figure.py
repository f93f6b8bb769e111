"""The labelled view (figure.py), the reproducible report and the command line's messages (issue 16).

The scale bar is measured on the written PNG against a known length: two beads a known distance apart on a
flat synthetic mucosa. The orientation labels are checked on the tiny J phantom against its markers' known
side (anterior or posterior), and the report is re-run from its recorded command line.
"""
import hashlib
import json
import os

import numpy as np
import pytest
import SimpleITK as sitk

from StomachUnfoldEval.phantom import write_phantom
from StomachUnfoldLib import figure
from StomachUnfoldLib import io as suio
from StomachUnfoldLib.cli import main
from StomachUnfoldLib.dicom_export import write_ct_series
from StomachUnfoldLib.distortion import DistortionMap
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.plausibility import failure_regions, plausibility_warnings
from StomachUnfoldLib.view import shade_first_hit

AIR, WALL, BEAD = -1000, 40, 400
STUDY = {"0010|0010": "PHANTOM^J", "0010|0020": "PH0042", "0020|000d": "1.2.826.0.1.3680043.2.1125.42"}


def flat_wall(spacing=(1.2, 0.8, 1.0), size_mm=(150.0, 90.0), beads_mm=((30.0, 45.0), (100.0, 45.0), (30.0, 75.0))):
    """Unfolded Volume (k, j, i) of a flat mucosa 6 mm up with 2 mm beads at (x, y) mm on it."""
    si, sj, sk = spacing
    ni, nj, nk = int(size_mm[0] / si), int(size_mm[1] / sj), 14
    k, j, i = np.meshgrid(np.arange(nk) * sk, np.arange(nj) * sj, np.arange(ni) * si, indexing="ij")
    a = np.where(k < 6.0, WALL, AIR)
    for x, y in beads_mm:
        a[(i - x) ** 2 + (j - y) ** 2 + (k - 6.0) ** 2 <= 2.0 ** 2] = BEAD
    return Volume(a.astype(np.int16), np.array(spacing, float), np.zeros(3), np.eye(3))


def read_png(path):
    """RGB uint8 (rows top to bottom) of a PNG."""
    return sitk.GetArrayFromImage(sitk.ReadImage(str(path)))


def blobs(mask):
    """Centroids (x, y) of the connected regions of a mask, largest first."""
    from scipy import ndimage

    lab, n = ndimage.label(mask)
    sizes = ndimage.sum(mask, lab, range(1, n + 1))
    order = np.argsort(sizes)[::-1]
    return [np.array(ndimage.center_of_mass(mask, lab, o + 1))[::-1] for o in order]


def test_scale_bar_matches_a_known_length_on_the_png(tmp_path):
    vol = flat_wall()
    png = tmp_path / "view.png"
    lay = figure.write_view(vol, str(png), shade_first_hit(vol), view_size=600)
    img = read_png(png).astype(int)
    panel = lay["panels"][0]
    (x0, y0), (w, h) = panel["view_origin_px"], panel["view_size_px"]
    nj, ni = vol.array.shape[1:]
    assert w == 600 and abs(h - 600 * (nj * 0.8) / (ni * 1.2)) <= 1  # square pixels: the voxels are 1.2 x 0.8 mm
    bar = panel["scale_bar"]
    assert bar["on_view"] and bar["mm"] == 20.0 and bar["text"] == "20 mm"
    # the bar measured on the image: the run of pure white pixels on its row
    row = img[bar["y"] + 1, :x0 + w]
    white = np.flatnonzero(np.all(row == 255, axis=1))
    bar_px = white.max() - white.min() + 1
    mm_per_px = bar["mm"] / bar_px
    # the beads measured on the image with that bar: 70 mm apart along i, 30 mm along j
    view = img[y0:y0 + h, x0:x0 + w]
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    beads = blobs((r > 120) & (g > 0.85 * r) & (b < 0.65 * r))[:3]
    beads.sort(key=lambda p: (p[1], p[0]))  # top (y = 75 mm) first
    assert len(beads) == 3
    top, left_b, right_b = beads[0], *sorted(beads[1:], key=lambda p: p[0])
    assert abs(np.linalg.norm(right_b - left_b) * mm_per_px - 70.0) < 1.0
    assert abs(np.linalg.norm(top - left_b) * mm_per_px - 30.0) < 1.0


def test_scale_bar_sits_where_lengths_hold(tmp_path):
    vol = flat_wall(spacing=(1.0, 1.0, 1.0), beads_mm=())
    nj, ni = vol.array.shape[1:]
    length = np.full((nj, ni), 1.5)
    length[:, ni // 2:] = 1.0  # lengths hold on the right half only
    dmap = DistortionMap(np.ones((nj, ni)), length, np.ones((nj, ni), bool))
    lay = figure.write_view(vol, str(tmp_path / "v.png"), shade_first_hit(vol), dmap, view_size=300)
    p = lay["panels"][0]
    bar = p["scale_bar"]
    assert bar["on_view"] and bar["x0"] >= p["view_origin_px"][0] + p["view_size_px"][0] / 2
    dmap_bad = DistortionMap(np.ones((nj, ni)), np.full((nj, ni), 2.0), np.ones((nj, ni), bool))
    lay = figure.write_view(vol, str(tmp_path / "v2.png"), shade_first_hit(vol), dmap_bad, view_size=300)
    bar = lay["panels"][0]["scale_bar"]
    p = lay["panels"][0]
    assert not bar["on_view"] and bar["y"] > p["view_origin_px"][1] + p["view_size_px"][1]  # in the margin


@pytest.fixture(scope="module")
def phantom_run(tmp_path_factory):
    """One CLI run of the tiny J phantom with its markers as landmarks: (tmp, truth, report, argv)."""
    tmp = tmp_path_factory.mktemp("fig")
    path, json_path = write_phantom(str(tmp / "ph.nrrd"), shape="j", size="tiny")
    truth = json.load(open(json_path))
    lm = tmp / "markers.mrk.json"
    suio.write_markups_fiducials(str(lm), {str(m["id"]): np.array(m["lps"]) for m in truth["markers"]}, "m")
    # the phantom as a DICOM series of a known patient and study, the input of a run with --dicom
    write_ct_series(suio.read_volume(path), str(tmp / "dicom_in"), STUDY, "phantom")
    argv = ["unfold", str(tmp / "dicom_in"), "--points", json_path, "-o", str(tmp / "out"), "--landmarks", str(lm),
            "--view-size", "400", "--dicom", "--quiet"]
    assert main(argv) == 0
    return tmp, truth, json.load(open(tmp / "out" / "report.json")), argv


def test_view_labels_match_the_anatomy(phantom_run):
    tmp, truth, rep, _ = phantom_run
    v = rep["view"]
    assert v["orientation"] == {"left": "cardia", "right": "pylorus", "edges": "greater", "middle": "lesser",
                                "upper_half": "posterior", "lower_half": "anterior"}
    for panel in v["panels"]:
        labels = {k: d["text"] for k, d in panel["labels"].items()}
        assert labels["left_end"] == "cardia" and labels["right_end"] == "pylorus"
        assert labels["top_edge"] == labels["bottom_edge"] == "greater curvature (cut)"
        assert labels["upper_half"] == "posterior" and labels["lower_half"] == "anterior"
        assert panel["scale_bar"]["on_view"] and panel["view_size_px"][0] == 400
    # the markers' known side: angle from the greater curvature 0-180 deg is anterior (-y LPS) on this phantom
    p = v["panels"][0]
    mid = p["view_origin_px"][1] + p["view_size_px"][1] / 2
    sides = {str(m["id"]): m["angle_from_greater_curvature_deg"] for m in truth["markers"]}
    marks = p["landmarks_px"]
    assert len(marks) == len(sides)
    for mid_id, (x, y) in marks.items():
        a = sides[mid_id] % 360
        if 20 < a < 160:
            assert y > mid, mid_id  # anterior: lower half
        elif 200 < a < 340:
            assert y < mid, mid_id
    assert read_png(tmp / "out" / "view.png").shape[1] == v["image_size_px"][0]


def test_report_records_and_reproduces_the_run(phantom_run, capsys):
    tmp, truth, rep, argv = phantom_run
    keys = list(rep)
    assert keys[:2] == ["summary", "quality"] and keys[-1] == "method"
    assert rep["summary"]["grade"] == rep["quality"]["grade"] and rep["summary"]["markers_seen"].endswith("/12")
    run = rep["run"]
    assert set(run["versions"]) == {"StomachUnfoldLib", "numpy", "scipy", "SimpleITK", "vtk", "python"}
    assert run["method"] == "isometric" and run["grid_size_voxels"] >= 1 and len(run["cell_mm"]) == 3
    assert run["files"]["input"]["path"] == os.path.abspath(argv[1]) and len(run["files"]["input"]["sha256"]) == 64
    digest = hashlib.sha256(open(argv[3], "rb").read()).hexdigest()
    assert run["files"]["points"] == {"path": os.path.abspath(argv[3]), "sha256": digest}
    assert rep["markers"]["seen"] >= 11 and rep["markers"]["pairwise_distance_distortion"] < 0.3
    # rerun from the recorded command line (another output folder) gives the same unfolded volume
    again = list(run["argv"][1:])
    again[again.index("-o") + 1] = str(tmp / "again")
    again.remove("--quiet")
    capsys.readouterr()
    assert main(again) == 0
    # progress in a log (stderr is not a terminal here): one line per stage with its seconds, reading the CT first
    lines = capsys.readouterr().err.splitlines()
    stages = [ln.rsplit(":", 1)[0] for ln in lines if ln.endswith(" s")]
    assert stages[0] == "reading the CT" and stages[-2:] == ["writing", "total"] and "flat map" in stages
    assert "%" not in "".join(lines)
    sha = [hashlib.sha256(open(tmp / d / "unfolded.nrrd", "rb").read()).hexdigest() for d in ("out", "again")]
    assert sha[0] == sha[1]
    again_rep = json.load(open(tmp / "again" / "report.json"))
    assert again_rep["parameters"] == rep["parameters"] and again_rep["run"]["files"] == run["files"]


def test_dicom_export_joins_the_source_study(phantom_run):
    tmp, truth, rep, _ = phantom_run
    vol = suio.read_volume(str(tmp / "out" / "unfolded.nrrd"))
    back = suio.read_volume(str(tmp / "out" / "dicom" / "unfolded"))
    assert np.array_equal(np.asarray(back.array), np.asarray(vol.array))
    assert np.allclose(back.spacing, vol.spacing) and np.allclose(back.origin, vol.origin, atol=1e-3)
    assert np.allclose(back.direction, vol.direction, atol=1e-5)
    sc = sitk.ReadImage(str(tmp / "out" / "dicom" / "view.dcm"))
    assert sitk.GetArrayFromImage(sc).reshape(-1, 3).shape[0] == np.prod(read_png(tmp / "out" / "view.png").shape[:2])
    first = sorted(os.listdir(tmp / "out" / "dicom" / "unfolded"))[0]
    ct = sitk.ReadImage(str(tmp / "out" / "dicom" / "unfolded" / first))
    for img in (sc, ct):
        for tag, value in STUDY.items():
            assert img.GetMetaData(tag).strip() == value
    assert ct.GetMetaData("0020|000e") != sc.GetMetaData("0020|000e")  # two new series
    assert rep["dicom"]["study_from_source"] and rep["dicom"]["patient_id"] == "PH0042"


def test_point_messages(tmp_path, capsys):
    path, json_path = write_phantom(str(tmp_path / "ph.nrrd"), shape="j", size="tiny")
    truth = json.load(open(json_path))
    c = ",".join(f"{v:.2f}" for v in truth["cardia_ras"])
    p = ",".join(f"{v:.2f}" for v in truth["pylorus_ras"])
    assert main(["unfold", path, "--cardia", "-54.9", "27.7", "64", "--pylorus", p, "-o", str(tmp_path / "o")]) == 2
    assert "use R,A,S with commas" in capsys.readouterr().err
    # LPS values typed as RAS: outside the volume, and the sign-flipped point is inside
    lo, hi = suio.read_volume(path).bounds_lps()
    assert lo[0] + 5 < 0 < hi[0] - 5 and abs(lo[0] + hi[0]) > 6  # (asymmetric in x)
    x = lo[0] + 3 if -(lo[0] + 3) > hi[0] else hi[0] - 3  # inside as LPS, outside as RAS
    for point, hint in ((f"{x:.1f},0,0", True), ("9999,0,0", False)):
        assert main(["unfold", path, "--cardia", point, "--pylorus", p, "-o", str(tmp_path / "o"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "outside the volume (RAS bounds: R " in err and ("sign-flipped" in err) == hint
    assert c and not (tmp_path / "o").exists()


def test_help_lists_units_choices_flags_and_examples(capsys):
    with pytest.raises(SystemExit):
        main(["unfold", "--help"])
    out = capsys.readouterr().out
    assert "--quality, --no-quality" in out and "--swap-check, --no-swap-check" in out
    assert "one of newmark, explicit" in out and "--view-size PIXELS" in out
    assert out.rstrip().splitlines()[-4].lstrip().startswith("stomach-unfold unfold")
    assert out.count("stomach-unfold unfold ") >= 2


def test_plausibility_warnings():
    ct = Volume(np.zeros((20, 30, 30), np.int16), np.ones(3), np.zeros(3), np.eye(3))
    w = plausibility_warnings(ct, [10.0, 10.0, 0.0], [12.0, 12.0, 10.0], 30.0, {"grade": "excellent"})
    assert len(w) == 2 and "30 mL" in w[0] and "--mask" in w[0] and "cardia point lies on the first slice" in w[1]
    w = plausibility_warnings(ct, [10.0, 10.0, 5.0], [12.0, 12.0, 10.0], 600.0,
                              {"grade": "fair", "visible_fraction": 0.6, "failure_parts": 2, "bent_area_fraction": 0.1})
    assert len(w) == 1 and w[0].startswith("grade fair: 40 % of the mucosa hidden, 2 failure parts") and "bent" in w[0]
    # a 10 x 10 mm hole in the view near its right end, lower half: named with the view's labels
    vol = flat_wall(spacing=(1.0, 1.0, 1.0), beads_mm=())
    a = np.asarray(vol.array).copy()
    a[:, 10:20, 125:135] = AIR
    vol = vol.with_array(a)
    orient = {"left": "cardia", "right": "pylorus", "upper_half": "posterior", "lower_half": "anterior"}
    parts = failure_regions(vol, orient)
    assert len(parts) == 1 and parts[0]["kind"] == "hole" and parts[0]["area_mm2"] == pytest.approx(100.0)
    assert parts[0]["where"] == "near the pylorus, anterior half"
    w = plausibility_warnings(ct, [10.0, 10.0, 5.0], [12.0, 12.0, 10.0], 600.0, {"grade": "bad", "visible_fraction": 0.4,
                              "failure_parts": 1}, vol, orient)
    assert "hole of 100 mm^2 near the pylorus, anterior half" in w[0]
    # a good view with that hole, where the stomach touches gas outside it: the hole is named with its cause
    good = {"grade": "good", "failure_parts": 1}
    w = plausibility_warnings(ct, [10.0, 10.0, 5.0], [12.0, 12.0, 10.0], 600.0, good, vol, orient, 0.03)
    assert len(w) == 1 and w[0].startswith("the view has holes (100 mm^2 near the pylorus, anterior half): 3.0 %")
    assert plausibility_warnings(ct, [10.0, 10.0, 5.0], [12.0, 12.0, 10.0], 600.0, good, vol, orient, 0.001) == []
    # a stomach the scan range cuts off (a label reaching the last slice; both ends of a slab): said once per side,
    # not again where a point on that slice has said it
    w = plausibility_warnings(ct, [10.0, 10.0, 5.0], [12.0, 12.0, 10.0], 600.0, {"grade": "excellent"},
                              cut_by_scan=("last",))
    assert len(w) == 1 and w[0].startswith("the stomach reaches the last slice of the scan: it is cut off")
    w = plausibility_warnings(ct, [10.0, 10.0, 0.0], [12.0, 12.0, 10.0], 600.0, {"grade": "excellent"},
                              cut_by_scan=("first", "last"))
    assert len(w) == 2 and "cardia point lies on the first slice" in w[0] and "reaches the last slice" in w[1]


def test_gas_contact_fraction_finds_gas_against_the_lumen():
    from StomachUnfoldLib.plausibility import gas_contact_fraction

    g = np.arange(40) - 20.0
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    lumen = x ** 2 + y ** 2 + z ** 2 <= 12.0 ** 2
    ct = np.where(lumen, -1000, 40).astype(np.int16)       # a wall all round: no contact
    crop = Volume(ct, np.ones(3), np.zeros(3), np.eye(3))
    assert gas_contact_fraction(crop, lumen, -500.0) == 0.0
    ct[:, :, 32:] = -1000                                   # colon gas against the +x side, no wall between
    frac = gas_contact_fraction(crop.with_array(ct), lumen, -500.0)
    assert 0.0 < frac < 0.05


def test_names_of_nearby_rings_do_not_stack():
    from StomachUnfoldLib.figure import annotate_panel

    rgb = np.full((60, 80, 3), 0.5)
    orient = {"left": "cardia", "right": "pylorus", "edges": None, "middle": None}
    _, layout = annotate_panel(rgb, (1.0, 1.0), np.ones((60, 80), bool), orient, 400,
                               landmarks_ij={"12": (40.0, 30.0)},
                               folds_ij={"F1": (40.5, 30.5, 6.0), "F2": (41.0, 29.5, 5.5)})
    boxes = layout["ring_name_boxes_px"]
    assert len(boxes) == 3
    for a in range(3):
        for b in range(a + 1, 3):
            A, B = boxes[a], boxes[b]
            assert not (A[0] < B[2] and B[0] < A[2] and A[1] < B[3] and B[1] < A[3]), (A, B)
