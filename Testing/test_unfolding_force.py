import numpy as np

from StomachUnfoldLib.unfolding_force import (base_line, distance_metric, unfolded_plane,
                                              unfolding_force, unfolding_targets, wall_depth)
from conftest import tube_model


def test_plane_normal_points_to_convex_side_of_a_bent_incision():
    th = np.linspace(0, np.pi / 2, 50)
    u = np.stack([80 * np.cos(th), np.zeros_like(th), 80 * np.sin(th)], 1)
    n, b = unfolded_plane(u, u)
    assert np.allclose(n, [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-2)
    assert np.allclose(b, u[25], atol=3)


def test_base_line_keeps_arc_length_and_orientation():
    th = np.linspace(0, np.pi / 2, 51)
    u = np.stack([80 * np.cos(th), np.zeros_like(th), 80 * np.sin(th)], 1)
    u[:, 1] = 15 * np.sin(2 * th)  # leaves the plane: projected length shorter than the 3D length
    n, b = unfolded_plane(u, u)
    p, v1, v2, up = base_line(u, n, b, arc="projected")
    seg_p = np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
    seg_up = np.linalg.norm(np.diff(up, axis=0), axis=1).sum()
    assert np.isclose(seg_p, seg_up)  # Eq. 7 as printed
    p3, *_ = base_line(u, n, b)
    seg_u = np.linalg.norm(np.diff(u, axis=0), axis=1).sum()
    assert np.isclose(np.linalg.norm(np.diff(p3, axis=0), axis=1).sum(), seg_u) and seg_u > seg_up + 1
    assert np.dot(p[-1] - p[0], up[-1] - up[0]) > 0  # cardia to pylorus
    assert np.allclose(np.cross(v1, v2), n)           # right-handed frame, viewer on +n
    assert np.allclose((p - b) @ n, 0, atol=1e-9)      # on the plane


def test_destinations_at_pi_epsilon_on_the_correct_side():
    vol, lumen, wall, cl, inc, m = tube_model("straight")
    depth = wall_depth(m.vertices, lumen, vol)
    tg = unfolding_targets(m, inc, cl, depth=depth)
    # distance of each destination from the base line in the plane equals pi * epsilon
    jj = np.argmin(np.linalg.norm(m.vertices[tg.vertex_ids][:, None] - inc.points_lps[None], axis=2), axis=1)
    rel = tg.destinations - tg.base_line[jj]
    across = rel @ tg.v2
    assert np.allclose(np.abs(across), np.pi * tg.epsilon, atol=1e-6)
    assert np.allclose(tg.epsilon, 20.0, atol=1.5)
    # side: vertices on the +v2 side of the cut go to +v2 (incision on +x, axis z: v2 is -y or +y)
    y_side = np.sign((m.vertices[tg.vertex_ids] - inc.points_lps[jj]) @ tg.v2)
    assert np.mean(y_side == tg.side) > 0.95
    # mucosa on the plane: destination height = - depth
    assert np.allclose((tg.destinations - tg.b) @ tg.n, -depth[tg.vertex_ids], atol=1e-6)


def test_wall_depth_signed():
    vol, lumen, wall, cl, inc, m = tube_model("straight")
    pts = np.array([[0, 0, 60.0], [24.0, 0, 60], [0, 21.0, 60]])
    dep = wall_depth(pts, lumen, vol)
    assert dep[0] < -15 and 2.0 < dep[1] < 5.5 and -0.5 < dep[2] < 2.5


def test_force_and_metric():
    r = np.array([[0.0, 0, 0], [1, 1, 1]])
    g = np.array([[3.0, 4, 0], [1, 1, 1]])
    assert np.allclose(unfolding_force(r, g, 2.0), [[6, 8, 0], [0, 0, 0]])
    assert distance_metric(r, g) == 2.5
