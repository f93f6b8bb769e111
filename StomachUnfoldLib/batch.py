"""Cohorts: unfold many CTs listed in one manifest into one output folder, resumable, with one summary.

The manifest is a CSV file with a header and the columns ``case,input,points`` and optionally ``mask`` and
``mask_label``; ``points`` is a Slicer ``.mrk.json`` with control points labelled ``cardia`` and ``pylorus``
(LPS or RAS mm); any further column is a parameter override by its command-line name (``kappa``,
``grid-mm`` or ``grid_mm``, ``method`` ...), an empty cell keeping the default. Relative paths are relative
to the manifest's folder.

Each case writes the usual output files of :meth:`pipeline.UnfoldResult.write` into ``OUT/CASE/`` (into
``OUT/CASE/VALUE/`` for each value of a sweep), and beside them ``batch_case.json``: the sha256 of its input
files, its parameters and its summary row. A rerun skips a case whose record matches and whose outputs are
all there, and reruns it when an input or a parameter changed. ``OUT/summary.csv`` and ``OUT/summary.json``
are rewritten as cases finish; ``OUT/contact_sheet.png`` shows every view with its case name and grade; a
sweep adds ``OUT/table1.md``, the paper's Table 1 (good, overlapping, bending, broken per value).

:func:`run_batch` runs the cases one after the other here, or on any ``concurrent.futures`` executor
(the command line passes a Dask cluster's); a failing case is a row with its error and never stops the
cohort. This module needs no Dask: it only submits to the executor it is given.
"""
from __future__ import annotations

import concurrent.futures as cf
import csv
import hashlib
import io as _stdio
import json
import os
import re
import time

import numpy as np

from . import __version__
from .errors import InputError, StomachUnfoldError

__all__ = ["MANIFEST_COLUMNS", "RECORD_NAME", "SUMMARY_FIELDS", "OUTPUT_FILES", "read_manifest",
           "manifest_from_folder", "parse_sweep", "expand_cases", "file_sha256", "case_record", "completed_row",
           "run_case", "run_case_in_worker", "case_memory_bytes", "LIBRARIES_BYTES", "worker_plan", "WORKER_OVERHEAD_BYTES",
           "paper_categories", "table1", "table1_markdown", "write_summary", "contact_sheet", "run_batch"]

#: The manifest's own columns; every other column is a parameter override.
MANIFEST_COLUMNS = ("case", "input", "points", "mask", "mask_label")
#: A case's record (input checksums, parameters, its summary row), written last into its output folder.
RECORD_NAME = "batch_case.json"
#: The output files a complete case has (``UnfoldResult.write`` without landmarks).
OUTPUT_FILES = ("unfolded.nrrd", "report.json", "view.png", "distortion.nrrd", "distortion.png", "model_rest.vtu",
                "model_unfolded.vtu", "incision.mrk.json", "centerline.mrk.json")
#: Columns of summary.csv, one row per case and sweep value.
SUMMARY_FIELDS = ("case", "sweep", "status", "grade", "visible_fraction", "seconds", "error", "failure_parts",
                  "overlap_area_fraction", "hole_area_fraction", "bent_area_fraction", "broken_springs_fraction",
                  "inverted_fraction", "area_distortion", "angle_distortion", "trusted_fraction", "crop_voxels",
                  "peak_memory_mb", "method", "reused", "output", "worker")
#: Quality figures copied from report.json into a row.
_QUALITY_FIELDS = ("grade", "visible_fraction", "failure_parts", "overlap_area_fraction", "hole_area_fraction",
                   "bent_area_fraction", "broken_springs_fraction", "inverted_fraction", "area_distortion",
                   "angle_distortion", "bending_plane_rms_mm")


# ----------------------------------------------------------------------------------------- manifest
def _parse_value(spec, text: str):
    """A manifest cell or sweep value as the parameter's type (float, int, str, bool); InputError if not."""
    t = text.strip()
    if spec.kind is bool:
        if t.lower() in ("1", "true", "yes", "on"):
            return True
        if t.lower() in ("0", "false", "no", "off"):
            return False
        raise InputError(f"{spec.name} must be true or false, got {text!r}")
    try:
        if spec.kind is int:
            v = float(t)
            if v != int(v):
                raise ValueError
            return int(v)
        return spec.kind(t)
    except ValueError:
        raise InputError(f"{spec.name} must be a {spec.kind.__name__}, got {text!r}") from None


def _specs() -> dict:
    """Parameter specs by flat name and by command-line name (``grid_mm`` and ``grid-mm``)."""
    from .params import parameter_specs

    out = {}
    for s in parameter_specs():
        out[s.name] = out[s.name.replace("_", "-")] = s
    return out


def _check_case_name(name: str, where: str) -> str:
    name = name.strip()
    if not name or name in (".", "..") or any(c in name for c in "/\\\0"):
        raise InputError(f"{where}: the case name {name!r} must be a plain folder name (no slash, not empty)")
    return name


def read_manifest(path) -> list[dict]:
    """Cases of a CSV manifest: [{case, input, points, mask, mask_label, params}] with absolute paths.

    InputError (naming the line or column) for a missing file, a missing column, an unknown parameter column
    or a repeated case name. Parameter values are parsed by their type; a bad value fails that case only.
    """
    path = os.fspath(path)
    try:
        with open(path, newline="") as f:
            text = f.read()
    except OSError as e:
        raise InputError(f"cannot read the manifest {path}: {e.strerror or e}") from None
    reader = csv.DictReader(_stdio.StringIO(text))
    header = [h.strip() for h in (reader.fieldnames or [])]
    missing = [c for c in ("case", "input", "points") if c not in header]
    if missing:
        raise InputError(f"the manifest {path} has no column {', '.join(missing)}; its header must start "
                         "case,input,points (then optional mask,mask_label and parameter columns)")
    specs = _specs()
    unknown = [h for h in header if h not in MANIFEST_COLUMNS and h not in specs]
    if unknown:
        raise InputError(f"the manifest {path} has unknown column(s) {', '.join(unknown)}; further columns must be "
                         "parameters by their command-line names (e.g. kappa, grid-mm, method)")
    base = os.path.dirname(os.path.abspath(path))
    cases, seen = [], set()
    for n, raw in enumerate(reader, start=2):
        row = {(k or "").strip(): (v or "").strip() for k, v in raw.items()}
        if not any(row.values()):
            continue
        name = _check_case_name(row["case"], f"{path} line {n}")
        if name in seen:
            raise InputError(f"{path} line {n}: the case name {name!r} is used twice; case names name the output "
                             "folders")
        seen.add(name)
        case = {"case": name, "params": {}, "param_text": {}}
        for col in ("input", "points", "mask"):
            v = row.get(col, "")
            case[col] = os.path.normpath(os.path.join(base, v)) if v else None
        case["mask_label"] = row.get("mask_label") or None
        for h in header:
            if h in specs and row.get(h, "") != "":
                case["param_text"][specs[h].name] = row[h]
        cases.append(case)
    if not cases:
        raise InputError(f"the manifest {path} lists no case")
    return cases


def manifest_from_folder(folder, pattern_exts=(".nrrd", ".nii.gz", ".nii", ".mha")) -> list[dict]:
    """Cases from a folder: every CT file with a ``NAME.mrk.json`` beside it (cardia, pylorus), named NAME."""
    folder = os.path.abspath(os.fspath(folder))
    if not os.path.isdir(folder):
        raise InputError(f"{folder} is not a folder")
    cases = []
    for fn in sorted(os.listdir(folder)):
        ext = next((e for e in pattern_exts if fn.endswith(e)), None)
        if ext is None:
            continue
        name = fn[:-len(ext)]
        points = os.path.join(folder, name + ".mrk.json")
        if os.path.exists(points):
            cases.append({"case": name, "input": os.path.join(folder, fn), "points": points, "mask": None,
                          "mask_label": None, "params": {}, "param_text": {}})
    if not cases:
        raise InputError(f"{folder} holds no CT file (.nrrd, .nii.gz, .nii, .mha) with a NAME.mrk.json beside it")
    return cases


def parse_sweep(text: str | None) -> tuple[str, list[str]] | None:
    """``"kappa=0.2,0.5,1"`` -> ("kappa", ["0.2", "0.5", "1"]); None for None; InputError if malformed."""
    if not text:
        return None
    name, sep, values = text.partition("=")
    specs = _specs()
    if not sep or name.strip() not in specs:
        raise InputError(f"--sweep must be NAME=V1,V2,... with NAME a parameter (e.g. kappa=0.2,0.5,1.0), got {text!r}")
    vals = [v.strip() for v in values.split(",") if v.strip()]
    if not vals or len(set(vals)) != len(vals):
        raise InputError(f"--sweep {text!r} needs distinct values separated by commas")
    spec = specs[name.strip()]
    for v in vals:
        _parse_value(spec, v)
    return spec.name, vals


def expand_cases(cases: list[dict], out_dir, sweep: tuple[str, list[str]] | None = None,
                 base_params: dict | None = None) -> list[dict]:
    """One job per case and sweep value, with its output folder (OUT/CASE or OUT/CASE/VALUE) and parameter texts."""
    out_dir = os.path.abspath(os.fspath(out_dir))
    jobs = []
    for c in cases:
        for value in (sweep[1] if sweep else [None]):
            job = dict(c, params=dict(base_params or {}), param_text=dict(c.get("param_text", {})),
                       sweep=None if value is None else f"{sweep[0]}={value}")
            job["params"].update(c.get("params", {}))
            if value is not None:
                job["param_text"][sweep[0]] = value
            job["output"] = os.path.join(out_dir, c["case"], *(() if value is None else (value,)))
            job["folder"] = os.path.relpath(job["output"], out_dir)
            jobs.append(job)
    return jobs


# ----------------------------------------------------------------------------------------- records
def file_sha256(path) -> str:
    """sha256 (hex) of a file, or of a folder's files (names and contents, sorted) such as a DICOM series."""
    path = os.fspath(path)
    h = hashlib.sha256()
    if os.path.isdir(path):
        for root, dirs, files in os.walk(path):
            dirs.sort()
            for fn in sorted(files):
                p = os.path.join(root, fn)
                h.update(os.path.relpath(p, path).encode() + b"\0")
                h.update(file_sha256(p).encode())
        return h.hexdigest()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


_SHA_CACHE: dict = {}


def case_record(job: dict) -> dict:
    """What a case's outputs depend on: its input files (path, sha256), all its parameters, the software version.

    InputError naming the file when an input is missing, or naming the parameter when a value is out of range.
    """
    from .params import UnfoldParameters

    inputs = {}
    for role in ("input", "points", "mask"):
        p = job.get(role)
        if role != "mask" and not p:
            raise InputError(f"case {job['case']}: no {role} file given")
        if not p:
            continue
        if not os.path.exists(p):
            raise InputError(f"{p} does not exist (case {job['case']}, column {role})")
        st = os.stat(p)
        key = (p, st.st_mtime_ns, st.st_size)  # a file shared by cases (or sweep values) is read once
        if key not in _SHA_CACHE or os.path.isdir(p):  # a folder's own mtime misses edits to its files
            _SHA_CACHE[key] = file_sha256(p)
        inputs[role] = {"path": p, "sha256": _SHA_CACHE[key]}
    specs = _specs()
    flat = dict(job.get("params", {}))
    flat.update({k: _parse_value(specs[k], v) for k, v in job.get("param_text", {}).items()})
    params = UnfoldParameters(**flat)
    params.validate()
    label = job.get("mask_label")
    if label is not None:
        try:
            label = int(label)
        except ValueError:
            raise InputError(f"case {job['case']}: mask_label must be a whole number, got {label!r}") from None
    return {"inputs": inputs, "mask_label": label, "parameters": params.flat(),
            "software": {"name": "StomachUnfoldLib", "version": __version__}}


def _by_content(record):
    """A record with its input files named by content alone (sha256): a cohort folder moved elsewhere is reused."""
    if not isinstance(record, dict):
        return record
    inputs = {role: {k: v for k, v in entry.items() if k != "path"} for role, entry in record.get("inputs", {}).items()}
    return {**record, "inputs": inputs}


def completed_row(job: dict, record: dict) -> dict | None:
    """The recorded row of a case already done with this record (inputs, parameters) and all outputs, else None."""
    path = os.path.join(job["output"], RECORD_NAME)
    try:
        with open(path) as f:
            old = json.load(f)
    except (OSError, ValueError):
        return None
    row = old.get("row") or {}
    if _by_content(old.get("record")) != _by_content(json.loads(json.dumps(record))) or row.get("status") != "ok":
        return None
    if not all(os.path.exists(os.path.join(job["output"], n)) for n in OUTPUT_FILES):
        return None
    return dict(row, reused=True, output=job["folder"])


def _base_row(job: dict) -> dict:
    return {"case": job["case"], "sweep": job.get("sweep") or "", "status": "pending", "error": "",
            "output": job["folder"], "reused": False}


def _row_from_report(row: dict, rep, seconds: float) -> dict:
    q = rep["quality"] or {}
    row.update({k: q.get(k) for k in _QUALITY_FIELDS})
    row.update(status="ok", seconds=seconds, method=rep["method"]["name"], crop_voxels=rep["input"]["crop_voxels"],
               peak_memory_mb=rep["peak_memory_mb"],
               trusted_fraction=(q.get("distortion_map") or {}).get("trusted_fraction"), warnings=list(rep["warnings"]))
    return row


def run_case(job: dict, record: dict) -> dict:
    """Unfold one case (read, unfold, write its outputs and record) and return its summary row; never raises."""
    from .io import atomic_write_text, cardia_pylorus_from_markups, read_label_volume, read_volume
    from .params import UnfoldParameters
    from .pipeline import unfold

    import socket

    t0 = time.perf_counter()
    row = _base_row(job)
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"  # the process that ran it (host:pid)
    try:
        try:
            os.remove(os.path.join(job["output"], RECORD_NAME))  # a run cut short leaves no matching record
        except FileNotFoundError:
            pass
        ct = read_volume(record["inputs"]["input"]["path"], stream=True)  # read box by box: memory follows the crop
        cardia, pylorus = cardia_pylorus_from_markups(record["inputs"]["points"]["path"])
        mask = None
        if "mask" in record["inputs"]:
            mask = read_label_volume(record["inputs"]["mask"]["path"], ct, label_value=record["mask_label"])
        result = unfold(ct, cardia, pylorus, UnfoldParameters(**record["parameters"]), mask=mask)
        del ct, mask
        result.write(job["output"])
        _row_from_report(row, result.report, time.perf_counter() - t0)
    except StomachUnfoldError as e:
        row.update(status="error", error=f"{type(e).__name__}: {e}")
    except MemoryError:
        row.update(status="error", error="MemoryError: out of memory; crop the CT or give the workers more memory")
    except Exception as e:  # a bug or a broken file is a row too, so that the cohort finishes
        row.update(status="error", error=f"{type(e).__name__}: {e}")
    if row["status"] != "ok":
        row["seconds"] = time.perf_counter() - t0
    try:
        atomic_write_text(os.path.join(job["output"], RECORD_NAME),
                          json.dumps({"record": record, "row": row}, indent=1, default=_json_default))
    except OSError as e:
        row.update(status="error", error=f"cannot write {job['output']}: {e}")
    return row


def run_case_in_worker(job: dict, record: dict) -> dict:
    """:func:`run_case` in a worker process the batch owns: freed memory goes back to the system at once first, and
    nothing runs beside the run's main thread (``spare_core.SPARE_CORES``: the other workers have the other cores)."""
    from . import spare_core
    from .frontend import return_freed_memory

    return_freed_memory()
    spare_core.SPARE_CORES = False
    return run_case(job, record)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


#: Resident memory of a process that has imported what a run needs (NumPy, SciPy, SimpleITK, VTK): 269 MiB
#: measured (docs/benchmark, memory part), rounded up.
LIBRARIES_BYTES = 300 * 2**20


def case_memory_bytes(path, mask: bool = False) -> int:
    """Estimated peak resident memory (bytes) of one unfold of the CT at ``path``, from its header alone.

    The libraries and a working memory that grows with the stomach's crop, unknown before the run: at most
    the CT's own size for a file read box by box (measured: 0.57x on the 512 x 512 x 500 phantom, whose crop
    is large), plus the CT itself for a format read whole (a DICOM folder, compressed MetaImage). With a
    stomach mask the label volume resampled onto the CT grid adds the front end's whole-grid estimate.
    """
    import SimpleITK as sitk

    from .frontend import estimate_memory_bytes
    from .geometry import Volume
    from .volume_file import open_volume

    if os.path.isdir(path):
        files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(path)
        if not files:
            return 0
        r = sitk.ImageFileReader()
        r.SetFileName(files[0])
        r.ReadImageInformation()
        size = list(r.GetSize()[:2]) + [len(files)]
        nbytes = 2
    else:
        r = sitk.ImageFileReader()
        r.SetFileName(os.fspath(path))
        r.ReadImageInformation()
        size = list(r.GetSize())
        bits = sitk.GetPixelIDValueAsString(r.GetPixelID()).split("-")[0]  # "16-bit signed integer"
        nbytes = int(bits) // 8 if bits.isdigit() else 4
    try:
        streamed = not os.path.isdir(path) and open_volume(path) is not None  # reads the header only
    except StomachUnfoldError:
        streamed = False
    need = LIBRARIES_BYTES + (1 if streamed else 2) * nbytes * int(np.prod(size))
    if mask:
        stand_in = Volume(np.broadcast_to(np.int16(0), tuple(int(v) for v in size[::-1])))  # a zero stride: no memory
        need += estimate_memory_bytes(stand_in)
    return int(need)


#: A Dask worker's own resident memory (its libraries and bookkeeping), beyond the case it runs (bytes).
WORKER_OVERHEAD_BYTES = 256 * 2**20


def worker_plan(jobs: list[dict], workers: int | None = None, cores: int | None = None,
                available_bytes: int | None = None) -> tuple[int, int]:
    """(workers, memory limit per worker in bytes) for a local cluster: the largest case's estimate with 25 %
    headroom plus the worker's own memory; as many workers as the cores, the cases and 90 % of the free memory
    allow (``workers`` fixes their number, at most one per case)."""
    from .frontend import available_memory_bytes

    sizes = [case_memory_bytes(j["input"], mask=bool(j.get("mask"))) for j in jobs
             if j.get("input") and os.path.exists(j["input"])]
    limit = int(1.25 * max(sizes + [0]) + WORKER_OVERHEAD_BYTES)
    if workers:
        return max(1, min(int(workers), len(jobs))), limit
    avail = available_memory_bytes() if available_bytes is None else available_bytes
    n = min(cores or os.cpu_count() or 1, max(1, len(jobs)), max(1, int(0.9 * avail // limit)))
    return max(1, n), limit


# ----------------------------------------------------------------------------------------- summary
def paper_categories(quality: dict) -> dict:
    """The paper's Table 1 categories of one view (good, overlapping, bending, broken) from its quality metrics."""
    q = quality or {}
    return {"good": q.get("grade") in ("excellent", "good"),
            "overlapping": (q.get("overlap_area_fraction") or 0) > 0.005 or (q.get("inverted_fraction") or 0) > 0.05,
            "bending": (q.get("bent_area_fraction") or 0) > 0.01 or (q.get("bending_plane_rms_mm") or 0) > 5.0,
            "broken": (q.get("broken_springs_fraction") or 0) > 0.05 or (q.get("hole_area_fraction") or 0) > 0.005}


def table1(rows: list[dict]) -> dict:
    """Counts of the paper's categories per sweep value: {value: {good, overlapping, bending, broken, n, failed}}."""
    out = {}
    for r in rows:
        if not r.get("sweep"):
            continue
        c = out.setdefault(r["sweep"], {"good": 0, "overlapping": 0, "bending": 0, "broken": 0, "n": 0, "failed": 0})
        if r.get("status") != "ok":
            c["failed"] += r.get("status") == "error"
            continue
        c["n"] += 1
        for k, v in paper_categories(r).items():
            c[k] += int(v)
    return out


def table1_markdown(rows: list[dict]) -> str:
    """The paper's Table 1 for a sweep (counts of good, overlapping, bending and broken views per value)."""
    t = table1(rows)
    if not t:
        return ""
    vals = list(t)
    name = vals[0].split("=")[0]
    L = [f"# Table 1 for this cohort ({name} sweep, counts over cases)\n",
         f"| {name} | " + " | ".join(v.split("=", 1)[1] for v in vals) + " |", "|---|" + "---|" * len(vals)]
    for key in ("good", "overlapping", "bending", "broken", "n", "failed"):
        L.append(f"| {key} | " + " | ".join(str(t[v][key]) for v in vals) + " |")
    L.append("\ngood: grade excellent or good; overlapping: over 0.5 % of the view two layers deep or over 5 % of "
             "the elements inverted; bending: over 1 % of the area 10 mm off the plane or an RMS above 5 mm; broken: "
             "over 5 % of the springs stretched or over 0.5 % holes (the benchmark's definitions); n: cases that ran.")
    return "\n".join(L) + "\n"


def write_summary(out_dir, rows: list[dict]) -> None:
    """Write OUT/summary.csv (SUMMARY_FIELDS) and OUT/summary.json (rows and, for a sweep, Table 1) atomically."""
    from .io import atomic_write_text

    buf = _stdio.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_FIELDS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in SUMMARY_FIELDS})
    atomic_write_text(os.path.join(out_dir, "summary.csv"), buf.getvalue())
    counts = {s: sum(r.get("status") == s for r in rows) for s in ("ok", "error", "pending")}
    doc = {"software": {"name": "StomachUnfoldLib", "version": __version__}, "cases": len(rows), **counts,
           "reused": sum(bool(r.get("reused")) for r in rows), "rows": rows}
    t = table1(rows)
    if t:
        doc["table1"] = t
    atomic_write_text(os.path.join(out_dir, "summary.json"), json.dumps(doc, indent=1, default=_json_default))


def _read_png(path) -> np.ndarray:
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkIOImage import vtkPNGReader

    r = vtkPNGReader()
    r.SetFileName(path)
    r.Update()
    img = r.GetOutput()
    w, h, _ = img.GetDimensions()
    a = ns.vtk_to_numpy(img.GetPointData().GetScalars()).reshape(h, w, -1)
    return np.ascontiguousarray(a[::-1, :, :3])


def _text_image(text: str, size_pt: int = 13) -> np.ndarray:
    """The text rendered by VTK's FreeType renderer (no display needed) as an alpha mask (rows top to bottom)."""
    import vtkmodules.vtkRenderingFreeType  # noqa: F401  (registers the FreeType text renderer)
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkRenderingCore import vtkTextProperty, vtkTextRenderer

    tp = vtkTextProperty()
    tp.SetFontSize(size_pt)
    tp.SetColor(1.0, 1.0, 1.0)
    img = vtkImageData()
    if not vtkTextRenderer().RenderString(tp, text, img, [0, 0], 72):
        return np.zeros((1, 1))
    w, h, _ = img.GetDimensions()
    a = ns.vtk_to_numpy(img.GetPointData().GetScalars()).reshape(h, w, -1)
    return a[::-1, :, -1].astype(float) / 255.0


def _fit(img: np.ndarray, box: int) -> np.ndarray:
    """Shrink an RGB image to fit a box x box square (area average), never enlarging."""
    from scipy.ndimage import zoom

    f = min(1.0, box / max(img.shape[:2]))
    if f >= 1.0:
        return img
    return np.clip(zoom(img.astype(float), (f, f, 1), order=1), 0, 255).astype(np.uint8)


_GRADE_COLOURS = {"excellent": (90, 200, 90), "good": (170, 210, 80), "fair": (230, 170, 60), "bad": (230, 80, 60)}


def contact_sheet(rows: list[dict], path, tile: int = 220, columns: int | None = None) -> str:
    """Write a PNG of every case's view.png (``output`` relative to the PNG's folder) under its case name and grade
    (a failed case as a dark tile with its error); returns the path."""
    from .view import save_png

    root = os.path.dirname(os.path.abspath(path))
    n = max(1, len(rows))
    cols = columns or int(min(8, np.ceil(np.sqrt(n))))
    nrows = int(np.ceil(n / cols))
    label_h = 36
    sheet = np.full((nrows * (tile + label_h), cols * tile, 3), 24, np.uint8)
    for idx, r in enumerate(rows):
        y0, x0 = (idx // cols) * (tile + label_h), (idx % cols) * tile
        name = r["case"] + (f" {r['sweep']}" if r.get("sweep") else "")
        view = os.path.join(root, r.get("output", ""), "view.png")
        if r.get("status") == "ok" and os.path.exists(view):
            img = _fit(_read_png(view), tile - 4)
            h, w = img.shape[:2]
            oy, ox = y0 + label_h + (tile - h) // 2, x0 + (tile - w) // 2
            sheet[oy:oy + h, ox:ox + w] = img
            status, colour = str(r.get("grade")), _GRADE_COLOURS.get(str(r.get("grade")), (220, 220, 220))
            vis = r.get("visible_fraction")
            if vis is not None:
                status += f", {100 * float(vis):.1f}% visible"
            lines = [(name, (235, 235, 235)), (status, colour)]
        else:
            err = re.sub(r"/[^\s,:()']*/", "", str(r.get("error") or ""))  # file names without folders
            lines = [(name, (235, 235, 235)), (str(r.get("status", "?")), (230, 80, 60))]
            lines += [(err[k:k + 34], (200, 200, 200)) for k in range(0, min(len(err), 34 * 6), 34)]
        for line, (text, rgb) in enumerate(lines):
            m = _text_image(text[:40])[:label_h // 2, :tile - 6]
            ty, tx = y0 + 2 + line * (label_h // 2), x0 + 4
            region = sheet[ty:ty + m.shape[0], tx:tx + m.shape[1]].astype(float)
            region = region * (1 - m[..., None]) + np.array(rgb, float) * m[..., None]
            sheet[ty:ty + m.shape[0], tx:tx + m.shape[1]] = region.astype(np.uint8)
    return save_png(sheet, os.fspath(path), (1.0, 1.0), min_pixels=1)


# ----------------------------------------------------------------------------------------- the batch
def _killed(job: dict, e: BaseException) -> dict:
    """The row of a case whose worker died (killed for memory, crashed) or whose task failed outside run_case."""
    row = _base_row(job)
    kind = type(e).__name__
    why = "the worker running it died (killed for memory or crashed)" if kind == "KilledWorker" else "it failed"
    row.update(status="error", error=f"{kind}: {why}: {e}"[:500])
    return row


def run_batch(cases: list[dict], out_dir, sweep: tuple[str, list[str]] | None = None, executor=None,
              progress=None, base_params: dict | None = None, contact: bool = True) -> list[dict]:
    """Run every case (and sweep value) into ``out_dir``; returns the summary rows in manifest order.

    ``cases``: from :func:`read_manifest` or :func:`manifest_from_folder` (or a manifest path); ``sweep``: from
    :func:`parse_sweep`; ``executor``: a ``concurrent.futures.Executor`` (e.g. a Dask client's
    ``get_executor()``), or a callable ``make(jobs)`` returning one, called only when some case must run (with
    those jobs), or None to run here one after the other; ``progress(stage, fraction)``: called as cases
    finish; ``base_params``: parameters for every case (flat names), under the manifest's columns. Done cases
    whose record matches are reused; the summary files are rewritten after every case.
    """
    if isinstance(cases, (str, os.PathLike)):
        cases = read_manifest(cases)
    out_dir = os.path.abspath(os.fspath(out_dir))
    os.makedirs(out_dir, exist_ok=True)
    jobs = expand_cases(cases, out_dir, sweep, base_params)
    rows = [_base_row(j) for j in jobs]
    todo = []
    for i, job in enumerate(jobs):
        try:
            record = case_record(job)
        except StomachUnfoldError as e:
            rows[i].update(status="error", error=f"{type(e).__name__}: {e}", seconds=0.0)
            continue
        done = completed_row(job, record)
        if done is not None:
            rows[i] = done
        else:
            todo.append((i, job, record))
    count = {"done": len(jobs) - len(todo)}

    def finish(i, row):
        if i is not None:
            rows[i] = row
            count["done"] += 1
        write_summary(out_dir, rows)
        if progress is not None:
            label = row["case"] if row else f"({sum(bool(r.get('reused')) for r in rows)} reused)"
            progress(f"cases {count['done']}/{len(jobs)} {label}"[:60], count["done"] / max(1, len(jobs)))
    finish(None, None)
    if todo and executor is not None and not isinstance(executor, cf.Executor):
        executor = executor([job for _, job, _ in todo])
    if not todo or executor is None:
        for i, job, record in todo:
            finish(i, run_case(job, record))
    else:
        futures = {executor.submit(run_case_in_worker, job, record): (i, job) for i, job, record in todo}
        for fut in cf.as_completed(futures):
            i, job = futures[fut]
            try:
                row = fut.result()
            except Exception as e:  # the worker died or the task could not run: a row, not a stop
                row = _killed(job, e)
            finish(i, row)
    if contact:
        contact_sheet(rows, os.path.join(out_dir, "contact_sheet.png"))
    if sweep:
        from .io import atomic_write_text

        atomic_write_text(os.path.join(out_dir, "table1.md"), table1_markdown(rows))
    return rows
