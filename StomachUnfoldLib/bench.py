"""``stomach-unfold bench``: unfold a set of phantoms, judge each from its unfolded volume, time every stage.

Writes ``results.json``, ``results.md`` and one view PNG per case into the output folder. Timings are
measurements of this machine for this run, never assertions: the test suite runs a tiny version and
checks the judging, not the seconds.
"""
from __future__ import annotations

import json
import os
import platform
import time

import numpy as np

from .errors import StomachUnfoldError

__all__ = ["BenchCase", "default_cases", "run_case", "run_benchmark"]


class BenchCase(dict):
    """One benchmark case: phantom keyword arguments plus unfold parameter overrides, with a name."""


def default_cases(quick: bool = False, full_size: bool = False) -> list[BenchCase]:
    """The phantom set: shapes and sizes of the benchmark (tiny ones when ``quick``)."""
    size = "tiny" if quick else "small"
    # cells of 5.6 mm: the paper's d = 8 voxels at 0.7 mm, whatever the phantom's spacing
    cell = {"grid_mm": 5.6}
    cases = [BenchCase(name=f"{shape}-{size}", phantom=dict(shape=shape, size=size),
                       params=dict(cell, wall_thickness_mm=3.0 if shape == "thin_wall" else 4.0))
             for shape in ("straight", "bent", "j", "twisted", "thin_wall")]
    cases.append(BenchCase(name=f"j-{size}-anisotropic", phantom=dict(shape="j", size=size,
                                                                     spacing=(1.2, 1.2, 2.5) if not quick
                                                                     else (1.8, 1.8, 3.0)), params=dict(cell)))
    cases.append(BenchCase(name=f"j-{size}-flipped", phantom=dict(shape="j", size=size, flip_direction=True),
                           params=dict(cell)))
    if not quick:
        cases.append(BenchCase(name="j-small-rugae", phantom=dict(shape="j", size="small", rugae=True),
                               params=dict(cell)))
    if full_size:
        # the paper's setting: d = 8 voxels at 0.7 mm
        cases.append(BenchCase(name="j-full-512x512x400", phantom=dict(shape="j", size="full"), params={}))
    return cases


def run_case(case: BenchCase, out_dir: str | None = None) -> dict:
    """Make the case's phantom, unfold it, judge the unfolded volume; failures become data, not crashes."""
    from .geometry import Volume  # noqa: F401
    from .phantom import make_phantom
    from .pipeline import UnfoldParameters, unfold
    from .quality import marker_report, overlap_fraction

    row = {"name": case["name"], "phantom": {k: (list(v) if isinstance(v, tuple) else v)
                                             for k, v in case["phantom"].items()},
           "params": case["params"]}
    t = time.perf_counter()
    ct, truth = make_phantom(**case["phantom"])
    row["phantom_seconds"] = time.perf_counter() - t
    row["size_ijk"] = list(ct.size)
    try:
        res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters(**case["params"]))
    except StomachUnfoldError as e:
        row.update(ok=False, error=f"{type(e).__name__}: {e}")
        return row
    markers = {m["id"]: m["lps"] for m in truth["markers"]}
    mapped = res.map_landmarks(markers)
    rep = marker_report(res.unfolded, mapped)
    row.update(ok=True, seconds=res.report["seconds"], iterations=res.report["iterations"],
               model=res.report["model"], peak_memory_mb=res.report["peak_memory_mb"],
               markers_seen=rep["n_seen"], markers_total=rep["n_total"], marker_regions=rep["n_regions"],
               overlap_fraction=overlap_fraction(res.unfolded), warnings=res.report["warnings"],
               D_final_mm=res.report["D_trace"][-1])
    if out_dir:
        from .view import render_view

        render_view(res.unfolded, os.path.join(out_dir, f"{case['name']}.png"))
    return row


def run_benchmark(out_dir: str = "docs/benchmark", quick: bool = False, full_size: bool = False) -> list[dict]:
    """Run every case, write results.json, results.md and per-case view PNGs into ``out_dir``."""
    os.makedirs(out_dir, exist_ok=True)
    rows = []
    for case in default_cases(quick, full_size):
        print(f"bench: {case['name']} ...", flush=True)
        row = run_case(case, out_dir)
        rows.append(row)
        if row["ok"]:
            print(f"  {row['seconds']['total']:.2f} s, {row['iterations']} it, markers {row['markers_seen']}/"
                  f"{row['markers_total']}, overlap {100 * row['overlap_fraction']:.2f} %", flush=True)
        else:
            print(f"  failed: {row['error']}", flush=True)
    meta = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump({"meta": meta, "cases": rows}, f, indent=2, default=lambda o: np.asarray(o).tolist())
    lines = ["| case | size (i,j,k) | total s | simulation s | iterations | hexahedra | markers seen | overlap % |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["ok"]:
            lines.append(f"| {r['name']} | {r['size_ijk']} | {r['seconds']['total']:.2f} | "
                         f"{r['seconds']['simulation']:.2f} | {r['iterations']} | {r['model']['hexahedra']} | "
                         f"{r['markers_seen']}/{r['markers_total']} | {100 * r['overlap_fraction']:.2f} |")
        else:
            lines.append(f"| {r['name']} | {r['size_ijk']} | failed: {r['error']} | | | | | |")
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(f"Benchmark run {meta['date']} on {meta['machine']['cpus']} CPUs ({meta['machine']['platform']}).\n\n")
        f.write("\n".join(lines) + "\n")
    return rows
