"""Input and output: CT volumes (NRRD, NIfTI, MHA, DICOM folders), label volumes and Slicer markups files.

Every writer is atomic: it writes a temporary file in the target folder and renames it into place, so a
failed or cancelled write leaves no partial file. ``check_output_folder`` checks a folder before a run writes to it. Markups files use Slicer's JSON schema with LPS
coordinates (Slicer's default for ``.mrk.json``); RAS files are read too.
"""
from __future__ import annotations

import errno
import gzip
import json
import os
import re
import secrets
import shutil
import struct
import zlib

import numpy as np

from .errors import InputError, OutputError, PointError
from .geometry import Volume, ras_to_lps

__all__ = ["read_volume", "write_volume", "atomic_write_text", "atomic_write_bytes", "read_markups_points",
           "cardia_pylorus_from_markups", "write_markups_curve", "write_markups_fiducials", "read_label_volume",
           "MARKUPS_SCHEMA", "check_output_folder", "check_outputs_spare_inputs", "check_single_label",
           "label_volumes_ml", "estimate_output_bytes", "point3", "read_json", "MARKUPS_SYSTEMS",
           "itk_reason", "check_not_truncated", "check_dicom_slices", "check_image_information"]

MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
                  "Schema/markups-schema-v1.0.3.json#")


def _atomic(path, write):
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    base = os.path.basename(path)
    # keep the full extension (e.g. .nii.gz) so that writers pick the right format
    ext = base[base.find("."):] if "." in base else ""
    # named first, made by the writer inside the try: an interruption at any point leaves no temporary file
    tmp = os.path.join(folder, f".tmp-{secrets.token_hex(6)}{ext}")
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a written file gets the user's usual mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


def _umask() -> int:
    """The process's file-mode creation mask (read without changing it where /proc allows)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_text(path, text: str) -> str:
    """Write text to ``path`` through a temporary file and a rename (no partial file on failure)."""
    def w(tmp):
        with open(tmp, "w") as f:
            f.write(text)
    return _atomic(path, w)


def atomic_write_bytes(path, data: bytes) -> str:
    """Write bytes to ``path`` through a temporary file and a rename (no partial file on failure)."""
    def w(tmp):
        with open(tmp, "wb") as f:
            f.write(data)
    return _atomic(path, w)


def check_image_information(img, source: str) -> None:
    """InputError unless a SimpleITK image (or an ImageFileReader after ReadImageInformation) is one 3D scalar
    volume with at least 4 voxels along each axis."""
    dim = img.GetDimension()
    if dim != 3:
        raise InputError(f"{source} is a {dim}D image; a 3D CT volume is needed")
    comps = img.GetNumberOfComponentsPerPixel() if hasattr(img, "GetNumberOfComponentsPerPixel") else \
        img.GetNumberOfComponents()
    if comps != 1:
        raise InputError(f"{source} has {comps} components per voxel (a vector or "
                         "4D image); give a single 3D scalar CT volume")
    if min(img.GetSize()) < 4:
        raise InputError(f"{source} is only {img.GetSize()} voxels; at least 4 along each axis are needed")


def itk_reason(error) -> str:
    """ITK's own description of a read or write failure (its first and most specific lines), without its source-file
    locations and object addresses."""
    lines = []
    for line in str(error).splitlines():
        line = line.strip()
        if not line or line.startswith("Exception thrown in SimpleITK") or re.search(r"\.(cxx|h|hxx|txx):\d+:?$", line):
            continue
        line = re.sub(r"^(itk::ERROR|ITK ERROR):\s*(\w+\(0x[0-9a-fA-F]+\):\s*)?", "", line)
        line = re.sub(r"^\[\w+\]\s*", "", line).rstrip(":")
        if line and (not lines or "trouble" not in line):
            lines.append(line)
    text = "; ".join(dict.fromkeys(lines[:1] + lines[-1:])) or "unknown error"
    return text if len(text) <= 400 else text[:397] + "..."


def check_not_truncated(path) -> None:
    """Refuse a NIfTI file (.nii, .nii.gz) shorter than its header says (a cut download reads as zero-filled)."""
    path = os.fspath(path)
    low = path.lower()
    if not (low.endswith(".nii") or low.endswith(".nii.gz")):
        return
    opener = gzip.open if low.endswith(".gz") else open
    try:
        with opener(path, "rb") as f:
            head = f.read(352)
    except (OSError, EOFError, zlib.error) as e:
        raise InputError(f"cannot read {path}: {e}; the file is damaged, export it again") from None
    if len(head) < 348:
        raise InputError(f"{path} is truncated ({len(head)} bytes, shorter than a NIfTI header); export it again")
    for order in "<>":
        if struct.unpack(order + "i", head[:4])[0] == 348:
            break
    else:
        return  # not a NIfTI-1 header (NIfTI-2, or damaged): ITK reads or reports it
    dims = struct.unpack(order + "8h", head[40:56])
    bitpix = struct.unpack(order + "h", head[72:74])[0]
    offset = int(struct.unpack(order + "f", head[108:112])[0])
    n = int(np.prod([max(int(d), 1) for d in dims[1:1 + max(0, min(int(dims[0]), 7))]]))
    expected = max(offset, 352) + n * max(int(bitpix), 8) // 8
    if low.endswith(".gz"):
        with open(path, "rb") as f:  # the gzip trailer holds the uncompressed size (mod 2**32): cheap to read
            f.seek(-4, os.SEEK_END)
            isize = struct.unpack("<I", f.read(4))[0]
        if isize == expected % 2 ** 32:
            return
        have = 0
        try:
            with gzip.open(path, "rb") as f:
                while chunk := f.read(1 << 24):
                    have += len(chunk)
        except (OSError, EOFError, zlib.error):
            pass
    else:
        have = os.path.getsize(path)
    if have < expected:
        raise InputError(f"{path} is truncated: it holds {have} of the {expected} bytes its header announces "
                         f"({100.0 * have / expected:.0f} %); the download or copy was cut, export it again")


def check_dicom_slices(files, folder) -> None:
    """Refuse a DICOM series with a missing slice (a gap over 1.5 times the usual slice step), naming the gap (mm)."""
    import SimpleITK as sitk

    if len(files) < 3:
        return
    pos, normal = [], None
    reader = sitk.ImageFileReader()
    for name in files:
        reader.SetFileName(name)
        try:
            reader.ReadImageInformation()
            p = [float(v) for v in reader.GetMetaData("0020|0032").replace(" ", "").split("\\")]
            if normal is None:
                o = [float(v) for v in reader.GetMetaData("0020|0037").replace(" ", "").split("\\")]
                normal = np.cross(o[:3], o[3:6])
        except (RuntimeError, ValueError, IndexError):
            return  # no usable positions: ITK's reader decides
        pos.append(float(np.dot(p, normal)))
    order = np.argsort(pos)
    z = np.asarray(pos)[order]
    steps = np.diff(z)
    step = float(np.median(steps))
    if step <= 0:
        return
    gaps = np.flatnonzero(steps > 1.5 * step)
    if len(gaps):
        g = int(gaps[0])
        names = os.path.basename(files[order[g]]), os.path.basename(files[order[g + 1]])
        raise InputError(f"the DICOM series in {folder} has a gap: {steps[g]:.2f} mm between slices at "
                         f"{z[g]:.2f} and {z[g + 1]:.2f} mm ({names[0]} and {names[1]}), where the slices are "
                         f"{step:.2f} mm apart elsewhere ({len(gaps)} gap{'s' if len(gaps) > 1 else ''}); "
                         "a slice is missing: export the complete series")


def read_volume(path, series_uid: str | None = None, stream: bool = False) -> Volume:
    """Read a 3D CT volume (HU) from a NRRD/NIfTI/MHA file or a DICOM folder into a Volume (LPS geometry).

    With ``stream=True`` a file whose format can be read in boxes (``volume_file.open_volume``) is not read
    now: the Volume's array is a ``volume_file.FileArray`` that reads the parts looked at, so a run's memory
    grows with the stomach's crop, not with the CT. Other formats are read whole either way.
    """
    import SimpleITK as sitk

    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"{path} does not exist")
    if stream and not os.path.isdir(path):
        from .volume_file import open_volume

        check_not_truncated(path)
        vol = open_volume(path)
        if vol is not None:
            if vol.array.dtype.kind not in "iuf":
                raise InputError(f"{path} does not hold numbers (dtype {vol.array.dtype})")
            return vol
    try:
        if os.path.isdir(path):
            ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(path)
            if not ids:
                raise InputError(f"{path} holds no DICOM series")
            if series_uid is None and len(ids) > 1:
                listing = ", ".join(f"{u} ({len(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(path, u))} slices)"
                                    for u in ids)
                raise InputError(f"{path} holds {len(ids)} DICOM series: {listing}; choose one with --series-uid")
            uid = series_uid or ids[0]
            if uid not in ids:
                raise InputError(f"series {uid} is not in {path}; it holds {', '.join(ids)}")
            files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(path, uid)
            check_dicom_slices(files, path)
            reader = sitk.ImageSeriesReader()
            reader.SetFileNames(files)
            img = reader.Execute()
        else:
            check_not_truncated(path)
            img = sitk.ReadImage(path)
    except RuntimeError as e:
        raise InputError(f"cannot read {path}: {itk_reason(e)}; check that it is a complete NRRD, NIfTI, MHA file "
                         "or DICOM folder (export it again from the viewer or PACS)") from None
    check_image_information(img, path)
    vol = Volume.from_sitk(img, copy=False)  # read-only view, no second copy of the CT
    if vol.array.dtype.kind not in "iuf":
        raise InputError(f"{path} does not hold numbers (dtype {vol.array.dtype})")
    return vol


def write_volume(volume: Volume, path) -> str:
    """Write a Volume through SimpleITK (compressed) atomically; the format follows the file extension."""
    import SimpleITK as sitk

    def w(tmp):
        try:
            sitk.WriteImage(volume.to_sitk(), tmp, useCompression=True)
        except RuntimeError as e:  # ITK's writers raise RuntimeError, also on a full disk
            full = shutil.disk_usage(os.path.dirname(os.path.abspath(tmp))).free < 65536
            raise OSError(errno.ENOSPC if full else errno.EIO,
                          f"{'no space left on the device' if full else itk_reason(e)}", os.fspath(path)) from None
    return _atomic(path, w)


#: Slicer's markups coordinate systems (a file without one is LPS, Slicer's default for .mrk.json).
MARKUPS_SYSTEMS = ("LPS", "RAS")


def point3(value, what: str) -> np.ndarray:
    """Three finite numbers (mm) from a JSON value; PointError naming ``what`` otherwise (strings, nulls, 2 or 4 values)."""
    if isinstance(value, (str, bytes, dict, bool)) or value is None:
        raise PointError(f"{what} must be a list of three numbers (mm), got {json.dumps(value)[:60]}")
    try:
        p = np.array(value, float).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise PointError(f"{what} must be a list of three numbers (mm), got {json.dumps(value, default=str)[:60]}") \
            from None
    if p.shape != (3,) or not np.all(np.isfinite(p)) or any(isinstance(v, bool) for v in value):
        raise PointError(f"{what} must be three finite numbers (mm), got {json.dumps(value, default=str)[:60]}")
    return p


def read_json(path, what: str = "file"):
    """The parsed JSON of ``path``; PointError saying why when it cannot be read or parsed."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError, RecursionError) as e:
        raise PointError(f"cannot read {what} {path}: {e}") from None


def _markups_list(data, path):
    if not isinstance(data, dict) or not isinstance(data.get("markups", []), list):
        raise PointError(f"{path} is not a Slicer markups file: it needs an object with a list \"markups\" (save the "
                         "points from Slicer as .mrk.json)")
    for m in data.get("markups", []):
        if not isinstance(m, dict):
            raise PointError(f"{path}: every entry of \"markups\" must be an object, got {json.dumps(m)[:60]}")
        system = m.get("coordinateSystem", "LPS")
        if not isinstance(system, str) or system.upper() not in MARKUPS_SYSTEMS:
            raise PointError(f"{path} has coordinateSystem {json.dumps(system)[:40]}; only LPS and RAS (mm) can be "
                             "read: save the points from Slicer again")
        cps = m.get("controlPoints", [])
        if not isinstance(cps, list) or not all(isinstance(cp, dict) for cp in cps):
            raise PointError(f"{path}: \"controlPoints\" must be a list of objects, got {json.dumps(cps)[:60]}")
        yield m, system.upper(), cps


def read_markups_points(path) -> dict[str, np.ndarray]:
    """All placed control points of a Slicer .mrk.json as {lower-case label: LPS point (mm)}.

    PointError on a file of another structure, a coordinate system other than LPS/RAS, or a point whose
    ``positionStatus`` is not ``defined`` (not placed, or placement still in progress).
    """
    data = read_json(path, "markups file")
    out: dict[str, np.ndarray] = {}
    for m, system, cps in _markups_list(data, path):
        for i, cp in enumerate(cps):
            if "position" not in cp:
                continue
            raw = cp.get("label")
            label = str(raw if raw not in (None, "") else f"{m.get('name', 'point')}-{i + 1}").strip().lower()
            status = cp.get("positionStatus", "defined")
            if status != "defined":
                raise PointError(f"control point {label!r} in {path} is not placed (positionStatus "
                                 f"{json.dumps(status)[:30]}): place it in Slicer, or delete it")
            p = point3(cp["position"], f"control point {label!r} in {path}")
            if label in out:
                raise PointError(f"{path} has two control points labelled {label!r}; labels must be unique")
            out[label] = ras_to_lps(p) if system == "RAS" else p
    if not out:
        raise PointError(f"{path} holds no control points")
    return out


def cardia_pylorus_from_markups(path):
    """The control points labelled 'cardia' and 'pylorus' of a .mrk.json, as LPS points (mm)."""
    pts = read_markups_points(path)
    missing = [n for n in ("cardia", "pylorus") if n not in pts]
    if missing:
        raise PointError(f"{path} has no control point labelled {' or '.join(repr(m) for m in missing)}; found "
                         f"{', '.join(repr(k) for k in pts) or 'none'}; label the two points 'cardia' and 'pylorus'")
    return pts["cardia"], pts["pylorus"]


def _markups_json(kind: str, name: str, points: list[tuple[str, np.ndarray]], color) -> str:
    cps = [{"id": str(i + 1), "label": label, "description": "", "associatedNodeID": "",
            "position": [float(v) for v in p], "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
            "selected": True, "locked": False, "visibility": True, "positionStatus": "defined"}
           for i, (label, p) in enumerate(points)]
    markup = {"type": kind, "coordinateSystem": "LPS", "coordinateUnits": "mm", "locked": False,
              "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d", "lastUsedControlPointNumber": len(cps),
              "controlPoints": cps, "measurements": [],
              "display": {"visibility": True, "opacity": 1.0, "color": list(color), "selectedColor": list(color),
                          "propertiesLabelVisibility": kind != "Curve", "pointLabelsVisibility": kind != "Curve",
                          "textScale": 3.0, "glyphType": "Sphere3D", "glyphScale": 1.0, "glyphSize": 3.0,
                          "useGlyphScale": True, "lineThickness": 0.3, "lineColorFadingStart": 1.0,
                          "lineColorFadingEnd": 10.0, "lineColorFadingSaturation": 1.0,
                          "lineColorFadingHueOffset": 0.0, "handlesInteractive": False, "snapMode": "toVisibleSurface"}}
    if kind == "Curve":
        markup["curveType"] = "Linear"
    markup["name"] = name
    return json.dumps({"@schema": MARKUPS_SCHEMA, "markups": [markup]}, indent=2)


def write_markups_curve(path, points_lps, name: str, color=(1.0, 0.5, 0.0)) -> str:
    """Write an open Slicer markups curve of LPS points (mm) atomically."""
    pts = np.asarray(points_lps, float)
    return atomic_write_text(path, _markups_json("Curve", name, [(f"{name}-{i + 1}", p) for i, p in enumerate(pts)],
                                                 color))


def write_markups_fiducials(path, points: dict, name: str, color=(0.9, 0.9, 0.2)) -> str:
    """Write labelled LPS points (mm) {label: (3,)} as a Slicer point list (.mrk.json) atomically."""
    return atomic_write_text(path, _markups_json("Fiducial", name, [(str(k), np.asarray(v, float))
                                                                     for k, v in points.items()], color))


def read_label_volume(path_or_volume, reference: Volume, label_value: int | None = None) -> np.ndarray:
    """Read a label volume and resample it onto ``reference``'s grid (nearest neighbour, physical space) as a bool mask."""
    import SimpleITK as sitk

    lab = path_or_volume if isinstance(path_or_volume, Volume) else read_volume(path_or_volume)
    check_single_label(lab, label_value, "the mask" if isinstance(path_or_volume, Volume) else os.fspath(path_or_volume))
    img = lab.to_sitk()
    if img.GetPixelID() not in (sitk.sitkUInt8, sitk.sitkInt8, sitk.sitkUInt16, sitk.sitkInt16, sitk.sitkUInt32,
                                sitk.sitkInt32):
        img = sitk.Cast(sitk.Round(img) if hasattr(sitk, "Round") else img, sitk.sitkInt32)
    ref = reference.to_sitk() if reference.array.size < 2 else sitk.Image(list(reference.size), sitk.sitkUInt8)
    ref.SetSpacing([float(s) for s in reference.spacing])
    ref.SetOrigin([float(o) for o in reference.origin])
    ref.SetDirection([float(d) for d in reference.direction.ravel()])
    out = sitk.Resample(img, ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0, img.GetPixelID())
    arr = sitk.GetArrayFromImage(out)
    mask = arr == label_value if label_value is not None else arr > 0
    if not mask.any():
        which = f"label {label_value}" if label_value is not None else "any label"
        raise InputError(f"the label volume has no voxel of {which} on the CT grid: check --mask-label and that "
                         "the label volume overlaps the CT")
    return mask


def label_volumes_ml(labels: Volume) -> dict[int, float]:
    """The volume (mL) of every non-zero label of a label volume, {label: mL}, largest first."""
    arr = np.asarray(labels.array)
    values, counts = np.unique(arr[arr != 0], return_counts=True)
    ml = counts * float(np.prod(labels.spacing)) / 1000.0
    return {int(v): float(c) for v, c in sorted(zip(values.tolist(), ml.tolist()), key=lambda t: -t[1])}


def check_single_label(labels: Volume, label_value: int | None, source: str = "the mask") -> None:
    """Refuse a label volume of several labels when no label is chosen, listing the labels found and their mL.

    A multi-class segmentation (TotalSegmentator's 117 classes) taken whole would be unfolded as one 'stomach'.
    A caller that recognises the stomach's label itself passes it as ``label_value`` and is not refused.
    """
    if label_value is not None:
        return
    vols = label_volumes_ml(labels)
    if len(vols) <= 1:
        return
    shown = ", ".join(f"{v}: {ml:.1f} mL" for v, ml in list(vols.items())[:12])
    more = f" and {len(vols) - 12} more" if len(vols) > 12 else ""
    raise InputError(f"{source} holds {len(vols)} labels ({shown}{more}); choose the stomach's with --mask-label "
                     "(TotalSegmentator: 6), or in Slicer select its segment")


def estimate_output_bytes(ct: Volume) -> int:
    """A low estimate of the output files' size (bytes) for a CT, before the run: they grow with the stomach's surface."""
    return int(500_000 + 40.0 * float(np.prod(ct.size)) ** (2.0 / 3.0))


def _existing_parent(folder: str) -> str:
    parent = folder
    while not os.path.exists(parent):
        up = os.path.dirname(parent)
        if up == parent:
            break
        parent = up
    return parent


def check_output_folder(folder, need_bytes: int = 0) -> str:
    """Check, before any work, that ``folder`` can take the outputs; OutputError saying what to do otherwise.

    The folder (or the nearest existing folder above it, where it will be made) must be a writable folder on a
    real file system with at least ``need_bytes`` free. Nothing is left behind. Returns the absolute path.
    """
    if folder is None or not str(folder).strip():
        raise OutputError("the output folder is empty: give one with --output-dir FOLDER")
    folder = os.path.abspath(os.fspath(folder))
    real = os.path.realpath(folder)
    if real.split(os.sep)[1:2] in (["proc"], ["sys"], ["dev"]):
        raise OutputError(f"{folder} lies in the /{real.split(os.sep)[1]} file system, which holds no files: "
                          "choose another --output-dir")
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OutputError(f"{folder} is a file, not a folder: choose another --output-dir")
    parent = _existing_parent(folder)
    if not os.path.isdir(parent):
        raise OutputError(f"{parent} is a file, so the folder {folder} cannot be made: choose another --output-dir")
    try:
        probe = os.path.join(parent, f".unfold-probe-{secrets.token_hex(6)}")
        try:
            os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        finally:
            if os.path.exists(probe):
                os.remove(probe)
    except OSError as e:
        why = "read-only" if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM) else e.strerror
        raise OutputError(f"cannot write into {parent} ({why}): choose a writable --output-dir") from None
    free = shutil.disk_usage(parent).free
    if free < need_bytes:
        raise OutputError(f"only {free / 1e6:.1f} MB are free in {parent} and the outputs need about "
                          f"{need_bytes / 1e6:.1f} MB: free some space or choose another --output-dir")
    return folder


def check_outputs_spare_inputs(folder, output_names, inputs) -> None:
    """OutputError when writing ``output_names`` into ``folder`` would overwrite an input file, or the folder is an
    input DICOM folder (or lies inside one)."""
    folder = os.path.realpath(os.path.abspath(os.fspath(folder)))
    targets = {os.path.join(folder, n) for n in output_names}
    for given in inputs:
        if not given:
            continue
        real = os.path.realpath(os.fspath(given))
        if real in targets:
            raise OutputError(f"the output folder {folder} holds the input {given}, which the outputs would "
                              "overwrite: choose another --output-dir")
        if os.path.isdir(real) and (folder == real or folder.startswith(real + os.sep)):
            raise OutputError(f"the output folder {folder} is inside the input folder {given}: choose another "
                              "--output-dir")
