"""Where along the stomach a view keeps the mucosa's area: its area scale per stretch of the centreline.

The view's area over the mucosa's area (1: true size) of the mucosa nearest each of ``parts`` equal stretches of the
centreline, cardia first, from any method's Mesh (its ``surface`` triangles before and after unfolding). A lesion
in a stretch drawn at 0.5 shows at half its area. The pairwise marker distortion does not tell this: few marker
pairs have both ends in the pyloric canal.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Equal stretches of the centreline the area scale is summed over.
PARTS = 10


def area_scale_along(mesh, centerline_lps, parts: int = PARTS) -> list:
    """View area / mucosa area (1: true) of the Mesh's surface triangles nearest each of ``parts`` equal stretches of
    the centreline (LPS mm, cardia first), by the triangle's rest centroid (LPS mm); None for a stretch with none."""
    from StomachUnfoldLib.distortion import triangle_stretch

    tris = np.asarray(mesh.surface, np.int64)
    cl = np.asarray(centerline_lps, float)
    if not len(tris) or len(cl) < 2:
        return [None] * parts
    s1, s2, a0, ok = triangle_stretch(mesh.rest_lps, mesh.unfolded_lps, tris)
    centroid = np.asarray(mesh.rest_lps, float)[tris].mean(1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cl, axis=0), axis=1))])
    _, k = cKDTree(cl).query(centroid)
    part = np.minimum((arc[k] / max(arc[-1], 1e-9) * parts).astype(int), parts - 1)
    out = []
    for p in range(parts):
        m = ok & (part == p)
        out.append(float(np.sum(a0[m] * s1[m] * s2[m]) / np.sum(a0[m])) if m.any() else None)
    return out


def area_scale_summary(rows: list[dict]) -> list | None:
    """Per stretch, the median over the rows (bench rows with ``quality.area_scale_along``) of its area scale."""
    vals = [r["quality"]["area_scale_along"] for r in rows if r.get("ok") and r["quality"].get("area_scale_along")]
    if not vals:
        return None
    return [float(np.median([v[p] for v in vals if v[p] is not None])) if any(v[p] is not None for v in vals)
            else None for p in range(len(vals[0]))]
