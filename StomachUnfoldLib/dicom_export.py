"""DICOM export for PACS: the view as a secondary capture and the unfolded volume as a CT series (SimpleITK/GDCM).

Both join the source study when the input was a DICOM series: its patient and study identifiers are copied
(:data:`STUDY_TAGS`); each export gets new series and instance UIDs. Positions and orientation are LPS mm
(DICOM's patient frame). NRRD stays the default output; this is written only when asked (``--dicom``).
"""
from __future__ import annotations

import os
import time
import uuid

import numpy as np

from .geometry import Volume

__all__ = ["STUDY_TAGS", "new_uid", "source_study_tags", "write_ct_series", "write_secondary_capture"]

#: Patient and study tags copied from the source series (name, ID, birth date, sex; study UID, date, time, ID,
#: accession number, referring physician).
STUDY_TAGS = ("0010|0010", "0010|0020", "0010|0030", "0010|0040", "0020|000d", "0008|0020", "0008|0030",
              "0020|0010", "0008|0050", "0008|0090")
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
SECONDARY_CAPTURE = "1.2.840.10008.5.1.4.1.1.7"


def new_uid() -> str:
    """A new globally unique DICOM UID (the 2.25 UUID form)."""
    return f"2.25.{uuid.uuid4().int}"


def source_study_tags(path: str, series_uid: str | None = None) -> dict:
    """The patient and study tags of the DICOM series at ``path`` (a folder), or {} when the input is not DICOM."""
    import SimpleITK as sitk

    if not path or not os.path.isdir(path):
        return {}
    ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(path)
    if not ids:
        return {}
    files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(path, series_uid or ids[0])
    reader = sitk.ImageFileReader()
    reader.SetFileName(files[0])
    reader.LoadPrivateTagsOff()
    reader.ReadImageInformation()
    return {t: reader.GetMetaData(t).strip() for t in STUDY_TAGS if reader.HasMetaDataKey(t)}


def _common(study: dict, series_uid: str, description: str, modality: str, number: int) -> dict:
    """Tags every file of one exported series shares: the study's (or a new study), the series', the date."""
    now = time.gmtime()
    tags = {"0010|0010": "ANONYMOUS", "0010|0020": "UNKNOWN", "0020|000d": new_uid(),
            "0008|0020": time.strftime("%Y%m%d", now), "0008|0030": time.strftime("%H%M%S", now)}
    tags.update({k: v for k, v in study.items() if v})
    tags.update({"0020|000e": series_uid, "0008|103e": description[:64], "0008|0060": modality,
                 "0020|0011": str(number), "0008|0021": time.strftime("%Y%m%d", now),
                 "0008|0031": time.strftime("%H%M%S", now), "0008|0070": "StomachUnfold",
                 "0008|0008": "DERIVED\\SECONDARY"})
    return tags


def write_ct_series(volume: Volume, folder: str, study: dict | None = None,
                    description: str = "Stomach unfolded volume") -> list[str]:
    """Write the unfolded volume (HU) as a CT series, one file per k slice, into ``folder``; returns the paths.

    Geometry: each slice's position is the LPS (mm) of its voxel (0, 0, k), the orientation the i and j axes.
    """
    import SimpleITK as sitk

    os.makedirs(folder, exist_ok=True)
    a = np.clip(np.rint(volume.array), -1024, 3071).astype(np.int16)
    tags = _common(study or {}, new_uid(), description, "CT", 901)
    d = np.asarray(volume.direction, float)
    orient = "\\".join(f"{v:.6f}" for v in np.r_[d[:, 0], d[:, 1]])
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    frame = new_uid()
    paths = []
    for k in range(a.shape[0]):
        img = sitk.GetImageFromArray(a[k])
        img.SetSpacing([float(volume.spacing[0]), float(volume.spacing[1])])
        pos = volume.index_to_lps(np.array([[0.0, 0.0, float(k)]]))[0]
        slice_tags = {**tags, "0008|0016": CT_IMAGE_STORAGE, "0008|0018": new_uid(), "0020|0052": frame,
                      "0020|0013": str(k + 1), "0020|0032": "\\".join(f"{v:.4f}" for v in pos),
                      "0020|0037": orient, "0018|0050": f"{float(volume.spacing[2]):.4f}",
                      "0028|0030": f"{float(volume.spacing[1]):.4f}\\{float(volume.spacing[0]):.4f}",
                      "0028|1052": "0", "0028|1053": "1", "0028|1054": "HU"}
        for t, v in slice_tags.items():
            img.SetMetaData(t, v)
        path = os.path.join(folder, f"unfolded_{k + 1:04d}.dcm")
        writer.SetFileName(path)
        writer.Execute(img)
        paths.append(path)
    return paths


def write_secondary_capture(rgb: np.ndarray, path: str, study: dict | None = None,
                            description: str = "Stomach unfolded view") -> str:
    """Write an RGB uint8 picture (rows top to bottom, e.g. ``view.png``) as a DICOM secondary capture."""
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(np.ascontiguousarray(rgb[..., :3], dtype=np.uint8), isVector=True)
    tags = {**_common(study or {}, new_uid(), description, "OT", 902), "0008|0016": SECONDARY_CAPTURE,
            "0008|0018": new_uid(), "0008|0064": "WSD", "0020|0013": "1"}
    for t, v in tags.items():
        img.SetMetaData(t, v)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    writer.SetFileName(str(path))
    writer.Execute(img)
    return str(path)
