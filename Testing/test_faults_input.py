"""Faults round two, the input side: wrong structures, unknown frames, unplaced points, multi-label masks, truncated
files, DICOM gaps, odd parameters and geometry, and errors that name the right point; plus a property test over
random structurally-wrong markups and points files that finds no traceback.
"""
import copy
import gzip
import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from StomachUnfoldLib import io as suio
from StomachUnfoldLib.cli import main
from StomachUnfoldLib.errors import AnatomyError, InputError, PointError
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.pipeline import UnfoldParameters, unfold
from StomachUnfoldEval.phantom import make_phantom
from conftest import write_dicom_series

GOOD = {"@schema": suio.MARKUPS_SCHEMA, "markups": [{
    "type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": [
        {"label": "cardia", "position": [1.0, 2.0, 3.0], "positionStatus": "defined"},
        {"label": "pylorus", "position": [4.0, 5.0, 6.0], "positionStatus": "defined"}]}]}


@pytest.fixture(scope="module")
def phantom():
    return make_phantom("j", "tiny")


def _write(tmp_path, data, name="p.mrk.json"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def _cli(argv, capsys):
    """Run the command in-process; (status, its stderr lines). Any exception but SystemExit fails the test."""
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("data,text", [
    ([], "not a Slicer markups file"),
    ({"markups": {}}, "not a Slicer markups file"),
    ({"markups": [[]]}, "must be an object"),
    ({"markups": [{"controlPoints": None}]}, "controlPoints"),
    ({"markups": [{"controlPoints": [{"label": "cardia", "position": "1,2,3"}]}]}, "three numbers"),
    ({"markups": [{"controlPoints": [{"label": "cardia", "position": [1, 2]}]}]}, "three"),
    ({"markups": [{"controlPoints": [{"label": "cardia", "position": [1e999, 2, 3]}]}]}, "finite"),
    ({"markups": [{"coordinateSystem": "IJK", "controlPoints": [{"label": "cardia", "position": [1, 2, 3]}]}]},
     "coordinateSystem \"IJK\""),
    ({"markups": [{"coordinateSystem": 5, "controlPoints": []}]}, "only LPS and RAS"),
])
def test_structurally_wrong_markups_are_refused_by_name(tmp_path, data, text):
    with pytest.raises(PointError, match=text):
        suio.read_markups_points(_write(tmp_path, data))


@pytest.mark.parametrize("status", ["undefined", "missing", "preview", None])
def test_a_point_not_placed_is_refused_not_read_at_the_origin(tmp_path, status):
    data = copy.deepcopy(GOOD)
    data["markups"][0]["controlPoints"][0]["positionStatus"] = status
    with pytest.raises(PointError, match="'cardia'.*not placed"):
        suio.cardia_pylorus_from_markups(_write(tmp_path, data))
    data["markups"][0]["controlPoints"][0]["positionStatus"] = "defined"
    c, p = suio.cardia_pylorus_from_markups(_write(tmp_path, data))
    assert np.allclose(c, [1, 2, 3]) and np.allclose(p, [4, 5, 6])
    data["markups"][0]["coordinateSystem"] = "ras"
    c, _ = suio.cardia_pylorus_from_markups(_write(tmp_path, data))
    assert np.allclose(c, [-1, -2, 3])


@pytest.mark.parametrize("truth,text", [
    ({"cardia_lps": "abc", "pylorus_lps": [1, 2, 3]}, "cardia_lps.*three numbers"),
    ({"cardia_ras": [1, 2, 3], "pylorus_ras": None}, "pylorus_ras.*three numbers"),
    ({"cardia_lps": [1, 2, 3], "pylorus_lps": [[1, 2], 3]}, "pylorus_lps"),
    ([1, 2, 3], "no cardia/pylorus"),
    ("\"text\"", "no cardia/pylorus"),
])
def test_structurally_wrong_truth_files_give_one_error_line(tmp_path, capsys, truth, text):
    path = _write(tmp_path, truth, "truth.json")
    rc, err = _cli(["unfold", tmp_path / "missing.nrrd", "--points", path, "-o", tmp_path / "o"], capsys)
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: "), err
    assert __import__("re").search(text, err[0]), err


def _mutations():
    """Random JSON values and random places in a good markups file to put them."""
    leaf = st.one_of(st.none(), st.booleans(), st.integers(-10 ** 30, 10 ** 30), st.floats(allow_nan=True),
                     st.text(max_size=6), st.sampled_from(["LPS", "RAS", "IJK", "defined", "undefined", "cardia"]))
    value = st.recursive(leaf, lambda kids: st.one_of(st.lists(kids, max_size=4),
                                                      st.dictionaries(st.text(max_size=6), kids, max_size=3)),
                         max_leaves=8)
    path = st.lists(st.sampled_from(["markups", 0, 1, "controlPoints", "position", "label", "positionStatus",
                                     "coordinateSystem", 2]), max_size=6)
    return st.lists(st.tuples(path, value), min_size=1, max_size=4)


def _mutate(doc, path, value):
    """Put ``value`` at ``path`` (as far as the path exists) in ``doc``; a path that does not exist replaces the root."""
    if not path:
        return value
    node = doc
    for key in path[:-1]:
        try:
            node = node[key]
        except (KeyError, IndexError, TypeError):
            return doc
    try:
        node[path[-1]] = value
    except (IndexError, TypeError):
        pass
    return doc


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(changes=_mutations(), as_truth=st.booleans())
def test_property_random_wrong_markups_and_points_files_give_an_error_line_never_a_traceback(tmp_path, capsys,
                                                                                            changes, as_truth):
    doc = copy.deepcopy(GOOD) if not as_truth else {"cardia_lps": [1.0, 2.0, 3.0], "pylorus_lps": [4.0, 5.0, 6.0]}
    for path, value in changes:
        if as_truth and path:
            path = [["cardia_lps", "pylorus_lps", "cardia_ras", "markups"][hash(str(path)) % 4]] + path[1:2]
        doc = _mutate(doc, path, value)
    path = _write(tmp_path, json.dumps(doc), "p.mrk.json" if not as_truth else "p.json")
    if not as_truth:
        try:
            pts = suio.read_markups_points(path)
            assert all(np.asarray(p).shape == (3,) and np.all(np.isfinite(p)) for p in pts.values())
        except PointError as e:
            assert str(e)
    # the command: either the points pass and the missing CT is the error, or the points file is
    rc, err = _cli(["unfold", tmp_path / "missing.nrrd", "--points", path, "-o", tmp_path / "o"], capsys)
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: "), err


def test_a_multi_label_mask_is_refused_listing_the_labels_and_their_volumes(phantom, tmp_path, capsys):
    ct, truth = phantom
    lab = np.zeros(ct.array.shape, np.uint8)
    lab[ct.array < -500] = 6  # the stomach's gas (and the lungs: one label here)
    lab[:, :, :3] = 1  # another organ
    lab[:3] = 117
    path = suio.write_volume(ct.with_array(lab), tmp_path / "seg.nii.gz")
    with pytest.raises(InputError, match=r"holds 3 labels \((6|1|117): [\d.]+ mL.*--mask-label"):
        suio.read_label_volume(path, ct)
    vols = suio.label_volumes_ml(ct.with_array(lab))
    assert set(vols) == {1, 6, 117} and vols[6] == pytest.approx((lab == 6).sum() * np.prod(ct.spacing) / 1000)
    assert suio.read_label_volume(path, ct, label_value=6).sum() == (lab == 6).sum()
    suio.check_single_label(ct.with_array((lab == 6).astype(np.uint8) * 3), None)  # one label: taken as the stomach


def test_a_whole_volume_mask_is_no_stomach(phantom):
    ct, truth = phantom
    with pytest.raises(AnatomyError, match="no stomach label.*all six sides.*--mask-label"):
        unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], mask=np.ones(ct.array.shape, bool))


def test_a_truncated_nifti_is_refused(tmp_path):
    rng = np.random.default_rng(3)
    v = Volume(rng.integers(-1000, 1000, size=(30, 40, 50)).astype(np.int16), [0.8, 0.8, 2.0], [0.0, 0.0, 0.0])
    whole = suio.write_volume(v, tmp_path / "ct.nii.gz")
    data = open(whole, "rb").read()
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(data[:int(0.92 * len(data))])
    with pytest.raises(InputError, match=r"cut.nii.gz is truncated: it holds \d+ of the \d+ bytes.*export it again"):
        suio.read_volume(cut)
    raw = tmp_path / "raw.nii"
    raw.write_bytes(gzip.decompress(data)[:-5000])
    with pytest.raises(InputError, match="truncated"):
        suio.read_volume(raw)
    assert np.array_equal(suio.read_volume(whole).array, v.array)


def test_a_dicom_series_with_a_missing_slice_is_refused_naming_the_gap(tmp_path):
    rng = np.random.default_rng(4)
    v = Volume(rng.integers(-1000, 1000, size=(12, 6, 7)).astype(np.int16), [0.8, 0.8, 1.25], [0.0, 0.0, 0.0])
    write_dicom_series(str(tmp_path / "ok"), v)
    assert suio.read_volume(str(tmp_path / "ok")).array.shape == v.array.shape
    write_dicom_series(str(tmp_path / "gap"), v, skip=(5,))
    with pytest.raises(InputError, match=r"gap: 2.50 mm between slices at 5.00 and 7.50 mm \(7.1_004.dcm and 7.1_006.dcm\)"
                                         r".*1.25 mm apart.*export the complete series"):
        suio.read_volume(str(tmp_path / "gap"))


def test_itk_read_errors_give_itks_description_not_a_source_line(tmp_path):
    bad = tmp_path / "bad.nrrd"
    bad.write_text("NRRD0004\ntype: short\ndimension: 3\nsizes: 10 10 10\nencoding: raw\n\n" + "x" * 10)
    with pytest.raises(InputError) as e:
        suio.read_volume(bad)
    msg = str(e.value)
    assert ".cxx" not in msg and "0x" not in msg and "complete NRRD" in msg, msg
    assert len(msg) > len(f"cannot read {bad}: ") + 20


def test_parameter_ranges_are_enforced(capsys, tmp_path):
    for flags, text in ((["--output-spacing-mm", "1e6"], "output_spacing_mm"), (["--output-spacing-mm", "6"], "at most 5"),
                        (["--max-retries", "-1"], "max_retries"), (["--max-snap-mm", "-5"], "max_snap_mm"),
                        (["--wall-thickness-mm", "100"], "wall_thickness_mm")):
        rc, err = _cli(["unfold", tmp_path / "missing.nrrd", "--cardia", "0,0,0", "--pylorus", "0,0,50", "-o",
                        tmp_path / "o", *flags], capsys)
        assert rc == 2 and text in err[-1], (flags, err)
    with pytest.raises(SystemExit) as e:
        main(["unfold", "x.nrrd", "--cardia", "0,0,0", "--pylorus", "0,0,50", "-o", str(tmp_path), "--quality", "maybe"])
    assert e.value.code == 2 and "unrecognized arguments: maybe" in capsys.readouterr().err   # --quality/--no-quality


def test_sheared_or_zero_spacing_volumes_are_refused(phantom):
    ct, truth = phantom
    shear = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(InputError, match="sheared"):
        unfold(Volume(ct.array, ct.spacing, ct.origin, shear), truth["cardia_lps"], truth["pylorus_lps"])


def test_nan_share_is_not_rounded_to_zero(phantom):
    ct, truth = phantom
    a = ct.array.astype(np.float32)
    a.reshape(-1)[:max(1, a.size // 4000)] = np.nan  # 0.025 %
    with pytest.raises(InputError, match=r"voxels \(0.025 %\) are NaN"):
        unfold(ct.with_array(a), truth["cardia_lps"], truth["pylorus_lps"])


def test_after_the_swap_check_errors_name_the_point_as_given(phantom):
    ct, truth = phantom
    # the "cardia" far below the pylorus, in tissue: exchanged, then it has no gas; the error names it the cardia
    far = np.asarray(truth["pylorus_lps"], float) + [-40.0, -40.0, -30.0]
    far = np.clip(far, *ct.bounds_lps() + np.array([[5.0], [-5.0]]))
    with pytest.raises((AnatomyError, PointError), match=r"near the cardia point .*swap check had exchanged"):
        unfold(ct, far, truth["pylorus_lps"], UnfoldParameters(method="cylindrical"))


def test_an_incision_curve_far_from_the_stomach_is_refused_before_the_method(phantom):
    ct, truth = phantom
    c, p = np.asarray(truth["cardia_lps"]), np.asarray(truth["pylorus_lps"])
    seen = []
    with pytest.raises(PointError, match=r"incision curve's point 2 of 2 .* mm from the stomach wall"):
        unfold(ct, c, p, UnfoldParameters(method="cylindrical"), incision_curve_lps=[c, c + [0, 0, 400.0]],
               progress=lambda stage, f: seen.append(stage))
    from StomachUnfoldLib.frontend import FRONT_STAGES

    assert set(seen) <= {name for name, _, _ in FRONT_STAGES}, set(seen)


def test_phantom_spacing_and_bench_parts_are_checked(capsys, tmp_path):
    rc, err = _cli(["phantom", tmp_path / "p.nrrd", "--size", "tiny", "--spacing", "0,0,0"], capsys)
    assert rc == 2 and "--spacing must be three voxel sizes" in err[-1]
    rc, err = _cli(["bench", "--parts", "nonsense", "-o", tmp_path / "b"], capsys)
    assert rc == 2 and "unknown benchmark part nonsense" in err[-1]
    rc, err = _cli(["bench", "--parts", "sizes", "--methods", "isometric,nonsense", "-o", tmp_path / "b"], capsys)
    assert rc == 2 and "unknown method nonsense; choose from" in err[-1]
    assert not os.path.exists(tmp_path / "p.nrrd") and not os.path.exists(tmp_path / "b")


def test_the_wall_models_memory_is_estimated_before_it_is_built(phantom, monkeypatch):
    from StomachUnfoldLib import frontend
    from StomachUnfoldLib.frontend import FRONT_STAGES, estimate_model_bytes, prepare

    ct, truth = phantom
    c, p = truth["cardia_lps"], truth["pylorus_lps"]
    prep = prepare(ct, c, p, UnfoldParameters(method="massspring", grid_size=3))
    sizes = []
    for d in (3, 2, 1):
        prep.params = UnfoldParameters(method="massspring", grid_size=d)
        sizes.append(estimate_model_bytes(prep))
    assert sizes[0] < sizes[1] < sizes[2] and sizes[2] > 20 * sizes[0]  # ~1/d**3
    # a machine where the d = 1 model cannot fit: one vertex costs a 30000th of the free memory
    monkeypatch.setattr(frontend, "MODEL_BYTES_PER_VERTEX", frontend.available_memory_bytes() // 30000)
    seen = []
    with pytest.raises(InputError, match=r"wall model of \[1.8, 1.8, 1.8\] mm cells needs about .* GiB.*--grid-mm"):
        unfold(ct, c, p, UnfoldParameters(method="massspring", grid_size=1), progress=lambda s, f: seen.append(s))
    assert set(seen) <= {name for name, _, _ in FRONT_STAGES}


def test_the_real_totalsegmentator_map_is_refused_without_its_label():
    from conftest import REAL_CT_NAME, REAL_SEG_NAME, shared_file

    ct = suio.read_volume(shared_file(REAL_CT_NAME))
    seg = shared_file(REAL_SEG_NAME)
    with pytest.raises(InputError, match=r"holds \d\d labels \(.*6: 1\d\d.\d mL.*--mask-label"):
        suio.read_label_volume(seg, ct)
    assert suio.read_label_volume(seg, ct, label_value=6).any()
