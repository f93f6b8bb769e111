"""End to end: phantom CT -> unfold -> files; judged from unfolded.nrrd alone by rays down -k."""
import json
import os

import numpy as np
import pytest

from StomachUnfoldLib import io as suio
from StomachUnfoldLib.cli import main
from StomachUnfoldLib.errors import Cancelled, PointError
from StomachUnfoldLib.geometry import lps_to_ras
from StomachUnfoldEval.phantom import make_phantom, write_phantom
from StomachUnfoldLib.params import AUTO_PIXEL_MAX_MM
from StomachUnfoldLib.pipeline import UnfoldParameters, unfold
from StomachUnfoldEval.markers import marker_report, visible_markers
from StomachUnfoldLib.quality import layer_runs, overlap_fraction

# grid of 3 voxels on the tiny (about 1.8 mm) phantoms: cells of about 5.4 mm, like the paper's d = 8 at 0.7 mm
TINY = UnfoldParameters(method="massspring", grid_size=3, wall_thickness_mm=4.0)


@pytest.fixture(scope="module")
def j_run():
    ct, truth = make_phantom("j", "tiny")
    before = ct.array.copy()
    res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], TINY)
    assert np.array_equal(ct.array, before)  # the input is never modified
    return ct, truth, res


def test_j_phantom_every_marker_seen_and_no_layer_over_another(j_run):
    ct, truth, res = j_run
    vol = res.unfolded
    # judged from the unfolded volume alone: one dense region per marker, one wall layer per ray
    seen = visible_markers(vol)
    assert len(seen) == len(truth["markers"])
    assert overlap_fraction(vol) < 0.01
    # and each region is where its marker went (the correspondence agrees with the picture)
    mapped = res.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]})
    rep = marker_report(vol, mapped)
    assert rep["n_seen"] == rep["n_total"]


def test_output_axes_and_orientation(j_run):
    ct, truth, res = j_run
    vol = res.unfolded
    D = vol.direction
    assert np.allclose(D.T @ D, np.eye(3), atol=1e-9) and np.linalg.det(D) > 0
    # i runs from the cardia end to the pylorus end
    c = vol.lps_to_index(res.map_landmarks({"c": res.centerline_lps[1]})["c"][None])[0]
    p = vol.lps_to_index(res.map_landmarks({"p": res.centerline_lps[-2]})["p"][None])[0]
    assert np.all(np.isfinite(c)) or True  # centreline points are in the lumen, maybe outside the wall cells
    u0, u1 = res.map_landmarks({"a": res.incision_lps[2], "b": res.incision_lps[-3]}).values()
    if np.all(np.isfinite(u0)) and np.all(np.isfinite(u1)):
        assert vol.lps_to_index(u1[None])[0][0] > vol.lps_to_index(u0[None])[0][0]
    # the mucosa faces +k: markers (on the mucosa) map above the median wall depth
    mk = np.array([v for v in res.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]}).values()])
    kk = vol.lps_to_index(mk)[:, 2]
    wall_k = np.nonzero((vol.array > -400).any(axis=(1, 2)))[0]
    assert np.median(kk) > np.median(wall_k)
    assert np.allclose(vol.spacing, min(ct.spacing[0], AUTO_PIXEL_MAX_MM))   # the CT's in-plane voxel, at most the cap


def test_report_contents(j_run):
    ct, truth, res = j_run
    r = res.report
    for key in ("parameters", "seconds", "method", "peak_memory_mb", "warnings", "quality"):
        assert key in r
    m = r["method"]
    assert m["name"] == "massspring"
    sim = m["simulation"]
    assert sim["iterations"] == len(sim["D_trace"]) - 1
    assert m["model"]["hexahedra"] > 100 and m["model"]["springs"] > m["model"]["vertices"]
    assert sim["D_trace"][-1] < sim["D_trace"][0]
    assert json.loads(r.to_json())["method"]["simulation"]["iterations"] == sim["iterations"]


def test_correspondence_round_trip_on_markers(j_run):
    ct, truth, res = j_run
    pts = np.array([m["lps"] for m in truth["markers"]])
    there = res.correspondence.to_unfolded(pts)
    back = res.correspondence.to_original(there)
    ok = np.all(np.isfinite(back), axis=1)
    assert ok.all()
    assert np.allclose(back[ok], pts[ok], atol=1e-3)


@pytest.mark.parametrize("kind", [dict(shape="bent"), dict(shape="straight"), dict(shape="twisted"), dict(shape="thin_wall"), dict(shape="hook"),
                                  dict(shape="j", spacing=(1.8, 1.8, 3.0)), dict(shape="j", flip_direction=True)])
def test_shapes_unfold_with_every_marker_seen(kind):
    ct, truth = make_phantom(size="tiny", **kind)
    params = TINY if kind.get("shape") != "thin_wall" else UnfoldParameters(grid_size=3, wall_thickness_mm=3.0)
    res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], params)
    assert len(visible_markers(res.unfolded)) == len(truth["markers"])
    assert overlap_fraction(res.unfolded) < 0.005


@pytest.mark.parametrize("method", ["isometric", "lscm", "cylindrical", "massspring"])
def test_the_output_spacing_is_the_view_voxel_of_every_method(method):
    """--output-spacing-mm sets the unfolded volume's voxel (mm) whatever the method; the view still shows every
    marker at the finer pixel (the tiny J's CT voxels are about 1.8 mm)."""
    ct, truth = make_phantom("j", "tiny")
    params = UnfoldParameters(method=method, output_spacing_mm=1.0, **(
        dict(grid_size=3, wall_thickness_mm=4.0) if method == "massspring" else {}))
    res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], params)
    assert np.allclose(res.unfolded.spacing, 1.0) and ct.spacing[0] > 1.5
    mapped = res.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]})
    assert marker_report(res.unfolded, mapped)["n_seen"] == len(truth["markers"])


def test_the_view_voxel_is_the_ct_in_plane_voxel_at_most_the_cap():
    """Without --output-spacing-mm the view's voxel is the CT's in-plane voxel, but at most AUTO_PIXEL_MAX_MM (1.5 mm):
    on the tiny J (about 1.8 mm) 1.5 mm, with every marker seen; on a 1.2 mm CT its own 1.2 mm."""
    ct, truth = make_phantom("j", "tiny")
    assert ct.spacing[0] > AUTO_PIXEL_MAX_MM == 1.5
    res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters(method="isometric"))
    assert np.allclose(res.unfolded.spacing, AUTO_PIXEL_MAX_MM)
    assert res.report["run"]["view_pixel_mm"] == pytest.approx([AUTO_PIXEL_MAX_MM] * 2)
    mapped = res.map_landmarks({m["id"]: m["lps"] for m in truth["markers"]})
    assert marker_report(res.unfolded, mapped)["n_seen"] == len(truth["markers"])
    ct, truth = make_phantom("j", "small")
    assert np.allclose(ct.spacing[:2], 1.2)
    res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters(method="cylindrical"))
    assert np.allclose(res.unfolded.spacing, 1.2)


def test_cli_writes_the_output_contract(tmp_path):
    vol_path = tmp_path / "ph.nrrd"
    path, json_path = write_phantom(str(vol_path), shape="j", size="tiny")
    truth = json.load(open(json_path))
    c = ",".join(f"{v:.3f}" for v in truth["cardia_ras"])
    p = ",".join(f"{v:.3f}" for v in truth["pylorus_ras"])
    out = tmp_path / "out"
    lm = tmp_path / "lm.mrk.json"
    suio.write_markups_fiducials(str(lm), {f"m{m['id']}": np.array(m["lps"]) for m in truth["markers"][:3]}, "lm")
    rc = main(["unfold", str(vol_path), "--cardia", c, "--pylorus", p, "-o", str(out), "--grid-size", "3",
               "--wall-thickness-mm", "4", "--quiet", "--landmarks", str(lm)])
    assert rc == 0
    for name in ("unfolded.nrrd", "report.json", "view.png", "model_rest.vtu", "model_unfolded.vtu",
                 "incision.mrk.json", "centerline.mrk.json", "landmarks_unfolded.mrk.json", "distortion.nrrd",
                 "distortion.png"):
        assert (out / name).stat().st_size > 100, name
    assert not [n for n in os.listdir(out) if n.startswith(".unfold-")]
    vol = suio.read_volume(str(out / "unfolded.nrrd"))
    assert len(visible_markers(vol)) == len(truth["markers"])
    rep = json.load(open(out / "report.json"))
    assert set(rep["landmarks"]) == {"m1", "m2", "m3"}
    # --points with the Slicer markups file written beside the phantom gives the same run
    rc = main(["unfold", str(vol_path), "--points", str(vol_path).replace(".nrrd", ".mrk.json"), "-o",
               str(tmp_path / "out2"), "--grid-size", "3", "--wall-thickness-mm", "4", "--quiet"])
    assert rc == 0


def test_cli_bad_input_one_line_error(tmp_path, capsys):
    path, json_path = write_phantom(str(tmp_path / "ph.nrrd"), shape="j", size="tiny")
    rc = main(["unfold", path, "--cardia", "1,2", "--pylorus", "0,0,0", "-o", str(tmp_path / "o"), "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:")
    rc = main(["unfold", path, "--cardia", "9999,0,0", "--pylorus", "0,0,0", "-o", str(tmp_path / "o"), "--quiet"])
    assert rc == 2 and "outside the volume" in capsys.readouterr().err
    assert not (tmp_path / "o" / "unfolded.nrrd").exists()


def test_cancel_from_progress_leaves_nothing(tmp_path):
    ct, truth = make_phantom("j", "tiny")
    stages = []

    def cb(stage, fraction):
        stages.append(stage)
        return stage != "simulation"

    with pytest.raises(Cancelled):
        unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], TINY, progress=cb)
    assert "air region" in stages and stages[-1] == "simulation"


def test_mask_replaces_air_for_a_fluid_filled_stomach(tmp_path):
    """A stomach full of fluid (no gas): the label gives the lumen, the fluid is cleared, markers show."""
    from StomachUnfoldLib.errors import AnatomyError

    ct, truth = make_phantom("j", "tiny", noise_hu=0.0)
    lumen = ct.array < -500
    lumen &= ~((ct.array < -500) & (np.indices(ct.array.shape)[0] > ct.array.shape[0] - 20))  # no lung
    from scipy import ndimage
    lab, _ = ndimage.label(ct.array < -500)
    c_ijk = np.rint(ct.lps_to_index(np.array([truth["cardia_lps"]]))[0]).astype(int)
    lumen = lab == lab[c_ijk[2], c_ijk[1], c_ijk[0]]
    fluid = ct.with_array(np.where(lumen, 15, ct.array).astype(np.int16))
    with pytest.raises(AnatomyError, match="--mask"):
        unfold(fluid, truth["cardia_lps"], truth["pylorus_lps"], TINY)
    res = unfold(fluid, truth["cardia_lps"], truth["pylorus_lps"], TINY, mask=lumen)
    assert len(visible_markers(res.unfolded)) == len(truth["markers"])
    assert overlap_fraction(res.unfolded) < 0.005


def test_phantom_command(tmp_path):
    assert main(["phantom", str(tmp_path / "p.nii.gz"), "--shape", "bent", "--size", "tiny", "--flip"]) == 0
    v = suio.read_volume(str(tmp_path / "p.nii.gz"))
    assert np.linalg.det(v.direction) < 0
    truth = json.load(open(tmp_path / "p.json"))
    assert len(truth["markers"]) == 12 and (tmp_path / "p.mrk.json").exists()


def test_a_stomach_cut_off_by_the_scan_range_is_said_in_the_warnings():
    # the J phantom's top slices removed: its fundus now reaches the scan's last slice while both points stay inside
    from StomachUnfoldLib.geometry import Volume

    ct, truth = make_phantom("j", "tiny", noise_hu=0.0)
    cut = Volume(np.ascontiguousarray(ct.array[:120]), ct.spacing, ct.origin, ct.direction)
    w = unfold(cut, truth["cardia_lps"], truth["pylorus_lps"], TINY).report["warnings"]
    assert sum("reaches the last slice of the scan" in x for x in w) == 1
    assert not any("first slice" in x or "point lies on" in x for x in w)
    whole = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], TINY).report["warnings"]
    assert not any("slice of the scan" in x for x in whole)


def test_a_cardia_clicked_deep_in_the_fundus_is_said_in_the_warnings():
    """The opening left out about a point deep in a wide lumen reaches twice its depth: that wall is neither shown nor
    graded, so the run says so (tiny random stomach 4, the cardia moved 10 mm, 12 mm from the wall)."""
    from StomachUnfoldEval.click_error import moved_clicks
    from StomachUnfoldEval.random_stomach import random_stomach
    from StomachUnfoldLib.plausibility import DEEP_POINT_WARNING

    ct, truth = random_stomach(4, "tiny")[:2]
    cardia, pylorus = moved_clicks(truth["cardia_lps"], truth["pylorus_lps"], 10.0, seed=4, draw=1)
    w = unfold(ct, cardia, pylorus, UnfoldParameters()).report["warnings"]
    said = [x for x in w if DEEP_POINT_WARNING in x]
    assert len(said) == 1 and said[0].startswith("the cardia point lies") and "place the cardia point" in said[0]
    true = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters()).report["warnings"]
    assert not any(DEEP_POINT_WARNING in x for x in true)
