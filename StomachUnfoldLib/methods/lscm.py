"""Least Squares Conformal Maps (Levy et al. 2002) of the inner lumen surface, cut open along the incision.

The surface (iso-surface of the CT around the lumen, trimmed at the centreline's end planes) is cut along the
incision into a disc and flattened, then rasterised and sampled along the surface normal
(``StomachUnfoldLib.surface``). By default the LSCM energy is minimised with the cardia and pylorus openings on
two parallel lines and the seam glued periodically (the tube's conformal rectangle, as conformal colon
flattening does); ``lscm_boundary="two_pins"`` is Levy's free boundary with two pinned seam vertices, which on a
long tube drifts toward an exponential-like map (extra area distortion), and ``"spectral"`` the pin-free form of
Mullen et al. 2008. Expected behaviour: angles are kept (conformal) and there is no overlap unless the mesh is
bad, but area is distorted where the radius changes (a wide fundus shrinks, a narrow antrum grows) and folds of
the surface are flattened with their geometry, not opened.
"""
from __future__ import annotations

import numpy as np

from ..correspondence import MapCorrespondence
from ..errors import AnatomyError
from ..frontend import timed_stage
from ..surface import (cut_surface, lscm, orient_and_scale, sample_flat_map, spectral_conformal,
                       tube_conformal)
from . import Method, Unfolding, register

__all__ = ["LSCMFlattening", "conformal_map", "MAX_MESH_VERTICES"]

MAX_MESH_VERTICES = 20000


def conformal_map(cut, boundary: str = "tube", warnings: list | None = None) -> np.ndarray:
    """LSCM flat map (V,2, unscaled) of a CutSurface with the given boundary form (tube, two_pins, spectral).

    The tube form needs both openings; where the end planes leave one closed (a point clicked off the opening, its
    plane behind no wall) the spectral form is used instead and ``warnings`` (a list) is told so."""
    v, f, near, is_copy, end_flag = cut.v, cut.f, cut.near, cut.is_copy, cut.end_flag
    seam = np.flatnonzero(is_copy)
    pa, pb = seam[np.argmin(near[seam])], seam[np.argmax(near[seam])]
    if pa == pb:
        raise AnatomyError("the seam of the cut surface is too short to pin the conformal map")
    if boundary == "tube":
        if (end_flag == 1).any() and (end_flag == 2).any():
            return tube_conformal(v, f, cut.partner, end_flag, pin=pa)
        if warnings is not None:
            warnings.append("the lumen surface has no opening at the cardia or pylorus end after trimming: flattened "
                            "with a free boundary (spectral conformal map) instead of the tube's; check the points")
        boundary = "spectral"
    if boundary == "spectral":
        return spectral_conformal(v, f, np.unique(cut.boundary_edges))
    return lscm(v, f, np.array([pa, pb]), np.array([[0.0, 0.0], [float(np.linalg.norm(v[pb] - v[pa])), 0.0]]))


@register
class LSCMFlattening(Method):
    """LSCM flattening of the cut-open inner wall surface (LPS mm in, unfolded Volume in mm)."""

    name = "lscm"
    description = "least squares conformal map of the cut-open inner wall (a peer: conformal flattening)"

    def unfold(self, prep, progress) -> Unfolding:
        """Cut the inner wall open along the incision, flatten it conformally, sample the CT along the normals."""
        warnings, seconds = [], {}
        with timed_stage(progress, "surface", seconds, 0.0, 0.25):
            cut = cut_surface(prep, MAX_MESH_VERTICES, warnings)
        with timed_stage(progress, "conformal map", seconds, 0.25, 0.5):
            uv = conformal_map(cut, prep.params.lscm_boundary, warnings)
            uv, flipped, area = orient_and_scale(uv, cut, prep.pixel_mm)
        with timed_stage(progress, "volume", seconds, 0.5, 1.0) as report:
            vol, fwd, inv, mesh, info = sample_flat_map(prep, cut, uv, report)
        section = {**cut.info, **info, "boundary_form": prep.params.lscm_boundary, "surface_area_mm2": area,
                   "flipped_triangle_fraction": flipped}
        return Unfolding(vol, MapCorrespondence(fwd, inv), mesh, section, warnings, seconds)
