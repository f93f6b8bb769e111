"""The paper's method (Oda et al.): hexahedral mass-spring-damper wall model pulled open by unfolding forces.

Stages: wall model (``wall_model``) -> unfolded plane, base line and destination points (``unfolding_force``)
-> Newmark-beta integration to the kappa stop (``newmark``) -> unfolded volume from the pre/post-deformation
correspondence (``unfolded_volume``, ``correspondence``).

Two registered forms: ``massspring`` adds guided destinations and a flattening pull during a ramp (our default
forces, ``solver.ramp_iterations`` and ``solver.flattening_stiffness``), ``paper`` uses the paper's forces alone
(fixed destinations g from the start, no flattening pull, the paper's weaker pull ``PAPER_FORCES``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..frontend import timed_stage
from . import Mesh, Method, Unfolding, register

__all__ = ["MassSpring", "PaperMassSpring", "PAPER_FORCES", "narrow_lumen_warning"]

#: The paper's forces: no guided destinations, no flattening pull, the pull of our first version.
PAPER_FORCES = {"ramp_iterations": 0, "flattening_stiffness": 0.0, "unfolding_stiffness": 0.5}


@register
class MassSpring(Method):
    """Hexahedral mass-spring-damper model, guided unfolding forces, Newmark-beta, kappa stop (LPS mm)."""

    name = "massspring"
    description = "the paper's mass-spring wall model with guided unfolding forces (our forces)"
    stages = (("wall model", 0.0, 0.1), ("unfolding forces", 0.1, 0.15), ("simulation", 0.15, 0.7),
              ("unfolded volume", 0.7, 0.97), ("correspondence", 0.97, 1.0))

    def solver_parameters(self, params):
        """The solver group this form runs with."""
        return params.solver

    def unfold(self, prep, progress) -> Unfolding:
        """Build the wall model of the prepared stomach, pull it open, and resample the CT into the view."""
        from ..correspondence import Correspondence
        from ..incision_line import incision_surface_points
        from ..newmark import simulate
        from ..unfolded_volume import build_unfolded_volume, make_grid
        from ..unfolding_force import unfolding_targets, wall_depth
        from ..wall_model import build_wall_model, inner_surface_triangles

        params, crop, cl, inc = prep.params, prep.crop, prep.centerline, prep.incision
        span = {name: (lo, hi) for name, lo, hi in self.stages}
        seconds, warnings = {}, []
        d = params.grid_voxels(prep.ct.spacing)
        cell = prep.cell_mm
        narrow = narrow_lumen_warning(cl.radius_mm, cell)
        if narrow:
            warnings.append(narrow)
        with timed_stage(progress, "wall model", seconds, *span["wall model"]):
            cut = incision_surface_points(inc, cl, depth_mm=params.wall_thickness_mm + 2.0 * cell.max(),
                                          inside_mm=cell.max(), sample_mm=0.3 * cell.min(), extend_mm=cell.max())
            openings = [(cl.points_lps[0], -cl.tangents[0]), (cl.points_lps[-1], cl.tangents[-1])]
            model = build_wall_model(crop, prep.wall, prep.lumen, d=d, cut_points_lps=cut, openings=openings,
                                     centerline_lps=cl.points_lps)
        with timed_stage(progress, "unfolding forces", seconds, *span["unfolding forces"]) as report:
            depth = wall_depth(model.vertices, prep.lumen, crop, progress=lambda f: report(0.9 * f))
            targets = unfolding_targets(model, inc, cl, depth=depth)
        solver = self.solver_parameters(params)
        with timed_stage(progress, "simulation", seconds, *span["simulation"]) as report:
            sim = simulate(model, targets, solver, progress=report)
        warnings += sim.warnings
        with timed_stage(progress, "unfolded volume", seconds, *span["unfolded volume"]) as report:
            out_sp = prep.pixel_mm
            grid = make_grid(sim.positions, targets.frame, np.full(3, out_sp), margin_mm=2.0)
            clear = prep.lumen if (prep.lumen_is_mask and params.clear_lumen) else None
            unfolded, info_vol = build_unfolded_volume(crop, model.vertices, sim.positions, model.hexes, grid,
                                                       background=-1024.0, clear_mask=clear, progress=report)
        if info_vol.get("outside_ct_voxels", 0) > 0:
            warnings.append(f"{info_vol['outside_ct_voxels']} voxels of the unfolded volume map outside the CT "
                            "crop; they show the background")
        with timed_stage(progress, "correspondence", seconds, *span["correspondence"]):
            corr = Correspondence(model.vertices, sim.positions, model.hexes, view_axis=grid.axes[:, 2])
        mesh = Mesh(model.vertices, sim.positions, model.hexes, "hexahedron", inner_surface_triangles(model))
        report = {
            "model": {**model.summary(), "grid_size_d": d, "cell_mm": cell.tolist(),
                      "wall_voxels": int(np.count_nonzero(prep.wall))},
            "unfolding": {"plane_normal_lps": targets.n.tolist(), "plane_point_lps": targets.b.tolist(),
                          "base_line_direction_lps": targets.v1.tolist(),
                          "pulled_vertices": int(len(targets.vertex_ids)),
                          "epsilon_mm": {"min": float(targets.epsilon.min()), "max": float(targets.epsilon.max())}},
            "simulation": {"iterations": int(sim.iterations), "converged": bool(sim.converged),
                           "reason": sim.reason, "time_step": sim.time_step, "retries": sim.retries,
                           "D_final_mm": sim.d_trace[-1], "D_trace": sim.d_trace,
                           "forces": {k: getattr(solver, k) for k in PAPER_FORCES}},
            "unfolded_volume_info": {k: v for k, v in info_vol.items() if np.isscalar(v)},
        }
        seconds["simulation"] = sim.seconds
        return Unfolding(unfolded, corr, mesh, report, warnings, seconds)


@register
class PaperMassSpring(MassSpring):
    """The paper's forces alone: fixed destinations, no flattening pull (a reproducible row for Table 1)."""

    name = "paper"
    description = "the paper's mass-spring method with the paper's forces alone (fixed destinations, no ramp)"

    def solver_parameters(self, params):
        """The user's solver group with the paper's forces (PAPER_FORCES) put in."""
        return dataclasses.replace(params.solver, **PAPER_FORCES)


def narrow_lumen_warning(radius_mm, cell_mm) -> str | None:
    """The warning for a lumen (centreline radii, mm) narrower than 1.5 cells (cell size mm), or None.

    The centreline's two end points sit in the cardia and pylorus openings, whose radius says nothing of the lumen
    between them: they are left out.
    """
    r = np.asarray(radius_mm, float)
    r = r[1:-1] if len(r) > 2 else r
    cell = float(np.max(np.asarray(cell_mm, float)[:2]))
    if not len(r) or float(np.min(r)) >= 1.5 * cell / 2:
        return None
    return (f"the lumen is as narrow as {np.min(r):.1f} mm radius, close to the cell size {cell:.1f} mm; a smaller "
            f"--grid-mm (e.g. --grid-mm {max(0.5, 0.5 * float(np.min(r))):.1f}) gives a finer model")
