"""Volumes with their geometry, and the coordinate frames used across the library.

Conventions (used by every module of the library):

* Arrays are indexed ``array[k, j, i]`` exactly as ``SimpleITK.GetArrayFromImage`` returns them.
* Point arrays are ``(N, 3)`` float arrays in ``(x, y, z)`` order.
* The library's internal physical frame is **LPS** in mm (the ITK/DICOM patient frame). Slicer
  and the command line speak **RAS** mm; convert at the boundary with :func:`ras_to_lps` and
  :func:`lps_to_ras` (the conversion is its own inverse: negate x and y).
* Continuous voxel indices are ``(i, j, k)`` float arrays (same order as ITK indices); voxel
  centres sit at integer indices.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .volume_file import FileArray

__all__ = ["Volume", "ras_to_lps", "lps_to_ras", "onto_edge_voxels"]


def ras_to_lps(points):
    """Convert points from RAS mm (Slicer) to LPS mm (ITK) by negating x and y; returns float64 (N,3) or (3,)."""
    p = np.array(points, dtype=float, copy=True)
    p[..., 0] *= -1.0
    p[..., 1] *= -1.0
    return p


def lps_to_ras(points):
    """Convert points from LPS mm (ITK) to RAS mm (Slicer) by negating x and y; returns float64 (N,3) or (3,)."""
    return ras_to_lps(points)


def onto_edge_voxels(coords, shape) -> np.ndarray:
    """Continuous voxel coordinates (rows per axis, in ``shape``'s axis order) with those in the outer half of an edge
    voxel moved onto its centre, so that they read that voxel; coordinates further out are left as they are."""
    coords = np.asarray(coords, float)
    top = np.asarray(shape, float)[:, None] - 1.0
    return np.where((coords >= -0.5) & (coords <= top + 0.5), np.clip(coords, 0.0, top), coords)


class _ImageBuffer:
    """Owner of a SimpleITK image exposing its pixel buffer read-only: numpy arrays made from it keep it alive."""

    def __init__(self, image):
        import SimpleITK as sitk

        self._image = image
        view = sitk.GetArrayViewFromImage(image)
        interface = dict(view.__array_interface__)
        interface["data"] = (interface["data"][0], True)  # read-only: the input CT is never modified
        self.__array_interface__ = interface


@dataclass
class Volume:
    """A 3D image with its geometry: ``array[k, j, i]``, spacing (mm, i/j/k order), LPS origin (mm), direction.

    ``array`` is an ndarray, or a ``volume_file.FileArray`` (a CT left on file, read box by box: ``crop``
    returns an ndarray-backed Volume).

    ``direction`` is a 3x3 matrix whose columns are the LPS unit vectors of the i, j and k axes
    (ITK's convention). The LPS position of continuous index ``(i, j, k)`` is
    ``origin + direction @ (spacing * (i, j, k))``.
    """

    array: np.ndarray
    spacing: np.ndarray = field(default_factory=lambda: np.ones(3))
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self):
        if not isinstance(self.array, FileArray):  # a CT left on file stays there, read box by box
            self.array = np.asarray(self.array)
        if self.array.ndim != 3:
            raise ValueError(f"a Volume needs a 3D array, got shape {self.array.shape}")
        self.spacing = np.asarray(self.spacing, dtype=float).reshape(3)
        self.origin = np.asarray(self.origin, dtype=float).reshape(3)
        self.direction = np.asarray(self.direction, dtype=float).reshape(3, 3)
        if np.any(self.spacing <= 0) or not np.all(np.isfinite(self.spacing)):
            raise ValueError(f"spacing must be positive and finite, got {self.spacing}")

    # ------------------------------------------------------------------ shape helpers
    @property
    def size(self) -> tuple[int, int, int]:
        """Number of voxels along i, j, k (ITK order)."""
        k, j, i = self.array.shape
        return (i, j, k)

    def with_array(self, array) -> "Volume":
        """Return a Volume with the same geometry and another array of the same shape."""
        array = np.asarray(array)
        if array.shape != self.array.shape:
            raise ValueError(f"shape {array.shape} differs from {self.array.shape}")
        return replace(self, array=array)

    # ------------------------------------------------------------------ frames
    @property
    def index_to_lps_matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix mapping continuous (i, j, k) index to LPS mm."""
        m = np.eye(4)
        m[:3, :3] = self.direction * self.spacing[None, :]
        m[:3, 3] = self.origin
        return m

    @property
    def index_to_ras_matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix mapping continuous (i, j, k) index to RAS mm (Slicer's IJKToRAS)."""
        flip = np.diag([-1.0, -1.0, 1.0, 1.0])
        return flip @ self.index_to_lps_matrix

    def index_to_lps(self, ijk) -> np.ndarray:
        """Map continuous voxel indices (N,3) in (i, j, k) order to LPS points in mm."""
        ijk = np.asarray(ijk, dtype=float)
        return ijk @ (self.direction * self.spacing[None, :]).T + self.origin

    def lps_to_index(self, lps) -> np.ndarray:
        """Map LPS points in mm (N,3) to continuous voxel indices in (i, j, k) order."""
        lps = np.asarray(lps, dtype=float)
        inv = np.linalg.inv(self.direction * self.spacing[None, :])
        return (lps - self.origin) @ inv.T

    def contains_lps(self, lps, margin: float = 0.5) -> np.ndarray:
        """True for LPS points (mm) whose continuous index lies inside the grid (margin in voxels)."""
        ijk = np.atleast_2d(self.lps_to_index(lps))
        hi = np.array(self.size, dtype=float) - 1 + margin
        return np.all((ijk >= -margin) & (ijk <= hi), axis=1)

    def voxel_lps(self, mask: np.ndarray) -> np.ndarray:
        """LPS centres (N,3, mm) of the voxels where ``mask[k, j, i]`` is true."""
        k, j, i = np.nonzero(mask)
        return self.index_to_lps(np.stack([i, j, k], axis=1))

    def bounds_lps(self) -> np.ndarray:
        """(2,3) array of the min and max LPS coordinates (mm) of the eight corner voxel centres."""
        s = np.array(self.size) - 1
        corners = np.array([[a, b, c] for a in (0, s[0]) for b in (0, s[1]) for c in (0, s[2])], float)
        p = self.index_to_lps(corners)
        return np.stack([p.min(0), p.max(0)])

    def crop(self, lo_ijk, hi_ijk) -> "Volume":
        """Sub-volume of voxels ``lo <= (i, j, k) < hi`` (indices clipped to the grid); geometry kept exact."""
        lo = np.clip(np.asarray(lo_ijk, int), 0, np.array(self.size))
        hi = np.clip(np.asarray(hi_ijk, int), lo, np.array(self.size))
        arr = self.array[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        return Volume(arr, self.spacing.copy(), self.index_to_lps(lo.astype(float)), self.direction.copy())

    def sample(self, lps, order: int = 1, cval: float = -1024.0) -> np.ndarray:
        """Interpolate the volume at LPS points (mm); trilinear by default, ``cval`` (HU) outside.

        A voxel spans half a voxel either side of its centre: a point in the outer half of an edge voxel takes that
        voxel's value (not ``cval``); beyond it the point is outside.
        """
        from scipy import ndimage

        lps = np.asarray(lps, dtype=float)
        ijk = self.lps_to_index(lps.reshape(-1, 3))
        coords = onto_edge_voxels(ijk[:, ::-1].T, self.array.shape)  # (k, j, i) rows for map_coordinates
        out = ndimage.map_coordinates(self.array, coords, order=order, mode="constant", cval=cval,
                                      output=np.float32, prefilter=False)
        return out.reshape(lps.shape[:-1])

    # ------------------------------------------------------------------ SimpleITK bridge
    @classmethod
    def from_sitk(cls, image, copy: bool = True) -> "Volume":
        """Build a Volume from a 3D SimpleITK image (geometry copied, LPS).

        With ``copy=False`` the array is a read-only view of the image's buffer that keeps the image alive: no
        second copy of a large CT (about 0.3 to 0.6 s and 260 MB for 512 x 512 x 500), and no way to modify it.
        """
        import SimpleITK as sitk

        if image.GetDimension() != 3:
            raise ValueError(f"expected a 3D image, got {image.GetDimension()}D")
        array = sitk.GetArrayFromImage(image) if copy else np.asarray(_ImageBuffer(image))
        return cls(array, np.array(image.GetSpacing()),
                   np.array(image.GetOrigin()), np.array(image.GetDirection()).reshape(3, 3))

    def to_sitk(self):
        """Return a SimpleITK image with this volume's array and geometry."""
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(self.array)
        img.SetSpacing([float(s) for s in self.spacing])
        img.SetOrigin([float(o) for o in self.origin])
        img.SetDirection([float(d) for d in self.direction.reshape(-1)])
        return img
