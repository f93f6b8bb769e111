"""The whole run, CT volume to unfolded volume: the shared front end, one method, the grade, the output files.

``unfold(ct, cardia_lps, pylorus_lps, params)`` runs :func:`~StomachUnfoldLib.frontend.prepare` (air region or
stomach mask -> crop -> centreline -> incision line; the wall region when the method asks for it), then the method
``params.method`` (``StomachUnfoldLib.methods``: ``isometric`` by default), then the quality grade.
``UnfoldResult.write(out_dir)`` writes the same files for every method: ``unfolded.nrrd``, ``report.json``,
``view.png``, ``distortion.nrrd`` and ``distortion.png`` (where lengths on the view can be trusted),
``model_rest.vtu``, ``model_unfolded.vtu``, ``incision.mrk.json`` and ``centerline.mrk.json`` (and
``landmarks_unfolded.mrk.json`` when landmarks are given).
"""
from __future__ import annotations

import os
import resource
import secrets
import shutil
import time
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np

from . import __version__
from .frontend import Prepared, check_model_memory, check_volume, prepare, timed_stage
from .geometry import Volume, lps_to_ras
from .methods import Mesh, get_method
from .params import DEFAULT_CELL_MM, UnfoldParameters
from .progress import Progress
from .report import Report
from .spare_core import Beside, signals_held
from .volume_file import FileArray

__all__ = ["UnfoldParameters", "UnfoldResult", "unfold", "STAGES", "OUTPUT_NAMES", "WALL_MODEL_METHODS", "signals_held",
           "stage_names", "DEFAULT_CELL_MM", "check_volume"]

#: The files a run writes into its output folder (landmarks_unfolded.mrk.json only with landmarks).
OUTPUT_NAMES = ("unfolded.nrrd", "report.json", "view.png", "distortion.nrrd", "distortion.png", "model_rest.vtu",
                "model_unfolded.vtu", "incision.mrk.json", "centerline.mrk.json", "landmarks_unfolded.mrk.json")

#: The methods that build the hexahedral wall model (its memory is estimated before it is built).
WALL_MODEL_METHODS = ("massspring", "paper")

#: The run's parts and their share of the progress bar.
STAGES = [("front end", 0.0, 0.24), ("method", 0.24, 0.93), ("quality", 0.93, 1.0)]


def stage_names(method: str) -> list[str]:
    """Every stage name a run of ``method`` reports to the progress callback, in order."""
    from .frontend import FRONT_STAGES

    return [n for n, _, _ in FRONT_STAGES] + [n for n, _, _ in get_method(method).stages] + ["quality"]


@dataclass
class UnfoldResult:
    """Everything a run produces: the unfolded volume (HU), report, correspondence, model, curves (LPS mm)."""

    unfolded: Volume
    report: Report
    correspondence: object
    mesh: Mesh
    centerline_lps: np.ndarray
    incision_lps: np.ndarray
    lumen_crop: Volume | None = field(default=None, repr=False)
    _distortion: object = field(default=None, repr=False)
    _orientation: dict | None = field(default=None, repr=False)

    def write(self, out_dir, landmarks_lps: dict | None = None, view_size: int | None = None,
              dicom_study: dict | None = None) -> dict:
        """Write the output files into ``out_dir`` all together or not at all; returns {name: path}.

        ``landmarks_lps``: named LPS points (mm) of the CT to map (and mark on the view); ``view_size``: width in
        pixels of each panel of ``view.png`` (default: the view's own width, at least 512); ``dicom_study``: when
        given (a dict, {} for a new study), also ``dicom/`` with the view as a secondary capture and the unfolded
        volume as a CT series carrying those patient/study tags (``dicom_export.source_study_tags``).
        OutputError (nothing written, no staging folder left) when the folder cannot take them (full, read-only).
        """
        from .errors import OutputError

        try:
            return self._write(out_dir, landmarks_lps, view_size, dicom_study)
        except OutputError:
            raise
        except OSError as e:  # a full disk, a read-only or vanished folder: nothing half-written is left
            what = e.strerror or str(e)
            raise OutputError(f"cannot write the outputs into {out_dir} ({what}); nothing was written: free some "
                              "space or choose another --output-dir") from None

    def _write(self, out_dir, landmarks_lps, view_size=None, dicom_study=None):
        """write() without the error translation: staged in a hidden folder inside ``out_dir``, then renamed."""
        from . import io as suio
        from .distortion import write_distortion
        from .figure import write_view
        from .view import shade_first_hit
        from .wall_model import write_vtu

        os.makedirs(out_dir, exist_ok=True)
        # named first and made inside the try: a signal right after the mkdir still finds it to remove
        tmp = os.path.join(out_dir, f".unfold-{secrets.token_hex(6)}")
        try:
            os.mkdir(tmp, 0o700)
            names = {}

            def path(name):
                names[name] = os.path.join(out_dir, name)
                return os.path.join(tmp, name)
            volume_p, rest_p, unfolded_p = path("unfolded.nrrd"), path("model_rest.vtu"), path("model_unfolded.vtu")

            def volume_and_models():  # beside the view's files: SimpleITK's and VTK's writers leave the lock free
                suio.write_volume(self.unfolded, volume_p)
                write_vtu(self.mesh.rest_lps, self.mesh.cells, rest_p)
                write_vtu(self.mesh.unfolded_lps, self.mesh.cells, unfolded_p)
            with Beside(volume_and_models, checked=False) as written:
                view = shade_first_hit(self.unfolded)  # shaded once, for the view and its distortion overlay
                mapped = self.map_landmarks(landmarks_lps) if landmarks_lps else {}
                self.report["view"] = write_view(self.unfolded, path("view.png"), view, self.distortion(),
                                                 self.orientation(), view_size, mapped,
                                                 (self.report["method"] or {}).get("hidden_folds"))
                write_distortion(self.unfolded, self.distortion(), path("distortion.nrrd"), path("distortion.png"),
                                 view)
                written.result()
            suio.write_markups_curve(path("incision.mrk.json"), self.incision_lps, "incision", color=(1.0, 0.3, 0.2))
            suio.write_markups_curve(path("centerline.mrk.json"), self.centerline_lps, "centerline",
                                     color=(0.2, 0.8, 1.0))
            if landmarks_lps:
                ok = {k: v for k, v in mapped.items() if np.all(np.isfinite(v))}
                self.report.landmarks = {k: {"original_lps": np.asarray(landmarks_lps[k]).tolist(),
                                             "unfolded_lps": (np.asarray(v).tolist() if k in ok else None)}
                                         for k, v in mapped.items()}
                suio.write_markups_fiducials(path("landmarks_unfolded.mrk.json"), ok, "landmarks_unfolded")
            if dicom_study is not None:
                self._write_dicom(path("dicom"), os.path.join(tmp, "view.png"), dicom_study)
            suio.atomic_write_text(path("report.json"), self.report.to_json())
            with signals_held():  # the renames happen all together: a signal waits until they are done
                for name, final in names.items():
                    if os.path.isdir(final):
                        shutil.rmtree(final)
                    os.replace(os.path.join(tmp, name), final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return names

    def _write_dicom(self, folder: str, view_png: str, study: dict) -> None:
        """``folder``/view.dcm (secondary capture of view.png) and ``folder``/unfolded/ (CT series), study tags kept."""
        import SimpleITK as sitk

        from .dicom_export import write_ct_series, write_secondary_capture

        os.makedirs(folder)
        write_secondary_capture(sitk.GetArrayFromImage(sitk.ReadImage(view_png)), os.path.join(folder, "view.dcm"),
                                study)
        write_ct_series(self.unfolded, os.path.join(folder, "unfolded"), study)
        self.report["dicom"] = {"folder": "dicom", "study_from_source": bool(study),
                                "patient_id": study.get("0010|0020"), "study_uid": study.get("0020|000d")}

    def distortion(self, progress=None):
        """The view's DistortionMap (area and length scale per pixel), computed once (``progress(fraction)``)."""
        if self._distortion is None:
            from .distortion import distortion_map

            self._distortion = distortion_map(self.unfolded, self.mesh, progress)
        return self._distortion

    def orientation(self) -> dict:
        """Which anatomy the view's edges and halves show (``figure.orientation``, measured on the model)."""
        from .figure import orientation

        if self._orientation is None:
            self._orientation = orientation(self.unfolded, self.mesh, self.centerline_lps, self.incision_lps,
                                            self.report.incision.get("side", "user"))
        return self._orientation

    def map_landmarks(self, points_lps: dict) -> dict:
        """Map named LPS points (mm) of the original CT into the unfolded volume's LPS frame (NaN if not on the wall)."""
        keys = list(points_lps)
        if not keys:
            return {}
        pts = np.array([points_lps[k] for k in keys], float)
        mapped = self.correspondence.to_unfolded(pts)
        return {k: mapped[i] for i, k in enumerate(keys)}


def run_info(prep: Prepared, method, unfolded: Volume) -> dict:
    """The report's ``run`` section: date (UTC), versions, platform, and the method and sizes actually used (mm)."""
    import datetime
    import platform

    import scipy
    import SimpleITK as sitk
    from vtkmodules.vtkCommonCore import vtkVersion

    ct = prep.ct
    return {"date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "method": method.name, "grid_size_voxels": int(prep.params.grid_voxels(ct.spacing)),
            "cell_mm": [float(v) for v in prep.cell_mm], "view_pixel_mm": [float(v) for v in unfolded.spacing[:2]],
            "versions": {"StomachUnfoldLib": __version__, "numpy": np.__version__, "scipy": scipy.__version__,
                         "SimpleITK": sitk.Version_VersionString(), "vtk": vtkVersion.GetVTKVersion(),
                         "python": platform.python_version()},
            "platform": platform.platform()}


def _report(prep: Prepared, method, out, seconds: dict) -> Report:
    """The common report of a run from the front end's and the method's outputs."""
    cl, inc, vol = prep.centerline, prep.incision, out.unfolded
    return Report(
        software={"name": "StomachUnfoldLib", "version": __version__},
        parameters=prep.params.to_dict(),
        method={"name": method.name, "description": method.description, **out.report},
        input=prep.input_summary(),
        points={"cardia_lps": prep.cardia_lps.tolist(), "pylorus_lps": prep.pylorus_lps.tolist(),
                "cardia_ras": lps_to_ras(prep.cardia_lps).tolist(), "pylorus_ras": lps_to_ras(prep.pylorus_lps).tolist()},
        air_region=prep.air_info,
        centerline={"points": int(len(cl.points_lps)), "length_mm": float(cl.length_mm),
                    "radius_mm": {"min": float(np.min(cl.radius_mm)), "median": float(np.median(cl.radius_mm)),
                                  "max": float(np.max(cl.radius_mm))}},
        incision={"side": inc.side, "points": int(len(inc.points_lps)), "length_mm": inc.length_mm},
        unfolded_volume={"size_ijk": list(vol.size), "spacing_mm": vol.spacing.tolist(),
                         "origin_lps": vol.origin.tolist(), "direction": vol.direction.tolist()},
        seconds=seconds, peak_memory_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        warnings=prep.warnings + list(out.warnings), extra={"run": run_info(prep, method, vol)})


def _cut_by_scan(ct: Volume, prep) -> tuple:
    """The CT's k slices ("first", "last") that the front end's lumen reaches: the stomach cut off by the scan."""
    edges = (("first", prep.crop_lo_ijk[2] == 0, 0), ("last", prep.crop_hi_ijk[2] == int(ct.size[2]), -1))
    return tuple(which for which, at_edge, sl in edges if at_edge and bool(np.any(prep.lumen[sl])))


def unfold(ct: Volume, cardia_lps, pylorus_lps, params: UnfoldParameters | None = None,
           mask: np.ndarray | None = None, incision_curve_lps=None, progress=None) -> UnfoldResult:
    """Unfold the stomach of CT ``ct`` (HU) between the cardia and pylorus points (LPS mm); returns UnfoldResult.

    ``mask`` is an optional bool stomach label on ct's grid that replaces the air threshold (for a stomach
    without gas); ``incision_curve_lps`` an optional user incision curve (LPS mm); ``progress`` a callable
    ``(stage, fraction)`` that may return False to cancel (raises Cancelled). The input is never modified.
    """
    params = params or UnfoldParameters()
    t_all = time.perf_counter()
    # a CT on file is scanned (zlib, outside the interpreter lock) while the parameters are checked and the methods'
    # modules load; the front end then finds the scan made (an invalid parameter stops the scan and is raised)
    on_file = mask is None and isinstance(getattr(ct, "array", None), FileArray)
    with (Beside(ct.array.scan, params.air_threshold_hu) if on_file else nullcontext()) as scan:
        params.validate()
        method = get_method(params.method)
        scan_s = scan.result() if on_file else 0.0
    prog = progress if isinstance(progress, Progress) else Progress(progress)
    span = {name: (lo, hi) for name, lo, hi in STAGES}
    prep = prepare(ct, cardia_lps, pylorus_lps, params, mask=mask, incision_curve_lps=incision_curve_lps,
                   progress=prog.sub("front end", *span["front end"]))
    if on_file:
        prep.seconds["reading"] += scan_s
    if method.name in WALL_MODEL_METHODS:
        check_model_memory(prep)
    from .quality import judge_mucosa_points, quality_metrics

    centerline_lps = np.asarray(prep.centerline.points_lps)
    # the grade's mucosa points depend only on the front end: drawn beside the method where a core is spare
    with (Beside(judge_mucosa_points, prep.lumen_crop, centerline_lps, checked=False) if params.quality
          else nullcontext()) as mucosa:
        out = method.unfold(prep, prog.sub("method", *span["method"]))
        seconds = {**prep.seconds, **out.seconds}
        result = UnfoldResult(unfolded=out.unfolded, report=_report(prep, method, out, seconds),
                              correspondence=out.correspondence, mesh=out.mesh, centerline_lps=centerline_lps,
                              incision_lps=np.asarray(prep.incision.points_lps), lumen_crop=prep.lumen_crop)
        if params.quality:
            with timed_stage(prog, "quality", seconds, *span["quality"]) as report:
                dmap = result.distortion(progress=lambda f: report(0.2 * f))
                folded = dmap.multiple if out.mesh.kind == "triangle" else None
                result.report.quality = quality_metrics(out.unfolded, out.correspondence, out.mesh, prep.lumen_crop,
                                                        centerline_lps, progress=lambda f: report(0.2 + 0.8 * f),
                                                        folded=folded, points_lps=mucosa.result(),
                                                        soft_level=(prep.air_info or {}).get("fluid_soft_level"))
                result.report.quality["distortion_map"] = dmap.summary()
    from .plausibility import gas_contact_fraction, hidden_fold_warnings, opening_warnings, plausibility_warnings

    orient = result.orientation() if params.quality else None

    def gas():  # what the view's holes touch: computed only when a hole part is there to explain (0.5 s full size)
        g = gas_contact_fraction(prep.crop, prep.lumen, params.air_threshold_hu)
        result.report.quality["lumen_gas_contact_fraction"] = g
        return g
    result.report.warnings += plausibility_warnings(
        ct, prep.cardia_lps, prep.pylorus_lps, (prep.air_info or {}).get("volume_ml"), result.report.quality,
        out.unfolded, orient, gas, _cut_by_scan(ct, prep))
    result.report.warnings += hidden_fold_warnings(out.report.get("hidden_folds") or [], out.unfolded, orient)
    result.report.warnings += opening_warnings(prep.lumen_crop, centerline_lps)
    seconds["total"] = time.perf_counter() - t_all
    return result
