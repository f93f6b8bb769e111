"""The benchmark's ``memory`` part: peak resident memory of one unfold against the stomach's crop size.

Each CT is written to a file by one fresh process, then read, unfolded and written by another fresh process
whose maximum resident set (``ru_maxrss``) is the run's peak: the interpreter and libraries, the CT, and the
working memory. The chart ``memory.png`` puts each run's peak against its crop voxels, beside the CT's own
size and the target of twice the CT's size (issue 14: a cluster runs as many cases at once as memory allows).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile

__all__ = ["MEMORY_SOURCES", "library_baseline_mb", "memory_run", "memory_runs", "memory_plot", "memory_markdown"]

#: (name, phantom keywords): CTs of growing size, and at full size stomachs of growing size in the same CT.
MEMORY_SOURCES = (
    ("j-small", {"shape": "j", "size": "small"}),
    ("j-medium", {"shape": "j", "size": "medium"}),
    ("j-full500-r0.6", {"shape": "j", "size": "full", "full_slices": 500, "radius_scale": 0.6}),
    ("j-full500", {"shape": "j", "size": "full", "full_slices": 500}),
)


def _rss_mb(key: str = "VmHWM") -> float:
    """This process's resident (VmRSS) or peak resident (VmHWM) memory in MB, from /proc/self/status."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def library_baseline_mb() -> float:
    """Resident MB of this process after importing what a run imports (NumPy, SciPy, SimpleITK, VTK, the library);
    call it in a fresh process: the floor under every run's peak."""
    import importlib

    for name in ("numpy", "scipy.ndimage", "scipy.sparse.linalg", "scipy.sparse.csgraph", "scipy.spatial",
                 "SimpleITK", "vtkmodules.vtkCommonDataModel", "vtkmodules.vtkFiltersCore", "vtkmodules.vtkIOXML",
                 "vtkmodules.vtkIOImage", "StomachUnfoldLib.pipeline", "StomachUnfoldLib.quality",
                 "StomachUnfoldLib.distortion", "StomachUnfoldLib.methods.isometric",
                 "StomachUnfoldLib.methods.massspring", "StomachUnfoldLib.centerline"):
        importlib.import_module(name)
    return _rss_mb("VmRSS")


def _write_source(kw: dict, path: str) -> dict:
    from StomachUnfoldLib.io import write_volume

    from .phantom import make_phantom

    ct, truth = make_phantom(**kw)
    write_volume(ct, path)
    return {"cardia_lps": list(truth["cardia_lps"]), "pylorus_lps": list(truth["pylorus_lps"])}


def memory_run(path: str, truth: dict, method: str | None = None, stream: bool = True) -> dict:
    """Read, unfold and write the CT file ``path`` here; peak resident MB overall and at each stage (fresh process).

    ``stream``: leave the CT on file and read it box by box, as the command line does (False: read it whole).
    """
    import StomachUnfoldLib.pipeline  # noqa: F401  (the libraries a run imports, before the baseline is taken)
    from StomachUnfoldLib.frontend import return_freed_memory
    from StomachUnfoldLib.io import read_volume
    from StomachUnfoldLib.params import UnfoldParameters
    from StomachUnfoldLib.pipeline import unfold

    stages, seen = [], {"stage": None}

    def progress(stage, fraction):
        if stage != seen["stage"]:
            stages.append([stage, _rss_mb()])  # the peak so far when this stage starts
            seen["stage"] = stage
    return_freed_memory()  # as the command line and the batch workers do
    vol = read_volume(path, stream=stream)
    after_read = _rss_mb()
    params = UnfoldParameters() if method is None else UnfoldParameters(method=method)
    res = unfold(vol, truth["cardia_lps"], truth["pylorus_lps"], params, progress=progress)
    ct_mb = vol.array.nbytes / 2**20
    del vol
    out = tempfile.mkdtemp(prefix="su-mem-")
    try:
        before_write = _rss_mb()
        res.write(out)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    q = res.report["quality"] or {}
    return {"size_ijk": res.report["input"]["size_ijk"], "ct_mb": ct_mb, "after_read_mb": after_read, "peak_before_write_mb": before_write, "peak_memory_mb": _rss_mb(),
            "stage_peaks_mb": stages, "crop_voxels": res.report["input"]["crop_voxels"],
            "method": res.report["method"]["name"], "seconds": res.report["seconds"]["total"],
            "grade": q.get("grade"), "visible_fraction": q.get("visible_fraction")}


def memory_runs(sources=MEMORY_SOURCES, method: str | None = None, isolated=None) -> list[dict]:
    """One benchmark row (group ``memory``) per source: its CT written, then read, unfolded and written alone."""
    if isolated is None:
        from .bench import isolated_call as isolated
    tmp = tempfile.mkdtemp(prefix="su-mem-src-")
    rows = []
    baseline = isolated(library_baseline_mb)
    try:
        for name, kw in sources:
            path = os.path.join(tmp, name + ".nrrd")
            row = {"name": f"{name}/memory", "group": "memory", "method": method or "default", "params": {},
                   "source": kw}
            try:
                truth = isolated(_write_source, kw, path)
                row.update(ok=True, baseline_mb=baseline, **isolated(memory_run, path, truth, method))
                row["ratio_to_ct"] = row["peak_memory_mb"] / row["ct_mb"]
            except Exception as e:  # a failure is a row, so the benchmark finishes
                row.update(ok=False, error=f"{type(e).__name__}: {e}")
            rows.append(row)
            if os.path.exists(path):
                os.remove(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def memory_plot(rows: list[dict], out_dir: str, made: list[str], plt) -> None:
    """memory.png: peak resident memory (MiB) against crop voxels; twice the largest CT's size, the libraries, and
    the floor a CT read whole would set."""
    rs = [r for r in rows if r.get("group") == "memory" and r.get("ok")]
    if not rs:
        return
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    cts = sorted({round(r["ct_mb"], 1) for r in rs})
    colours = dict(zip(cts, ("tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:red")))
    for n, r in enumerate(sorted(rs, key=lambda r: r["crop_voxels"])):
        c = colours.get(round(r["ct_mb"], 1), "k")
        ax.scatter(r["crop_voxels"], r["peak_memory_mb"], color=c, s=40, zorder=3,
                   label=f"CT {'x'.join(str(v) for v in r['size_ijk'])} ({r['ct_mb']:.0f} MiB)")
        ax.annotate(f"{r['name'].split('/')[0]}: {r['peak_memory_mb']:.0f} MiB = {r['ratio_to_ct']:.1f}x its CT",
                    (r["crop_voxels"], r["peak_memory_mb"]), fontsize=7, textcoords="offset points",
                    ha="right" if n == len(rs) - 1 else "left",  # above and below in turn, the last above
                    xytext=(10 if n == len(rs) - 1 else -10, 8 if (len(rs) - 1 - n) % 2 == 0 else -14))
    big = cts[-1]
    base = min(r["baseline_mb"] for r in rs)
    lines = ((2 * big, "--", f"target: 2x the {big:.0f} MiB CT ({2 * big:.0f} MiB)"),
             (base + big, ":", f"libraries + that CT read whole ({base + big:.0f} MiB): the floor before box-by-box reading"),
             (base, "-", f"interpreter and libraries alone ({base:.0f} MiB)"))
    for y, ls, text in lines:
        ax.axhline(y, color="grey" if ls == "-" else colours[big], ls=ls, lw=1)
        ax.annotate(text, (0.01, y), xycoords=("axes fraction", "data"), fontsize=7, va="bottom",
                    color="grey" if ls == "-" else colours[big])
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    ax.legend(uniq.values(), uniq.keys(), fontsize=7, loc="lower right")
    ax.set_xscale("log")
    ax.set_xlim(min(r["crop_voxels"] for r in rs) / 1.6, max(r["crop_voxels"] for r in rs) * 1.6)
    ax.set_ylim(0, max(max(r["peak_memory_mb"] for r in rs), 2 * big) * 1.12)
    ax.set_xlabel("crop voxels (the stomach's box plus margin)")
    ax.set_ylabel("peak resident memory of one run, MiB (fresh process)")
    ax.set_title("Memory of one unfold (read, unfold, write) against the stomach's crop")
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "memory.png"), dpi=110)
    plt.close(fig)
    made.append("memory.png")


def memory_markdown(rows: list[dict]) -> list[str]:
    """The memory part's table: peak MB, the CT's MB, their ratio, crop voxels, and the peak at each stage."""
    rs = [r for r in rows if r.get("group") == "memory"]
    if not rs:
        return []
    L = ["## Memory: peak resident memory of one run against the crop (each run alone in a fresh process)\n",
         "| case | CT voxels | CT MiB | crop voxels | peak MiB | peak / CT | libraries alone MiB | after read MiB | "
         "peak before writing MiB | method | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rs:
        if not r.get("ok"):
            L.append(f"| {r['name']} | failed: {r.get('error', '')[:80]} | | | | | | | | | |")
            continue
        L.append(f"| {r['name']} | {'x'.join(str(v) for v in r['size_ijk'])} | {r['ct_mb']:.0f} | "
                 f"{r['crop_voxels']:,} | **{r['peak_memory_mb']:.0f}** | {r['ratio_to_ct']:.2f} | "
                 f"{r['baseline_mb']:.0f} | {r['after_read_mb']:.0f} | {r['peak_before_write_mb']:.0f} | "
                 f"{r['method']} | {r['seconds']:.1f} |")
    L.append("")
    return L


if __name__ == "__main__":  # python -m StomachUnfoldEval.memory [names...]: print the rows as JSON
    import sys

    names = sys.argv[1:]
    print(json.dumps(memory_runs([s for s in MEMORY_SOURCES if not names or s[0] in names]), indent=1))
