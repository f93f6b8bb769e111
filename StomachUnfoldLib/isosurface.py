"""Isosurface of a scalar field on a voxel grid with VTK (flying edges), in place of skimage's marching cubes.

The mesh is returned in array index coordinates (k, j, i), the order of the array's axes, with triangles wound
as ``skimage.measure.marching_cubes`` winds them by default (``gradient_direction="descent"``): seen from the
side of the higher field values, the vertices of each triangle run counter-clockwise, so the right-hand normal
of a triangle points from the high side (the object) to the low side (the exterior).
"""
from __future__ import annotations

import numpy as np

__all__ = ["isosurface"]


def isosurface(field: np.ndarray, level: float, step: int = 1, sampled: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of ``field == level``: ``(verts (N, 3) float64 in (k, j, i) index units, faces (F, 3) int64)``.

    Parameters
    ----------
    field : (K, J, I) array
        Scalar field (converted to float32).
    level : float
        Iso value.
    step : int
        Sample every ``step``-th voxel along each axis (as skimage's ``step_size``): the vertex count falls
        about as ``step ** 2``; vertices stay in the full grid's index units.
    sampled : bool
        ``field`` already holds only every ``step``-th voxel of the grid (``grid[::step, ::step, ::step]``).

    Returns
    -------
    verts : (N, 3) float64 array
        Vertex positions, (k, j, i) index coordinates.
    faces : (F, 3) int64 array
        Triangles, consistently oriented with skimage's winding (see the module docstring); none is
        degenerate (coincident vertices are merged and zero-area triangles dropped). Empty arrays if the
        level is not crossed.
    """
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersCore import vtkCleanPolyData, vtkFlyingEdges3D

    step = int(step)
    if step < 1:
        raise ValueError(f"step must be a positive integer, got {step}")
    f = np.asarray(field)
    if f.ndim != 3:
        raise ValueError(f"field must be 3-D (k, j, i), got shape {f.shape}")
    sub = np.ascontiguousarray(f if sampled else f[::step, ::step, ::step], dtype=np.float32)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    if min(sub.shape) < 2 or not np.nanmin(sub) <= level <= np.nanmax(sub) or np.nanmin(sub) == np.nanmax(sub):
        return empty
    img = vtkImageData()
    img.SetDimensions(sub.shape[2], sub.shape[1], sub.shape[0])  # x = i, y = j, z = k
    img.SetSpacing(step, step, step)
    img.SetOrigin(0.0, 0.0, 0.0)
    scalars = numpy_to_vtk(sub.ravel(), deep=False)  # keep a reference while VTK reads it
    img.GetPointData().SetScalars(scalars)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, float(level))
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    clean = vtkCleanPolyData()  # merge coincident vertices (level hit exactly on a grid point); drop collapsed cells
    clean.SetInputConnection(fe.GetOutputPort())
    clean.PointMergingOn()
    clean.SetTolerance(0.0)
    clean.ConvertPolysToLinesOn()
    clean.ConvertLinesToPointsOn()
    clean.Update()
    poly = clean.GetOutput()
    if poly.GetNumberOfPoints() == 0 or poly.GetNumberOfPolys() == 0:
        return empty
    xyz = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    polys = poly.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    conn = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    if not np.all(np.diff(offsets) == 3):
        raise RuntimeError("flying edges returned non-triangle cells")
    faces = conn.reshape(-1, 3)
    # VTK winds its triangles with the right-hand normal along -grad in (x, y, z) = (i, j, k); reversing the
    # axes to (k, j, i) mirrors the space, which flips the winding to skimage's "descent" convention
    verts = xyz[:, ::-1].copy()
    # zero-area triangles (three distinct but collinear vertices)
    e = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    keep = np.einsum("ij,ij->i", e, e) > 0.0
    faces = faces[keep]
    used = np.zeros(len(verts), bool)
    used[faces.ravel()] = True
    if not used.all():
        remap = np.cumsum(used) - 1
        verts, faces = verts[used], remap[faces]
    return verts, faces.astype(np.int64)
