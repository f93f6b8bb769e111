"""Hexahedral mass-spring-damper model of the stomach wall (Oda et al., "Definition of Stomach Wall Model").

The wall region is covered by hexahedra on a regular grid of ``d x d x d_hat`` voxels aligned with the CT
axes (``d_hat = d * pixel spacing / slice spacing`` along the slice axis k). A cell is part of the model
when it holds a wall voxel. Cells crossed by the incision surface, and cells beyond the cardia and pylorus
ends of the centreline (the openings of the stomach), are removed. Mass points sit on the shared cell
vertices; springs and dampers sit on the cell edges, face diagonals and body diagonals.

Vertex sets, as in the paper: ``S_vi`` (inner surface: faces touching the lumen or the incision),
``S_vo`` (outer surface: faces touching neither lumen nor model, or the incision) and ``S_vb``
(vertices on the incision faces, which are in both).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import AnatomyError, InputError
from .geometry import Volume

__all__ = ["WallModel", "grid_steps", "build_wall_model", "HEX_OFFSETS"]

#: Grid offsets (i, j, k) of the 8 vertices of a cell, in VTK_HEXAHEDRON order.
HEX_OFFSETS = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
                        (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)], dtype=np.int64)

# Local vertex pairs of the springs of one cell: 12 edges, 12 face diagonals, 4 body diagonals.
_EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
_FACE_DIAGONALS = [(0, 2), (1, 3), (4, 6), (5, 7), (0, 5), (1, 4), (3, 6), (2, 7), (0, 7), (3, 4), (1, 6), (2, 5)]
_BODY_DIAGONALS = [(0, 6), (1, 7), (2, 4), (3, 5)]

# The six faces of a cell: (neighbour offset, local vertex ids of that face).
_FACES = [((-1, 0, 0), (0, 3, 7, 4)), ((1, 0, 0), (1, 2, 6, 5)),
          ((0, -1, 0), (0, 1, 5, 4)), ((0, 1, 0), (3, 2, 6, 7)),
          ((0, 0, -1), (0, 1, 2, 3)), ((0, 0, 1), (4, 5, 6, 7))]


@dataclass
class WallModel:
    """The hexahedral wall model: rest vertices (LPS mm), cells, springs and the vertex sets of the paper."""

    vertices: np.ndarray        # (N,3) rest positions, LPS mm
    hexes: np.ndarray           # (M,8) vertex ids, VTK_HEXAHEDRON order
    cells_ijk: np.ndarray       # (M,3) integer cell coordinates on the model grid (i, j, k order)
    springs: np.ndarray         # (S,2) vertex ids
    spring_kind: np.ndarray     # (S,) 0 edge, 1 face diagonal, 2 body diagonal
    rest_length: np.ndarray     # (S,) mm
    mass: np.ndarray            # (N,) lumped mass (mean 1)
    inner: np.ndarray           # (N,) bool, S_vi
    outer: np.ndarray           # (N,) bool, S_vo
    boundary: np.ndarray        # (N,) bool, S_vb (incision faces)
    cut_normal: np.ndarray      # (N,3) LPS: sum over a vertex's incision faces of (kept cell - cut cell) centres
    steps: tuple                # (d, d, d_hat) voxels per cell along i, j, k
    grid_origin_ijk: np.ndarray # continuous CT index of grid vertex (0,0,0)
    removed_incision: int = 0   # cells removed by the incision
    removed_openings: int = 0   # cells removed beyond the cardia and pylorus
    removed_fragments: int = 0  # cells dropped as disconnected fragments

    @property
    def n_vertices(self) -> int:
        """Number of mass points."""
        return len(self.vertices)

    @property
    def n_hexes(self) -> int:
        """Number of hexahedra."""
        return len(self.hexes)

    @property
    def n_springs(self) -> int:
        """Number of springs (each with a damper)."""
        return len(self.springs)

    def summary(self) -> dict:
        """Model sizes for the report (counts, cell size in voxels)."""
        return {"vertices": int(self.n_vertices), "hexahedra": int(self.n_hexes),
                "springs": int(self.n_springs), "cell_voxels": [int(s) for s in self.steps],
                "inner_vertices": int(self.inner.sum()), "outer_vertices": int(self.outer.sum()),
                "incision_vertices": int(self.boundary.sum()),
                "removed_incision_cells": int(self.removed_incision),
                "removed_opening_cells": int(self.removed_openings),
                "removed_fragment_cells": int(self.removed_fragments)}


def grid_steps(spacing, d: int = 8) -> tuple[int, int, int]:
    """Cell size in voxels along (i, j, k): ``(d, d, d_hat)`` with ``d_hat = d * pixel / slice spacing`` (>= 1)."""
    spacing = np.asarray(spacing, float)
    if d < 1:
        raise InputError(f"grid size d must be at least 1 voxel, got {d}")
    pixel = float(np.sqrt(spacing[0] * spacing[1]))
    d_hat = max(1, int(round(d * pixel / spacing[2])))
    return (int(d), int(d), d_hat)


def _block_any(mask: np.ndarray, steps, shape_cells) -> np.ndarray:
    """Per cell (k, j, i order) whether any voxel of ``mask[k, j, i]`` lies in it; cells tile from index 0."""
    sk, sj, si = steps[2], steps[1], steps[0]
    nk, nj, ni = shape_cells
    pad = np.zeros((nk * sk, nj * sj, ni * si), dtype=bool)
    pad[:mask.shape[0], :mask.shape[1], :mask.shape[2]] = mask
    return pad.reshape(nk, sk, nj, sj, ni, si).any(axis=(1, 3, 5))


def _remove_openings(keep, cell_centres_lps, openings, centerline_lps) -> int:
    """Clear the kept cells beyond the cardia and pylorus planes (in place); returns how many were removed."""
    if not openings:
        return 0
    idx = np.argwhere(keep)
    centres = cell_centres_lps(idx)
    beyond = np.zeros(len(idx), bool)
    nearest = None
    if centerline_lps is not None:
        from scipy.spatial import cKDTree

        cl = np.asarray(centerline_lps, float)
        _, nearest = cKDTree(cl).query(centres)
        ends = {0: 0, 1: len(cl) - 1}
    for which, (point, normal) in enumerate(openings):
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        out = (centres - np.asarray(point, float)) @ normal > 0
        if nearest is not None and which in ends:
            out &= nearest == ends[which]
        beyond |= out
    keep[tuple(idx[beyond].T)] = False
    return int(beyond.sum())


def _springs(hexes: np.ndarray, vertices: np.ndarray):
    """Unique springs (S,2) of the cells' edges, face and body diagonals, their kinds and rest lengths (mm)."""
    pairs = np.array(_EDGES + _FACE_DIAGONALS + _BODY_DIAGONALS)
    kinds = np.array([0] * len(_EDGES) + [1] * len(_FACE_DIAGONALS) + [2] * len(_BODY_DIAGONALS))
    s = hexes[:, pairs]  # (M, 28, 2)
    s = np.sort(s.reshape(-1, 2), axis=1)
    kind_all = np.tile(kinds, len(hexes))
    key = s[:, 0] * len(vertices) + s[:, 1]
    _, first = np.unique(key, return_index=True)
    springs = s[first]
    rest_length = np.linalg.norm(vertices[springs[:, 0]] - vertices[springs[:, 1]], axis=1)
    return springs, kind_all[first], rest_length


def _surface_sets(volume, cells, hexes, n_vertices, keep, incision_cells, lumen_cells, step_arr, ncells):
    """The paper's vertex sets from the faces of kept cells: inner (S_vi), outer (S_vo), boundary (S_vb), cut normal."""
    inner = np.zeros(n_vertices, bool)
    outer = np.zeros(n_vertices, bool)
    boundary = np.zeros(n_vertices, bool)
    cut_normal = np.zeros((n_vertices, 3))
    axes_lps = volume.direction * (volume.spacing * step_arr)[None, :]  # LPS vector of one cell step along i, j, k
    shape_c = np.array(ncells)
    for off, local in _FACES:
        nb = cells + np.array(off[::-1])  # neighbour in (k, j, i)
        inside = np.all((nb >= 0) & (nb < shape_c), axis=1)
        nbc = np.clip(nb, 0, shape_c - 1)
        nb_keep = inside & keep[nbc[:, 0], nbc[:, 1], nbc[:, 2]]
        nb_cut = inside & incision_cells[nbc[:, 0], nbc[:, 1], nbc[:, 2]] & ~nb_keep
        nb_lumen = inside & lumen_cells[nbc[:, 0], nbc[:, 1], nbc[:, 2]] & ~nb_keep & ~nb_cut
        free = ~nb_keep
        vids = hexes[:, list(local)]
        inner[vids[nb_lumen].ravel()] = True
        boundary[vids[nb_cut].ravel()] = True
        # from the removed cell toward the kept one: which side of the cut this face is on
        step_lps = -(axes_lps @ np.array(off, float))
        for c in range(4):
            np.add.at(cut_normal, vids[nb_cut][:, c], step_lps)
        outer[vids[free & ~nb_lumen & ~nb_cut].ravel()] = True
    inner |= boundary
    outer |= boundary
    return inner, outer, boundary, cut_normal


def build_wall_model(volume: Volume, wall: np.ndarray, lumen: np.ndarray, d: int = 8,
                     cut_points_lps: np.ndarray | None = None,
                     openings: list[tuple[np.ndarray, np.ndarray]] | None = None,
                     centerline_lps: np.ndarray | None = None) -> WallModel:
    """Build the hexahedral wall model on ``volume``'s grid (LPS mm) from wall and lumen masks.

    Parameters
    ----------
    volume : Volume
        Geometry of the (cropped) CT; masks are on its grid.
    wall, lumen : ndarray of bool, shape ``volume.array.shape``
        Stomach wall region and lumen (air region or mask).
    d : int
        In-plane cell size in voxels (the paper's d); the slice-axis size follows from the spacing.
    cut_points_lps : (P,3) array, optional
        Points sampled densely (spacing below half a cell) on the incision surface; cells holding one
        are removed (the hexahedra on the incision line).
    openings : list of (point_lps, outward_normal)
        Half-spaces beyond the cardia and pylorus: cells whose centre lies beyond a plane are removed.
    centerline_lps : (K,3) array, optional
        With it, an opening removes only cells whose nearest centreline point is that end's (first or last)
        point, so a curled stomach does not lose its far parts to the half-space of the other end.
    """
    steps = grid_steps(volume.spacing, d)
    shape_vox = wall.shape  # (k, j, i)
    ncells = tuple(int(np.ceil(shape_vox[a] / steps[2 - a])) for a in range(3))  # (nk, nj, ni)
    occupied = _block_any(wall, steps, ncells)
    lumen_cells = _block_any(lumen, steps, ncells)
    if not occupied.any():
        raise AnatomyError("the stomach wall region is empty: check the air threshold or pass a stomach mask")

    grid_origin = -0.5 * np.ones(3)  # continuous index of grid vertex (0,0,0): voxel boundary
    step_arr = np.array(steps, float)

    def cell_centres_lps(idx_kji):
        ijk = grid_origin + (idx_kji[:, ::-1] + 0.5) * step_arr
        return volume.index_to_lps(ijk)

    # --- cells on the incision surface
    incision_cells = np.zeros_like(occupied)
    if cut_points_lps is not None and len(cut_points_lps):
        ijk = volume.lps_to_index(np.asarray(cut_points_lps, float))
        cidx = np.floor((ijk - grid_origin) / step_arr).astype(np.int64)  # (i, j, k)
        ok = np.all((cidx >= 0) & (cidx < np.array(ncells[::-1])), axis=1)
        cidx = cidx[ok]
        incision_cells[cidx[:, 2], cidx[:, 1], cidx[:, 0]] = True
    removed_incision = int((occupied & incision_cells).sum())
    keep = occupied & ~incision_cells

    # --- openings at the cardia and pylorus ends
    removed_open = _remove_openings(keep, cell_centres_lps, openings, centerline_lps)

    # --- keep the largest face-connected piece
    labels, n = ndimage.label(keep)
    if n == 0:
        raise AnatomyError("no wall cells remain after the incision: the grid size d is too large for this "
                           "stomach; use a smaller --grid-size")
    sizes = np.bincount(labels.ravel())[1:]
    largest = 1 + int(np.argmax(sizes))
    removed_frag = int(sizes.sum() - sizes.max())
    keep = labels == largest

    cells = np.argwhere(keep)  # (M,3) in (k, j, i)
    cells_ijk = cells[:, ::-1].astype(np.int64)
    # --- vertices: unique corners of kept cells
    corners = cells_ijk[:, None, :] + HEX_OFFSETS[None, :, :]  # (M,8,3) in (i,j,k)
    nv_shape = np.array(ncells[::-1]) + 1  # vertex grid size (i, j, k)
    flat = np.ravel_multi_index((corners[..., 0].ravel(), corners[..., 1].ravel(), corners[..., 2].ravel()),
                                tuple(nv_shape))
    uniq, inverse = np.unique(flat, return_inverse=True)
    hexes = inverse.reshape(-1, 8).astype(np.int64)
    vijk = np.stack(np.unravel_index(uniq, tuple(nv_shape)), axis=1).astype(float)
    vertices = volume.index_to_lps(grid_origin + vijk * step_arr)

    springs, spring_kind, rest_length = _springs(hexes, vertices)

    # --- lumped masses (equal share of each cell's volume), normalised to mean 1
    mass = np.bincount(hexes.ravel(), minlength=len(vertices)).astype(float)
    mass /= mass.mean()

    inner, outer, boundary, cut_normal = _surface_sets(volume, cells, hexes, len(vertices), keep, incision_cells,
                                                       lumen_cells, step_arr, ncells)

    return WallModel(vertices=vertices, hexes=hexes, cells_ijk=cells_ijk, springs=springs,
                     spring_kind=spring_kind, rest_length=rest_length, mass=mass, inner=inner, outer=outer,
                     boundary=boundary, cut_normal=cut_normal, steps=steps, grid_origin_ijk=grid_origin,
                     removed_incision=removed_incision, removed_openings=removed_open,
                     removed_fragments=removed_frag)


def inner_surface_triangles(model) -> np.ndarray:
    """Triangles (T,3 vertex ids) of the model's inner surface: cell faces whose four vertices are all in S_vi."""
    tris = []
    for _, local in _FACES:
        q = model.hexes[:, list(local)]
        ok = model.inner[q].all(axis=1)
        q = q[ok]
        tris.append(q[:, [0, 1, 2]])
        tris.append(q[:, [0, 2, 3]])
    t = np.vstack(tris)
    return np.unique(np.sort(t, axis=1), axis=0)


def model_to_vtk(vertices_lps: np.ndarray, hexes: np.ndarray, frame: str = "LPS"):
    """vtkUnstructuredGrid of the cells (8 ids: VTK_HEXAHEDRON, 3: VTK_TRIANGLE) from vertices in mm (LPS, or RAS)."""
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import VTK_HEXAHEDRON, VTK_TRIANGLE, vtkCellArray, vtkUnstructuredGrid

    pts = np.asarray(vertices_lps, float).copy()
    if frame.upper() == "RAS":
        pts[:, :2] *= -1.0
    grid = vtkUnstructuredGrid()
    vp = vtkPoints()
    vp.SetData(ns.numpy_to_vtk(np.ascontiguousarray(pts), deep=True))
    grid.SetPoints(vp)
    h = np.asarray(hexes, np.int64)
    per = h.shape[1] if h.ndim == 2 else 8
    cells = vtkCellArray()
    offsets = ns.numpy_to_vtkIdTypeArray(np.arange(0, per * len(h) + 1, per, dtype=np.int64), deep=True)
    cells.SetData(offsets, ns.numpy_to_vtkIdTypeArray(np.ascontiguousarray(h.ravel()), deep=True))
    grid.SetCells(VTK_HEXAHEDRON if per == 8 else VTK_TRIANGLE, cells)
    return grid


def write_vtu(vertices_lps: np.ndarray, hexes: np.ndarray, path: str) -> None:
    """Write a model (hexahedra or triangles; vertices in LPS mm, as Slicer's model files default to) to a .vtu file."""
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter  # the submodule alone: `import vtk` costs 0.7 s

    from .io import atomic_write_bytes

    writer = vtkXMLUnstructuredGridWriter()
    writer.SetInputData(model_to_vtk(vertices_lps, hexes))
    writer.SetDataModeToBinary()  # base64 inline: the document is text
    # written in memory, then to the file by Python: VTK's own file writer crashes the process on a full disk
    writer.WriteToOutputStringOn()
    if not writer.Write():
        raise OSError(f"could not write {path}")
    atomic_write_bytes(path, writer.GetOutputString().encode("ascii"))
