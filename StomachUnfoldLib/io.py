"""Input and output: CT volumes (NRRD, NIfTI, MHA, DICOM folders), label volumes and Slicer markups files.

Every writer is atomic: it writes a temporary file in the target folder and renames it into place, so a
failed or cancelled write leaves no partial file. Markups files use Slicer's JSON schema with LPS
coordinates (Slicer's default for ``.mrk.json``); RAS files are read too.
"""
from __future__ import annotations

import json
import os
import tempfile

import numpy as np

from .errors import InputError, PointError
from .geometry import Volume, ras_to_lps

__all__ = ["read_volume", "write_volume", "atomic_write_text", "atomic_write_bytes", "read_markups_points",
           "cardia_pylorus_from_markups", "write_markups_curve", "write_markups_fiducials", "read_label_volume",
           "MARKUPS_SCHEMA"]

MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
                  "Schema/markups-schema-v1.0.3.json#")


def _atomic(path, write):
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    base = os.path.basename(path)
    # keep the full extension (e.g. .nii.gz) so that writers pick the right format
    ext = base[base.find("."):] if "." in base else ""
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=ext, dir=folder)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


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


def _check_image(img, source: str) -> None:
    dim = img.GetDimension()
    if dim != 3:
        raise InputError(f"{source} is a {dim}D image; a 3D CT volume is needed")
    if img.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"{source} has {img.GetNumberOfComponentsPerPixel()} components per voxel (a vector or "
                         "4D image); give a single 3D scalar CT volume")
    if min(img.GetSize()) < 4:
        raise InputError(f"{source} is only {img.GetSize()} voxels; at least 4 along each axis are needed")


def read_volume(path, series_uid: str | None = None) -> Volume:
    """Read a 3D CT volume (HU) from a NRRD/NIfTI/MHA file or a DICOM folder into a Volume (LPS geometry)."""
    import SimpleITK as sitk

    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"{path} does not exist")
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
            reader = sitk.ImageSeriesReader()
            reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(path, uid))
            img = reader.Execute()
        else:
            img = sitk.ReadImage(path)
    except RuntimeError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else "unknown error"
        raise InputError(f"cannot read {path}: {first}") from None
    _check_image(img, path)
    vol = Volume.from_sitk(img, copy=False)  # read-only view, no second copy of the CT
    if vol.array.dtype.kind not in "iuf":
        raise InputError(f"{path} does not hold numbers (dtype {vol.array.dtype})")
    return vol


def write_volume(volume: Volume, path) -> str:
    """Write a Volume through SimpleITK (compressed) atomically; the format follows the file extension."""
    import SimpleITK as sitk

    def w(tmp):
        sitk.WriteImage(volume.to_sitk(), tmp, useCompression=True)
    return _atomic(path, w)


def read_markups_points(path) -> dict[str, np.ndarray]:
    """All control points of a Slicer .mrk.json as {lower-case label: LPS point (mm)}."""
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError) as e:
        raise PointError(f"cannot read markups file {path}: {e}") from None
    out: dict[str, np.ndarray] = {}
    for m in data.get("markups", []):
        system = str(m.get("coordinateSystem", "LPS")).upper()
        for i, cp in enumerate(m.get("controlPoints", [])):
            if "position" not in cp:
                continue
            label = str(cp.get("label") or f"{m.get('name', 'point')}-{i + 1}").strip().lower()
            p = np.asarray(cp["position"], float)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise PointError(f"control point {label!r} in {path} has no valid position")
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
