import numpy as np
import pytest

from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.incision_line import (compute_incision_line, cutting_directions, incision_from_curve,
                                            incision_surface_points)
from conftest import make_tube


def test_bent_tube_incision_on_convex_side_and_on_inner_wall():
    vol, lumen, wall, cl = make_tube("bent")
    inc = compute_incision_line(lumen, vol, cl, side="greater")
    # the bend centre is at (-30, 0, 0): the greater curvature lies at 60 + r from it
    dist_from_bend_centre = np.linalg.norm(inc.points_lps - np.array([-30.0, 0, 0]), axis=1)
    assert np.all(dist_from_bend_centre > 60 + 20 - 2.5)
    # each point sits on the inner wall: at the radius from its centreline point
    r = np.linalg.norm(inc.points_lps - cl.points_lps[inc.centerline_index], axis=1)
    assert np.allclose(r, 20.0, atol=1.5)
    # connected: consecutive points no further apart than a few mm
    assert np.linalg.norm(np.diff(inc.points_lps, axis=0), axis=1).max() < 5.0
    lesser = compute_incision_line(lumen, vol, cl, side="lesser")
    d_less = np.linalg.norm(lesser.points_lps - np.array([-30.0, 0, 0]), axis=1)
    assert np.all(d_less < 60 - 20 + 2.5)


@pytest.mark.parametrize("side,axis,sign", [("anterior", 1, -1), ("posterior", 1, 1)])
def test_anterior_posterior_sides(side, axis, sign):
    vol, lumen, wall, cl = make_tube("straight")
    inc = compute_incision_line(lumen, vol, cl, side=side)
    assert np.all(sign * inc.points_lps[:, axis] > 18.0)


def test_straight_tube_defaults_to_patient_left_and_bad_side():
    vol, lumen, wall, cl = make_tube("straight")
    d = cutting_directions(cl.points_lps, cl.tangents, cl.radius_mm, "greater")
    assert np.all(d[:, 0] > 0.95)
    with pytest.raises(InputError):
        cutting_directions(cl.points_lps, cl.tangents, cl.radius_mm, "sideways")


def test_user_curve_and_cut_surface_reaches_through_wall():
    vol, lumen, wall, cl = make_tube("straight")
    curve = np.stack([np.full(30, 0.0), np.full(30, -20.0), np.linspace(110, 10, 30)], 1)
    inc = incision_from_curve(curve, cl)
    assert inc.points_lps[0, 2] < inc.points_lps[-1, 2]  # reordered cardia -> pylorus along the centreline
    assert np.allclose(inc.directions[:, 1], -1.0, atol=1e-6)
    pts = incision_surface_points(inc, cl, depth_mm=8.0, inside_mm=3.0, sample_mm=1.0, extend_mm=2.0)
    radial = np.linalg.norm(pts[:, :2], axis=1)
    assert radial.min() < 17.5 and radial.max() > 27.5
