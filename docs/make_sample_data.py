"""Make the module's sample data once: a small J-shaped stomach phantom (int16, gzip NRRD) and its points.

Run from the repository root: ``.venv/bin/python docs/make_sample_data.py``. Writes
``StomachUnfold/Resources/SampleData/StomachPhantom.nrrd`` and ``StomachPhantomPoints.mrk.json``
(cardia and pylorus, LPS in the file as Slicer writes it). The phantom generator is not shipped with the
extension, so Slicer loads these files through Sample Data (``file://`` URIs) instead of generating them.
"""
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
OUT = os.path.join(ROOT, "StomachUnfold", "Resources", "SampleData")


def main(size="tiny"):
    """Write the phantom volume (HU, int16) and its cardia/pylorus points (LPS mm) into OUT; returns the paths."""
    sys.path.insert(0, ROOT)
    try:
        from StomachUnfoldEval.phantom import make_phantom
    except ImportError:  # before the split of issue 11
        from StomachUnfoldLib.phantom import make_phantom
    from StomachUnfoldLib.io import write_markups_fiducials, write_volume

    ct, truth = make_phantom("j", size)
    ct = ct.with_array(np.clip(np.rint(ct.array), -32768, 32767).astype(np.int16))
    os.makedirs(OUT, exist_ok=True)
    vol_path = write_volume(ct, os.path.join(OUT, "StomachPhantom.nrrd"))
    pts_path = write_markups_fiducials(os.path.join(OUT, "StomachPhantomPoints.mrk.json"),
                                       {"cardia": np.array(truth["cardia_lps"]),
                                        "pylorus": np.array(truth["pylorus_lps"])}, "StomachPhantomPoints")
    return vol_path, pts_path


if __name__ == "__main__":
    for p in main(*sys.argv[1:]):
        print(p, os.path.getsize(p), "bytes")
