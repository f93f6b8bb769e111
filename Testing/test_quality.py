"""Automatic quality metrics and grade."""
import numpy as np
import pytest

from StomachUnfoldLib.geometry import Volume
from StomachUnfoldEval.phantom import make_phantom
from StomachUnfoldLib.pipeline import UnfoldParameters, unfold
from StomachUnfoldLib.quality import GRADE_THRESHOLDS, layer_runs, surface_distortion, visible_points
from StomachUnfoldLib.view import first_hit


def test_surface_distortion_known_maps():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(30, 3)) * 10
    tris = np.array([[i, i + 1, i + 2] for i in range(0, 27, 3)])
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    same = surface_distortion(rest, rest @ R.T + 5.0, tris)  # rigid motion: no distortion
    assert same["area_distortion"] < 1e-9 and same["angle_distortion"] < 1e-9
    scaled = surface_distortion(rest, 2.0 * rest, tris)  # uniform scale: area x4, angles kept
    assert np.isclose(scaled["area_distortion"], np.log(4.0)) and scaled["angle_distortion"] < 1e-9
    sheared = surface_distortion(rest, rest * np.array([3.0, 1.0, 1.0]), tris)
    assert sheared["angle_distortion"] > 0.1


def test_layer_runs_counts_separate_layers():
    a = np.full((20, 2, 2), -1000, np.int16)
    a[2:5] = 40
    a[10:14, 0, 0] = 40  # a second layer over one column
    runs = layer_runs(Volume(a, [1.0, 1.0, 1.0]))
    assert runs[0, 0] == 2 and runs[1, 1] == 1


@pytest.mark.parametrize("spacing, gap_voxels, runs_expected", [(1.2, 1, 1), (1.2, 2, 2), (0.7, 2, 1), (0.7, 3, 2),
                                                                (1.8, 1, 2), (0.5, 2, 1)])
def test_layer_runs_merge_gaps_under_min_gap_mm(spacing, gap_voxels, runs_expected):
    a = np.full((20, 1, 1), -1000, np.int16)  # a crease of gap_voxels * spacing mm inside one wall layer
    a[3:7] = 40
    a[7 + gap_voxels:12 + gap_voxels] = 40
    assert layer_runs(Volume(a, [1.0, 1.0, spacing]), min_gap_mm=1.5)[0, 0] == runs_expected


def test_visible_points_only_the_first_layer_of_a_column():
    a = np.full((20, 4, 4), -1000, np.int16)  # (k, j, i); the viewer looks down -k, so the top layer is at high k
    a[14:16] = 40  # top layer over every column
    a[5:7, :, :2] = 40  # a deeper layer under the left half
    vol = Volume(a, [1.0, 1.0, 1.0])
    k_hit, _ = first_hit(vol)
    pts = vol.index_to_lps(np.array([[1, 1, 15], [1, 1, 6], [3, 3, 15], [9, 1, 15]], float))
    pts = np.vstack([pts, [np.nan, 0, 0]])
    assert visible_points(vol, pts, k_hit).tolist() == [True, False, True, False, False]


@pytest.fixture(scope="module")
def j_phantom():
    return make_phantom("j", "tiny")


def test_grade_and_metrics_of_default_and_paper_forces(j_phantom):
    ct, truth = j_phantom
    markers = {m["id"]: m["lps"] for m in truth["markers"]}
    ours = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters(method="massspring", grid_size=3,
                                                                           wall_thickness_mm=4.0))
    q = ours.report["quality"]
    assert q["grade"] in ("excellent", "good")
    assert q["visible_fraction"] > 0.85 and q["failure_parts"] <= 1
    from StomachUnfoldEval.markers import marker_metrics
    mq = marker_metrics(ours, markers)
    assert mq["seen"] == 12 and 0.7 < mq["pairwise_distance_ratio_median"] < 1.4
    # the paper's forces alone (no guided destinations, no flattening, weak pull) bend and fold the wall
    paper = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"],
                   UnfoldParameters(method="paper", grid_size=3, wall_thickness_mm=4.0)).report["quality"]
    assert paper["visible_fraction"] < q["visible_fraction"] - 0.1
    assert paper["bending_plane_rms_mm"] > 3 * q["bending_plane_rms_mm"]
    order = ["excellent", "good", "fair", "bad"]
    assert order.index(paper["grade"]) > order.index(q["grade"])
    assert set(GRADE_THRESHOLDS) == {"excellent", "good", "fair"}


def _ball_with_side_tube():
    """Lumen: a ball of radius 25 mm (1 mm voxels, centre at LPS 0) and a gas tube (radius 2 mm) leaving its +x side."""
    n = 81
    g = (np.arange(n) - 40).astype(float)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    lumen = (x ** 2 + y ** 2 + z ** 2 <= 25.0 ** 2) | ((x > 0) & (y ** 2 + z ** 2 <= 2.0 ** 2))
    vol = Volume(lumen.astype(np.uint8), [1.0, 1.0, 1.0], [-40.0, -40.0, -40.0])
    cl = np.stack([np.linspace(20.0, -20.0, 21), np.zeros(21), np.zeros(21)], 1)  # cardia 5 mm inside the +x wall
    return vol, cl


def test_the_judge_keeps_the_wall_beside_a_side_opening_and_drops_the_tube_beyond():
    from StomachUnfoldLib.centerline import OPENING_RADIUS_MM, in_openings
    from StomachUnfoldLib.quality import mucosa_points

    vol, cl = _ball_with_side_tube()
    pts = mucosa_points(vol, cl, max_points=10 ** 6)
    d0 = np.linalg.norm(pts - cl[0], axis=1)
    behind = pts[:, 0] > cl[0, 0]                       # behind the cardia's end plane
    # the wall behind the end plane but farther than the opening radius is the stomach's own: counted
    assert np.sum(behind & (d0 > OPENING_RADIUS_MM + 1.0)) > 100
    # nothing inside the opening, and the gas tube beyond it (an open oesophagus) is not the stomach's mucosa
    assert not np.any(behind & (d0 < OPENING_RADIUS_MM - 1.0))
    assert pts[:, 0].max() < 25.0 + 1.0
    # at the end of a tube (end point in the middle of the lumen) the whole end is the opening
    tube = np.stack([np.full(200, 31.0), 15.0 * np.cos(np.linspace(0, 6.28, 200)),
                     15.0 * np.sin(np.linspace(0, 6.28, 200))], 1)
    cap = np.array([[40.0, 0.0, 0.0], [36.0, 9.0, 0.0], [32.0, 0.0, 14.0]])
    cl_t = np.stack([np.linspace(30.0, -30.0, 31), np.zeros(31), np.zeros(31)], 1)[::-1]
    assert in_openings(np.vstack([tube, cap]), cl_t)[-3:].all()


def test_a_point_clicked_deep_in_a_wide_lumen_is_warned_of_and_a_point_at_its_opening_or_a_tube_end_is_not():
    from StomachUnfoldLib.plausibility import opening_warnings

    vol, cl = _ball_with_side_tube()  # the cardia 5 mm from the wall by the gas tube, the pylorus 5 mm from the wall
    assert opening_warnings(vol, cl) == []
    # the cardia clicked 13 mm from the wall: its opening reaches 26 mm, while the wall behind it reaches 28 mm
    deep = np.stack([np.linspace(12.0, -20.0, 17), np.zeros(17), np.zeros(17)], 1)
    w = opening_warnings(vol, deep)
    assert len(w) == 1 and w[0].startswith(("the cardia point lies 12 mm from the wall", "the cardia point lies 13 mm"))
    share = float(w[0].split("takes ")[1].split(" %")[0])   # the cap from 10 to 25 mm behind the point, of the ball
    assert 10 <= share <= 40
    # the end of a tube (a cylinder whose end point sits on its axis, 12 mm from its flat end): the whole end opens
    g = (np.arange(61) - 30).astype(float)
    z, y, x = np.meshgrid(g, g, np.arange(121) - 60.0, indexing="ij")
    tube = Volume(((y ** 2 + z ** 2 <= 15.0 ** 2) & (np.abs(x) <= 50.0)).astype(np.uint8), [1.0, 1.0, 1.0],
                  [-60.0, -30.0, -30.0])
    cl_t = np.stack([np.linspace(-38.0, 38.0, 39), np.zeros(39), np.zeros(39)], 1)
    assert opening_warnings(tube, cl_t) == []


def test_the_hash_sample_keeps_the_same_mucosa_points_where_two_lumens_agree():
    # an ellipsoidal lumen and the same one with a bump on one side: the judge's "hash" sample keeps its points away
    # from the bump, where a random draw from the edge's list picks another sample
    from StomachUnfoldLib.quality import mucosa_points

    k, j, i = np.mgrid[0:60, 0:60, 0:70]
    base = ((i - 35) / 28.0) ** 2 + ((j - 30) / 24.0) ** 2 + ((k - 30) / 24.0) ** 2 < 1.0
    bumped = base | ((i - 62) ** 2 + (j - 30) ** 2 + (k - 30) ** 2 < 16)
    vol = lambda m: Volume(m.astype(np.uint8), (1.0, 1.0, 2.0), (-35.0, -30.0, -60.0), np.eye(3))  # noqa: E731
    n = 3000
    far = lambda p: p[:, 0] < 10.0  # noqa: E731   LPS x: far from the bump at x = 27 mm
    shared = {}
    for sample in ("hash", "draw"):
        a = mucosa_points(vol(base), max_points=n, sample=sample)
        b = mucosa_points(vol(bumped), max_points=n, sample=sample)
        assert len(a) == len(b) == n
        sa = {tuple(np.round(p, 3)) for p in a[far(a)]}
        sb = {tuple(np.round(p, 3)) for p in b[far(b)]}
        shared[sample] = len(sa & sb) / max(len(sa), 1)
    assert shared["hash"] > 0.97 and shared["draw"] < 0.7
    again = mucosa_points(vol(base), max_points=n, sample="hash")
    assert np.array_equal(again, mucosa_points(vol(base), max_points=n, sample="hash"))
    with pytest.raises(ValueError, match="sample"):
        mucosa_points(vol(base), max_points=n, sample="random")
