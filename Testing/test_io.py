import json
import os

import numpy as np
import pytest

from StomachUnfoldLib import io as suio
from StomachUnfoldLib.errors import InputError, PointError
from StomachUnfoldLib.geometry import Volume

from conftest import SHARED_DIR, write_dicom_series

DATA = os.path.join(SHARED_DIR, "data")
need_data = pytest.mark.skipif(not os.path.isdir(DATA), reason=f"the real CTs are not in {DATA} (set STOMACHUNFOLD_SHARED)")


def _random_volume(direction):
    rng = np.random.default_rng(0)
    return Volume(rng.integers(-1000, 1000, size=(6, 7, 8)).astype(np.int16), [0.7, 0.8, 2.5],
                  [10.0, -20.0, 30.0], direction)


@pytest.mark.parametrize("ext", [".nrrd", ".nii.gz", ".mha"])
@pytest.mark.parametrize("direction", [np.eye(3), np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]]),
                                       np.array([[0.6, -0.8, 0], [0.8, 0.6, 0], [0, 0, 1]])])
def test_volume_round_trip_keeps_geometry(tmp_path, ext, direction):
    v = _random_volume(direction)
    path = suio.write_volume(v, tmp_path / f"v{ext}")
    w = suio.read_volume(path)
    assert np.array_equal(w.array, v.array) and w.array.dtype == np.int16
    assert np.allclose(w.spacing, v.spacing, atol=1e-5) and np.allclose(w.origin, v.origin, atol=1e-4)
    assert np.allclose(w.direction, v.direction, atol=1e-5)
    assert [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")] == []


def test_bad_volumes_are_refused_with_a_reason(tmp_path):
    import SimpleITK as sitk

    with pytest.raises(InputError, match="does not exist"):
        suio.read_volume(tmp_path / "nope.nrrd")
    sitk.WriteImage(sitk.Image(10, 10, sitk.sitkInt16), str(tmp_path / "flat.nrrd"))
    with pytest.raises(InputError, match="2D"):
        suio.read_volume(tmp_path / "flat.nrrd")
    sitk.WriteImage(sitk.Image([5, 5, 5, 3], sitk.sitkInt16), str(tmp_path / "t.nrrd"))
    with pytest.raises(InputError, match="4D"):
        suio.read_volume(tmp_path / "t.nrrd")
    (tmp_path / "junk.nrrd").write_text("not an image")
    with pytest.raises(InputError, match="cannot read"):
        suio.read_volume(tmp_path / "junk.nrrd")


def test_markups_round_trip_and_ras_files(tmp_path):
    pts = {"cardia": np.array([1.0, 2.0, 3.0]), "Pylorus": np.array([-4.0, 5.0, -6.0])}
    suio.write_markups_fiducials(tmp_path / "p.mrk.json", pts, "pts")
    got = suio.read_markups_points(tmp_path / "p.mrk.json")
    assert set(got) == {"cardia", "pylorus"} and np.allclose(got["pylorus"], [-4, 5, -6])
    c, p = suio.cardia_pylorus_from_markups(tmp_path / "p.mrk.json")
    assert np.allclose(c, [1, 2, 3])
    data = json.load(open(tmp_path / "p.mrk.json"))
    data["markups"][0]["coordinateSystem"] = "RAS"
    (tmp_path / "ras.mrk.json").write_text(json.dumps(data))
    assert np.allclose(suio.read_markups_points(tmp_path / "ras.mrk.json")["cardia"], [-1, -2, 3])
    suio.write_markups_fiducials(tmp_path / "one.mrk.json", {"cardia": np.zeros(3)}, "one")
    with pytest.raises(PointError, match="pylorus"):
        suio.cardia_pylorus_from_markups(tmp_path / "one.mrk.json")
    suio.write_markups_curve(tmp_path / "c.mrk.json", np.random.default_rng(0).normal(size=(5, 3)), "curve")
    d = json.load(open(tmp_path / "c.mrk.json"))
    assert d["markups"][0]["type"] == "Curve" and len(d["markups"][0]["controlPoints"]) == 5


@need_data
def test_dicom_folder_matches_its_nifti_conversion():
    d = suio.read_volume(os.path.join(DATA, "02_totalseg_example_ct_dicom_slab"))
    n = suio.read_volume(os.path.join(DATA, "02_totalseg_example_ct_dicom_slab_2mm.nii.gz"))
    assert d.array.shape == (20, 512, 512)
    assert np.allclose(d.spacing, n.spacing, atol=1e-4) and np.allclose(d.origin, n.origin, atol=1e-2)
    assert np.array_equal(d.array, n.array)


@need_data
def test_stomach_label_resampled_onto_the_ct_in_physical_space():
    ct = suio.read_volume(os.path.join(DATA, "02_totalseg_example_ct_dicom_slab_2mm.nii.gz"))
    m = suio.read_label_volume(os.path.join(DATA, "02_totalseg_example_ct_dicom_slab_seg117_stomach6.nii.gz"), ct, 6)
    ml = m.sum() * np.prod(ct.spacing) / 1000.0
    assert 130 < ml < 150  # the data README: 141 mL inside the slab
    with pytest.raises(InputError, match="no voxel of label 250"):
        suio.read_label_volume(os.path.join(DATA, "02_totalseg_example_ct_dicom_slab_seg117_stomach6.nii.gz"), ct, 250)


def test_dicom_folder_with_several_series_names_them_and_reads_the_chosen_one(tmp_path):
    rng = np.random.default_rng(1)
    a = Volume(rng.integers(-1000, 1000, size=(5, 6, 7)).astype(np.int16), [0.8, 0.8, 2.0], [0.0, 0.0, 0.0])
    b = Volume(rng.integers(-1000, 1000, size=(9, 6, 7)).astype(np.int16), [0.8, 0.8, 1.0], [0.0, 0.0, 0.0])
    study = "1.2.826.0.1.3680043.8.498.1"
    ua, ub = study + ".101", study + ".202"
    write_dicom_series(str(tmp_path), a, ua, study)
    write_dicom_series(str(tmp_path), b, ub, study)
    with pytest.raises(InputError, match=r"2 DICOM series.*5 slices.*9 slices.*--series-uid|2 DICOM series.*9 slices.*5 slices.*--series-uid"):
        suio.read_volume(str(tmp_path))
    got = suio.read_volume(str(tmp_path), series_uid=ub)
    assert got.array.shape == b.array.shape and np.array_equal(got.array, b.array)
    assert np.allclose(got.spacing, b.spacing, atol=1e-3)
    with pytest.raises(InputError, match="not in"):
        suio.read_volume(str(tmp_path), series_uid=study + ".999")


def test_read_volume_is_a_read_only_view_that_outlives_its_image(tmp_path):
    import gc

    a = (np.arange(6 * 7 * 8, dtype=np.int16).reshape(8, 7, 6) * 3 - 1000)
    path = suio.write_volume(Volume(a, [0.8, 0.9, 2.0], [1.0, 2.0, 3.0]), str(tmp_path / "ct.nrrd"))
    vol = suio.read_volume(path)
    gc.collect()  # the SimpleITK image is referenced only through the array's base
    assert np.array_equal(vol.array, a) and not vol.array.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        vol.array[0, 0, 0] = 0
    sub = vol.array[2:5]
    del vol
    gc.collect()
    assert np.array_equal(sub, a[2:5])
