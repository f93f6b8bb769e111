import numpy as np
import pytest

from StomachUnfoldLib.wall_model import grid_steps, model_to_vtk, write_vtu
from conftest import tube_model


def _signed_volumes(P, hexes):
    a = P[hexes[:, 1]] - P[hexes[:, 0]]
    b = P[hexes[:, 3]] - P[hexes[:, 0]]
    c = P[hexes[:, 4]] - P[hexes[:, 0]]
    return np.einsum("ij,ij->i", np.cross(a, b), c)


def test_grid_steps_follow_slice_spacing():
    assert grid_steps([0.7, 0.7, 0.7], 8) == (8, 8, 8)
    assert grid_steps([0.7, 0.7, 1.4], 8) == (8, 8, 4)
    assert grid_steps([0.7, 0.7, 5.0], 2) == (2, 2, 1)


def test_model_covers_wall_and_has_paper_springs():
    vol, lumen, wall, cl, inc, m = tube_model()
    # every hexahedron is a cube of d voxels (1.5 mm * 4 = 6 mm edges)
    assert np.allclose(np.abs(_signed_volumes(m.vertices, m.hexes)), 6.0 ** 3)
    # springs: edges (6 mm), face diagonals (6*sqrt2) and body diagonals (6*sqrt3), no duplicates
    for kind, length in ((0, 6.0), (1, 6.0 * np.sqrt(2)), (2, 6.0 * np.sqrt(3))):
        assert np.allclose(m.rest_length[m.spring_kind == kind], length)
    assert len(np.unique(np.sort(m.springs, 1), axis=0)) == m.n_springs
    # four body diagonals per hexahedron are never shared
    assert (m.spring_kind == 2).sum() == 4 * m.n_hexes
    # the vertex sets: S_vb is inside both S_vi and S_vo, and non-empty
    assert m.boundary.sum() > 20
    assert np.all(m.inner[m.boundary]) and np.all(m.outer[m.boundary])
    # inner vertices are closer to the axis than outer-only ones
    r = np.linalg.norm(m.vertices[:, :2], axis=1)
    assert np.median(r[m.inner & ~m.boundary]) < np.median(r[m.outer & ~m.boundary])


def test_incision_cuts_the_tube_open():
    *_, m_closed = tube_model(cut=False)
    *_, inc, m = tube_model()
    assert m.removed_incision > 0
    # around the axis the closed tube covers all angles; the cut one leaves a gap on the incision side (+x)
    def largest_gap(model):
        centres = model.vertices[model.hexes].mean(1)
        ang = np.sort(np.degrees(np.arctan2(centres[:, 1], centres[:, 0])))
        gaps = np.diff(np.concatenate([ang, [ang[0] + 360]]))
        return gaps.max(), ang[np.argmax(gaps)] + gaps.max() / 2
    gap_closed, _ = largest_gap(m_closed)
    gap, where = largest_gap(m)
    assert gap_closed < 20 and gap > gap_closed + 8, (gap_closed, gap)
    assert abs((where + 180) % 360 - 180) < 10  # the gap is on the +x side


@pytest.mark.parametrize("direction", [np.diag([1.0, -1.0, 1.0]),
                                       np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]])])
def test_model_in_lps_with_flipped_direction(direction):
    vol, lumen, wall, cl, inc, m = tube_model(direction=direction)
    r = np.linalg.norm(m.vertices[:, :2], axis=1)
    assert r.min() > 20.0 - 6.0 * 1.8 and r.max() < 24.0 + 6.0 * 1.8


def test_vtu_round_trip(tmp_path):
    import vtk
    *_, m = tube_model()
    write_vtu(m.vertices, m.hexes, tmp_path / "m.vtu")
    r = vtk.vtkXMLUnstructuredGridReader()
    r.SetFileName(str(tmp_path / "m.vtu"))
    r.Update()
    g = r.GetOutput()
    assert g.GetNumberOfCells() == m.n_hexes and g.GetNumberOfPoints() == m.n_vertices
    assert g.GetCellType(0) == vtk.VTK_HEXAHEDRON
    assert model_to_vtk(m.vertices, m.hexes, frame="RAS").GetPoint(0)[0] == pytest.approx(-m.vertices[0, 0])
